"""Compose one frame's grids (semantics, instance ids, flow) from the background surface and placed objects.

Everything is in the EGO frame of the frame (metres, m/s). Order of operations:
1. background surface -> exact voxels (voxelize.mesh_voxel_grid); its ground height per column is
   estimated (ground.estimate_ground_height);
2. background voxels whose centre is inside a current box (grown by `box_margin_m`) are removed unless
   they are in the ground layer (within ground_tolerance_m of the local ground): the object replaces
   what the background mesh put in its box, but the road under a car is kept;
3. each object's surface is posed by its box (box frame -> ego), voxelized exactly on the grid lattice
   (also beyond the grid), filled inside if `fill_objects` (closed surfaces: voxels not 6-connected to
   the outside; see voxelize.fill_enclosed), then clipped to its box grown by `box_margin_m` (voxel
   centres) and to the grid. Objects are painted in list order (a later object wins a shared voxel) and
   overwrite background; object voxels of `ground_layer_classes` in the ground layer become ground;
4. background left over is labeled by ground.label_background with the BEV (OTHER if bev is None);
5. instance ids and flow (the object's ground-relative velocity in the ego frame) go to object voxels;
   0 elsewhere.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numba
import numpy as np

from nuplan_occ.geometry import yaw_matrix
from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.labels import OTHER
from nuplan_occ.voxel.frame_lookup import point_voxels
from nuplan_occ.voxel.ground import estimate_ground_height, ground_height_index, label_background
from nuplan_occ.voxel.voxelize import (
    VoxelizeError, box_voxel_indices, fill_enclosed, in_box, inside_grid, mesh_voxel_grid, mesh_voxel_indices,
)


def _unique_grid_indices(indices: np.ndarray, grid: GridSpec) -> np.ndarray:
    """The unique rows of (M, 3) int voxel indices that all lie inside the grid, sorted (as int64)."""
    return _grid_indices_of(np.unique(np.ravel_multi_index(np.asarray(indices).T, grid.shape)), grid)


def _grid_indices_of(flat: np.ndarray, grid: GridSpec) -> np.ndarray:
    """(M, 3) int64 voxel indices of flat C-order indices (M,) of the grid (sorted flat indices: sorted rows)."""
    return np.stack(np.unravel_index(flat, grid.shape), axis=1).astype(np.int64)


@dataclass
class PlacedObject:
    """One object at one frame. vertices (V, 3) metres in the object's BOX frame (origin at the box
    centre, x along its heading, z up), faces (F, 3) int (empty: vertices are raw points); center (3,)
    metres, yaw rad, size (3,) [length, width, height] metres and velocity (3,) m/s (relative to the
    ground) of its box in the EGO frame; class_id: semantic id; instance_id: >0, stable per track."""

    vertices: np.ndarray
    faces: np.ndarray
    center: np.ndarray
    yaw: float
    size: np.ndarray
    class_id: int
    instance_id: int
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    min_points_per_voxel: int = 1
    anchors: np.ndarray | None = None
    """Raw points only (no faces): a voxel is the object's when it holds at least min_points_per_voxel of
    them, or one marked in `anchors` (V,) bool (e.g. solid cells that hold an observed point)."""
    own_points: np.ndarray | None = None
    """(N, 3) the object's own LiDAR points in its BOX frame, or None: every voxel holding one of them is the
    object's, besides its geometry's voxels (a return is where the object is, also where a solid's cell
    centres or a clipped surface stop short of a voxel it reaches into; the points are not clipped again)."""

    def vertices_ego(self) -> np.ndarray:
        """(V, 3) vertices moved from the box frame into the ego frame."""
        return self._to_ego(self.vertices)

    def _to_ego(self, points_box: np.ndarray) -> np.ndarray:
        v = np.asarray(points_box, dtype=np.float64).reshape(-1, 3)
        return v @ yaw_matrix(self.yaw).T + np.asarray(self.center, dtype=np.float64)

    def own_point_voxels(self, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
        """(M, 3) unique indices of the grid voxels holding at least one of `own_points` (none if None)."""
        if self.own_points is None or len(self.own_points) == 0:
            return np.zeros((0, 3), dtype=np.int64)
        flat = point_voxels(self._to_ego(self.own_points), grid)
        return _grid_indices_of(np.unique(flat[flat >= 0]), grid)


@dataclass
class FrameGrids:
    """A frame's grids in the ego frame: semantics uint8 (X, Y, Z) label ids; instance uint16 (0 =
    background/empty); flow float16 (X, Y, Z, 3) m/s; occupied_background bool (X, Y, Z): background
    voxels kept (not overwritten by objects); ground_height float (X, Y) metres (NaN unknown);
    mover_voxels: voxels painted for unboxed movers (nuplan_occ.voxel.movers), 0 when none were;
    ego_cleared: occupied voxels emptied inside the ego vehicle's box (`clear_ego_box`), 0 when none were;
    object_points bool (X, Y, Z): voxels holding an own point of a placed object (`PlacedObject.own_points`)."""

    semantics: np.ndarray
    instance: np.ndarray
    flow: np.ndarray
    occupied_background: np.ndarray
    ground_height: np.ndarray | None = None
    mover_voxels: int = 0
    ego_cleared: int = 0
    object_points: np.ndarray | None = None


@numba.njit(cache=True)
def _zero_emptied(instance, flow, semantics):
    for v in range(len(instance)):
        if instance[v] != 0 and semantics[v] == 0:
            instance[v] = 0
            for c in range(flow.shape[1]):
                flow[v, c] = 0


def zero_emptied_objects(grids: FrameGrids, semantics: np.ndarray) -> None:
    """Set the instance id and flow of grids (FrameGrids) to 0, in place, in the object voxels (instance id
    set) that `semantics` (uint8 (X, Y, Z), e.g. after free-space clearing) left empty (0)."""
    if grids.instance.shape != semantics.shape or grids.flow.shape != (*semantics.shape, 3):
        raise VoxelizeError(f"zero_emptied_objects: grids of shape {grids.instance.shape} / {grids.flow.shape}, "
                            f"semantics {semantics.shape}")
    if not (grids.instance.flags.c_contiguous and grids.flow.flags.c_contiguous):
        raise VoxelizeError("zero_emptied_objects: the instance and flow grids must be C-contiguous (set in place)")
    flow_bits = grids.flow.reshape(-1, 3).view(np.dtype(f"u{grids.flow.itemsize}"))  # 0 bits are +0.0 (numba has no float16)
    _zero_emptied(grids.instance.reshape(-1), flow_bits, semantics.reshape(-1))


def clear_ego_box(grids: FrameGrids, center: np.ndarray, size: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> int:
    """Empty, in place, the voxels of `grids` (semantics, instance, flow, occupied_background) whose centre lies
    inside the ego vehicle's box (center (3,) m in the EGO frame, size [length, width, height] m, yaw 0) and above
    the column's ground layer (the layer holding grids.ground_height; every such voxel where that is unknown):
    the ego occupies that space at its own frame, so nothing else can. The ground layer stays (the road under
    the ego). Returns how many occupied voxels were emptied."""
    idx = box_voxel_indices(center, 0.0, size, grid)
    if grids.ground_height is not None:
        layer = ground_height_index(grids.ground_height, grid)[idx[:, 0], idx[:, 1]]
        idx = idx[idx[:, 2] > layer]
    i, j, k = idx.T
    emptied = int(np.count_nonzero(grids.semantics[i, j, k]))
    grids.semantics[i, j, k] = 0
    grids.instance[i, j, k] = 0
    grids.flow[i, j, k] = 0
    grids.occupied_background[i, j, k] = False
    return emptied


def crowded_or_anchored(points_ego: np.ndarray, anchors: np.ndarray | None, min_count: int,
                        grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """(N,) bool: points (N, 3, ego frame, m) inside the grid whose voxel holds at least min_count of them or
    an anchor point (anchors (N,) bool or None)."""
    flat = point_voxels(points_ego, grid)
    inside = flat >= 0
    keep = np.zeros(len(flat), dtype=bool)
    if not inside.any():
        return keep
    _, inverse, counts = np.unique(flat[inside], return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    crowded = counts >= min_count
    if anchors is not None:
        crowded |= np.bincount(inverse, weights=np.asarray(anchors, dtype=bool)[inside], minlength=len(counts)) > 0
    keep[inside] = crowded[inverse]
    return keep


def object_voxel_indices(obj: PlacedObject, grid: GridSpec = DEFAULT_GRID, fill: bool = True,
                         box_margin_m: float | None = None) -> np.ndarray:
    """(M, 3) unique grid indices of an object's voxels: its surface posed by its box, voxelized exactly,
    filled when `fill`, clipped to its box grown by box_margin_m (default half a voxel) and to the grid;
    together with the voxels holding the object's own points (so an object with points is never lost)."""
    return _object_voxels(obj, grid, fill, box_margin_m)[0]


