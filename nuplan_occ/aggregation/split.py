"""Per-frame foreground/background split of a LiDAR sweep by oriented boxes (paper: "Separated Point Cloud
Aggregation": points in a box follow the object, the rest are background).

Frames: "ego" (nuPlan rear axle) for the sweep, the boxes and the sensor origin; "box" (origin at the box
centre, x along the heading, z up) for foreground points. Units: metres.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from nuplan_occ.points import PointInputError
from nuplan_occ.points.box_kernels import first_upright_box
from nuplan_occ.geometry import transform_points
from nuplan_occ.io.types import PACIFICA, Boxes, PointCloud, VehicleFootprint

FACE_TOLERANCE_M = 1e-6
"""Points within this distance outside a (scaled) box face still count as inside: faces are inclusive."""


def _as_points(points: np.ndarray, name: str) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise PointInputError(f"{name}: expected an (N, 3) array of points, got shape {pts.shape}")
    return pts


def points_in_boxes(points: np.ndarray, boxes: Boxes, scale: float = 1.0, pad_m: float = 0.0) -> np.ndarray:
    """Index of the box containing each point.

    points (N, 3) m in `boxes.frame`. A box's half-extents are sizes / 2 * scale + pad_m (pad_m: metres added on
    every side after scaling). Faces are inclusive (FACE_TOLERANCE_M). Boxes are upright (yaw only).
    Returns (N,) int64: the lowest index of a box containing the point, -1 if none.
    Compiled (nuplan_occ.points.box_kernels): each point tries the boxes in order, bounding rectangle first.
    """
    pts = _as_points(points, "points")
    out = np.full(len(pts), -1, dtype=np.int64)
    if len(boxes) == 0 or len(pts) == 0:
        return out
    centers = np.asarray(boxes.centers, dtype=np.float64)
    half = np.asarray(boxes.sizes, dtype=np.float64) * (0.5 * scale) + pad_m + FACE_TOLERANCE_M
    cos, sin = np.cos(boxes.yaws), np.sin(boxes.yaws)
    # Axis-aligned bounding rectangle of every (scaled) box: a cheap test that drops most points early.
    ext_x = np.abs(cos) * half[:, 0] + np.abs(sin) * half[:, 1]
    ext_y = np.abs(sin) * half[:, 0] + np.abs(cos) * half[:, 1]
    lo = np.stack([centers[:, 0] - ext_x, centers[:, 1] - ext_y, centers[:, 2] - half[:, 2]], axis=1)
    hi = np.stack([centers[:, 0] + ext_x, centers[:, 1] + ext_y, centers[:, 2] + half[:, 2]], axis=1)
    return first_upright_box(pts, centers, half, cos, sin, lo, hi)


@dataclass
class FrameSplit:
    """One sweep split by boxes.

    background: the points outside every enlarged box and outside the ego vehicle (PointCloud, frame "ego").
    foreground: track token -> (n, 3) points of that track's box, in the track's BOX frame at this sweep.
    foreground_origins: track token -> (n, 3) the sweep's sensor origin in that box frame (one row per point).
    n_shell: points inside an enlarged box but outside the box itself (dropped from both sets).
    n_ego: points on the ego vehicle (inside its enlarged footprint), dropped.
    """

    background: PointCloud
    foreground: dict[str, np.ndarray]
    foreground_origins: dict[str, np.ndarray]
    n_shell: int
    n_ego: int

    def track_points(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """track token -> (points, sensor origins), both in the track's box frame (see `aggregate_objects`)."""
        return {track: (points, self.foreground_origins[track]) for track, points in self.foreground.items()}


def ego_footprint_boxes(ego: VehicleFootprint = PACIFICA, margin_m: float = 0.0) -> Boxes:
    """The ego vehicle as one Boxes entry in the ego frame, enlarged by margin_m on every side."""
    center, size = ego.box_center_and_size()
    return Boxes(
        "ego", center[None], (size + 2.0 * margin_m)[None], np.zeros(1), np.zeros((1, 3)), ["ego"], ["ego"], ["ego"],
    )


