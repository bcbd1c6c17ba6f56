"""Per-frame cost of the voxel work (compose, BEV labeling, LiDAR and camera visibility) on a realistic
synthetic frame. Called by the project benchmark (`make bench`); no file I/O.

The synthetic frame (`synthetic_frame`), all in the EGO frame (rear axle, ground at z = 0, metres):
- background surface: a gently undulating road/sidewalk ground mesh (0.4 m lattice, curbs at |y| = 7 m)
  over the grid plus a margin, building facades along both sides (closed boxes, 0.5 m lattice, taller
  than the grid) and trees (pole + canopy);
- objects: parked and moving cars (closed ellipsoid-like surfaces, ~1.3k triangles each, box frame),
  pedestrians given as raw points, traffic cones;
- LiDAR: ~100k returns of a 5-LiDAR-like rig (a 64-ring roof LiDAR and four 16-ring corner LiDARs)
  ray-cast against that scene with open3d; rays start at the roof LiDAR (as in the pipeline);
- cameras: 8 pinhole cameras 1920 x 1080, fx ~ 1545 px, around the roof, OpenCV axes;
- map: a road polygon (|y| <= 7 m) and lane boundary lines in a global frame 60 deg yawed from ego.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import shapely
import trimesh

from nuplan_occ.geometry import make_transform, yaw_matrix
from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.io.types import CAMERA_CHANNELS, CameraCalibration, MapLayer
from nuplan_occ.labels import PEDESTRIAN, TRAFFIC_CONE, VEHICLE
from nuplan_occ.map_labels.bev import rasterize_bev
from nuplan_occ.voxel.compose import PlacedObject, compose_frame
from nuplan_occ.voxel.ground import label_background
from nuplan_occ.rays.visibility import camera_visibility, lidar_visibility

ROOF_LIDAR_EGO = np.array([1.5185, 0.0, 1.6309])
"""Roof LiDAR position in the ego frame (m): the rays' origin."""

_CAMERA_YAW_DEG = (0, 180, 55, 110, 150, -55, -110, -150)  # in CAMERA_CHANNELS order


@dataclass
class BenchFrame:
    """Inputs of one frame's voxel work, all in the ego frame (metres): the background surface
    (vertices (V, 3), faces (F, 3)), placed objects, LiDAR returns (N, 3) and their origin (3,),
    8 camera calibrations, map layers in the global frame and T_global_from_ego (4, 4)."""

    background_vertices: np.ndarray
    background_faces: np.ndarray
    objects: list[PlacedObject]
    points_ego: np.ndarray
    origin: np.ndarray
    cameras: list[CameraCalibration]
    map_layers: dict[str, MapLayer]
    T_global_from_ego: np.ndarray


def _lattice_mesh(corner: np.ndarray, u: np.ndarray, v: np.ndarray, nu: int, nv: int,
                  height: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None):
    """Triangulated nu x nv lattice on corner + a u + b v (a in [0, nu], b in [0, nv]); `height(x, y)`
    adds z. Returns vertices ((nu+1)(nv+1), 3) and faces (2 nu nv, 3)."""
    a, b = np.meshgrid(np.arange(nu + 1), np.arange(nv + 1), indexing="ij")
    p = corner + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    if height is not None:
        p[:, 2] += height(p[:, 0], p[:, 1])
    q = (np.arange(nu)[:, None] * (nv + 1) + np.arange(nv)[None, :]).ravel()
    faces = np.concatenate([np.stack([q, q + nv + 1, q + 1], 1), np.stack([q + 1, q + nv + 1, q + nv + 2], 1)])
    return p, faces


def _box_surface(lo: np.ndarray, hi: np.ndarray, step: float):
    """Closed surface of an axis-aligned box between lo and hi, its six faces on a ~step lattice."""
    parts = []
    size = hi - lo
    for axis in range(3):
        a, b = [k for k in range(3) if k != axis]
        n_a, n_b = max(1, int(np.ceil(size[a] / step))), max(1, int(np.ceil(size[b] / step)))
        u, v = np.zeros(3), np.zeros(3)
        u[a], v[b] = size[a] / n_a, size[b] / n_b
        for side in (lo, hi):
            corner = lo.copy()
            corner[axis] = side[axis]
            parts.append(_lattice_mesh(corner, u, v, n_a, n_b))
    return _merge(parts)


def _merge(parts):
    """Concatenate (vertices, faces) meshes."""
    offsets = np.cumsum([0] + [len(v) for v, _ in parts])
    return (np.concatenate([v for v, _ in parts]),
            np.concatenate([f + o for (_, f), o in zip(parts, offsets[:-1])]).astype(np.int64))


