"""Per-log content of a synthetic world: the ego route and the agents (local frame, seconds from log start).

Agents are drawn at random and kept only if their footprint circle never comes near the ego's or an
already accepted agent's over the log (checked every 0.25 s), so objects never interpenetrate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from nuplan_occ.io.types import PACIFICA
from nuplan_occ.synth.agents import Agent
from nuplan_occ.synth.ground import on_walkway
from nuplan_occ.synth.mapgen import RoadNetwork
from nuplan_occ.synth.presets import Preset, SynthOptions
from nuplan_occ.synth.scenery import Scenery, frontage
from nuplan_occ.synth.trajectory import Motion, Path, drive, lane_route

_ARMS = ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))
_CHECK_DT = 0.25


@dataclass
class EgoRoute:
    """The TRUE ego motion: the rear axle follows `path` with `motion`; turns taken at intersections."""

    path: Path
    motion: Motion
    turns: list[str]


def _approach_start(net: RoadNetwork, rng: np.random.Generator, distance: float, lane: int) -> tuple[np.ndarray, np.ndarray]:
    """A start point on `lane` of a random arm, `distance` m before an intersection centre, heading to it."""
    lay = net.layout
    centre = np.array([rng.choice(lay.xs), rng.choice(lay.ys)], dtype=np.float64)
    d = np.array(_ARMS[int(rng.integers(4))])
    right = np.array([d[1], -d[0]])
    return centre - d * distance + right * (lane + 0.5) * lay.lane_width, d


def _route_motion(net: RoadNetwork, start: np.ndarray, d: np.ndarray, lane: int, turns: list[str], margin: float,
                  duration: float, cruise: float, dwells: list[float], lateral_shift: float = 0.0) -> tuple[Path, Motion, list[str]]:
    route = lane_route(net.layout, start, d, lane, turns, margin, cruise * duration + 60.0)
    pts = route.points
    if lateral_shift:
        seg = np.gradient(pts, axis=0)
        seg /= np.maximum(np.linalg.norm(seg, axis=1, keepdims=True), 1e-9)
        pts = pts + lateral_shift * np.stack([seg[:, 1], -seg[:, 0]], 1)
    path = Path.through(pts, smooth=1.0)  # vehicles stay on the road: ground height 0
    stop_s = path.project(np.array(route.stop_points)) if route.stop_points else []
    stops = [(float(s), dwell) for s, dwell in zip(stop_s, dwells) if dwell > 0]
    return path, drive(path, duration, cruise, stops), route.turns


def ego_route(net: RoadNetwork, rng: np.random.Generator, duration: float) -> EgoRoute:
    """A route that approaches an intersection, stops at its stop line, turns (or not) and continues."""
    turns = [str(t) for t in rng.choice(["right", "left", "straight"], size=8, p=[0.4, 0.35, 0.25])]
    lane = 1 if turns[0] == "right" else 0
    cruise = float(rng.uniform(6.0, 8.0))
    distance = net.layout.approach + 0.5 + PACIFICA.front + cruise ** 2 / 3.5 + 1.0
    start, d = _approach_start(net, rng, distance, lane)
    dwells = [float(rng.uniform(1.0, 1.5))] + [float(rng.choice([0.0, 1.0, 2.0])) for _ in range(7)]
    path, motion, taken = _route_motion(net, start, d, lane, turns, PACIFICA.front, duration, cruise, dwells)
    return EgoRoute(path, motion, taken)


def _ego_track(ego: EgoRoute, times: np.ndarray) -> np.ndarray:
    s, _, _ = ego.motion.sample(times)
    xy, yaw, _ = ego.path.at(s)
    offset = (PACIFICA.front - PACIFICA.rear) / 2.0
    return xy + offset * np.stack([np.cos(yaw), np.sin(yaw)], 1)


def _radius(size: np.ndarray) -> float:
    return 0.5 * float(np.hypot(size[0], size[1])) + 0.4


class _Occupancy:
    """Footprint circles over time of everything accepted so far."""

    def __init__(self, times: np.ndarray, ego: EgoRoute):
        self.times = times
        self.tracks = [_ego_track(ego, times)]
        self.radii = [_radius(np.array([PACIFICA.front + PACIFICA.rear, PACIFICA.width]))]

    def try_add(self, agent: Agent) -> bool:
        center, _, _ = agent.state(self.times)
        r = _radius(agent.size)
        for track, other in zip(self.tracks, self.radii):
            if np.any(np.linalg.norm(track - center[:, :2], axis=1) < r + other):
                return False
        self.tracks.append(center[:, :2])
        self.radii.append(r)
        return True


def _vehicle_size(rng: np.random.Generator) -> np.ndarray:
    if rng.random() < 0.15:
        return np.array([rng.uniform(6.0, 8.5), rng.uniform(2.3, 2.5), rng.uniform(2.6, 3.3)])
    return np.array([rng.uniform(4.2, 5.2), rng.uniform(1.8, 2.0), rng.uniform(1.45, 1.9)])


def populate(net: RoadNetwork, scenery: Scenery, preset: Preset, options: SynthOptions, ego: EgoRoute,
             rng: np.random.Generator, duration: float) -> list[Agent]:
    """Moving vehicles, cyclists, pedestrians, parked vehicles and static box objects, instance ids 1..K."""
    lay = net.layout
    occ = _Occupancy(np.arange(0.0, duration + 1e-9, _CHECK_DT), ego)
    agents: list[Agent] = []

    def accept(agent: Agent) -> bool:
        if occ.try_add(agent):
            agents.append(agent)
            return True
        return False

    for _ in range(preset.n_vehicles * 3):
        if sum(a.category == "vehicle" and a.moving for a in agents) >= preset.n_vehicles:
            break
        lane = int(rng.integers(2))
        turns = [str(t) for t in rng.choice(["right", "left", "straight"], size=4)]
        lane = 1 if turns[0] == "right" else (0 if turns[0] == "left" else lane)
        size = _vehicle_size(rng)
        start, d = _approach_start(net, rng, float(rng.uniform(18.0, 110.0)), lane)
        dwells = [float(rng.choice([0.0, 1.5, 3.0])) for _ in range(4)]
        path, motion, _ = _route_motion(net, start, d, lane, turns, size[0] / 2, duration, float(rng.uniform(6.0, 12.0)), dwells)
        accept(Agent(0, "vehicle", size, path, motion))
    for _ in range(preset.n_cyclists * 4):
        if sum(a.category == "bicycle" for a in agents) >= preset.n_cyclists:
            break
        start, d = _approach_start(net, rng, float(rng.uniform(15.0, 90.0)), 1)
        path, motion, _ = _route_motion(net, start, d, 1, ["straight"], 1.0, duration, float(rng.uniform(3.5, 6.0)), [],
                                        lateral_shift=lay.lane_width / 2 - 0.7)
        accept(Agent(0, "bicycle", np.array([1.8, 0.7, 1.7]), path, motion))
    walk_pts, walk_head = frontage(net, lay.half_width + 2.0, 6.0, rng, clearance=-lay.walkway_width)
    for _ in range(preset.n_pedestrians * 4):
        if sum(a.category == "pedestrian" for a in agents) >= preset.n_pedestrians:
            break
        k = int(rng.integers(len(walk_pts)))
        heading = walk_head[k] + (np.pi if rng.random() < 0.5 else 0.0)
        end = walk_pts[k] + rng.uniform(25.0, 70.0) * np.array([np.cos(heading), np.sin(heading)])
        path = Path.through(np.array([walk_pts[k], end]), smooth=0.0)
        path.ground = np.where(on_walkway(net, path.xy), lay.curb_height, 0.0)
        size = np.array([rng.uniform(0.5, 0.7), rng.uniform(0.6, 0.75), rng.uniform(1.6, 1.9)])
        accept(Agent(0, "pedestrian", size, path, drive(path, duration, float(rng.uniform(1.0, 1.6)), [], accel=0.6)))
    _parked(net, preset, rng, accept)
    _static_objects(net, scenery, preset, ego, rng, accept)
    for k, agent in enumerate(agents):
        agent.instance = k + 1
    if options.unboxed_moving_object:
        movers = [a for a in agents if a.moving and a.category != "pedestrian"]
        if movers:
            track = _ego_track(ego, occ.times)
            gap = [np.min(np.linalg.norm(a.state(occ.times)[0][:, :2] - track, axis=1)) for a in movers]
            movers[int(np.argmin(gap))].boxed = False
    return agents


def _parked(net: RoadNetwork, preset: Preset, rng: np.random.Generator, accept) -> None:
    x0, y0, x1, y1 = net.carpark.bounds
    slots = [(x, y, yaw) for y, yaw in ((y0 + 3.0, np.pi / 2), (y1 - 9.0, -np.pi / 2), ((y0 + y1) / 2 - 3.0, np.pi / 2))
             for x in np.arange(x0 + 2.0, x1 - 2.0, 2.9) if y0 + 2.5 < y < y1 - 2.5]
    order = rng.permutation(len(slots))[: preset.n_parked]
    for k in sorted(order):
        x, y, yaw = slots[k]
        accept(Agent(0, "vehicle", _vehicle_size(rng), pose=(float(x), float(y), float(yaw + rng.normal(0, 0.03)))))


def _static_objects(net: RoadNetwork, scenery: Scenery, preset: Preset, ego: EgoRoute, rng: np.random.Generator, accept) -> None:
    lay = net.layout
    driven = ego.path.s <= ego.motion.s[-1] if preset.static_on_driven_route else np.ones(len(ego.path.s), bool)
    route = ego.path.xy[driven][:: max(1, int(driven.sum()) // 200)]
    kinds = preset.static_kinds
    candidates = []
    for kind in kinds:
        pts, head = frontage(net, lay.half_width + kind.inset, 3.0, rng, jitter=1.0, clearance=1.0)
        near = np.min(np.linalg.norm(pts[:, None] - route[None], axis=2), axis=1) < preset.static_route_distance_m
        candidates.append((pts[near], head[near]))
    placed = 0
    for _ in range(preset.n_static_objects * 4):
        if placed >= preset.n_static_objects:
            break
        kind = kinds[placed % len(kinds)]
        size = np.array(kind.size)
        pts, head = candidates[placed % len(kinds)]
        if not len(pts):
            continue
        k = int(rng.integers(len(pts)))
        p = pts[k]
        if shapely.intersects(scenery.keepout, shapely.Point(p).buffer(_radius(size))):
            continue
        ground = lay.curb_height if on_walkway(net, p)[0] else 0.0
        placed += accept(Agent(0, kind.category, size, pose=(float(p[0]), float(p[1]), float(head[k] + rng.normal(0, 0.2))),
                               ground=ground))
