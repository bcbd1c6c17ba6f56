"""The ray-casting LiDAR baseline: 5 LiDARs cast against the occupied voxels of a semantic grid.

Frames: rays, origins and returned points are in the ego frame (nuPlan rear axle, x forward, y left,
z up, metres). Written sweeps use the ego frame as their "lidar" frame (identity ego_from_lidar: a reader
that applies the log's lidar extrinsic, as nuPlan's devkit does, then gets ego coordinates), so
`PointCloud.frame == "lidar"` holds ego coordinates.

The rig (`default_lidar_rig`, our own choice: nuPlan publishes no per-LiDAR extrinsics):
    lidar_info 0 top            (1.52,  0.00, 1.90) m, yaw   0 deg, 64 beams -25..+15 deg, 360 deg
    lidar_info 1 right A-pillar (2.20, -0.95, 1.55) m, yaw -60 deg, 40 beams -30..+10 deg, 180 deg
    lidar_info 2 left A-pillar  (2.20,  0.95, 1.55) m, yaw  60 deg, 40 beams -30..+10 deg, 180 deg
    lidar_info 3 back           (-1.10, 0.00, 1.00) m, yaw 180 deg, 40 beams -30..+10 deg, 180 deg
    lidar_info 4 front          (3.90,  0.00, 0.70) m, yaw   0 deg, 40 beams -30..+10 deg, 180 deg
Beams are evenly spaced in elevation; azimuth steps: 1024 over 360 deg, 512 over 180 deg, times `density`.
Each ray is cast with open3d's RaycastingScene against a mesh of the exposed voxel faces (faces between
an occupied voxel and an empty or outside neighbour), so hits are exact on the voxel boundaries.
Intensity of a hit (our model): reflectivity(label) * |cos(incidence)|, in [0, 1].

`SensorEffects` turns the ideal caster into a stand-in "real" sensor (range noise, incidence-dependent
ray drop, a mounting error): the occupancy dataset carries no LiDAR sweeps, so benches compare against it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import open3d as o3d

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.io.pcd import encode_pcd
from nuplan_occ.io.types import LIDAR_NAMES, PointCloud
from nuplan_occ.labels import (BARRIER, EMPTY, OTHER_GROUND, PEDESTRIAN, ROAD, ROAD_LINE, TRAFFIC_CONE, VEHICLE)

REFLECTIVITY = np.full(256, 0.3)
REFLECTIVITY[[ROAD, OTHER_GROUND]] = 0.15
REFLECTIVITY[ROAD_LINE] = 0.8
REFLECTIVITY[VEHICLE] = 0.5
REFLECTIVITY[[TRAFFIC_CONE, BARRIER]] = 0.7
REFLECTIVITY[PEDESTRIAN] = 0.25
"""Label id -> surface reflectivity in [0, 1] used by the intensity model."""


@dataclass(frozen=True)
class LidarSpec:
    """One LiDAR: lidar_info id, mounting (position_ego (3,) m, yaw deg about +z), beam elevations (deg,
    ring 0 = lowest), azimuth field (deg, centred on the yaw) and steps, min / max range (m)."""

    lidar_info: int
    position_ego: tuple[float, float, float]
    yaw_deg: float
    elevations_deg: tuple[float, ...]
    azimuth_fov_deg: float
    azimuth_steps: int
    min_range: float = 1.0
    max_range: float = 80.0

    @property
    def name(self) -> str:
        return LIDAR_NAMES[self.lidar_info]

    @property
    def shape(self) -> tuple[int, int]:
        """(beams, azimuth steps) of the sensor's range image."""
        return len(self.elevations_deg), self.azimuth_steps

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """(origin (3,) m, unit directions (beams, steps, 3)) in the ego frame. Azimuth steps run
        counter-clockwise from yaw - fov/2 (a 360 deg sensor: index 0 looks backwards, steps // 2 along yaw)."""
        elev = np.radians(np.asarray(self.elevations_deg))
        half = np.radians(self.azimuth_fov_deg) / 2.0
        full = self.azimuth_fov_deg >= 360.0
        az = np.radians(self.yaw_deg) + (np.linspace(-half, half, self.azimuth_steps, endpoint=not full))
        el, a = np.meshgrid(elev, az, indexing="ij")
        dirs = np.stack([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)], axis=-1)
        return np.asarray(self.position_ego, dtype=np.float64), dirs


