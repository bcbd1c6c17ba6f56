"""Moving a release grid onto ours: nearest-voxel resampling under a rigid transform. Pure numpy/scipy."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from nuplan_occ.grid import GridSpec


def source_grid(z_min: float, shape: tuple[int, int, int]) -> GridSpec:
    """The release grid in its own frame: x, y in [-50, 50) m, z in [z_min, z_min + 8) m, `shape` voxels
    (cubic voxels required: 100 m / X = 100 m / Y = 8 m / Z; ValueError otherwise)."""
    sizes = {100.0 / shape[0], 100.0 / shape[1], 8.0 / shape[2]}
    if max(sizes) - min(sizes) > 1e-9:
        raise ValueError(f"grid {list(shape)} over 100 x 100 x 8 m has no cubic voxels")
    return GridSpec(z_min=z_min, z_max=z_min + 8.0, voxel_size=100.0 / shape[0])


def output_grid(src: GridSpec) -> GridSpec:
    """Our grid (x, y in [-50, 50) m, z in [-3, 5) m, ego frame) at the release's voxel size."""
    return GridSpec(voxel_size=src.voxel_size)


def resample(semantics: np.ndarray, src: GridSpec, out: GridSpec, T_src_from_out: np.ndarray) -> np.ndarray:
    """uint8 grid on `out`: each output voxel takes the label of the source voxel holding its centre
    (mapped by the (4, 4) T_src_from_out, metres), 0 (empty) where that centre is outside `src`.

    semantics: uint8 [X, Y, Z] on `src`. A pure z shift by whole voxels (the r800_old convention) moves
    labels exactly; a lidar-to-ego transform is a nearest-neighbour resampling.
    """
    T = np.asarray(T_src_from_out, dtype=np.float64)
    if src == out and np.allclose(T, np.eye(4)):
        return semantics
    rotation = T[:3, :3]
    # output index o -> centre lower_out + (o + 0.5) s_out -> source point -> source index (centre at i + 0.5)
    matrix = rotation * (out.voxel_size / src.voxel_size)
    offset = (rotation @ (out.lower + 0.5 * out.voxel_size) + T[:3, 3] - src.lower) / src.voxel_size - 0.5
    return ndimage.affine_transform(semantics, matrix, offset=offset, output_shape=out.shape, order=0,
                                    mode="constant", cval=0)
