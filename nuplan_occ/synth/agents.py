"""Objects of a synthetic world that carry boxes: moving agents and static box objects (local frame).

Every agent has an upright box (length along its heading, width, height) whose bottom rests on the ground
under its reference point, a solid shape inside that box made of cuboid parts (by kind, `shape_parts`), a
semantic id (its box category) and an instance id (1..K). Moving agents follow a `Path` with a `Motion`;
static ones have a fixed pose. The truth fills the agent's parts; the LiDAR sees their surfaces.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.labels import LABELS
from nuplan_occ.synth.trajectory import Motion, Path


def cuboid_triangles(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(12, 3, 3) triangles of the surface of an axis-aligned cuboid [lo, hi] (3,) (box frame, metres)."""
    x, y, z = (lo[0], hi[0]), (lo[1], hi[1]), (lo[2], hi[2])
    v = np.array([[x[i], y[j], z[k]] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    return np.array([[v[a], v[b], v[c]] for a, b, c, d in quads for a, b, c in ((a, b, c), (a, c, d))])


def shape_parts(kind: str, size: np.ndarray) -> np.ndarray:
    """(P, 2, 3) solid axis-aligned cuboid parts [lo, hi] of an object in its box frame (origin at the box
    centre, x along the heading, z up; metres). Their union is the object's solid shape: the LiDAR sees
    its surface (`mesh_template`), the truth fills it (`truth.semantic_truth`). Every part lies inside
    the box [-size/2, size/2]; kinds without a template are the whole box."""
    L, W, H = (float(v) for v in size)
    hl, hw, hh = L / 2, W / 2, H / 2
    if kind == "vehicle":
        clear, belt = 0.3 * min(1.0, H / 1.5), -hh + 0.55 * H
        wheel = min(0.35, 0.25 * H)
        parts = [((-hl, -hw, -hh + clear), (hl, hw, belt)),
                 ((-0.3 * L, -0.45 * W, belt), (0.22 * L, 0.45 * W, hh))]
        for sx in (-0.3 * L, 0.3 * L):
            for sy in (-1, 1):
                y0, y1 = sorted((sy * hw, sy * (hw - 0.25)))
                parts.append(((sx - wheel, y0, -hh), (sx + wheel, y1, -hh + clear)))
    elif kind == "pedestrian":
        parts = [((-0.6 * hl, -hw, -hh), (0.6 * hl, hw, hh - 0.28)),
                 ((-0.5 * hl, -0.5 * hw, hh - 0.28), (0.5 * hl, 0.5 * hw, hh))]
    elif kind == "bicycle":
        parts = [((-hl, -0.15 * hw, -hh), (hl, 0.15 * hw, -hh + 0.9)),
                 ((-0.3 * hl, -hw, -hh + 0.9), (0.2 * hl, hw, hh))]
    elif kind == "traffic_cone":
        tiers = [(1.0, 0.0, 0.12), (0.75, 0.12, 0.5), (0.45, 0.5, 0.8), (0.25, 0.8, 1.0)]
        parts = [((-f * hl, -f * hw, -hh + a * H), (f * hl, f * hw, -hh + b * H)) for f, a, b in tiers]
    elif kind == "czone_sign":
        parts = [((-0.1 * hl, -0.1 * hw, -hh), (0.1 * hl, 0.1 * hw, hh - 0.6)),
                 ((-hl, -hw, hh - 0.6), (hl, hw, hh))]
    else:
        parts = [((-hl, -hw, -hh), (hl, hw, hh))]
    return np.array(parts, dtype=np.float64)


def mesh_template(kind: str, size: np.ndarray) -> np.ndarray:
    """Triangles (T, 3, 3) of an object's mesh in its box frame: the surfaces of its `shape_parts`."""
    return np.concatenate([cuboid_triangles(lo, hi) for lo, hi in shape_parts(kind, size)])


@dataclass
class Agent:
    """One object with a box. category: nuPlan category name; size [length, width, height] m;
    instance: 1..K; boxed: whether the log annotates it; path/motion for moving agents, else pose
    (x, y, yaw) local; ground: height of the ground under a static agent (relative to world ground)."""

    instance: int
    category: str
    size: np.ndarray
    path: Path | None = None
    motion: Motion | None = None
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ground: float = 0.0
    boxed: bool = True

    @property
    def label(self) -> int:
        return LABELS.box_category_to_id[self.category]

    @property
    def moving(self) -> bool:
        return self.motion is not None

    def state(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Box centre (T, 3) local m (z relative to the world ground level), yaw (T,) rad, velocity (T, 3)
        m/s at times t (T,) seconds from the log start."""
        t = np.atleast_1d(np.asarray(t, np.float64))
        if self.motion is None:
            center = np.tile([self.pose[0], self.pose[1], self.ground + self.size[2] / 2], (len(t), 1))
            return center, np.full(len(t), self.pose[2]), np.zeros((len(t), 3))
        s, v, _ = self.motion.sample(t)
        xy, yaw, ground = self.path.at(s)
        center = np.concatenate([xy, (ground + self.size[2] / 2)[:, None]], axis=1)
        vel = np.stack([v * np.cos(yaw), v * np.sin(yaw), np.zeros_like(v)], axis=1)
        return center, yaw, vel


def posed_triangles(template: np.ndarray, center: np.ndarray, yaw: float) -> np.ndarray:
    """Template triangles (T, 3, 3) in the box frame -> local frame at box centre (3,) and yaw."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return np.einsum("ij,tkj->tki", R, template) + center


def posed_prisms(parts: np.ndarray, center: np.ndarray,
                 yaw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Parts (P, 2, 3) in the box frame -> upright prisms in the frame of the box centre (3,) and yaw (rad):
    (centre_xy (P, 2), half_uv (P, 2), z0 (P,), z1 (P,)) metres; every prism has the box's yaw."""
    mid, half = (parts[:, 0] + parts[:, 1]) / 2.0, (parts[:, 1] - parts[:, 0]) / 2.0
    c, s = np.cos(yaw), np.sin(yaw)
    xy = np.stack([c * mid[:, 0] - s * mid[:, 1], s * mid[:, 0] + c * mid[:, 1]], axis=1) + np.asarray(center)[:2]
    return xy, half[:, :2], center[2] + parts[:, 0, 2], center[2] + parts[:, 1, 2]
