"""Shared fixtures of the reconstruction tests: noisy analytic shapes
(all points and origins in a local "scene" frame, metres)."""

from __future__ import annotations

import numpy as np


def plane_scan(rng: np.random.Generator, size: float = 6.0, n: int = 20000, noise: float = 0.01,
               z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Points on z = `z` over [-size/2, size/2]^2 with Gaussian noise, sensor 2 m above the centre."""
    xy = rng.uniform(-size / 2, size / 2, (n, 2))
    pts = np.column_stack([xy, z + rng.normal(0, noise, n)])
    return pts, np.tile([0.0, 0.0, z + 2.0], (n, 1))


def sphere_scan(rng: np.random.Generator, radius: float = 1.5, n: int = 20000, noise: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Points on a sphere at the origin, each seen from 3 m outside along its radius."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = d * (radius + rng.normal(0, noise, (n, 1)))
    return pts, d * (radius + 3.0)


def box_scan(rng: np.random.Generator, half: np.ndarray, n_per_m2: float = 1500, noise: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Points on the 6 faces of an axis-aligned box centred at the origin (half extents `half`),
    each seen from 3 m outside its face."""
    pts, origins = [], []
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        area = 4 * half[others[0]] * half[others[1]]
        n = int(area * n_per_m2)
        for sign in (-1.0, 1.0):
            p = np.zeros((n, 3))
            p[:, others] = rng.uniform(-1, 1, (n, 2)) * half[others]
            p[:, axis] = sign * half[axis] + rng.normal(0, noise, n)
            o = p.copy()
            o[:, axis] = sign * (half[axis] + 3.0)
            pts.append(p)
            origins.append(o)
    return np.concatenate(pts), np.concatenate(origins)


def curb_scan(rng: np.random.Generator, step: float = 0.15, n: int = 30000, noise: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Road z = 0 for y < 0, sidewalk z = step for y > 0, the curb face at y = 0; 8 m x 8 m; the
    sensor is on the road side at (0, -3, 1.8)."""
    xy = rng.uniform(-4, 4, (n, 2))
    z = np.where(xy[:, 1] > 0, step, 0.0)
    n_face = n // 20
    face = np.column_stack([rng.uniform(-4, 4, n_face), np.zeros(n_face), rng.uniform(0, step, n_face)])
    pts = np.concatenate([np.column_stack([xy, z]), face])
    pts += rng.normal(0, noise, pts.shape)
    return pts, np.tile([0.0, -3.0, 1.8], (len(pts), 1))
