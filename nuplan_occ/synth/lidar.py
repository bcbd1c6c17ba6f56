"""A simulated nuPlan LiDAR rig (5 sensors) ray cast against a world with open3d.

Sensors (lidar_info, mounting in the ego frame, pattern): 0 top on the roof (64 rings, 360 deg, 120 m),
1 right A-pillar and 2 left A-pillar (40 rings, 200 deg, 60 m), 3 back and 4 front (32 rings, 180 deg,
40 m). Every sensor is mounted just outside the ego vehicle's box; rays that pass through that box are
blocked (self-occlusion). All rays of a sweep are cast at the frame time (no rolling shutter).

The merged cloud is expressed in the "lidar" frame of the MergedPointCloud row, whose extrinsic
T_EGO_FROM_LIDAR is deliberately not the identity (translation [1.5185, 0, 1.6309] m, roll 0.3 deg,
pitch -0.5 deg, yaw 1.2 deg) so frame mistakes show.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import open3d as o3d

from nuplan_occ.geometry import make_transform, rotation_from_euler
from nuplan_occ.io.types import PACIFICA, PointCloud
from nuplan_occ.synth.presets import SynthOptions
from nuplan_occ.synth.voxelize import slab_interval
from nuplan_occ.synth.world import World, raycasting_scene

T_EGO_FROM_LIDAR = make_transform(rotation_from_euler(*np.radians([0.3, -0.5, 1.2])), [1.5185, 0.0, 1.6309])
"""Extrinsic of the MergedPointCloud "lidar" frame (lidar -> ego)."""

_REFLECTIVITY = np.zeros(256, np.float32)
for _id, _r in {1: 0.35, 2: 0.55, 3: 0.45, 4: 0.25, 5: 0.7, 6: 0.5, 7: 0.85, 8: 0.3, 12: 0.12, 13: 0.22, 14: 0.8}.items():
    _REFLECTIVITY[_id] = _r


@dataclass(frozen=True)
class LidarSpec:
    """One LiDAR: lidar_info index, mounting (x, y, z m; roll, pitch, yaw deg) in the ego frame, ring
    elevations (deg, sensor frame), horizontal field of view (deg, centred on the sensor's x axis),
    azimuth samples per 360 deg and maximum range (m)."""

    index: int
    mount: tuple[float, float, float, float, float, float]
    elevations_deg: tuple[float, ...]
    fov_deg: float
    azimuths_per_turn: int
    max_range: float

    @property
    def T_ego_from_sensor(self) -> np.ndarray:
        x, y, z, roll, pitch, yaw = self.mount
        return make_transform(rotation_from_euler(*np.radians([roll, pitch, yaw])), [x, y, z])

    def directions(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit ray directions (N, 3) in the sensor frame and their ring index (N,)."""
        n_az = max(1, int(round(self.azimuths_per_turn * self.fov_deg / 360.0)))
        az = np.radians(-self.fov_deg / 2 + (np.arange(n_az) + 0.5) * self.fov_deg / n_az)
        el = np.radians(np.asarray(self.elevations_deg))
        A, E = np.meshgrid(az, el, indexing="ij")
        dirs = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)
        ring = np.tile(np.arange(len(el), dtype=np.int16), n_az)
        return dirs, ring


def _top_elevations() -> tuple[float, ...]:
    """64 rings from -25 to +15 deg, densest near the horizon."""
    u = np.linspace(-1.0, 1.0, 64)
    return tuple(float(v) for v in np.where(u < 0, -25.0, 15.0) * np.abs(u) ** 1.5)