def _object_voxels(obj: PlacedObject, grid: GridSpec, fill: bool, box_margin_m: float | None) -> tuple[np.ndarray, np.ndarray]:
    """(`object_voxel_indices`, the voxels holding its own points)."""
    points = obj.own_point_voxels(grid)
    geometry = _geometry_voxel_indices(obj, grid, fill, box_margin_m)
    return _unique_grid_indices(np.concatenate([geometry, points]), grid), points


def _geometry_voxel_indices(obj: PlacedObject, grid: GridSpec, fill: bool, box_margin_m: float | None) -> np.ndarray:
    margin = grid.voxel_size / 2.0 if box_margin_m is None else box_margin_m
    vertices = obj.vertices_ego()
    if len(obj.faces) == 0 and obj.min_points_per_voxel > 1:
        vertices = vertices[crowded_or_anchored(vertices, obj.anchors, obj.min_points_per_voxel, grid)]
    if len(vertices) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    try:
        idx = mesh_voxel_indices(vertices, obj.faces, grid, clip=False)
    except VoxelizeError as err:
        raise VoxelizeError(f"object instance {obj.instance_id}: {err}") from err
    if fill:
        idx = fill_enclosed(idx)
    idx = inside_grid(idx, grid)
    return idx[in_box(grid.index_to_center(idx), obj.center, obj.yaw, obj.size, margin)]


