"""Objects that stand on the ground reach it: the voxels between a vehicle and the road under it.

A car stands on its wheels, and its body clears the road by 0.1-0.3 m. Rays pass under the body and carve
that gap out of the car's solid, and its wheels give few returns, so the car's voxels often stop one or two
layers above the road. In the grid a 0.25 m layer there holds wheels and the body's underside, and is the
car's. Per column of the ego frame's grid (arrays [x, y, z]): when the lowest voxel of the given classes (a
boxed object's, or an unboxed mover's: nuplan_occ.voxel.movers) stands over empty voxels whose floor (the highest
occupied voxel under it) is ground (its centre within `ground_tolerance_m` of the column's ground height), and the
gap is at most `reach_m` tall, the gap's voxels become that voxel's (class, instance id, flow). Columns of
unknown ground are left alone.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID, GridSpec, column_runs
from nuplan_occ.voxel.compose import FrameGrids


def reach_down_to_ground(grids: FrameGrids, class_ids: tuple[int, ...], reach_m: float,
                         ground_tolerance_m: float = 0.3, grid: GridSpec = DEFAULT_GRID) -> int:
    """Fill, in place, the gaps under the voxels of `class_ids` down to their ground (module doc);
    grids.ground_height (X, Y) m, ego frame, NaN unknown. reach_m: the tallest gap filled (m; 0: none). Returns
    how many voxels were filled."""
    layers = int(np.floor(reach_m / grid.voxel_size + 1e-9))
    if not class_ids or layers < 1 or grids.ground_height is None:
        return 0
    semantics, instance, flow = grids.semantics, grids.instance, grids.flow
    of_class = np.isin(semantics, np.asarray(class_ids, np.uint8))
    ci, cj = np.nonzero(of_class.any(axis=2))  # the columns holding one
    column, obj = semantics[ci, cj], of_class[ci, cj]  # (C, Z)
    low = np.argmax(obj, axis=1)
    k = np.arange(grid.shape[2])
    floor = np.where((column > 0) & (k < low[:, None]), k, -1).max(axis=1, initial=-1)
    floor_z = grid.z_min + (floor + 0.5) * grid.voxel_size
    with np.errstate(invalid="ignore"):
        on_ground = (floor >= 0) & (np.abs(floor_z - grids.ground_height[ci, cj]) <= ground_tolerance_m + 1e-9)
    gap = low - floor - 1
    keep = on_ground & (gap >= 1) & (gap <= layers)
    ci, cj, low, floor, gap = ci[keep], cj[keep], low[keep], floor[keep], gap[keep]
    run, z = column_runs(floor + 1, gap)
    i, j, source = ci[run], cj[run], low[run]
    semantics[i, j, z] = semantics[i, j, source]
    instance[i, j, z] = instance[i, j, source]
    flow[i, j, z] = flow[i, j, source]
    return int(len(i))