def nuplan_rig(top_azimuths: int, side_azimuths: int) -> tuple[LidarSpec, ...]:
    """The 5-LiDAR rig of a preset (azimuth samples per full turn for the top and the other sensors)."""
    f = PACIFICA
    top = LidarSpec(0, (1.30, 0.0, f.height + 0.18, 0.0, 0.0, 0.0), _top_elevations(), 360.0, top_azimuths, 120.0)
    pillar_el = tuple(float(v) for v in np.linspace(-30.0, 10.0, 40))
    right = LidarSpec(1, (2.05, -(f.width / 2 + 0.03), 1.45, 0.0, 8.0, -70.0), pillar_el, 200.0, side_azimuths, 60.0)
    left = LidarSpec(2, (2.05, f.width / 2 + 0.03, 1.45, 0.0, 8.0, 70.0), pillar_el, 200.0, side_azimuths, 60.0)
    fb_el = tuple(float(v) for v in np.linspace(-35.0, 12.0, 32))
    back = LidarSpec(3, (-(f.rear + 0.06), 0.0, 0.85, 0.0, 5.0, 180.0), fb_el, 180.0, side_azimuths, 40.0)
    front = LidarSpec(4, (f.front + 0.06, 0.0, 0.62, 0.0, 5.0, 0.0), fb_el, 180.0, side_azimuths, 40.0)
    return (top, right, left, back, front)


def rotate(vectors: np.ndarray, R: np.ndarray) -> np.ndarray:
    """R @ v for vectors (N, 3); einsum instead of BLAS, which stalls on small matrices when cores are busy."""
    return np.einsum("ij,nj->ni", R, vectors)


