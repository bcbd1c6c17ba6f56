"""Frames and grids of the consumers: a frame's members moved into the LiDAR frame, or onto a coarser grid.

`to_lidar_frame`: the same grid (bounds, voxel size) placed in the LiDAR frame instead of the ego (rear-axle)
frame. Each output voxel takes the value of the ego-grid voxel that holds its centre mapped by
T_ego_from_lidar (nearest voxel, `release.regrid.resample`); where that centre lies outside the ego grid the
output is empty (0), unobserved (masks 0), instance 0 and flow 0. Flow vectors are also rotated into the
LiDAR axes. A LiDAR mount offset by whole voxels with no rotation moves voxels exactly; any other mount
(nuPlan's: about 1.52 m forward, 1.63 m up, under half a degree of tilt) is this nearest-voxel resampling.

`coarsen`: onto a target grid in the same frame. The children of a target voxel are the source voxels whose
centres lie inside it (0.25 m -> 0.5 m: 2 x 2 x 2; -> 0.4 m: 1 or 2 per axis). Rules:
    semantics: occupied if any child is occupied (thin poles and lines survive), with the class most children
        hold among the occupied ones; ties go to the class earlier in TIE_PRECEDENCE (objects before surfaces);
    masks: observed if any child is observed;
    instance: the id most children of the chosen class hold (ties: the smallest id), 0 if none has one;
    flow: mean flow of the children of the chosen class (0 for empty voxels).
Target voxels with no child (outside the source grid, e.g. Occ3D's z in [5.0, 5.4) m above our 5 m top) are
empty, unobserved, instance 0, flow 0; `coverage` gives them.
Named targets (`target_grid`): "occ3d" = Occ3D-nuScenes' 200 x 200 x 16 at 0.4 m over [-40, 40]^2 x [-1, 5.4] m,
"<size>m" (e.g. "0.5m") = our bounds at that voxel size.
"""

from __future__ import annotations

import re

import numpy as np

from nuplan_occ.geometry import invert_transform
from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import LABELS
from nuplan_occ.release.regrid import resample

OCC3D_GRID = GridSpec(x_min=-40.0, x_max=40.0, y_min=-40.0, y_max=40.0, z_min=-1.0, z_max=5.4, voxel_size=0.4)
TIE_PRECEDENCE = ("pedestrian", "bicycle", "traffic_cone", "czone_sign", "barrier", "generic_object", "vehicle",
                  "road_line", "other", "other_ground", "road")
"""Class order that breaks ties between equally frequent classes of a target voxel's children."""
MASKS = ("mask_lidar", "mask_camera")
LIDAR_FRAME_RULE = ("each voxel of the LiDAR-frame grid takes the ego-grid voxel holding its centre mapped by "
                    "T_ego_from_lidar (nearest voxel); outside the ego grid: empty, unobserved; flow rotated")
COARSEN_RULES = ("children = source voxels whose centres lie in the target voxel; semantics: occupied if any child "
                 "is, class = most frequent among occupied children, ties by TIE_PRECEDENCE " + " > ".join(TIE_PRECEDENCE)
                 + "; masks: observed if any child is; instance: most frequent id among children of the chosen class; "
                   "flow: their mean; voxels without children: empty, unobserved")


class GridError(ValueError):
    """A target grid name or shape that cannot be used."""


def target_grid(name: str, source: GridSpec) -> GridSpec:
    """The grid named `name` ("occ3d" or "<size>m"); GridError when the size does not tile our bounds."""
    if name == "occ3d":
        return OCC3D_GRID
    match = re.fullmatch(r"(\d+(?:\.\d+)?)m", name)
    if not match:
        raise GridError(f"grid {name!r}: use occ3d or a voxel size such as 0.5m")
    size = float(match.group(1))
    extents = source.upper - source.lower
    if size <= 0 or np.any(np.abs(extents / size - np.round(extents / size)) > 1e-9):
        raise GridError(f"grid {name!r}: {size} m does not divide the grid's extents {extents.tolist()} m")
    return GridSpec(source.x_min, source.x_max, source.y_min, source.y_max, source.z_min, source.z_max, size)


def to_lidar_frame(frame: dict, grid: GridSpec, lidar_to_ego: np.ndarray) -> dict:
    """The members of `frame` (semantics, masks, instance, flow as stored) on `grid` placed in the LiDAR frame
    (module doc); other keys are copied."""
    T = np.asarray(lidar_to_ego, dtype=np.float64)
    out = dict(frame)
    for name in ("semantics", "instance", *MASKS):
        if name in frame:
            values = np.asarray(frame[name])
            moved = resample(values.astype(np.uint8) if values.dtype == bool else values, grid, grid, T)
            out[name] = moved.astype(values.dtype)
    if "flow" in frame:
        flow = np.asarray(frame["flow"])
        rotation = invert_transform(T)[:3, :3]
        parts = [resample(flow[..., k].astype(np.float32), grid, grid, T) for k in range(3)]
        out["flow"] = (np.stack(parts, axis=-1) @ rotation.T).astype(flow.dtype)
    return out