def remove_background_in_boxes(background: np.ndarray, objects: list[PlacedObject], ground_height: np.ndarray,
                               grid: GridSpec, ground_tolerance_m: float, box_margin_m: float) -> np.ndarray:
    """Copy of the background bool grid without voxels inside current boxes above the ground layer."""
    out = background.copy()
    for obj in objects:
        idx = box_voxel_indices(obj.center, obj.yaw, obj.size, grid, box_margin_m)
        z = grid.z_min + (idx[:, 2] + 0.5) * grid.voxel_size
        h = ground_height[idx[:, 0], idx[:, 1]]
        with np.errstate(invalid="ignore"):
            in_ground_layer = np.abs(z - h) <= ground_tolerance_m + 1e-9
        idx = idx[~in_ground_layer]
        out[idx[:, 0], idx[:, 1], idx[:, 2]] = False
    return out


def compose_frame(background_vertices: np.ndarray, background_faces: np.ndarray, objects: list[PlacedObject],
                  bev: np.ndarray | None, grid: GridSpec = DEFAULT_GRID, fill_objects: bool = True,
                  ground_tolerance_m: float = 0.3, box_margin_m: float | None = None,
                  ground_layer_classes: tuple[int, ...] = ()) -> FrameGrids:
    """The frame's grids (see module doc). background_vertices (V, 3) metres in the ego frame,
    background_faces (F, 3) int (empty: vertices are points); bev uint8 (X, Y) or None;
    ground_layer_classes: object classes (ids > 0) whose voxels in the ground layer (the layer holding the
    column's estimated ground height) are ground instead (the road under a car's body)."""
    margin = grid.voxel_size / 2.0 if box_margin_m is None else box_margin_m
    try:
        background = mesh_voxel_grid(background_vertices, background_faces, grid)
    except VoxelizeError as err:
        raise VoxelizeError(f"background surface: {err}") from err
    ground_height = estimate_ground_height(background, grid)
    background = remove_background_in_boxes(background, objects, ground_height, grid, ground_tolerance_m, margin)

    instance = np.zeros(grid.shape, dtype=np.uint16)
    flow = np.zeros((*grid.shape, 3), dtype=np.float16)
    object_class = np.zeros(grid.shape, dtype=np.uint8)
    painted = [np.zeros((0, 3), dtype=np.int64)]
    object_points = np.zeros(grid.shape, dtype=bool)
    for obj in objects:
        idx, points = _object_voxels(obj, grid, fill_objects, margin)
        object_points[tuple(points.T)] = True
        i, j, k = idx[:, 0], idx[:, 1], idx[:, 2]
        object_class[i, j, k] = obj.class_id
        instance[i, j, k] = obj.instance_id
        flow[i, j, k] = np.asarray(obj.velocity, dtype=np.float16).reshape(3)
        painted.append(idx)
    i, j, k = np.concatenate(painted).T  # every voxel an object painted (repeats allowed)
    if ground_layer_classes:
        layer = ground_height_index(ground_height, grid)[i, j]
        to_ground = (k == layer) & (layer >= 0) & np.isin(object_class[i, j, k], ground_layer_classes)
        g = (i[to_ground], j[to_ground], k[to_ground])
        background[g] = True
        object_class[g], instance[g], flow[g] = 0, 0, 0
    is_object = object_class[i, j, k] > 0
    i, j, k = i[is_object], j[is_object], k[is_object]
    background[i, j, k] = False
    if bev is None:
        semantics = np.where(background, np.uint8(OTHER), np.uint8(0)).astype(np.uint8)
    else:
        semantics = label_background(background, bev, grid, ground_tolerance_m, ground_height)
    semantics[i, j, k] = object_class[i, j, k]
    return FrameGrids(semantics, instance, flow, background, ground_height, object_points=object_points)
