"""Artefacts of real merged LiDAR sweeps, added to a simulated sweep before it is written (no I/O).

Floaters (returns in the air where nothing is), multipath ghosts (a ground return seen again further along its
ray, below the road) and self-hits (returns off the ego's own roof and sides). Each is a `SynthOptions` field, off
by default. The artefacts go only into the written point cloud: the truth is computed from the clean sweep, so
it never contains them (no voxel, no observed ray). Frame: the ego frame of the TRUE pose at the sweep time.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.io.types import PACIFICA
from nuplan_occ.labels import OTHER_GROUND, ROAD, ROAD_LINE
from nuplan_occ.synth.lidar import Sweep
from nuplan_occ.synth.presets import SynthOptions

GROUND_LABELS = (ROAD, ROAD_LINE, OTHER_GROUND)
FLOATER_CLEARANCE_M = 0.5
"""Floaters lie at least this far above the ground under the ego."""
MIN_GHOST_DESCENT = 0.1
"""Ghosts come from ground returns whose ray descends at least this much per metre (shallower rays would put the
ghost tens of metres further)."""


def has_artefacts(options: SynthOptions) -> bool:
    """Whether any sensor artefact is switched on."""
    return bool(options.floater_share or options.ghost_share or options.self_hits)


def _count(share: float, n: int, rng: np.random.Generator) -> int:
    return int(rng.poisson(share * n)) if share > 0 else 0


def floaters(sweep: Sweep, share: float, ground_z: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(points (M, 3), index (M,) of the return whose ray each lies on): about share x returns placed at 15-85 % of
    a returned ray's range, kept only at least FLOATER_CLEARANCE_M above ground_z (ego-frame z of the ground)."""
    m = _count(share, len(sweep.points), rng)
    if not m:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    index = rng.integers(len(sweep.points), size=4 * m)
    points = sweep.origins[index] + (sweep.hits[index] - sweep.origins[index]) * rng.uniform(0.15, 0.85, (4 * m, 1))
    keep = np.flatnonzero(points[:, 2] >= ground_z + FLOATER_CLEARANCE_M)[:m]
    return points[keep], index[keep]


def ghosts(sweep: Sweep, share: float, depth_m: tuple[float, float], rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(points (M, 3), index (M,) of their ground return): about share x returns, each a ground return moved further
    along its ray until it lies a uniform depth_m below that return."""
    m = _count(share, len(sweep.points), rng)
    rays = sweep.hits - sweep.origins
    length = np.linalg.norm(rays, axis=1)
    descent = -rays[:, 2] / np.maximum(length, 1e-9)
    candidates = np.flatnonzero(np.isin(sweep.label, GROUND_LABELS) & (descent >= MIN_GHOST_DESCENT))
    if not m or not len(candidates):
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    index = candidates[rng.integers(len(candidates), size=m)]
    depth = rng.uniform(depth_m[0], depth_m[1], m)
    unit = rays[index] / length[index, None]
    return sweep.points[index] + unit * (depth / descent[index])[:, None], index


def self_hits(count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3) points on the ego vehicle's box (PACIFICA, ego frame): on its roof and on the upper half of its
    four sides, spread in proportion to their areas."""
    if count <= 0:
        return np.zeros((0, 3))
    center, size = PACIFICA.box_center_and_size()
    lo, hi = center - size / 2, center + size / 2
    L, W, H = size
    areas = np.array([L * W, L * H / 2, L * H / 2, W * H / 2, W * H / 2])
    face = rng.choice(5, size=count, p=areas / areas.sum())
    u = rng.random((count, 3))
    p = lo + u * size
    p[:, 2] = np.where(face == 0, hi[2], lo[2] + H / 2 + u[:, 2] * H / 2)
    p[:, 1] = np.select([face == 1, face == 2], [lo[1], hi[1]], p[:, 1])
    p[:, 0] = np.select([face == 3, face == 4], [lo[0], hi[0]], p[:, 0])
    return p


def with_artefacts(sweep: Sweep, options: SynthOptions, ground_z: float, rng: np.random.Generator) -> Sweep:
    """The sweep plus its artefacts (label and instance 0, low intensity; self-hits credited to the top LiDAR,
    the others to the LiDAR of the return they come from). ground_z: ego-frame z of the ground under the ego
    (-axle height). The sweep itself is returned when no artefact is switched on."""
    if not has_artefacts(options):
        return sweep
    f_points, f_index = floaters(sweep, options.floater_share, ground_z, rng)
    g_points, g_index = ghosts(sweep, options.ghost_share, options.ghost_depth_m, rng)
    s_points = self_hits(options.self_hits, rng)
    source = np.concatenate([f_index, g_index])
    top = np.zeros(len(s_points), np.int64)
    points = np.concatenate([f_points, g_points, s_points])
    n = len(points)
    origins = np.concatenate([sweep.origins[source], np.broadcast_to(sweep.origins[0] if len(sweep.origins) else np.zeros(3),
                                                                      (len(s_points), 3))])
    return Sweep(
        np.concatenate([sweep.origins, origins]), np.concatenate([sweep.hits, points]), np.concatenate([sweep.points, points]),
        np.concatenate([sweep.intensity, rng.uniform(0.0, 20.0, n).astype(np.float32)]),
        np.concatenate([sweep.ring, sweep.ring[source], top.astype(sweep.ring.dtype)]),
        np.concatenate([sweep.lidar_info, sweep.lidar_info[source], top.astype(sweep.lidar_info.dtype)]),
        np.concatenate([sweep.label, np.zeros(n, sweep.label.dtype)]),
        np.concatenate([sweep.instance, np.zeros(n, sweep.instance.dtype)]))
