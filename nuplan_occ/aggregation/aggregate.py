"""Multi-frame aggregation: background points in one scene frame, object points in their own box frames
(paper: "Background/Foreground Point Cloud Aggregation"; P_local = R_obj^T (P_world - c_obj)).

Frames: "ego" per frame (inputs), "global" (poses are T_global_from_ego), "scene" (T_global_from_scene, by
default the first frame's ego pose), "box" (origin at the box centre, x along the heading). Units: metres.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from nuplan_occ.points import PointInputError
from nuplan_occ.points.box_kernels import inside_any_frame_box
from nuplan_occ.points.outliers import remove_statistical_outliers
from nuplan_occ.points.voxel_reduce import KeySet, first_of_each_key, voxel_keys
from nuplan_occ.geometry import invert_transform, transform_points
from nuplan_occ.io.types import Boxes

RIGID_CATEGORIES = ("vehicle", "bicycle", "traffic_cone", "barrier", "czone_sign", "generic_object")


@dataclass
class BackgroundAggregate:
    """points (M, 3) in the SCENE frame; frame_ids (M,) int32 index of each point's source frame;
    frame_origins (F, 3): each source frame's sensor origin in the scene frame; T_global_from_scene (4, 4).
    A point's sensor origin is its frame's (frame_origins[frame_ids]), so the aggregate holds no second
    point-sized array of coordinates."""

    points: np.ndarray
    frame_ids: np.ndarray
    frame_origins: np.ndarray
    T_global_from_scene: np.ndarray

    def subset(self, keep: np.ndarray) -> "BackgroundAggregate":
        """The aggregate of the points selected by `keep` (a bool mask or indices over the points)."""
        return BackgroundAggregate(self.points[keep], self.frame_ids[keep], self.frame_origins,
                                   self.T_global_from_scene)


def without_outliers(aggregate: BackgroundAggregate, test: dict) -> tuple[BackgroundAggregate, np.ndarray]:
    """The aggregate without the points that nuplan_occ.points.outliers finds to be outliers (test: keyword
    arguments of `remove_statistical_outliers` but origin; each point is scored against its own sweep's sensor
    origin), or the aggregate itself when there is none; with the count removed per source frame (F,) int64."""
    keep = remove_statistical_outliers(aggregate.points, origin=aggregate.frame_origins,
                                       origin_ids=aggregate.frame_ids, **test)
    removed = np.bincount(aggregate.frame_ids[~keep], minlength=len(aggregate.frame_origins))
    return (aggregate if keep.all() else aggregate.subset(keep)), removed


def voxel_first_indices(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Sorted indices of the first point (in input order) of every occupied voxel of size voxel_m (m)."""
    return first_of_each_key(voxel_keys(points, voxel_m))