def _children(source: GridSpec, target: GridSpec) -> list[np.ndarray]:
    """Per axis: the target index of each source index (-1 where the source centre is outside the target)."""
    out = []
    for lo, n_src, t_lo, n_t in zip(source.lower, source.shape, target.lower, target.shape):
        centres = lo + (np.arange(n_src) + 0.5) * source.voxel_size
        index = np.floor((centres - t_lo) / target.voxel_size + 1e-9).astype(np.int64)
        out.append(np.where((index >= 0) & (index < n_t), index, -1))
    return out


def coverage(source: GridSpec, target: GridSpec) -> np.ndarray:
    """bool target.shape: target voxels with at least one child."""
    axes = []
    for index, n_t in zip(_children(source, target), target.shape):
        has = np.zeros(n_t, dtype=bool)
        has[index[index >= 0]] = True
        axes.append(has)
    return axes[0][:, None, None] & axes[1][None, :, None] & axes[2][None, None, :]


def _rank() -> np.ndarray:
    """(256,) tie rank of each class id (lower wins)."""
    rank = np.full(256, len(TIE_PRECEDENCE), dtype=np.int64)
    for r, name in enumerate(TIE_PRECEDENCE):
        rank[LABELS.id_of(name)] = r
    return rank


def _mode(groups: np.ndarray, values: np.ndarray, tie_key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per distinct group: the value held most often (ties: smallest tie_key of that value). Returns (groups,
    values) sorted by group."""
    pairs, counts = np.unique(np.stack([groups, values], axis=1), axis=0, return_counts=True)
    order = np.lexsort((tie_key[pairs[:, 1]] if tie_key is not None else pairs[:, 1], -counts, pairs[:, 0]))
    pairs = pairs[order]
    first = np.ones(len(pairs), dtype=bool)
    first[1:] = pairs[1:, 0] != pairs[:-1, 0]
    return pairs[first, 0], pairs[first, 1]


def coarsen(frame: dict, source: GridSpec, target: GridSpec) -> dict:
    """The members of `frame` (on `source`) on `target`, same frame, by the module doc's rules; other keys are
    copied. semantics uint8, masks bool, instance as stored, flow as stored."""
    axes = _children(source, target)
    shape = target.shape
    out = dict(frame)
    semantics = np.asarray(frame["semantics"])
    ix, iy, iz = np.nonzero(semantics)
    tx, ty, tz = axes[0][ix], axes[1][iy], axes[2][iz]
    inside = (tx >= 0) & (ty >= 0) & (tz >= 0)
    ix, iy, iz = ix[inside], iy[inside], iz[inside]
    flat = np.ravel_multi_index((tx[inside], ty[inside], tz[inside]), shape)
    classes = semantics[ix, iy, iz].astype(np.int64)
    chosen = np.zeros(int(np.prod(shape)), dtype=np.uint8)
    if len(flat):
        where, label = _mode(flat, classes, _rank())
        chosen[where] = label
    out["semantics"] = chosen.reshape(shape)
    of_class = chosen[flat] == classes  # children holding their target voxel's class
    for name in MASKS:
        if name in frame:
            mask = np.asarray(frame[name], dtype=bool)
            ox, oy, oz = np.nonzero(mask)
            sx, sy, sz = axes[0][ox], axes[1][oy], axes[2][oz]
            keep = (sx >= 0) & (sy >= 0) & (sz >= 0)
            observed = np.zeros(len(chosen), dtype=bool)
            observed[np.ravel_multi_index((sx[keep], sy[keep], sz[keep]), shape)] = True
            out[name] = observed.reshape(shape)
    if "instance" in frame:
        instance = np.asarray(frame["instance"])
        ids = instance[ix, iy, iz].astype(np.int64)
        pick = of_class & (ids > 0)
        result = np.zeros(len(chosen), dtype=instance.dtype)
        if pick.any():
            where, value = _mode(flat[pick], ids[pick], None)
            result[where] = value
        out["instance"] = result.reshape(shape)
    if "flow" in frame:
        flow = np.asarray(frame["flow"], dtype=np.float64)[ix, iy, iz][of_class]
        groups = flat[of_class]
        counts = np.bincount(groups, minlength=len(chosen))
        mean = np.stack([np.bincount(groups, weights=flow[:, k], minlength=len(chosen)) for k in range(3)], axis=1)
        mean /= np.maximum(counts, 1)[:, None]
        out["flow"] = mean.reshape(*shape, 3).astype(np.asarray(frame["flow"]).dtype)
    return out