def default_lidar_rig(density: float = 1.0) -> list[LidarSpec]:
    """The 5-LiDAR rig of the module docstring; density scales the azimuth steps."""
    top = tuple(np.linspace(-25.0, 15.0, 64))
    side = tuple(np.linspace(-30.0, 10.0, 40))
    n360, n180 = max(8, int(round(1024 * density))), max(4, int(round(512 * density)))
    return [
        LidarSpec(0, (1.52, 0.0, 1.90), 0.0, top, 360.0, n360),
        LidarSpec(1, (2.20, -0.95, 1.55), -60.0, side, 180.0, n180),
        LidarSpec(2, (2.20, 0.95, 1.55), 60.0, side, 180.0, n180),
        LidarSpec(3, (-1.10, 0.0, 1.00), 180.0, side, 180.0, n180),
        LidarSpec(4, (3.90, 0.0, 0.70), 0.0, side, 180.0, n180),
    ]


# The 6 faces of a unit cube: (neighbour offset, 4 corners in counter-clockwise order seen from outside)
_FACES = [
    ((-1, 0, 0), [(0, 0, 0), (0, 0, 1), (0, 1, 1), (0, 1, 0)]),
    ((1, 0, 0), [(1, 0, 0), (1, 1, 0), (1, 1, 1), (1, 0, 1)]),
    ((0, -1, 0), [(0, 0, 0), (1, 0, 0), (1, 0, 1), (0, 0, 1)]),
    ((0, 1, 0), [(0, 1, 0), (0, 1, 1), (1, 1, 1), (1, 1, 0)]),
    ((0, 0, -1), [(0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 0)]),
    ((0, 0, 1), [(0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]),
]


def exposed_faces(semantics: np.ndarray, grid: GridSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangle mesh of the occupied voxels' exposed faces.

    Returns (vertices (V, 3) m in the ego frame, triangles (F, 3) uint32, label of each triangle (F,) uint8).
    """
    occ = semantics != EMPTY
    padded = np.pad(occ, 1)
    verts, labels = [], []
    for offset, corners in _FACES:
        shifted = padded[tuple(slice(1 + o, padded.shape[a] - 1 + o) for a, o in enumerate(offset))]
        idx = np.argwhere(occ & ~shifted)
        quad = idx[:, None, :] + np.asarray(corners)[None]  # (n, 4, 3) corner indices
        verts.append(grid.lower + quad.reshape(-1, 3) * grid.voxel_size)
        labels.append(semantics[tuple(idx.T)])
    vertices = np.concatenate(verts)
    n_quads = len(vertices) // 4
    base = np.arange(n_quads)[:, None] * 4
    triangles = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=1).reshape(-1, 3)
    return vertices, triangles.astype(np.uint32), np.repeat(np.concatenate(labels), 2).astype(np.uint8)


class VoxelRaycaster:
    """Exact ray casting against the occupied voxels of `semantics` (indexed [x, y, z] on `grid`)."""

    def __init__(self, semantics: np.ndarray, grid: GridSpec = DEFAULT_GRID):
        if semantics.shape != grid.shape:
            raise ValueError(f"semantics has shape {semantics.shape}, grid expects {grid.shape}")
        vertices, triangles, self.labels = exposed_faces(np.asarray(semantics), grid)
        self.scene = o3d.t.geometry.RaycastingScene()
        if len(triangles):
            self.scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles))

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays origins (R, 3), unit dirs (R, 3) (ego frame) -> (range t (R,) m, inf on a miss;
        label (R,) uint8, EMPTY on a miss; surface normal (R, 3))."""
        rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
        ans = self.scene.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        prim = ans["primitive_ids"].numpy()
        hit = np.isfinite(t)
        label = np.zeros(len(t), dtype=np.uint8)
        label[hit] = self.labels[prim[hit]]
        return t, label, ans["primitive_normals"].numpy().astype(np.float64)


@dataclass(frozen=True)
class SensorEffects:
    """Imperfections of a stand-in real sensor: Gaussian range noise (m), ray drop probability
    drop_base + drop_grazing * (1 - |cos incidence|)^2, and a mounting error (m, deg of yaw) drawn once
    per sensor from `seed`."""

    range_noise_m: float = 0.03
    drop_base: float = 0.05
    drop_grazing: float = 0.6
    mount_error_m: float = 0.05
    mount_error_deg: float = 0.5
    seed: int = 0
    rng: np.random.Generator = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "rng", np.random.default_rng(self.seed))


@dataclass
class RangeImage:
    """One LiDAR's returns on its (beams, steps) grid, ego frame: origin (3,), dirs (B, A, 3), range
    (B, A) m with NaN where no return, intensity (B, A), label (B, A) uint8."""

    spec: LidarSpec
    origin: np.ndarray
    dirs: np.ndarray
    range: np.ndarray
    intensity: np.ndarray
    label: np.ndarray


def scan(caster: VoxelRaycaster, spec: LidarSpec, effects: SensorEffects | None = None) -> RangeImage:
    """Cast one LiDAR's rays (optionally through `effects`, which then also moves the sensor)."""
    origin, dirs = spec.rays()
    if effects is not None:
        rng = effects.rng
        origin = origin + rng.normal(0.0, effects.mount_error_m, 3)
        yaw = np.radians(rng.normal(0.0, effects.mount_error_deg))
        c, s = np.cos(yaw), np.sin(yaw)
        dirs = dirs @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # rotate about +z by yaw
    flat = dirs.reshape(-1, 3)
    t, label, normal = caster.cast(np.broadcast_to(origin, flat.shape), flat)
    ok = np.isfinite(t) & (t >= spec.min_range) & (t <= spec.max_range)
    cos_inc = np.abs((normal * flat).sum(1))
    if effects is not None:
        rng = effects.rng
        t = t + rng.normal(0.0, effects.range_noise_m, len(t))
        p_drop = effects.drop_base + effects.drop_grazing * (1.0 - cos_inc) ** 2
        ok &= rng.random(len(t)) >= p_drop
    intensity = np.where(ok, REFLECTIVITY[label] * cos_inc, np.nan)
    return RangeImage(spec, origin, dirs, np.where(ok, t, np.nan).reshape(spec.shape),
                      intensity.reshape(spec.shape), np.where(ok, label, EMPTY).reshape(spec.shape).astype(np.uint8))


def to_point_cloud(images: list[RangeImage]) -> PointCloud:
    """Returns of range images as one merged sweep (frame "lidar" = ego, ring = beam index)."""
    parts = []
    for img in images:
        beam, _ = np.nonzero(np.isfinite(img.range))
        ok = np.isfinite(img.range)
        xyz = img.origin + img.dirs[ok] * img.range[ok][:, None]
        parts.append((xyz, img.intensity[ok], beam, np.full(len(xyz), img.spec.lidar_info)))
    xyz, inten, ring, info = (np.concatenate([p[k] for p in parts]) if parts else np.zeros(0) for k in range(4))
    return PointCloud(xyz=xyz.reshape(-1, 3), intensity=inten.astype(np.float32), ring=ring.astype(np.int16),
                      lidar_info=info.astype(np.int8), frame="lidar")


def raycast_sweep(
    semantics: np.ndarray, grid: GridSpec = DEFAULT_GRID, rig: list[LidarSpec] | None = None,
    effects: SensorEffects | None = None,
) -> PointCloud:
    """The baseline sweep of one grid: every LiDAR of `rig` (default: `default_lidar_rig()`)."""
    caster = VoxelRaycaster(semantics, grid)
    return to_point_cloud([scan(caster, spec, effects) for spec in (rig or default_lidar_rig())])


def write_sweep(path: str | Path, cloud: PointCloud) -> None:
    """Write a sweep as a nuPlan-format binary PCD (fields x y z intensity ring lidar_info)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_bytes(encode_pcd(cloud))