def within_boxes(points: np.ndarray, T_box_from_points: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """(N,) bool: whether each point (N, 3) lies in [lower, upper) (3,) m of at least one of the K axis-aligned
    boxes, box k being given in its own frame with T_box_from_points (K, 4, 4) from the points' frame.
    Compiled (nuplan_occ.points.box_kernels): boxes are tried nearest first, and a point stops at the first box that holds
    it or is too far from it to (same answer as trying every box)."""
    Ts = np.asarray(T_box_from_points, dtype=np.float64).reshape(-1, 4, 4)
    if not len(points) or not len(Ts):
        return np.zeros(len(points), dtype=bool)
    reach = float(np.linalg.norm(np.maximum(np.abs(lower), np.abs(upper))))  # farthest box point from its centre
    centre_distance = np.linalg.norm(Ts[:, :3, 3], axis=1)  # distance from the box centre to the points' origin
    order = np.argsort(centre_distance, kind="stable")
    return inside_any_frame_box(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(Ts[order]),
                                centre_distance[order], np.asarray(lower, np.float64), np.asarray(upper, np.float64),
                                reach)


def aggregate_background(
    clouds_ego: Sequence[np.ndarray],
    sensor_origins_ego: np.ndarray,
    poses: np.ndarray,
    T_global_from_scene: np.ndarray | None = None,
    voxel_downsample_m: float | None = None,
    crop: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> BackgroundAggregate:
    """Background points of all frames in the scene frame.

    clouds_ego: F arrays (n_i, 3), frame i's background in its ego frame (any sequence: each is read once);
    sensor_origins_ego (F, 3): frame i's sensor origin in its ego frame; poses (F, 4, 4): T_global_from_ego
    (refined). crop = (crop_poses (K, 4, 4) T_global_from_ego, lower (3,), upper (3,) m): if set, keep only
    the points inside [lower, upper) of the ego frame of at least one crop pose (e.g. the output frames' grids
    plus a margin), before any downsampling.
    voxel_downsample_m: if set, keep only the first point (earliest frame) of every voxel of that size, with its
    own frame id; applied frame by frame as the aggregate is built (a hash set of the voxels kept so far), so
    memory follows the downsampled aggregate, not the raw points of the scene.
    """
    poses = np.asarray(poses, dtype=np.float64)
    origins = np.asarray(sensor_origins_ego, dtype=np.float64)
    F = len(clouds_ego)
    if poses.shape != (F, 4, 4) or origins.shape != (F, 3):
        raise PointInputError(
            f"aggregate_background: {F} clouds need poses (F, 4, 4) and sensor_origins_ego (F, 3), got "
            f"{poses.shape} and {origins.shape}"
        )
    T_gs = poses[0] if T_global_from_scene is None and F else np.asarray(
        np.eye(4) if T_global_from_scene is None else T_global_from_scene, dtype=np.float64)
    scene_from_global = invert_transform(T_gs)
    if crop is not None:
        crop_from_global = np.stack([invert_transform(T) for T in np.asarray(crop[0], np.float64).reshape(-1, 4, 4)])
    frame_origins = np.array([transform_points(scene_from_global @ poses[i], origins[i][None])[0]
                              for i in range(F)]).reshape(F, 3)
    kept_voxels = KeySet()
    points, ids = [np.zeros((0, 3))], [np.zeros(0, np.int32)]
    for i in range(F):
        cloud = clouds_ego[i]
        if crop is not None:
            cloud = cloud[within_boxes(cloud, crop_from_global @ poses[i], crop[1], crop[2])]
        pts = transform_points(scene_from_global @ poses[i], cloud)
        if voxel_downsample_m:  # first point per voxel so far: the same points as downsampling all at once
            pts = pts[kept_voxels.new(voxel_keys(pts, voxel_downsample_m))]
        points.append(pts)
        ids.append(np.full(len(pts), i, dtype=np.int32))
    return BackgroundAggregate(np.vstack(points), np.concatenate(ids), frame_origins, T_gs)


@dataclass
class ObjectAggregate:
    """All points of one track in its BOX frame.

    size (3,) [length, width, height] m: median over the frames; points / sensor_origins (n, 3) box frame;
    frame_ids (n,) int32 index of the source frame; rigid: whether the category keeps its shape over time."""

    track_token: str
    category: str
    size: np.ndarray
    points: np.ndarray
    sensor_origins: np.ndarray
    frame_ids: np.ndarray
    rigid: bool

    def points_for_frame(self, frame_id: int, window: int) -> tuple[np.ndarray, np.ndarray]:
        """(points, sensor_origins) in the box frame to rebuild the object at frame_id: every point of a rigid
        object; only the points of frames within +-window of frame_id for a non-rigid one."""
        if self.rigid:
            return self.points, self.sensor_origins
        keep = np.abs(self.frame_ids.astype(np.int64) - int(frame_id)) <= window
        return self.points[keep], self.sensor_origins[keep]


def aggregate_objects(
    track_points: list[dict[str, tuple[np.ndarray, np.ndarray]]],
    boxes_per_frame: list[Boxes],
    rigid_categories: tuple[str, ...] = RIGID_CATEGORIES,
) -> dict[str, ObjectAggregate]:
    """Per-track aggregation of the foreground points of all frames.

    track_points[i] (frame i): track -> (points (n, 3), sensor origins (n, 3)), both in the track's box frame
    (`FrameSplit.track_points`, or the track stage's corrected `object_points`); boxes_per_frame[i]: the
    frame's boxes. A track's category is its most frequent box category and its size the per-axis median of
    its box sizes; tracks with boxes but no points get empty point arrays."""
    if len(track_points) != len(boxes_per_frame):
        raise PointInputError(f"aggregate_objects: {len(track_points)} frames of points but {len(boxes_per_frame)} box sets")
    categories: dict[str, Counter] = {}
    sizes: dict[str, list[np.ndarray]] = {}
    for boxes in boxes_per_frame:
        for token, category, size in zip(boxes.track_tokens, boxes.categories, boxes.sizes):
            categories.setdefault(token, Counter())[category] += 1
            sizes.setdefault(token, []).append(np.asarray(size, dtype=np.float64))
    points: dict[str, list[np.ndarray]] = {t: [] for t in sizes}
    origins: dict[str, list[np.ndarray]] = {t: [] for t in sizes}
    ids: dict[str, list[np.ndarray]] = {t: [] for t in sizes}
    for i, frame in enumerate(track_points):
        for token, (pts, pts_origins) in frame.items():
            if token not in points:
                raise PointInputError(f"aggregate_objects: frame {i} has points of track {token} but no box of it")
            points[token].append(pts)
            origins[token].append(pts_origins)
            ids[token].append(np.full(len(pts), i, dtype=np.int32))
    out = {}
    for token in sizes:
        category = categories[token].most_common(1)[0][0]
        out[token] = ObjectAggregate(
            token, category, np.median(np.stack(sizes[token]), axis=0),
            np.vstack(points[token]) if points[token] else np.zeros((0, 3)),
            np.vstack(origins[token]) if origins[token] else np.zeros((0, 3)),
            np.concatenate(ids[token]) if ids[token] else np.zeros(0, np.int32),
            category in rigid_categories,
        )
    return out
