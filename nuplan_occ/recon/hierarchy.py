"""Sparse voxel hierarchy over the input points (the structure of NKSR, Huang et al., CVPR 2023).

Coordinates are integer voxel indices in level-0 units relative to a lattice anchor (see
`nksr_lite`); level l has voxels of 2**l level-0 voxels. Level 0 holds the voxels that contain
points, every coarser level the parents of level 0 dilated by one voxel (NKSR-lite dilation
(0, 1, 1, ...)): the coarse basis functions reach about one coarse voxel beyond the data and fill
holes there. Each level keeps a dense int32 index volume (voxel -> global coefficient id or -1)
over its padded bounding box, so lookups are a single gather.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from nuplan_occ.recon.params import ReconError

MAX_INDEX_VOLUME = 1 << 28
"""Largest dense index volume (entries) of one level; larger inputs must be chunked or cropped."""
PADDING = 4
"""Voxels of index volume around a level's voxels: covers the 27-stencils of the solver's queries (at
most one voxel beyond the data at level 0) and of mesh extraction (band of 2 voxels, cell corners), so
that lookups take the fast path of `LevelGrid.ids`."""


@dataclass
class LevelGrid:
    """One level: voxel size `size` (level-0 units), voxel coordinates `coords` (M_l, 3) int64,
    their global coefficient ids starting at `offset`, and the dense index volume whose entry
    [0, 0, 0] is voxel `lo`."""

    size: int
    coords: torch.Tensor
    offset: int
    lo: torch.Tensor
    volume: torch.Tensor

    def ids(self, ijk: torch.Tensor) -> torch.Tensor:
        """Global coefficient ids of voxel coordinates ijk (..., 3) int64; -1 where absent.

        When every query lies inside the index volume (the usual case, thanks to its padding) the ids
        are one gather at linear indices; otherwise out-of-volume queries are masked first."""
        rel = ijk - self.lo
        shape = torch.tensor(self.volume.shape)
        flat = rel.reshape(-1, 3)
        if len(flat) and bool((flat.amin(dim=0) >= 0).all()) and bool((flat.amax(dim=0) < shape).all()):
            linear = (rel[..., 0] * shape[1] + rel[..., 1]) * shape[2] + rel[..., 2]
            return self.volume.reshape(-1)[linear].to(torch.int64)
        inside = ((rel >= 0) & (rel < shape)).all(dim=-1)
        rel = torch.where(inside.unsqueeze(-1), rel, torch.zeros_like(rel))
        found = self.volume[rel[..., 0], rel[..., 1], rel[..., 2]].to(torch.int64)
        return torch.where(inside, found, torch.full_like(found, -1))


def unique_voxels(coords: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unique rows of int64 voxel coordinates (K, 3) via 1-D linear keys (faster than
    torch.unique(dim=0)). Returns (unique (M, 3) in lexicographic order, inverse (K,), counts (M,))."""
    lo = coords.min(dim=0).values
    rel = coords - lo
    ext = rel.max(dim=0).values + 1
    keys = (rel[:, 0] * ext[1] + rel[:, 1]) * ext[2] + rel[:, 2]
    uniq, inverse, counts = torch.unique(keys, return_inverse=True, return_counts=True)
    z = uniq % ext[2]
    y = torch.div(uniq, ext[2], rounding_mode="floor") % ext[1]
    x = torch.div(uniq, ext[2] * ext[1], rounding_mode="floor")
    return torch.stack([x, y, z], dim=1) + lo, inverse, counts


