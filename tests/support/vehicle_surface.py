"""Points on the synthetic vehicle's surface (the synth's mesh template), for the track tests."""

from __future__ import annotations

import numpy as np

from nuplan_occ.synth.agents import mesh_template


def surface_samples(rng: np.random.Generator, n: int, size: np.ndarray) -> np.ndarray:
    """(n, 3) points spread uniformly over the triangles of the `vehicle` template of size (3,) [l, w, h] m,
    box frame (origin at the box centre)."""
    tris = mesh_template("vehicle", np.asarray(size, dtype=np.float64))
    a = tris[rng.integers(len(tris), size=n)]
    u = rng.random((n, 2))
    flip = u.sum(axis=1) > 1
    u[flip] = 1 - u[flip]
    return a[:, 0] + u[:, :1] * (a[:, 1] - a[:, 0]) + u[:, 1:] * (a[:, 2] - a[:, 0])
