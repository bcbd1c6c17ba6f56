"""Surface primitives of a synthetic world and their triangle meshes (pure numpy).

A `Faces` set holds upright planar rectangles in one frame (normally "local", metres):
- horizontal rectangles (z0 == z1): centre, half extents (along u = heading, along v), yaw;
- vertical faces (half_v == 0): a segment of half length half_u through the centre along yaw, swept over
  z in [z0, z1].
Each face carries a semantic id (nuplan_occ.labels) and an instance id (0 = background).
The same faces are meshed for ray casting and voxelized exactly for the truth, so both agree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Faces:
    """N upright rectangles (see module doc). Arrays: center (N,2), half (N,2), yaw (N,), z0 (N,), z1 (N,),
    label (N,) uint8, instance (N,) uint16."""

    center: np.ndarray
    half: np.ndarray
    yaw: np.ndarray
    z0: np.ndarray
    z1: np.ndarray
    label: np.ndarray
    instance: np.ndarray

    def __len__(self) -> int:
        return int(len(self.center))

    @classmethod
    def empty(cls) -> "Faces":
        return cls(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0),
                   np.zeros(0, np.uint8), np.zeros(0, np.uint16))

    @classmethod
    def concat(cls, parts: list["Faces"]) -> "Faces":
        parts = [p for p in parts if len(p)] or [cls.empty()]
        return cls(*[np.concatenate([getattr(p, f) for p in parts]) for f in
                     ("center", "half", "yaw", "z0", "z1", "label", "instance")])

    def subset(self, keep: np.ndarray) -> "Faces":
        return Faces(self.center[keep], self.half[keep], self.yaw[keep], self.z0[keep], self.z1[keep],
                     self.label[keep], self.instance[keep])

    def moved(self, rotation_yaw: float, translation: np.ndarray) -> "Faces":
        """The faces after a yaw rotation about +z then a translation (3,) (a yaw-only rigid transform)."""
        c, s = np.cos(rotation_yaw), np.sin(rotation_yaw)
        xy = np.einsum("ij,nj->ni", np.array([[c, -s], [s, c]]), self.center) + np.asarray(translation[:2], np.float64)
        dz = float(translation[2])
        return Faces(xy, self.half, self.yaw + rotation_yaw, self.z0 + dz, self.z1 + dz, self.label, self.instance)

    def triangles(self) -> np.ndarray:
        """(2N, 3, 3) triangles of the faces (two per face, same order as the faces)."""
        u = np.stack([np.cos(self.yaw), np.sin(self.yaw)], axis=1)
        v = np.stack([-u[:, 1], u[:, 0]], axis=1)
        flat = self.z0 == self.z1
        a = self.half[:, :1] * u
        b = self.half[:, 1:] * v
        corners = np.zeros((len(self), 4, 3))
        for k, (su, sv) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1))):
            corners[:, k, :2] = self.center + su * a + sv * b
            corners[:, k, 2] = self.z0
        # vertical faces: corners 0/1 at the segment ends (bottom), 2/3 the same ends at the top
        seg0, seg1 = self.center - a, self.center + a
        vertical = ~flat
        corners[vertical, 0, :2], corners[vertical, 1, :2] = seg0[vertical], seg1[vertical]
        corners[vertical, 2, :2], corners[vertical, 3, :2] = seg1[vertical], seg0[vertical]
        corners[vertical, 2, 2] = corners[vertical, 3, 2] = self.z1[vertical]
        tris = np.stack([corners[:, [0, 1, 2]], corners[:, [0, 2, 3]]], axis=1)
        return tris.reshape(-1, 3, 3)


def faces(center, half, yaw, z0, z1, label, instance=0) -> Faces:
    """Faces from array-likes (scalars broadcast)."""
    center = np.asarray(center, np.float64).reshape(-1, 2)
    n = len(center)
    return Faces(center, np.broadcast_to(np.asarray(half, np.float64), (n, 2)).copy(),
                 np.broadcast_to(np.asarray(yaw, np.float64), (n,)).copy(),
                 np.broadcast_to(np.asarray(z0, np.float64), (n,)).copy(),
                 np.broadcast_to(np.asarray(z1, np.float64), (n,)).copy(),
                 np.broadcast_to(np.asarray(label, np.uint8), (n,)).copy(),
                 np.broadcast_to(np.asarray(instance, np.uint16), (n,)).copy())


def box_surfaces(center_xy, length: float, width: float, yaw: float, z0: float, z1: float, label: int,
                 instance: int = 0, top: bool = True) -> Faces:
    """The 4 side faces (and the top) of an upright box: centre (2,), length along yaw, width across."""
    c = np.asarray(center_xy, np.float64)
    u = np.array([np.cos(yaw), np.sin(yaw)])
    v = np.array([-u[1], u[0]])
    centers = [c + v * width / 2, c - v * width / 2, c + u * length / 2, c - u * length / 2]
    halves = [(length / 2, 0.0)] * 2 + [(width / 2, 0.0)] * 2
    yaws = [yaw, yaw, yaw + np.pi / 2, yaw + np.pi / 2]
    sides = Faces.concat([faces(cc, hh, yy, z0, z1, label, instance) for cc, hh, yy in zip(centers, halves, yaws)])
    if not top:
        return sides
    return Faces.concat([sides, faces(c, (length / 2, width / 2), yaw, z1, z1, label, instance)])


def split_long(center: np.ndarray, half: np.ndarray, max_ratio: float = 4.0, min_len: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Split axis-aligned rectangles (centre (N,2), half extents (N,2) along x, y) into pieces whose long
    side is at most max(min_len, max_ratio * short side), so their rotated bounding boxes stay tight."""
    out_c, out_h = [], []
    for (cx, cy), (hx, hy) in zip(center, half):
        long_axis = 0 if hx >= hy else 1
        long_h, short_h = (hx, hy) if long_axis == 0 else (hy, hx)
        limit = max(min_len, max_ratio * 2 * short_h)
        parts = max(1, int(np.ceil(2 * long_h / limit)))
        edges = np.linspace(-long_h, long_h, parts + 1)
        mids, halves = (edges[:-1] + edges[1:]) / 2, (edges[1:] - edges[:-1]) / 2
        for m, hh in zip(mids, halves):
            out_c.append((cx + m, cy) if long_axis == 0 else (cx, cy + m))
            out_h.append((hh, hy) if long_axis == 0 else (hx, hh))
    return np.array(out_c).reshape(-1, 2), np.array(out_h).reshape(-1, 2)
