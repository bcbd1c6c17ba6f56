"""Road network of a synthetic world and its nuPlan vector map layers (local frame, metres; no I/O).

The network is a Manhattan grid: east-west roads at y = ys[k] and north-south roads at x = xs[k] (local
frame), each with 2 lanes per direction (right-hand traffic), walkways raised `curb_height` behind the
curbs, 4 crosswalks and stop polygons per intersection, and one carpark reached by a driveway.

Painted lines (`boundaries` LineStrings: centre line, lane dividers, edge lines) are painted in the world
as flat-capped strips of width `paint_width` centred on the LineString (default 0.15 m).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.geometry import LineString, box

from nuplan_occ.io.types import MapLayer


@dataclass(frozen=True)
class RoadLayout:
    """Dimensions of the road network (metres, local frame)."""

    xs: tuple[float, ...] = (0.0,)
    ys: tuple[float, ...] = (0.0,)
    extent: float = 170.0
    lane_width: float = 3.5
    lanes_per_direction: int = 2
    walkway_width: float = 4.0
    curb_height: float = 0.15
    paint_width: float = 0.15
    edge_line_inset: float = 0.3
    crosswalk_gap: float = 0.5
    crosswalk_width: float = 3.0
    stop_depth: float = 2.0
    carpark: tuple[float, float, float, float] = (22.0, 78.0, -62.0, -18.0)
    driveway: tuple[float, float] = (44.0, 50.0)

    @property
    def half_width(self) -> float:
        """Curb-to-centre distance of a road."""
        return self.lane_width * self.lanes_per_direction

    @property
    def walk_outer(self) -> float:
        """Centre-to-outer-walkway-edge distance."""
        return self.half_width + self.walkway_width

    @property
    def approach(self) -> float:
        """Distance from an intersection centre to where painted lanes start (after the crosswalk)."""
        return self.half_width + self.crosswalk_gap + self.crosswalk_width + self.crosswalk_gap

    def bounds(self) -> tuple[float, float, float, float]:
        """Ground extent (xmin, xmax, ymin, ymax)."""
        return (min(self.xs) - self.extent, max(self.xs) + self.extent,
                min(self.ys) - self.extent, max(self.ys) + self.extent)


@dataclass
class RoadNetwork:
    """Shapely geometry of the network in the local frame, and the map layers built from it."""

    layout: RoadLayout
    road_segments: list = field(default_factory=list)
    intersections: list = field(default_factory=list)
    lanes: list = field(default_factory=list)  # (polygon, heading rad, road key, lane index 0 = leftmost)
    crosswalks: list = field(default_factory=list)
    stop_polygons: list = field(default_factory=list)
    boundaries: list = field(default_factory=list)
    walkways: object = None
    carpark: object = None
    driveway: object = None

    @property
    def drivable(self):
        """Union of road segments, intersections, generic drivable areas and carparks (devkit DRIVABLE_AREA)."""
        return shapely.union_all(self.road_segments + self.intersections + [self.driveway, self.carpark])

    @property
    def paint(self):
        """Union of the painted strips (boundaries buffered by paint_width / 2 with flat caps)."""
        half = self.layout.paint_width / 2.0
        return shapely.union_all([line.buffer(half, cap_style="flat", join_style="mitre") for line in self.boundaries])


def _spans(centers: tuple[float, ...], lo: float, hi: float, gap: float) -> list[tuple[float, float]]:
    """Intervals of [lo, hi] left between squares of half size `gap` around each centre."""
    cuts = sorted(centers)
    edges = [lo] + [v for c in cuts for v in (c - gap, c + gap)] + [hi]
    return [(edges[i], edges[i + 1]) for i in range(0, len(edges), 2)]


def build_network(layout: RoadLayout) -> RoadNetwork:
    """The road network of `layout` (all geometry in the local frame)."""
    net = RoadNetwork(layout)
    x_lo, x_hi, y_lo, y_hi = layout.bounds()
    hw, lw = layout.half_width, layout.lane_width
    roads = [("ew", yc, x_lo, x_hi, layout.xs) for yc in layout.ys] + [("ns", xc, y_lo, y_hi, layout.ys) for xc in layout.xs]
    for xc in layout.xs:
        for yc in layout.ys:
            net.intersections.append(box(xc - hw, yc - hw, xc + hw, yc + hw))
            for sx, sy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                near = hw + layout.crosswalk_gap
                far = near + layout.crosswalk_width
                if sx:
                    a, b = sorted((xc + sx * near, xc + sx * far))
                    net.crosswalks.append(box(a, yc - hw, b, yc + hw))
                    # incoming lanes on the east arm drive west (y > yc), on the west arm east (y < yc)
                    a, b = sorted((xc + sx * far, xc + sx * (far + layout.stop_depth)))
                    net.stop_polygons.append(box(a, yc, b, yc + hw) if sx > 0 else box(a, yc - hw, b, yc))
                else:
                    a, b = sorted((yc + sy * near, yc + sy * far))
                    net.crosswalks.append(box(xc - hw, a, xc + hw, b))
                    a, b = sorted((yc + sy * far, yc + sy * (far + layout.stop_depth)))
                    net.stop_polygons.append(box(xc - hw, a, xc, b) if sy > 0 else box(xc, a, xc + hw, b))
    for kind, c, lo, hi, crossing in roads:
        for a, b in _spans(crossing, lo, hi, hw):
            net.road_segments.append(box(a, c - hw, b, c + hw) if kind == "ew" else box(c - hw, a, c + hw, b))
            for lane in range(2 * layout.lanes_per_direction):
                off0, off1 = -hw + lane * lw, -hw + (lane + 1) * lw
                first_side = off1 <= 0  # eastbound (ew) or southbound (ns) half of the road
                poly = box(a, c + off0, b, c + off1) if kind == "ew" else box(c + off0, a, c + off1, b)
                heading = {("ew", True): 0.0, ("ew", False): np.pi, ("ns", True): -np.pi / 2, ("ns", False): np.pi / 2}[
                    (kind, bool(first_side))]
                # lane_index 0 = leftmost = nearest the road axis
                L = layout.lanes_per_direction
                index = L - 1 - lane if first_side else lane - L
                net.lanes.append((poly, heading, f"{kind}{c:+.0f}", index))
        for a, b in _spans(crossing, lo, hi, layout.approach):
            for off in _paint_offsets(layout):
                pts = [(a, c + off), (b, c + off)] if kind == "ew" else [(c + off, a), (c + off, b)]
                net.boundaries.append(LineString(pts))
    bands = []
    for kind, c, lo, hi, _ in roads:
        for sign in (-1, 1):
            a, b = sorted((c + sign * hw, c + sign * layout.walk_outer))
            bands.append(box(lo, a, hi, b) if kind == "ew" else box(a, lo, b, hi))
    xa, xb, ya, yb = layout.carpark
    net.carpark = box(xa, ya, xb, yb)
    y_road = min(layout.ys, key=lambda y: abs(y - yb))
    net.driveway = box(layout.driveway[0], yb, layout.driveway[1], y_road - hw)
    carved = shapely.union_all(net.road_segments + net.intersections + [net.driveway])
    net.walkways = shapely.union_all(bands).difference(carved)
    return net


def _paint_offsets(layout: RoadLayout) -> list[float]:
    """Lateral offsets (m, left of the road axis) of the painted lines of a road."""
    hw, lw = layout.half_width, layout.lane_width
    dividers = [k * lw for k in range(-layout.lanes_per_direction + 1, layout.lanes_per_direction)]
    return [-hw + layout.edge_line_inset] + dividers + [hw - layout.edge_line_inset]


def _polygons(geometry) -> list:
    """The polygons of a Polygon or MultiPolygon."""
    return list(getattr(geometry, "geoms", [geometry]))


def map_layers(net: RoadNetwork, origin_xy: np.ndarray) -> dict[str, MapLayer]:
    """The nuPlan vector layers of the network, translated by origin_xy into the global (UTM) frame."""
    ox, oy = float(origin_xy[0]), float(origin_xy[1])

    def layer(geoms: list, **attributes) -> MapLayer:
        moved = np.array([shapely.affinity.translate(g, ox, oy) for g in geoms], dtype=object)
        return MapLayer(moved, {k: np.asarray(v) for k, v in attributes.items()})

    lane_fids = np.arange(len(net.lanes), dtype=np.int64)
    n_b = len(net.boundaries)
    return {
        "road_segments": layer(net.road_segments),
        "intersections": layer(net.intersections, intersection_type_fid=np.ones(len(net.intersections), np.int64),
                               is_mini=np.zeros(len(net.intersections), np.int64)),
        "generic_drivable_areas": layer([net.driveway]),
        "carpark_areas": layer([net.carpark], heading=np.zeros(1)),
        "lanes_polygons": layer(
            [lane[0] for lane in net.lanes], lane_fid=lane_fids, lane_index=np.array([lane[3] for lane in net.lanes]),
            speed_limit_mps=np.full(len(net.lanes), 13.4), heading=np.array([lane[1] for lane in net.lanes])),
        "walkways": layer(_polygons(net.walkways)),
        "crosswalks": layer(net.crosswalks, is_marked=np.zeros(len(net.crosswalks), np.int64)),
        "boundaries": layer(net.boundaries, boundary_type_fid=np.full(n_b, 2, np.int64),
                            has_reflectors=np.zeros(n_b, np.int64)),
        "stop_polygons": layer(net.stop_polygons, stop_polygon_type_fid=np.full(len(net.stop_polygons), 2, np.int64)),
    }
