"""Exact occupancy truth of a synthetic world in the project's grid convention (ego frame of the TRUE pose).

semantics (uint8): a voxel is occupied when a world surface intersects it (exact overlap, see
voxelize.py): ground rectangles, curb faces, building / wall / pole faces, tree crowns. Box-class objects
(vehicles, pedestrians, cyclists, cones, barriers, signs, generic objects) are SOLID in their actual
shape: every voxel one of their cuboid parts intersects is occupied (agents.shape_parts, e.g. a vehicle's
body, cabin and wheels; the empty rest of the box is not), and the LiDAR sees the surfaces of the same
parts. When several surfaces share a voxel the label with the highest priority wins: box objects >
other (1) > road_line (14) > road (12) > other_ground (13); among objects the higher instance id wins.
The ego vehicle itself is not in the world.
instance (uint16): the object's instance id (1..K) in its voxels, 0 elsewhere.
mask_lidar (bool): voxels observed by the rig at that frame = traversed by a returned ray on its exact
(noise-free) segment from the sensor origin to the surface hit, or containing the hit. Dropped rays and
rays without a return observe nothing.
mask_camera (bool, when the cameras are given): the voxels the cameras see, by the rule of the build's
mask_camera (nuplan_occ.rays.visibility: pinhole frustum of each camera's K and image size, lens
distortion ignored; along a ray the voxels up to and including the first occupied one, within
CAMERA_MAX_RANGE_M) applied to the TRUE occupancy (semantics > 0) with one ray through every pixel cell
of every camera (the build's pixel lattice at its finest, in one range band), where the build samples
rays about a voxel apart: so the truth's mask is exact at the cameras' resolution.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.io.types import CameraCalibration
from nuplan_occ.labels import OTHER, OTHER_GROUND, ROAD, ROAD_LINE
from nuplan_occ.rays.visibility import camera_visibility
from nuplan_occ.synth.agents import posed_prisms, shape_parts
from nuplan_occ.synth.lidar import Sweep, sweep_at
from nuplan_occ.synth.voxelize import prism_voxel_hits, reduce_labels, segment_voxels, triangle_voxel_hits
from nuplan_occ.synth.world import World

_RANK = np.zeros(256, np.int64)
_RANK[[OTHER_GROUND, ROAD, ROAD_LINE, OTHER]] = [1, 2, 3, 4]
_OBJECT_RANK = 5
CAMERA_MAX_RANGE_M = 60.0
"""Farthest distance (m) a camera observes in mask_camera: the build's default (visibility.camera_max_range_m)."""


def upright_yaw(T_local_from_ego: np.ndarray) -> float:
    """Yaw of an upright pose; ValueError if the pose has roll or pitch (the truth's exact prism
    voxelization assumes the TRUE ego pose is upright, which the synthetic world guarantees)."""
    R = np.asarray(T_local_from_ego)[:3, :3]
    if abs(R[2, 0]) > 1e-9 or abs(R[2, 1]) > 1e-9 or abs(R[2, 2] - 1.0) > 1e-9:
        raise ValueError("truth_for_frame: the TRUE ego pose must be upright (yaw only); got roll/pitch")
    return float(np.arctan2(R[1, 0], R[0, 0]))


def _culled(center_xy: np.ndarray, reach: np.ndarray, position: np.ndarray, grid: GridSpec) -> np.ndarray:
    radius = float(np.hypot(max(abs(grid.x_min), abs(grid.x_max)), max(abs(grid.y_min), abs(grid.y_max))))
    return np.linalg.norm(center_xy - position[:2], axis=1) <= radius + reach


