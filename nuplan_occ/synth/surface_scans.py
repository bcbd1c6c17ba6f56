"""Synthetic LiDAR scenes with known surfaces, for tests and the benchmark (frame "scene", metres).

A street scene: ground (z = 0) with raised sidewalks (curb step `curb` m) along two crossing
streets, building blocks in the four quadrants, car-like boxes parked at the curbs. A spinning
LiDAR (32 beams over -25..+10 degrees) drives along both streets at `sensor_height`; rays are
cast with Open3D's RaycastingScene, with Gaussian range noise. The truth surface is the
noise-free return set of a denser scan from the same poses (the observable surface).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d


@dataclass(frozen=True)
class SyntheticScan:
    """points (N, 3) and their sensor origins (N, 3) in "scene" metres, truth_points (M, 3) dense
    noise-free samples of the observed surface, mesh = the scene's triangles (vertices, faces)."""

    points: np.ndarray
    origins: np.ndarray
    truth_points: np.ndarray
    mesh: tuple[np.ndarray, np.ndarray]


def _box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> o3d.geometry.TriangleMesh:
    size = np.subtract(hi, lo)
    mesh = o3d.geometry.TriangleMesh.create_box(*size)
    return mesh.translate(lo)


def street_mesh(half: float, street_half_width: float = 6.0, curb: float = 0.15, seed: int = 0) -> o3d.geometry.TriangleMesh:
    """Triangle mesh of a crossing of two streets over [-half, half]^2 metres."""
    rng = np.random.default_rng(seed)
    w = street_half_width
    parts = [_box((-half, -half, -1.0), (half, half, 0.0))]
    for sx in (-1, 1):
        for sy in (-1, 1):
            x0, x1 = sorted((sx * w, sx * half))
            y0, y1 = sorted((sy * w, sy * half))
            parts.append(_box((x0, y0, -1.0), (x1, y1, curb)))
            setback = 3.0
            bx0, bx1 = sorted((sx * (w + setback), sx * half))
            by0, by1 = sorted((sy * (w + setback), sy * half))
            parts.append(_box((bx0, by0, curb), (bx1, by1, curb + rng.uniform(6.0, 14.0))))
    for x in np.arange(-half + 8.0, half - 8.0, 14.0):
        if abs(x) < w + 3:
            continue
        y = w - 1.1 if rng.random() < 0.5 else -(w - 1.1)
        parts.append(_box((x - 2.3, y - 0.9, 0.3), (x + 2.3, y + 0.9, 1.1)))
        parts.append(_box((x - 1.2, y - 0.8, 1.1), (x + 1.0, y + 0.8, 1.6)))
    mesh = parts[0]
    for part in parts[1:]:
        mesh += part
    return mesh


def _cast(scene: o3d.t.geometry.RaycastingScene, origins: np.ndarray, beams: int, azimuths: int, max_range: float) -> tuple[np.ndarray, np.ndarray]:
    elevation = np.deg2rad(np.linspace(-25.0, 10.0, beams))
    azimuth = np.linspace(0, 2 * np.pi, azimuths, endpoint=False)
    el, az = np.meshgrid(elevation, azimuth, indexing="ij")
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)
    rays = np.concatenate([np.repeat(origins, len(dirs), axis=0), np.tile(dirs, (len(origins), 1))], axis=1)
    hit = scene.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))
    t = hit["t_hit"].numpy().astype(np.float64)
    ok = np.isfinite(t) & (t < max_range)
    return rays[ok, :3], rays[ok, 3:], t[ok]


def street_scan(
    half: float = 20.0,
    sweeps_per_street: int = 6,
    beams: int = 32,
    azimuths: int = 1024,
    noise: float = 0.02,
    sensor_height: float = 1.8,
    seed: int = 0,
) -> SyntheticScan:
    """Scan of `street_mesh(half)` from sensors along both streets (x and y axes)."""
    rng = np.random.default_rng(seed)
    mesh = street_mesh(half, seed=seed)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    track = np.linspace(-0.8 * half, 0.8 * half, sweeps_per_street)
    poses = np.concatenate([
        np.stack([track, rng.uniform(-1.5, 1.5, len(track)), np.full(len(track), sensor_height)], axis=1),
        np.stack([rng.uniform(-1.5, 1.5, len(track)), track, np.full(len(track), sensor_height)], axis=1),
    ])
    max_range = 2.0 * half
    origins, dirs, t = _cast(scene, poses, beams, azimuths, max_range)
    t = t + rng.normal(0.0, noise, len(t))
    dense_origins, dense_dirs, dense_t = _cast(scene, poses, 3 * beams, 2 * azimuths, max_range)
    truth = dense_origins + dense_dirs * dense_t[:, None]
    verts = np.asarray(mesh.vertices)
    faces = np.asarray(mesh.triangles).astype(np.int64)
    return SyntheticScan(points=origins + dirs * t[:, None], origins=origins, truth_points=truth, mesh=(verts, faces))
