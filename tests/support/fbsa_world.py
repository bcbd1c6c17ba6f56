"""A small analytic street for the FBSA tests: flat ground (z = 0 in the truth "global" frame), building blocks
with gaps, poles, parked cars, one kiosk at an angle, one car driving the other way and a walking pedestrian.
Sweeps are ray-cast analytically (ground plane + oriented boxes) from known true ego poses.

Frames: "global" = truth world (metres); "ego" = rear axle of the ego car (x forward, z up, z = 0 on the road).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.geometry import invert_transform, make_transform, rotation_from_euler, transform_points, yaw_matrix
from nuplan_occ.io.types import Boxes, PointCloud

SENSOR_EGO = np.array([1.3, 0.0, 1.9])
"""LiDAR origin in the ego frame (m)."""

GROUND = -1
"""Instance id of ground points."""


@dataclass
class World:
    """Static boxes (global frame) and the two movers. Instance ids: index into `static` for static boxes,
    len(static) for the moving car, len(static) + 1 for the pedestrian."""

    static_centers: np.ndarray
    static_sizes: np.ndarray
    static_yaws: np.ndarray
    static_labels: list[str]
    car_size: np.ndarray
    ped_size: np.ndarray

    @property
    def car_id(self) -> int:
        return len(self.static_centers)

    @property
    def ped_id(self) -> int:
        return len(self.static_centers) + 1

    def movers(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centres (2, 3), sizes (2, 3), yaws (2,) of the moving car and the pedestrian at time t (s), global."""
        car = np.array([40.0 - 8.0 * t, -3.5, self.car_size[2] / 2])
        ped = np.array([8.0 + 1.2 * t, 7.5, self.ped_size[2] / 2])
        return np.stack([car, ped]), np.stack([self.car_size, self.ped_size]), np.array([np.pi, 0.0])


def make_world(seed: int = 0) -> World:
    rng = np.random.default_rng(seed)
    centers, sizes, yaws, labels = [], [], [], []

    def add(center, size, yaw, label):
        centers.append(center)
        sizes.append(size)
        yaws.append(yaw)
        labels.append(label)

    for side in (-1.0, 1.0):
        x = -60.0
        while x < 110.0:
            length, height = rng.uniform(8, 16), rng.uniform(5, 14)
            depth = rng.uniform(6, 10)
            add([x + length / 2, side * (12.0 + depth / 2 + rng.uniform(0, 2)), height / 2], [length, depth, height],
                rng.uniform(-0.05, 0.05), "building")
            x += length + rng.uniform(3, 6)
        for x in np.arange(-50.0, 100.0, 9.0) + rng.uniform(0, 3):
            add([x, side * 9.0, 2.5], [0.3, 0.3, 5.0], 0.0, "pole")
        for x in np.arange(-40.0, 95.0, 17.0) + rng.uniform(0, 6):
            add([x, side * 6.2, 0.75], [4.5, 1.9, 1.5], rng.uniform(-0.1, 0.1), "parked")
    add([25.0, 10.0, 1.5], [3.0, 2.0, 3.0], np.deg2rad(35.0), "kiosk")
    return World(np.array(centers, float), np.array(sizes, float), np.array(yaws, float), labels,
                 np.array([4.6, 1.9, 1.6]), np.array([0.6, 0.6, 1.8]))


def true_poses(n_frames: int, dt: float = 0.1, speed: float = 10.0) -> np.ndarray:
    """(F, 4, 4) T_global_from_ego along a gently weaving path on the flat ground."""
    t = np.arange(n_frames) * dt
    x, y = speed * t, 1.0 * np.sin(0.4 * t)
    yaw = np.arctan2(0.4 * np.cos(0.4 * t), speed)
    return np.stack([make_transform(yaw_matrix(a), [xi, yi, 0.0]) for a, xi, yi in zip(yaw, x, y)])


def noisy_log(truth: np.ndarray, sigma_t: float = 0.3, sigma_deg: float = 1.0, z_drift: float = 0.3,
              seed: int = 1) -> np.ndarray:
    """Logged poses: truth with white noise (sigma_t m per horizontal axis, sigma_deg on yaw, a quarter of it
    on roll/pitch, sigma_t / 4 on z) plus a slow z drift running linearly from -z_drift/2 to +z_drift/2."""
    rng = np.random.default_rng(seed)
    out = np.empty_like(truth)
    drift = np.linspace(-z_drift / 2, z_drift / 2, len(truth))
    for i, T in enumerate(truth):
        roll, pitch = np.deg2rad(rng.normal(0, sigma_deg / 4, 2))
        R = rotation_from_euler(roll, pitch, np.deg2rad(rng.normal(0, sigma_deg))) @ T[:3, :3]
        dt = np.array([rng.normal(0, sigma_t), rng.normal(0, sigma_t), rng.normal(0, sigma_t / 4) + drift[i]])
        out[i] = make_transform(R, T[:3, 3] + dt)
    return out