def semantic_truth(world: World, t: float, T_local_from_ego: np.ndarray, grid: GridSpec = DEFAULT_GRID) -> tuple[np.ndarray, np.ndarray]:
    """(semantics uint8, instance uint16) grids at time t (s from log start) for the TRUE pose
    T_local_from_ego (4, 4, upright)."""
    yaw = upright_yaw(T_local_from_ego)
    p = np.asarray(T_local_from_ego)[:3, 3]
    c, s = np.cos(-yaw), np.sin(-yaw)
    R2 = np.array([[c, -s], [s, c]])
    shift = np.r_[-(R2 @ p[:2]), -p[2]]
    flats, ranks, labels, insts = [], [], [], []

    faces = world.faces.subset(_culled(world.faces.center, np.hypot(*world.faces.half.T), p, grid)).moved(-yaw, shift)
    flat, owner = prism_voxel_hits(faces.center, faces.half, faces.yaw, faces.z0, faces.z1, grid)
    flats.append(flat)
    ranks.append(_RANK[faces.label[owner]])
    labels.append(faces.label[owner])
    insts.append(np.zeros(len(flat), np.int64))

    crowns = world.crowns
    if len(crowns):
        crowns = crowns[_culled(crowns[:, 0, :2], np.full(len(crowns), 5.0), p, grid)]
        R3 = np.eye(3)
        R3[:2, :2] = R2
        local = np.einsum("ij,tkj->tki", R3, crowns - p)
        flat, _ = triangle_voxel_hits(local, grid)
        flats.append(flat)
        ranks.append(np.full(len(flat), _RANK[OTHER]))
        labels.append(np.full(len(flat), OTHER))
        insts.append(np.zeros(len(flat), np.int64))

    if world.agents:
        prisms, yaws, owners = [], [], []
        for n, agent in enumerate(world.agents):
            center, a_yaw, _ = agent.state(np.array([t]))
            ego_center = np.r_[R2 @ (center[0, :2] - p[:2]), center[0, 2] - p[2]]
            parts = shape_parts(agent.category, agent.size)
            prisms.append(posed_prisms(parts, ego_center, float(a_yaw[0]) - yaw))
            yaws.append(np.full(len(parts), float(a_yaw[0]) - yaw))
            owners.append(np.full(len(parts), n))
        xy, half, z0, z1 = (np.concatenate(column) for column in zip(*prisms))
        flat, part = prism_voxel_hits(xy, half, np.concatenate(yaws), z0, z1, grid)
        owner = np.concatenate(owners)[part]
        flats.append(flat)
        ranks.append(np.full(len(flat), _OBJECT_RANK))
        labels.append(np.array([a.label for a in world.agents])[owner])
        insts.append(np.array([a.instance for a in world.agents])[owner])

    return reduce_labels(np.concatenate(flats), np.concatenate(ranks), np.concatenate(labels), np.concatenate(insts), grid)


def lidar_mask(sweep: Sweep, grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """(nx, ny, nz) bool: voxels traversed by the sweep's returned rays (exact segments origin -> hit, ego frame)."""
    mask = np.zeros(int(np.prod(grid.shape)), dtype=bool)
    mask[segment_voxels(sweep.origins, sweep.hits, grid)] = True
    return mask.reshape(grid.shape)


def camera_mask(semantics: np.ndarray, cameras: list[CameraCalibration], grid: GridSpec = DEFAULT_GRID) -> np.ndarray:
    """(nx, ny, nz) bool mask_camera of a truth grid `semantics` (ego frame) seen by `cameras` (module doc)."""
    if not cameras:
        return np.zeros(grid.shape, dtype=bool)
    finest = 0.5 / max(float(max(c.K[0, 0], c.K[1, 1])) for c in cameras)  # below one pixel: the lattice's floor
    return camera_visibility(semantics > 0, cameras, grid, CAMERA_MAX_RANGE_M, angular_step_rad=finest, range_bands=1)


def truth_for_frame(world: World, t_us: int, T_global_from_ego_true: np.ndarray, grid: GridSpec = DEFAULT_GRID,
                    sweep: Sweep | None = None, cameras: list[CameraCalibration] | None = None) -> dict[str, np.ndarray]:
    """Truth of one frame at absolute time t_us (us) in the ego frame of the TRUE pose T_global_from_ego_true
    (4, 4): {"semantics": uint8, "instance": uint16, "mask_lidar": bool, and "mask_camera": bool when
    `cameras` are given}, each of grid.shape, [x, y, z]. `sweep` (the rig's sweep at that time and pose) is
    simulated when not given."""
    T_local = world.local_from_global(T_global_from_ego_true)
    semantics, instance = semantic_truth(world, float(world.seconds(t_us)), T_local, grid)
    if sweep is None:
        sweep = sweep_at(world, t_us, T_global_from_ego_true)
    arrays = {"semantics": semantics, "instance": instance, "mask_lidar": lidar_mask(sweep, grid)}
    if cameras is not None:
        arrays["mask_camera"] = camera_mask(semantics, cameras, grid)
    return arrays