def foreground_by_track(xyz: np.ndarray, owner: np.ndarray, boxes: Boxes, origin: np.ndarray
                        ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Points (N, 3) of each box (owner (N,): box index, -1 = none), moved into that box's frame, and the
    sensor origin (3,) in the same box frame once per point: (track -> points, track -> origins). Points
    and origin in the boxes' frame. Two boxes of one track keep both point sets."""
    foreground: dict[str, np.ndarray] = {}
    origins: dict[str, np.ndarray] = {}
    box_from_frame = boxes.box_from_frame()
    owned = np.flatnonzero(owner >= 0)
    owned = owned[np.argsort(owner[owned], kind="stable")]  # grouped by box, each group in point order
    box_ids, firsts = np.unique(owner[owned], return_index=True)
    for k, members in zip(box_ids, np.split(owned, firsts[1:])):
        token = boxes.track_tokens[k]
        local = transform_points(box_from_frame[k], xyz[members])
        local_origin = np.repeat(transform_points(box_from_frame[k], origin[None]), len(local), axis=0)
        if token in foreground:
            local = np.vstack([foreground[token], local])
            local_origin = np.vstack([origins[token], local_origin])
        foreground[token], origins[token] = local, local_origin
    return foreground, origins


def split_frame(
    cloud_ego: PointCloud,
    boxes_ego: Boxes,
    sensor_origin_ego: np.ndarray,
    margin: float = 1.1,
    ego: VehicleFootprint = PACIFICA,
    ego_margin_m: float = 0.3,
) -> FrameSplit:
    """Split one sweep into per-track foreground points and background points.

    cloud_ego: the sweep in the ego frame; boxes_ego: the sweep's boxes in the ego frame; sensor_origin_ego (3,):
    the LiDAR origin in the ego frame. Foreground = points inside a box (scale 1, first box wins on overlap),
    moved into that box's frame. Background = points outside every box scaled by `margin` and outside the ego
    footprint enlarged by ego_margin_m. The points in between (the shell) go to neither set.
    """
    if cloud_ego.frame != "ego" or boxes_ego.frame != "ego":
        raise PointInputError(
            f"split_frame: cloud and boxes must be in the 'ego' frame, got {cloud_ego.frame!r} and {boxes_ego.frame!r}"
        )
    origin = np.asarray(sensor_origin_ego, dtype=np.float64).reshape(-1)
    if origin.shape != (3,):
        raise PointInputError(f"split_frame: sensor_origin_ego must have 3 values, got {origin.shape}")
    xyz = _as_points(cloud_ego.xyz, "cloud_ego.xyz")
    in_enlarged = points_in_boxes(xyz, boxes_ego, max(margin, 1.0)) >= 0
    owner = np.full(len(xyz), -1, dtype=np.int64)
    owner[in_enlarged] = points_in_boxes(xyz[in_enlarged], boxes_ego, 1.0)
    on_ego = points_in_boxes(xyz, ego_footprint_boxes(ego, ego_margin_m)) >= 0
    is_fg = owner >= 0
    shell = in_enlarged & ~is_fg
    ego_only = on_ego & ~in_enlarged

    foreground, origins = foreground_by_track(xyz, owner, boxes_ego, origin)
    background = cloud_ego.subset(~in_enlarged & ~on_ego)
    return FrameSplit(background, foreground, origins, int(shell.sum()), int(ego_only.sum()))


def outside_boxes(points: np.ndarray, boxes: Boxes, pad_m: float, ground_keep_m: float) -> np.ndarray:
    """(N,) bool: points (N, 3) that lie outside every box grown by pad_m sideways and upward; the grown
    box's bottom is raised to ground_keep_m above the box's bottom, so the ground around and under an
    object is kept. points and boxes in the same frame, metres."""
    if len(boxes) == 0:
        return np.ones(len(points), dtype=bool)
    sizes = np.asarray(boxes.sizes, dtype=np.float64)
    # Bottom face up by ground_keep_m, top face up by pad_m, sides out by pad_m.
    grown = replace(boxes,
                    centers=np.asarray(boxes.centers, dtype=np.float64) + [0.0, 0.0, (pad_m + ground_keep_m) / 2.0],
                    sizes=sizes + [2.0 * pad_m, 2.0 * pad_m, pad_m - ground_keep_m])
    return points_in_boxes(points, grown) < 0


def cleared_background(cloud: np.ndarray, boxes: Boxes | None, max_range_m: float, clearance_m: float,
                       ground_keep_m: float) -> np.ndarray:
    """The points of one sweep's background cloud (N, 3), ego frame, m, within max_range_m of its ego (x-y
    distance; 0: no limit) and outside its objects' `boxes` (same sweep, ego frame) grown by clearance_m
    sideways and up from ground_keep_m above their bottom (`outside_boxes`; clearance_m < 0: none removed,
    and boxes may be None)."""
    if max_range_m > 0:
        cloud = cloud[np.hypot(cloud[:, 0], cloud[:, 1]) <= max_range_m]
    if clearance_m < 0:
        return cloud
    return cloud[outside_boxes(cloud, boxes, clearance_m, ground_keep_m)]


def points_per_box(cloud_ego: np.ndarray, boxes: Boxes, origin_ego: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """track -> (points (n, 3), sensor origins (n, 3)) in that track's box frame (m), for the points of cloud_ego
    (N, 3), ego frame, inside each of `boxes` (ego frame); origin_ego (3,) the sensor in the ego frame."""
    points, origins = foreground_by_track(cloud_ego, points_in_boxes(cloud_ego, boxes), boxes, origin_ego)
    return {track: (points[track], origins[track]) for track in points}