def _ground_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Ground z (m, ego frame) of the synthetic street: undulation plus 0.15 m curbs at |y| >= 7 m."""
    return 0.05 * np.sin(x / 7.0) + 0.03 * np.cos(y / 5.0) + 0.15 * (np.abs(y) >= 7.0)


def _background(rng: np.random.Generator):
    """Ground, facades and trees (ego frame)."""
    parts = [_lattice_mesh(np.array([-52.0, -52.0, 0.0]), np.array([0.4, 0, 0]), np.array([0, 0.4, 0]), 260, 260,
                           _ground_height)]
    for side in (-1.0, 1.0):
        x = -52.0
        while x < 52.0:
            length = rng.uniform(8.0, 20.0)
            depth_lo = 13.0 + rng.uniform(0.0, 3.0)
            y0, y1 = sorted((side * depth_lo, side * (depth_lo + 8.0)))
            parts.append(_box_surface(np.array([x, y0, 0.0]), np.array([x + length, y1, rng.uniform(6.0, 15.0)]), 0.5))
            x += length + rng.uniform(1.0, 5.0)
        for tx in np.arange(-45.0, 46.0, 9.0) + rng.uniform(-1, 1):
            ty = side * 9.5
            parts.append(_box_surface(np.array([tx - 0.15, ty - 0.15, 0.1]), np.array([tx + 0.15, ty + 0.15, 3.0]), 0.5))
            crown = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
            parts.append((np.asarray(crown.vertices) * [2.0, 2.0, 1.5] + [tx, ty, 4.0], np.asarray(crown.faces)))
    return _merge(parts)


def _objects(rng: np.random.Generator) -> list[PlacedObject]:
    """Cars along the lanes and parked at the curbs, pedestrians (points) and cones on the sidewalks."""
    car = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    car_v = np.clip(np.asarray(car.vertices) * 1.3, -1.0, 1.0)  # a rounded box of half-size 1
    objects = []
    instance = 1
    for lane_y, heading in ((-5.25, np.pi), (-1.75, np.pi), (1.75, 0.0), (5.25, 0.0)):
        for x in np.arange(-45.0, 46.0, 11.0) + rng.uniform(-3, 3):
            if abs(x) < 6.0 and abs(lane_y) < 2.0:
                continue  # the ego's own place
            size = np.array([rng.uniform(4.2, 5.2), rng.uniform(1.8, 2.0), rng.uniform(1.45, 1.9)])
            speed = 0.0 if abs(lane_y) > 5.0 else rng.uniform(3.0, 12.0)
            yaw = heading + rng.normal(0.0, 0.03)
            objects.append(PlacedObject(
                car_v * (size / 2.0 - 0.05), np.asarray(car.faces), np.array([x, lane_y, size[2] / 2.0]), yaw, size,
                VEHICLE, instance, np.array([speed * np.cos(yaw), speed * np.sin(yaw), 0.0])))
            instance += 1
    for _ in range(12):
        size = np.array([0.6, 0.6, 1.75])
        points = rng.uniform(-0.25, 0.25, size=(400, 3)) * [1.0, 1.0, 3.4]
        center = np.array([rng.uniform(-40, 40), rng.choice([-1, 1]) * rng.uniform(7.5, 11.0), 0.15 + size[2] / 2.0])
        objects.append(PlacedObject(points, np.zeros((0, 3), np.int64), center, rng.uniform(-np.pi, np.pi), size,
                                    PEDESTRIAN, instance, np.array([1.2, 0.0, 0.0])))
        instance += 1
    for x in np.arange(8.0, 20.0, 3.0):
        cone_v, cone_f = _box_surface(np.array([-0.2, -0.2, -0.35]), np.array([0.2, 0.2, 0.35]), 0.1)
        objects.append(PlacedObject(cone_v, cone_f, np.array([x, -3.5, 0.35]), 0.0, np.array([0.4, 0.4, 0.7]),
                                    TRAFFIC_CONE, instance))
        instance += 1
    return objects


def _lidar_rays() -> tuple[np.ndarray, np.ndarray]:
    """Origins (R, 3) and unit directions (R, 3), ego frame, of a 5-LiDAR-like rig."""
    def ring_rays(origin, elevations_deg, n_azimuth, yaw_deg, fov_deg):
        az = np.radians(yaw_deg + np.linspace(-fov_deg / 2.0, fov_deg / 2.0, n_azimuth, endpoint=fov_deg < 360))
        el = np.radians(np.asarray(elevations_deg))
        A, E = np.meshgrid(az, el, indexing="ij")
        d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
        return np.broadcast_to(origin, d.shape), d

    rigs = [ring_rays(ROOF_LIDAR_EGO, np.linspace(-25.0, 15.0, 64), 1400, 0.0, 360.0)]
    for x, y, yaw in ((3.6, 0.9, 45.0), (3.6, -0.9, -45.0), (-0.9, 0.9, 135.0), (-0.9, -0.9, -135.0)):
        rigs.append(ring_rays(np.array([x, y, 1.0]), np.linspace(-30.0, 10.0, 16), 500, yaw, 180.0))
    return np.concatenate([o for o, _ in rigs]), np.concatenate([d for _, d in rigs])


def _cast_lidar(vertices: np.ndarray, faces: np.ndarray, max_range_m: float = 80.0) -> np.ndarray:
    """Returns (N, 3), ego frame, of the rig's rays on the scene mesh (misses and far hits dropped)."""
    import open3d as o3d  # heavy import, only for building the benchmark frame

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    origins, dirs = _lidar_rays()
    rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    hit = np.isfinite(t) & (t < max_range_m)
    return origins[hit] + t[hit, None] * dirs[hit]


