"""One frame's 4-DoF point-to-plane ICP against a track's model, compiled (numba): the inner loop of
`track_refine.register_frame`, which runs once per frame of every track and round (tens of thousands of
small registrations per scene, where numpy's per-call overhead dominated).

Frames and units as in `nuplan_occ.tracks.track_refine`: points in their frame's box frame, the model in the
model frame, a correction (dx, dy, dz, dyaw) in metres and radians, p_model = Rz(dyaw) p_box + (dx, dy, dz).
Sums run in a fixed order: the result is identical run to run.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from nuplan_occ.points.knn import search_nearest


@numba.njit(cache=True)
def icp_4dof(points_box: np.ndarray, frame_id: int, model_points: np.ndarray, model_normals: np.ndarray,
             model_frame_ids: np.ndarray, tree: tuple, start: np.ndarray, prior: np.ndarray, k: int, iterations: int,
             max_distance_m: float, huber_m: float, min_points: int) -> np.ndarray:
    """Correction (4,) of one frame from `start` (4,): each iteration matches every point (moved by the
    current correction) to the mean of its k nearest model points within max_distance_m that come from
    other frames than frame_id, with the normal of the nearest of them, and takes one Gauss-Newton step of
    the Huber-weighted (scale huber_m) point-to-plane residuals plus the Gaussian prior (4,) (inverse
    variances, pulling the correction toward 0). Stops after `iterations`, when fewer than min_points
    points have a match, or when a step moves less than 1e-4 m and 1e-5 rad.
    tree: `KdTree.kernel_arrays` of model_points (n, 3); model_normals (n, 3); model_frame_ids (n,)."""
    ordered, order, tstart, tend, child, lo, hi = tree
    n = len(points_box)
    c = start.copy()
    moved = np.empty((n, 3))
    query_order = np.arange(n)
    for _ in range(iterations):
        cs, sn = math.cos(c[3]), math.sin(c[3])
        for i in range(n):
            x, y, z = points_box[i, 0], points_box[i, 1], points_box[i, 2]
            moved[i, 0] = cs * x - sn * y + c[0]
            moved[i, 1] = sn * x + cs * y + c[1]
            moved[i, 2] = z + c[2]
        dist, idx = search_nearest(ordered, order, tstart, tend, child, lo, hi, moved, query_order, k,
                                   max_distance_m * max_distance_m)
        H = np.zeros((4, 4))
        g = np.zeros(4)
        matched = 0
        for i in range(n):
            qx = qy = qz = 0.0
            count = 0
            nearest = -1
            for j in range(k):
                if not math.isfinite(dist[i, j]) or model_frame_ids[idx[i, j]] == frame_id:
                    continue
                m = idx[i, j]
                if nearest < 0:
                    nearest = m
                qx += model_points[m, 0]
                qy += model_points[m, 1]
                qz += model_points[m, 2]
                count += 1
            if count == 0:
                continue
            matched += 1
            px, py, pz = moved[i, 0], moved[i, 1], moved[i, 2]
            nx, ny, nz = model_normals[nearest, 0], model_normals[nearest, 1], model_normals[nearest, 2]
            r = nx * (px - qx / count) + ny * (py - qy / count) + nz * (pz - qz / count)
            w = min(1.0, huber_m / max(abs(r), 1e-12)) / (huber_m * huber_m)
            J = (nx, ny, nz, ny * px - nx * py)
            for a in range(4):
                g[a] += w * J[a] * r
                for b in range(4):
                    H[a, b] += w * J[a] * J[b]
        if matched < min_points:
            break
        for a in range(4):
            H[a, a] += prior[a]
            g[a] += prior[a] * c[a]
        step = -np.linalg.solve(H, g)
        cs, sn = math.cos(step[3]), math.sin(step[3])
        x, y = c[0], c[1]
        c[0] = cs * x - sn * y + step[0]
        c[1] = sn * x + cs * y + step[1]
        c[2] = c[2] + step[2]
        c[3] = c[3] + step[3]
        if max(abs(step[0]), abs(step[1]), abs(step[2])) < 1e-4 and abs(step[3]) < 1e-5:
            break
    return c