def dilate(coords: torch.Tensor, times: int = 1) -> torch.Tensor:
    """Unique voxel coordinates (M', 3) int64, in lexicographic order, of `coords` (M, 3) grown by `times`
    26-neighbourhoods (coords as given when times is 0 or there are none). Grown on a dense occupancy volume
    over their bounding box (a separable maximum filter), which holds one byte per voxel of the box instead
    of the 27 * M candidate rows a sparse growth sorts."""
    if times <= 0 or len(coords) == 0:
        return coords
    lo = coords.min(dim=0).values - times
    rel = (coords - lo).numpy()
    volume = np.zeros(tuple((rel.max(axis=0) + times + 1).tolist()), dtype=np.uint8)
    volume[rel[:, 0], rel[:, 1], rel[:, 2]] = 1
    grown = ndimage.maximum_filter(volume, size=2 * times + 1, mode="constant", cval=0)
    return torch.from_numpy(np.argwhere(grown).astype(np.int64)) + lo


def _level(coords: torch.Tensor, size: int, offset: int) -> LevelGrid:
    lo = coords.min(dim=0).values - PADDING
    extent = coords.max(dim=0).values + PADDING + 1 - lo
    if int(extent.prod()) > MAX_INDEX_VOLUME:
        raise ReconError(
            f"voxel hierarchy: level of voxel size {size} spans {extent.tolist()} voxels; "
            "crop the input or enable chunking (ReconParams.chunk_size)"
        )
    volume = torch.full(tuple(extent.tolist()), -1, dtype=torch.int32)
    rel = coords - lo
    volume[rel[:, 0], rel[:, 1], rel[:, 2]] = torch.arange(offset, offset + len(coords), dtype=torch.int32)
    return LevelGrid(size=size, coords=coords, offset=offset, lo=lo, volume=volume)


@dataclass
class VoxelHierarchy:
    """Levels 0..L-1 of the sparse hierarchy; coefficient ids are global over all levels."""

    levels: list[LevelGrid]

    @property
    def num_unknowns(self) -> int:
        """Total number of basis functions (voxels over all levels)."""
        last = self.levels[-1]
        return last.offset + len(last.coords)

    @classmethod
    def build(cls, occupied: torch.Tensor, num_levels: int) -> "VoxelHierarchy":
        """Hierarchy over the occupied level-0 voxels `occupied` (M0, 3) int64 (unique)."""
        levels = [_level(occupied, 1, 0)]
        for level in range(1, num_levels):
            size = 1 << level
            parents = unique_voxels(torch.div(occupied, size, rounding_mode="floor"))[0]
            coords = dilate(parents)
            prev = levels[-1]
            levels.append(_level(coords, size, prev.offset + len(prev.coords)))
        return cls(levels=levels)


@dataclass(frozen=True)
class FlatLevels:
    """The index volumes of a hierarchy's levels in flat arrays, as the numba kernels take them:
    `volumes` every level's C-ordered volume one after another (int32 coefficient ids, -1 where
    absent), `starts` (L,) where each begins, `shapes` and `los` (L, 3) int64 their extents and
    lower voxels, `sizes` (L,) int64 the voxel sizes (level-0 units)."""

    volumes: np.ndarray
    starts: np.ndarray
    shapes: np.ndarray
    los: np.ndarray
    sizes: np.ndarray

    def subset(self, levels: slice) -> "FlatLevels":
        """These index volumes restricted to the levels `levels` (a slice of level numbers): design rows made with
        it hold only those levels' basis functions, under their global coefficient ids."""
        return FlatLevels(self.volumes, self.starts[levels], self.shapes[levels], self.los[levels], self.sizes[levels])

    @classmethod
    def of(cls, hierarchy: VoxelHierarchy) -> "FlatLevels":
        levels = hierarchy.levels
        lengths = [level.volume.numel() for level in levels]
        return cls(
            volumes=torch.cat([level.volume.reshape(-1) for level in levels]).numpy(),
            starts=np.cumsum([0] + lengths[:-1]).astype(np.int64),
            shapes=np.array([level.volume.shape for level in levels], dtype=np.int64),
            los=torch.stack([level.lo for level in levels]).numpy().astype(np.int64),
            sizes=np.array([level.size for level in levels], dtype=np.int64),
        )