@lru_cache(maxsize=32)
def _rays_in_ego(spec: LidarSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(origins (N, 3), unit directions (N, 3), ring (N,), distance to the ego box (N,)) of one LiDAR in
    the ego frame (read-only)."""
    d, ring = spec.directions()
    T = spec.T_ego_from_sensor
    origins, dirs = np.broadcast_to(T[:3, 3], d.shape).copy(), rotate(d, T[:3, :3])
    out = (origins, dirs, ring, _ego_box_entry(origins, dirs))
    for a in out:
        a.setflags(write=False)
    return out


@dataclass
class Sweep:
    """Returns of one merged sweep. Ego frame = the TRUE ego pose at the sweep time (m).

    origins (N, 3): sensor origin of each return; hits (N, 3): exact (noise-free) surface point;
    points (N, 3): measured point (range noise); intensity (N,) float32 0..255; ring (N,) int16;
    lidar_info (N,) int8; label (N,) uint8 and instance (N,) uint16 of the surface hit.
    """

    origins: np.ndarray
    hits: np.ndarray
    points: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    lidar_info: np.ndarray
    label: np.ndarray
    instance: np.ndarray

    def cloud(self) -> PointCloud:
        """The measured points as a PointCloud in the MergedPointCloud "lidar" frame."""
        T_lidar_from_ego = np.linalg.inv(T_EGO_FROM_LIDAR)
        xyz = rotate(self.points, T_lidar_from_ego[:3, :3]) + T_lidar_from_ego[:3, 3]
        return PointCloud(xyz, self.intensity, self.ring, self.lidar_info, "lidar")


def _ego_box_entry(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(N,) distance along each ray (ego frame) at which it enters the ego vehicle's box; inf if never."""
    center, size = PACIFICA.box_center_and_size()
    t_near, t_far = slab_interval(origins, dirs, center - size / 2, center + size / 2)
    return np.where((t_near <= t_far) & (t_far > 0), np.maximum(t_near, 0.0), np.inf)


def cast_rays(scene: o3d.t.geometry.RaycastingScene, origins: np.ndarray,
              dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(distance to the first hit (N,) m, inf for none; its triangle (N,); its unit normal (N, 3)) of rays
    origins (N, 3) + t * unit dirs (N, 3) in the scene's frame."""
    rays = o3d.core.Tensor(np.ascontiguousarray(np.concatenate([origins, dirs], axis=1), dtype=np.float32))
    out = scene.cast_rays(rays)
    return out["t_hit"].numpy().astype(np.float64), out["primitive_ids"].numpy().astype(np.int64), out["primitive_normals"].numpy()


def simulate_sweep(world: World, t: float, T_local_from_ego: np.ndarray, rig: tuple[LidarSpec, ...],
                   options: SynthOptions, rng: np.random.Generator) -> Sweep:
    """Cast every ray of the rig at time t (s) from the TRUE pose T_local_from_ego (4, 4) against the static
    mesh and the agents posed at t; apply self-occlusion, ray drop, range noise and intensity."""
    origins, dirs, rings, infos, max_range, ego_box = [], [], [], [], [], []
    for spec in rig:
        o, d, ring, box_at = _rays_in_ego(spec)
        ego_box.append(box_at)
        origins.append(o)
        dirs.append(d)
        rings.append(ring)
        infos.append(np.full(len(d), spec.index, np.int8))
        max_range.append(np.full(len(d), spec.max_range))
    o_e, d_e = np.concatenate(origins), np.concatenate(dirs)
    ring, info, max_range = np.concatenate(rings), np.concatenate(infos), np.concatenate(max_range)
    R, p = T_local_from_ego[:3, :3], T_local_from_ego[:3, 3]
    o_l, d_l = rotate(o_e, R) + p, rotate(d_e, R)
    static = world.static_mesh()
    agents = world.agent_mesh(t)
    t_s, id_s, n_s = cast_rays(world.static_scene(), o_l, d_l)
    t_a, id_a, n_a = cast_rays(raycasting_scene(agents.triangles), o_l, d_l)
    use_agent = t_a < t_s
    rng_hit = np.where(use_agent, t_a, t_s)
    valid = np.isfinite(rng_hit) & (rng_hit <= max_range) & (rng_hit > 0.3)
    valid &= np.concatenate(ego_box) >= rng_hit  # self-occlusion: the ray enters the ego's box first
    normal = np.where(use_agent[:, None], n_a, n_s)
    cos_inc = np.abs(np.einsum("nd,nd->n", normal, d_l))
    drop_p = options.ray_drop + 0.3 * (1.0 - cos_inc) ** 6 + 0.15 * (np.minimum(rng_hit, max_range) / max_range) ** 2
    u = rng.random(len(rng_hit))
    noise = rng.normal(0.0, options.range_noise, len(rng_hit))
    speckle = rng.normal(0.0, 4.0, len(rng_hit))
    keep = valid & (u >= drop_p)
    label = np.where(use_agent, agents.label[np.where(use_agent, id_a, 0)] if len(agents.label) else 0,
                     static.label[np.where(use_agent | ~valid, 0, id_s)])[keep]
    instance = np.where(use_agent, agents.instance[np.where(use_agent, id_a, 0)] if len(agents.instance) else 0, 0)[keep]
    r = rng_hit[keep]
    hits = o_e[keep] + d_e[keep] * r[:, None]
    points = o_e[keep] + d_e[keep] * (r + noise[keep])[:, None]
    intensity = 255.0 * _REFLECTIVITY[label] * np.sqrt(cos_inc[keep]) * np.exp(-r / 150.0) + speckle[keep]
    return Sweep(np.ascontiguousarray(o_e[keep]), hits, points, np.clip(intensity, 0, 255).astype(np.float32),
                 ring[keep], info[keep], label.astype(np.uint8), instance.astype(np.uint16))


def world_rig(world: World) -> tuple[LidarSpec, ...]:
    """The rig of the world's preset."""
    return nuplan_rig(world.preset.top_azimuths, world.preset.side_azimuths)


def sweep_at(world: World, t_us: int, T_global_from_ego: np.ndarray) -> Sweep:
    """The sweep of the world's rig at absolute time t_us (us) from the given TRUE ego pose; its noise is
    a pure function of (world seed, log index, t_us)."""
    rng = np.random.default_rng([*world.noise_key, int(t_us)])
    return simulate_sweep(world, float(world.seconds(t_us)), world.local_from_global(T_global_from_ego),
                          world_rig(world), world.options, rng)