def bench_cameras(rng: np.random.Generator) -> list[CameraCalibration]:
    """8 pinhole cameras (1920 x 1080, fx ~ 1545 px) around the roof, OpenCV axes (x right, y down, z forward)."""
    out = []
    for channel, yaw_deg in zip(CAMERA_CHANNELS, _CAMERA_YAW_DEG):
        yaw = np.radians(yaw_deg)
        forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
        R = np.stack([right, np.array([0.0, 0.0, -1.0]), forward], axis=1)
        position = np.array([1.6, 0.0, 1.75]) + 0.6 * forward
        f = 1545.0 * rng.uniform(0.98, 1.02)
        K = np.array([[f, 0.0, 960.0 + rng.normal(0, 4)], [0.0, f, 560.0 + rng.normal(0, 4)], [0.0, 0.0, 1.0]])
        out.append(CameraCalibration(f"bench{channel}", channel, "pinhole", K, np.zeros(5), make_transform(R, position),
                                     1920, 1080))
    return out


def _map(T_global_from_ego: np.ndarray) -> dict[str, MapLayer]:
    """A road (|y| <= 7 m) with lane boundaries every 3.5 m, given in the global frame."""
    def to_global(xy):
        return np.asarray(xy, dtype=np.float64) @ T_global_from_ego[:2, :2].T + T_global_from_ego[:2, 3]

    road = shapely.Polygon(to_global([[-80, -7], [80, -7], [80, 7], [-80, 7]]))
    lines = [shapely.LineString(to_global([[-80, y], [80, y]])) for y in (-7.0, -3.5, 0.0, 3.5, 7.0)]
    return {"road_segments": MapLayer(np.array([road], dtype=object)),
            "boundaries": MapLayer(np.array(lines, dtype=object))}


def synthetic_frame(seed: int = 0) -> BenchFrame:
    """A realistic synthetic frame (see module doc) for the default grid."""
    rng = np.random.default_rng(seed)
    vertices, faces = _background(rng)
    objects = _objects(rng)
    meshed = [(o.vertices_ego(), np.asarray(o.faces)) for o in objects if len(o.faces)]
    scene_v, scene_f = _merge([(vertices, faces), *meshed])
    T = make_transform(yaw_matrix(np.radians(60.0)), np.array([587_000.0, 4_140_000.0, 12.0]))
    return BenchFrame(vertices, faces, objects, _cast_lidar(scene_v, scene_f), ROOF_LIDAR_EGO.copy(),
                      bench_cameras(rng), _map(T), T)


def _median_seconds(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def frame_costs(points_ego: np.ndarray, origin: np.ndarray, occupied: np.ndarray, cameras: list[CameraCalibration],
                grid: GridSpec = DEFAULT_GRID, frame: BenchFrame | None = None, repeats: int = 3) -> dict[str, float]:
    """Median wall seconds over `repeats` runs of each per-frame voxel function.

    points_ego (N, 3) LiDAR returns and origin (3,) their rays' start, metres in the ego frame; occupied
    bool (X, Y, Z) the frame's occupancy; cameras: calibrations (T_ego_from_camera). With `frame`, also
    times compose_frame (its background and objects), rasterize_bev and label_background (its map).
    Keys: lidar_visibility, camera_visibility[, compose_frame, rasterize_bev, label_background], total.
    """
    costs = {
        "lidar_visibility": _median_seconds(lambda: lidar_visibility(points_ego, origin, grid), repeats),
        "camera_visibility": _median_seconds(lambda: camera_visibility(occupied, cameras, grid), repeats),
    }
    if frame is not None:
        composed = compose_frame(frame.background_vertices, frame.background_faces, frame.objects, None, grid)
        costs["compose_frame"] = _median_seconds(
            lambda: compose_frame(frame.background_vertices, frame.background_faces, frame.objects, None, grid), repeats)
        bev = rasterize_bev(frame.map_layers, frame.T_global_from_ego, grid)
        costs["rasterize_bev"] = _median_seconds(lambda: rasterize_bev(frame.map_layers, frame.T_global_from_ego, grid),
                                                 repeats)
        costs["label_background"] = _median_seconds(
            lambda: label_background(composed.occupied_background, bev, grid), repeats)
    costs["total"] = sum(costs.values())
    return costs


def synthetic_frame_costs(seed: int = 0, repeats: int = 3) -> dict[str, float]:
    """frame_costs on synthetic_frame(seed), its occupancy composed first (see frame_costs for the keys)."""
    frame = synthetic_frame(seed)
    grids = compose_frame(frame.background_vertices, frame.background_faces, frame.objects, None)
    return frame_costs(frame.points_ego, frame.origin, grids.semantics > 0, frame.cameras, DEFAULT_GRID, frame, repeats)
