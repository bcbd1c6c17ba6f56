"""Static background of a synthetic world (no boxes): buildings, carpark walls, poles with signs, trees.
Everything is in the local frame, z relative to the world's ground level; label other (1), instance 0.
Buildings, walls and poles are sets of upright faces; tree crowns are hexagonal bipyramids (triangles)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import box

from nuplan_occ.labels import OTHER
from nuplan_occ.synth.ground import on_walkway
from nuplan_occ.synth.mapgen import RoadNetwork
from nuplan_occ.synth.presets import Preset
from nuplan_occ.synth.primitives import Faces, box_surfaces, faces


@dataclass
class Scenery:
    """faces: upright faces; crowns: (M, 3, 3) triangles; keepout: shapely area agents must avoid."""

    faces: Faces
    crowns: np.ndarray
    keepout: object


def frontage(net: RoadNetwork, offset: float, spacing: float, rng: np.random.Generator, jitter: float = 0.0,
             clearance: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 2) at lateral `offset` from every road axis (both sides) every `spacing` m (+- jitter),
    away from intersections, crosswalks and the driveway; with the heading (N,) of their road."""
    lay = net.layout
    x_lo, x_hi, y_lo, y_hi = lay.bounds()
    avoid = shapely.union_all(net.intersections + net.crosswalks + [net.driveway]).buffer(clearance + lay.walkway_width)
    pts, heads = [], []
    for axis, coords, lo, hi in ((0, lay.ys, x_lo, x_hi), (1, lay.xs, y_lo, y_hi)):
        for c in coords:
            for side in (-1.0, 1.0):
                along = np.arange(lo + spacing / 2, hi - spacing / 2, spacing)
                along = along + rng.uniform(-jitter, jitter, len(along))
                lateral = np.full(len(along), c + side * offset)
                xy = np.stack([along, lateral], 1) if axis == 0 else np.stack([lateral, along], 1)
                pts.append(xy)
                heads.append(np.full(len(xy), 0.0 if axis == 0 else np.pi / 2))
    xy, head = np.concatenate(pts), np.concatenate(heads)
    keep = ~shapely.intersects_xy(avoid, xy[:, 0], xy[:, 1])
    return xy[keep], head[keep]


def _buildings(net: RoadNetwork, preset: Preset, rng: np.random.Generator) -> tuple[list[Faces], list]:
    lay = net.layout
    x_lo, x_hi, y_lo, y_hi = lay.bounds()
    inner = box(x_lo + 5, y_lo + 5, x_hi - 5, y_hi - 5)
    blocked = shapely.union_all([net.drivable.buffer(2.0), net.walkways.buffer(2.0), net.carpark.buffer(4.0)])
    out, footprints = [], []
    for _ in range(preset.n_buildings * 8):
        if len(footprints) >= preset.n_buildings:
            break
        axis = int(rng.integers(2))
        road = float(rng.choice(lay.ys if axis == 0 else lay.xs))
        side = float(rng.choice([-1.0, 1.0]))
        length, depth = rng.uniform(12, 35), rng.uniform(10, 24)
        setback = lay.walk_outer + rng.uniform(2.5, 7.0)
        along = rng.uniform(*(lay.bounds()[0:2] if axis == 0 else lay.bounds()[2:4]))
        near, far = road + side * setback, road + side * (setback + depth)
        lo_l, hi_l = min(near, far), max(near, far)
        rect = box(along - length / 2, lo_l, along + length / 2, hi_l) if axis == 0 else box(lo_l, along - length / 2, hi_l, along + length / 2)
        if not inner.contains(rect) or rect.intersects(blocked) or any(rect.distance(f) < 3.0 for f in footprints):
            continue
        footprints.append(rect)
        x0, y0, x1, y1 = rect.bounds
        out.append(box_surfaces(((x0 + x1) / 2, (y0 + y1) / 2), x1 - x0, y1 - y0, 0.0, 0.0, rng.uniform(6, 30), OTHER))
    return out, footprints


def _carpark_walls(net: RoadNetwork) -> list[Faces]:
    x0, y0, x1, y1 = net.carpark.bounds
    t, h = 0.25, 1.8
    sides = [((x0 - t / 2, (y0 + y1) / 2), t, y1 - y0), ((x1 + t / 2, (y0 + y1) / 2), t, y1 - y0),
             (((x0 + x1) / 2, y0 - t / 2), x1 - x0 + 2 * t, t)]
    return [box_surfaces(c, length, width, 0.0, 0.0, h, OTHER) for c, length, width in sides]


def _crown(center: np.ndarray, radius: float, up: float, down: float, spin: float) -> np.ndarray:
    ang = spin + np.arange(6) * np.pi / 3
    ring = np.stack([center[0] + radius * np.cos(ang), center[1] + radius * np.sin(ang), np.full(6, center[2])], 1)
    top, bottom = center + [0, 0, up], center - [0, 0, down]
    tris = []
    for k in range(6):
        a, b = ring[k], ring[(k + 1) % 6]
        tris += [[a, b, top], [b, a, bottom]]
    return np.array(tris)


def build_scenery(net: RoadNetwork, preset: Preset, rng: np.random.Generator) -> Scenery:
    """Buildings along the frontages, carpark walls, street lights, sign poles and trees."""
    lay = net.layout
    parts, footprints = _buildings(net, preset, rng)
    parts += _carpark_walls(net)
    poles, _ = frontage(net, lay.half_width + 0.6, preset.pole_spacing, rng)
    for p in poles:
        parts.append(box_surfaces(p, 0.22, 0.22, 0.0, lay.curb_height, 7.5, OTHER))
    for xc in lay.xs:
        for yc in lay.ys:
            for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                p = np.array([xc + sx * (lay.half_width + 0.8), yc + sy * (lay.half_width + 0.8)])
                parts.append(box_surfaces(p, 0.1, 0.1, 0.0, lay.curb_height, 3.2, OTHER))
                parts.append(faces(p + [0.0, -0.06 * sy], (0.35, 0.0), 0.0, 2.4, 3.1, OTHER))
    trees, _ = frontage(net, lay.walk_outer - 1.2, preset.tree_spacing, rng, jitter=2.0)
    trees = trees[np.min(np.linalg.norm(trees[:, None] - poles[None], axis=2), axis=1) > 2.5] if len(poles) else trees
    crowns = []
    for p in trees:
        base = lay.curb_height if on_walkway(net, p)[0] else 0.0
        trunk = rng.uniform(2.0, 2.8)
        parts.append(box_surfaces(p, 0.3, 0.3, rng.uniform(0, np.pi / 2), base, base + trunk, OTHER, top=False))
        down = rng.uniform(0.9, 1.3)
        crowns.append(_crown(np.array([p[0], p[1], base + trunk + 0.9 * down]), rng.uniform(1.3, 2.1),
                             rng.uniform(1.5, 2.3), down, rng.uniform(0, np.pi)))
    keepout = shapely.union_all(footprints + [shapely.Point(p).buffer(0.8) for p in np.concatenate([poles, trees])])
    return Scenery(Faces.concat(parts), np.concatenate(crowns) if crowns else np.zeros((0, 3, 3)), keepout)
