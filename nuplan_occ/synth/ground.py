"""The ground of a synthetic world: a partition of the map extent into labelled horizontal rectangles
plus the vertical curb faces of the raised walkways (local frame, metres; heights relative to the
world's ground level).

Labels follow the map's layers: paint strips -> road_line (14); walkways and anything
outside the drivable area -> other_ground (13) (walkways raised by the curb height); drivable area
(road segments, intersections incl. crosswalks, driveway, carpark) -> road (12). Curb faces -> other_ground.
"""

from __future__ import annotations

import numpy as np
import shapely

from nuplan_occ.labels import OTHER_GROUND, ROAD, ROAD_LINE
from nuplan_occ.synth.mapgen import RoadNetwork
from nuplan_occ.synth.primitives import Faces, faces, split_long


def _breaks(geoms: list, axis: int, lo: float, hi: float) -> np.ndarray:
    coords = np.concatenate([shapely.get_coordinates(g)[:, axis] for g in geoms] + [np.array([lo, hi])])
    return np.unique(np.round(np.clip(coords, lo, hi), 9))


def _merge_rows(cls: np.ndarray) -> list[tuple[int, int, int, int, int]]:
    """Greedy rectangles (i0, i1, j0, j1, class) covering a class grid cls[i, j] (i along x, j along y):
    runs along x per row j, then identical runs stacked along y."""
    runs: dict[tuple[int, int, int], int] = {}  # (i0, i1, class) -> j0 of the open rectangle
    out = []
    nx, ny = cls.shape
    for j in range(ny + 1):
        row = set()
        if j < ny:
            col = cls[:, j]
            starts = np.flatnonzero(np.r_[True, col[1:] != col[:-1]])
            ends = np.r_[starts[1:], nx]
            row = {(int(a), int(b), int(col[a])) for a, b in zip(starts, ends)}
        for key in list(runs):
            if key not in row:
                out.append((key[0], key[1], runs.pop(key), j, key[2]))
        for key in row:
            runs.setdefault(key, j)
    return out


def ground_faces(net: RoadNetwork) -> Faces:
    """Horizontal ground rectangles covering the layout bounds, labelled by the map (see module doc)."""
    lay = net.layout
    x_lo, x_hi, y_lo, y_hi = lay.bounds()
    paint, walk, drivable = net.paint, net.walkways, net.drivable
    geoms = [paint, walk, drivable]
    xb, yb = _breaks(geoms, 0, x_lo, x_hi), _breaks(geoms, 1, y_lo, y_hi)
    cx, cy = (xb[:-1] + xb[1:]) / 2, (yb[:-1] + yb[1:]) / 2
    gx, gy = np.meshgrid(cx, cy, indexing="ij")
    # class: 0 other_ground, 1 walkway, 2 road, 3 paint (first match in reverse order wins)
    cls = np.zeros(gx.shape, np.int64)
    for value, geom in ((2, drivable), (1, walk), (3, paint)):
        cls[shapely.contains_xy(geom, gx, gy)] = value
    rects = np.array(_merge_rows(cls), dtype=np.int64)
    x0, x1, y0, y1 = xb[rects[:, 0]], xb[rects[:, 1]], yb[rects[:, 2]], yb[rects[:, 3]]
    center, half = split_long(np.stack([(x0 + x1) / 2, (y0 + y1) / 2], 1), np.stack([(x1 - x0) / 2, (y1 - y0) / 2], 1))
    cls_of = shapely.contains_xy(paint, *center.T) * 3
    cls_of = np.where(cls_of == 0, np.where(shapely.contains_xy(walk, *center.T), 1,
                                            np.where(shapely.contains_xy(drivable, *center.T), 2, 0)), cls_of)
    label = np.array([OTHER_GROUND, OTHER_GROUND, ROAD, ROAD_LINE], np.uint8)[cls_of]
    z = np.where(cls_of == 1, lay.curb_height, 0.0)
    return faces(center, half, 0.0, z, z, label)


def curb_faces(net: RoadNetwork, max_len: float = 2.0) -> Faces:
    """Vertical curb faces (other_ground) along the walkway outlines, from 0 to the curb height, in pieces
    of at most max_len metres. Outline parts on the layout bounds get no face."""
    lay = net.layout
    x_lo, x_hi, y_lo, y_hi = lay.bounds()
    parts = []
    for poly in getattr(net.walkways, "geoms", [net.walkways]):
        for ring in [poly.exterior, *poly.interiors]:
            pts = np.asarray(ring.coords)[:, :2]
            for p, q in zip(pts[:-1], pts[1:]):
                on_x = np.isclose(p[0], q[0]) and (np.isclose(p[0], x_lo) or np.isclose(p[0], x_hi))
                on_y = np.isclose(p[1], q[1]) and (np.isclose(p[1], y_lo) or np.isclose(p[1], y_hi))
                length = float(np.hypot(*(q - p)))
                if on_x or on_y or length < 1e-9:
                    continue
                n = int(np.ceil(length / max_len))
                t = (np.arange(n) + 0.5) / n
                yaw = float(np.arctan2(q[1] - p[1], q[0] - p[0]))
                parts.append(faces(p + t[:, None] * (q - p), (length / n / 2, 0.0), yaw, 0.0, lay.curb_height, OTHER_GROUND))
    return Faces.concat(parts)


def on_walkway(net: RoadNetwork, xy: np.ndarray) -> np.ndarray:
    """(N,) bool: local points (N, 2) on a (raised) walkway; their ground is at the curb height."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    return shapely.intersects_xy(net.walkways, xy[:, 0], xy[:, 1])
