"""Bird's-eye-view ground semantics of a frame from the map's vector layers. Pure (shapely 2 + numpy).

Layers are in the map's global frame (UTM metres). Each grid column (i, j) is represented by its cell
centre in the ego frame (z = 0), moved to the global frame with T_global_from_ego, and classified with
shapely's vectorized predicates (no per-cell Python loop):
- ROAD: centre inside (or on the boundary of) the union of DRIVABLE_LAYERS. Crosswalks lie on the road
  surface and are included.
- ROAD_LINE: painted lines = `boundaries` linestrings and the outlines of `stop_polygons` (a thin stop
  polygon's outline is its stop line; a deep one gives its front and back edges, one being the painted
  line). A cell is a line cell if its square overlaps the painted strip (the line buffered to half the
  painted width, flat caps), so lines thinner than a cell never vanish and a strip is never narrowed.
- OTHER_GROUND: every other column (walkways, verges, unmapped ground).
Line beats road beats other ground.
Centres are tested one by one only in the 8 x 8-cell blocks an area's boundary comes near; every other block
lies wholly on its middle's side (same result, ~2x faster per frame on the scale bench's city map).
A line cell whose centre is off the strip is found by walking the strip's outline through the columns
(compiled): a square holds a strip's point exactly where the outline meets it, since its centre is outside.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import shapely

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.io.types import MapLayer
from nuplan_occ.labels import OTHER_GROUND, ROAD, ROAD_LINE

DRIVABLE_LAYERS: tuple[str, ...] = (
    "road_segments", "intersections", "generic_drivable_areas", "carpark_areas", "lanes_polygons", "crosswalks",
)
LINE_LAYERS: tuple[str, ...] = ("boundaries",)
STOP_LINE_LAYERS: tuple[str, ...] = ("stop_polygons",)
BLOCK_CELLS = 8
"""Side (cells) of the blocks whose centres are classified together when no area boundary comes near."""


class BevError(ValueError):
    """Malformed map layer or pose given to the BEV rasterizer."""


def cell_centers_global(T_global_from_ego: np.ndarray, grid: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y) global-frame x and y of the grid's column centres (ego z = 0)."""
    T = np.asarray(T_global_from_ego, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise BevError(f"rasterize_bev: T_global_from_ego must be a finite 4x4 matrix, got shape {T.shape}")
    nx, ny, _ = grid.shape
    xs = grid.x_min + (np.arange(nx) + 0.5) * grid.voxel_size
    ys = grid.y_min + (np.arange(ny) + 0.5) * grid.voxel_size
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    gx = T[0, 0] * X + T[0, 1] * Y + T[0, 3]
    gy = T[1, 0] * X + T[1, 1] * Y + T[1, 3]
    return gx, gy


def _footprint(T_global_from_ego: np.ndarray, grid: GridSpec, margin_m: float) -> shapely.Geometry:
    """The grid's square in the global frame, grown by margin_m (to pre-select map features)."""
    corners = np.array([[grid.x_min, grid.y_min], [grid.x_max, grid.y_min],
                        [grid.x_max, grid.y_max], [grid.x_min, grid.y_max]])
    T = np.asarray(T_global_from_ego, dtype=np.float64)
    g = corners @ T[:2, :2].T + T[:2, 3]
    return shapely.buffer(shapely.Polygon(g), margin_m)


def _geometries_near(layers: dict[str, MapLayer], names: tuple[str, ...], area: shapely.Geometry) -> np.ndarray:
    """Valid, non-empty geometries of the named layers that meet `area`."""
    found = []
    for name in names:
        if name not in layers:
            continue
        geoms = np.asarray(layers[name].geometries, dtype=object).reshape(-1)
        if len(geoms) and not all(isinstance(g, shapely.Geometry) or g is None for g in geoms):
            raise BevError(f"rasterize_bev: layer {name!r} holds non-shapely geometries")
        geoms = geoms[~shapely.is_missing(geoms)]
        geoms = geoms[~shapely.is_empty(geoms)]
        found.append(geoms[shapely.intersects(geoms, area)])
    return np.concatenate(found) if found else np.zeros(0, dtype=object)


def _line_cells(lines: shapely.Geometry, gx: np.ndarray, gy: np.ndarray, T_global_from_ego: np.ndarray,
                grid: GridSpec, width_m: float) -> np.ndarray:
    """(X, Y) bool: the cell's square overlaps the painted strip (lines buffered to half the painted width,
    flat caps; a zero width means the line itself)."""
    s = grid.voxel_size
    out = np.zeros(gx.shape, dtype=bool)
    reach = shapely.buffer(lines, width_m / 2.0 + s * np.sqrt(0.5) + 1e-6)  # centres of cells that may overlap
    near = _covers_centres(reach, gx, gy)
    if near.any():
        painted = shapely.buffer(lines, width_m / 2.0, cap_style="flat") if width_m > 0 else lines
        shapely.prepare(painted)
        out[near] = shapely.intersects_xy(painted, gx[near], gy[near])  # a square overlaps a strip holding its centre
        # a square whose centre is off the strip overlaps it exactly where the strip's outline meets the square
        outline = shapely.boundary(painted) if shapely.get_dimensions(painted) == 2 else painted
        touched = np.zeros(gx.shape, dtype=bool)
        starts, ends = _cell_unit_segments(outline, T_global_from_ego, grid)
        mark_segment_cells(starts, ends, touched)
        out |= near & touched
    return out


def _cell_unit_segments(lines: shapely.Geometry, T_global_from_ego: np.ndarray,
                        grid: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """The straight pieces of lineal `lines` (global frame) as (S, 2) start and end points in cell units of
    the grid's columns (ego x, y minus the grid's lower corner, over the voxel size), mapped by the inverse of
    `cell_centers_global`'s map from the ego plane z = 0 to global x, y."""
    parts = shapely.get_parts(lines)
    coords, part = shapely.get_coordinates(parts, return_index=True)
    T = np.asarray(T_global_from_ego, dtype=np.float64)
    ego = np.linalg.solve(T[:2, :2], (coords - T[:2, 3]).T).T  # inverse of the cell centres' map (ego z = 0)
    cells = (ego - np.array([grid.x_min, grid.y_min])) / grid.voxel_size
    same = part[1:] == part[:-1]
    return np.ascontiguousarray(cells[:-1][same]), np.ascontiguousarray(cells[1:][same])


@numba.njit(cache=True)
def mark_segment_cells(starts: np.ndarray, ends: np.ndarray, out: np.ndarray) -> None:
    """out[i, j] = True for every cell, the closed square [i, i + 1] x [j, j + 1] (cell units), that a segment
    starts[k] -> ends[k] ((S, 2), cell units) meets; cells outside out's (X, Y) are skipped. Each column the
    segment spans is met over the y range of the segment's piece within that column."""
    nx, ny = out.shape
    for k in range(len(starts)):
        x0, y0, x1, y1 = starts[k, 0], starts[k, 1], ends[k, 0], ends[k, 1]
        if x0 > x1:
            x0, y0, x1, y1 = x1, y1, x0, y0
        slope = (y1 - y0) / (x1 - x0) if x1 > x0 else 0.0
        for i in range(max(int(math.ceil(x0)) - 1, 0), min(int(math.floor(x1)), nx - 1) + 1):
            xa, xb = max(x0, float(i)), min(x1, float(i + 1))
            if xa > xb:
                continue
            ya = y0 + (xa - x0) * slope
            yb = y0 + (xb - x0) * slope if x1 > x0 else y1  # a vertical segment spans y0 .. y1 in its column
            lo, hi = min(ya, yb), max(ya, yb)
            for j in range(max(int(math.ceil(lo)) - 1, 0), min(int(math.floor(hi)), ny - 1) + 1):
                out[i, j] = True


def _covers_centres(area: shapely.Geometry, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """(X, Y) bool: shapely.intersects_xy(area, gx, gy) for the cell centres gx, gy (X, Y) of a regular grid,
    tested point by point only in the blocks of BLOCK_CELLS x BLOCK_CELLS cells that area's boundary comes
    near: every centre of a block farther than its centres' reach from the boundary is on the same side as
    the block's middle (the segment between them does not cross the boundary)."""
    nx, ny = gx.shape
    b = BLOCK_CELLS
    if nx % b or ny % b:
        return shapely.intersects_xy(area, gx, gy)
    shapely.prepare(area)
    bx, by = (gx.reshape(nx // b, b, ny // b, b), gy.reshape(nx // b, b, ny // b, b))
    mid_x = (bx[:, 0, :, 0] + bx[:, -1, :, -1]) / 2.0  # the grid is regular: its opposite corners' middle
    mid_y = (by[:, 0, :, 0] + by[:, -1, :, -1]) / 2.0
    reach = np.hypot(bx[0, :, 0, :] - mid_x[0, 0], by[0, :, 0, :] - mid_y[0, 0]).max() + 1e-6
    border = shapely.boundary(area)
    shapely.prepare(border)
    mixed = shapely.dwithin(border, shapely.points(mid_x, mid_y), reach)
    out = np.repeat(np.repeat(shapely.intersects_xy(area, mid_x, mid_y), b, axis=0), b, axis=1)
    cells = np.repeat(np.repeat(mixed, b, axis=0), b, axis=1)
    out[cells] = shapely.intersects_xy(area, gx[cells], gy[cells])
    return out


def rasterize_bev(layers: dict[str, MapLayer], T_global_from_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID,
                  line_width_m: float = 0.15, stop_line_width_m: float | None = None,
                  stop_lines: np.ndarray | None = None) -> np.ndarray:
    """uint8 (X, Y) ground class per grid column: ROAD (12), OTHER_GROUND (13) or ROAD_LINE (14).

    layers: map layer name -> MapLayer in the global (UTM) frame; absent layers are skipped.
    T_global_from_ego: (4, 4) pose of the frame's ego (rear axle). Rows/cols follow the grid's x/y
    axes of the EGO frame. line_width_m: painted width of boundaries; stop_line_width_m: of stop lines
    (defaults to line_width_m). stop_lines: the painted stop lines (global-frame LineStrings, e.g. the
    stop polygon edges the LiDAR shows painted); None draws every stop polygon's whole outline.
    """
    gx, gy = cell_centers_global(T_global_from_ego, grid)
    bev = np.full(gx.shape, OTHER_GROUND, dtype=np.uint8)
    area = _footprint(T_global_from_ego, grid, margin_m=max(line_width_m, grid.voxel_size))
    drivable = _geometries_near(layers, DRIVABLE_LAYERS, area)
    if len(drivable):
        bev[_covers_centres(shapely.union_all(shapely.make_valid(drivable)), gx, gy)] = ROAD
    if stop_lines is None:
        stop_geoms = shapely.boundary(_geometries_near(layers, STOP_LINE_LAYERS, area))
    else:
        stop_geoms = np.asarray(stop_lines, dtype=object).reshape(-1)
        stop_geoms = stop_geoms[shapely.intersects(stop_geoms, area)]
    line_sets = [
        (_geometries_near(layers, LINE_LAYERS, area), line_width_m),
        (stop_geoms, line_width_m if stop_line_width_m is None else stop_line_width_m),
    ]
    for geoms, width in line_sets:
        if len(geoms):
            lines = shapely.union_all(geoms)
            bev[_line_cells(lines, gx, gy, T_global_from_ego, grid, width)] = ROAD_LINE
    return bev


def map_geometries(layers: dict[str, MapLayer], names: tuple[str, ...]) -> np.ndarray:
    """Every valid, non-empty geometry of the named layers (global frame)."""
    return _geometries_near(layers, names, shapely.box(-1e12, -1e12, 1e12, 1e12))


def painted_lines(layers: dict[str, MapLayer]) -> np.ndarray:
    """Object array of the painted lines' centre lines (global frame): the parts of every `boundaries`
    linestring and of every stop polygon's outline, as single LineStrings."""
    lines = np.concatenate([map_geometries(layers, LINE_LAYERS),
                            shapely.boundary(map_geometries(layers, STOP_LINE_LAYERS))])
    parts = shapely.get_parts(lines) if len(lines) else np.zeros(0, dtype=object)
    return parts[shapely.get_type_id(parts) != 0] if len(parts) else parts