def _ray_boxes(origin: np.ndarray, dirs: np.ndarray, centers, sizes, yaws) -> tuple[np.ndarray, np.ndarray]:
    """Distance along each ray (R,) to the first box hit (inf if none) and that box's index (-1)."""
    best = np.full(len(dirs), np.inf)
    which = np.full(len(dirs), -1)
    for k, (c, s, a) in enumerate(zip(centers, sizes, yaws)):
        R = yaw_matrix(a)
        o = R.T @ (origin - c)
        d = dirs @ R
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-s / 2 - o) / d, (s / 2 - o) / d
        t_near = np.nanmax(np.minimum(t1, t2), axis=1)
        t_far = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (t_far >= t_near) & (t_near > 0) & (t_near < best)
        best[hit], which[hit] = t_near[hit], k
    return best, which


def cast_sweep(world: World, T_global_from_ego: np.ndarray, t: float, rng: np.random.Generator,
               n_azimuth: int = 300, n_beams: int = 24, max_range: float = 60.0, noise_m: float = 0.01):
    """One sweep: points (N, 3) in the EGO frame and instance ids (N,) (GROUND, a static index, car_id, ped_id)."""
    elev = np.deg2rad(np.linspace(-25.0, 8.0, n_beams))
    az = np.linspace(-np.pi, np.pi, n_azimuth, endpoint=False) + rng.uniform(0, 2 * np.pi / n_azimuth)
    e, a = np.meshgrid(elev, az, indexing="ij")
    dirs_ego = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)
    R = T_global_from_ego[:3, :3]
    origin = transform_points(T_global_from_ego, SENSOR_EGO[None])[0]
    dirs = dirs_ego @ R.T
    mc, ms, my = world.movers(t)
    centers = np.vstack([world.static_centers, mc])
    sizes = np.vstack([world.static_sizes, ms])
    yaws = np.concatenate([world.static_yaws, my])
    dist, ids = _ray_boxes(origin, dirs, centers, sizes, yaws)
    with np.errstate(divide="ignore"):
        t_ground = np.where(dirs[:, 2] < 0, -origin[2] / dirs[:, 2], np.inf)
    ground = t_ground < dist
    dist = np.where(ground, t_ground, dist)
    ids = np.where(ground, GROUND, ids)
    ok = dist < max_range
    dist = dist[ok] + rng.normal(0, noise_m, ok.sum())
    pts_global = origin + dirs[ok] * dist[:, None]
    return transform_points(invert_transform(T_global_from_ego), pts_global), ids[ok]


def boxes_in_ego(world: World, T_global_from_ego: np.ndarray, t: float, with_parked: bool = True) -> Boxes:
    """Annotated boxes of the sweep (the movers and, optionally, the parked cars) in the ego frame."""
    mc, ms, my = world.movers(t)
    parked = [i for i, lab in enumerate(world.static_labels) if lab == "parked"] if with_parked else []
    centers = np.vstack([mc, world.static_centers[parked]])
    sizes = np.vstack([ms, world.static_sizes[parked]])
    yaws = np.concatenate([my, world.static_yaws[parked]])
    tokens = ["car", "ped"] + [f"parked{i}" for i in parked]
    cats = ["vehicle", "pedestrian"] + ["vehicle"] * len(parked)
    g = Boxes("global", centers, sizes, yaws, np.zeros((len(centers), 3)), cats, tokens, tokens)
    return g.transformed(invert_transform(T_global_from_ego), "ego")


def as_cloud(points_ego: np.ndarray, instance_ids: np.ndarray) -> PointCloud:
    """A PointCloud in the ego frame that carries the true instance ids in `intensity` (so they follow subsets)."""
    n = len(points_ego)
    return PointCloud(points_ego, instance_ids.astype(np.float32), np.zeros(n, np.int16), np.zeros(n, np.int8), "ego")


@dataclass
class Sequence:
    world: World
    truth: np.ndarray
    logged: np.ndarray
    clouds: list[np.ndarray]
    instance_ids: list[np.ndarray]
    times: np.ndarray


def make_sequence(n_frames: int = 30, seed: int = 0, **log_kwargs) -> Sequence:
    """Sweeps from the true poses at 10 Hz and noisy logged poses (see noisy_log)."""
    world = make_world(seed)
    truth = true_poses(n_frames)
    rng = np.random.default_rng(seed + 100)
    times = np.arange(n_frames) * 0.1
    clouds, ids = [], []
    for T, t in zip(truth, times):
        p, i = cast_sweep(world, T, t, rng)
        clouds.append(p)
        ids.append(i)
    return Sequence(world, truth, noisy_log(truth, seed=seed + 1, **log_kwargs), clouds, ids, times)
