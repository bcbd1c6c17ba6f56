"""Plain data records shared by the nuPlan reader, the writer, the synthetic worlds and the pipeline.

Frames named in this module:
- "global": the map's projected CRS (UTM metres) of the log's city.
- "ego":    nuPlan rear axle at the record's timestamp: x forward, y left, z up.
- "lidar":  the frame of the `MergedPointCloud` lidar row; ego_from_lidar is that row's extrinsic.
- "box":    a box's own frame: origin at the box centre, x along the heading, z up.
Tokens are lowercase hex strings at this API; the DB stores them as BLOBs.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from nuplan_occ.geometry import (
    invert_transform, make_transform, quaternion_to_matrix, rotate_vectors, transform_points, wrap_angle, yaw_matrix,
    yaw_of,
)

NUPLAN_CATEGORIES: tuple[str, ...] = (
    "vehicle", "pedestrian", "bicycle", "traffic_cone", "barrier", "czone_sign", "generic_object",
)
"""The 7 `category.name` strings of nuPlan."""

LIDAR_NAMES: dict[int, str] = {0: "top", 1: "right_a_pillar", 2: "left_a_pillar", 3: "back", 4: "front"}
"""`lidar_info` value of a merged-cloud point -> the LiDAR that produced it."""

CAMERA_CHANNELS: tuple[str, ...] = ("CAM_F0", "CAM_B0", "CAM_L0", "CAM_L1", "CAM_L2", "CAM_R0", "CAM_R1", "CAM_R2")

LIDAR_CHANNEL = "MergedPointCloud"


@dataclass(frozen=True)
class VehicleFootprint:
    """The ego vehicle's box relative to the rear axle (ego frame), metres. Default: Chrysler Pacifica."""

    front: float = 4.049
    rear: float = 1.127
    width: float = 2.297
    height: float = 1.777
    wheel_base: float = 3.089

    def box_center_and_size(self) -> tuple[np.ndarray, np.ndarray]:
        """Centre (3,) in the ego frame and size [length, width, height] of the vehicle's box."""
        center = np.array([(self.front - self.rear) / 2.0, 0.0, self.height / 2.0])
        return center, np.array([self.front + self.rear, self.width, self.height])


PACIFICA = VehicleFootprint()


@dataclass
class Boxes:
    """K oriented 3D boxes expressed in one frame (`frame` = "global" or "ego").

    centers (K, 3) m: box centres; sizes (K, 3) m: [length along heading, width, height];
    yaws (K,) rad: heading about +z in `frame`; velocities (K, 3) m/s in `frame`;
    categories, track_tokens, tokens: K strings each (nuPlan category name, track hex, lidar_box hex).
    """

    frame: str
    centers: np.ndarray
    sizes: np.ndarray
    yaws: np.ndarray
    velocities: np.ndarray
    categories: list[str]
    track_tokens: list[str]
    tokens: list[str]

    def __len__(self) -> int:
        return int(len(self.centers))

    @classmethod
    def empty(cls, frame: str) -> "Boxes":
        """No boxes."""
        return cls(frame, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), [], [], [])

    def subset(self, keep: np.ndarray) -> "Boxes":
        """The boxes selected by a boolean mask or index array."""
        idx = np.arange(len(self))[keep]
        return Boxes(
            self.frame, self.centers[idx], self.sizes[idx], self.yaws[idx], self.velocities[idx],
            [self.categories[i] for i in idx], [self.track_tokens[i] for i in idx], [self.tokens[i] for i in idx],
        )

    def transformed(self, T_to_from: np.ndarray, to_frame: str) -> "Boxes":
        """The same boxes in another frame; T_to_from maps points of `self.frame` into `to_frame`.

        Only the yaw of the transform's rotation is applied to the boxes' headings (boxes stay upright).
        """
        return replace(
            self,
            frame=to_frame,
            centers=transform_points(T_to_from, self.centers),
            yaws=np.asarray(wrap_angle(self.yaws + yaw_of(T_to_from[:3, :3])), dtype=np.float64).reshape(-1),
            velocities=rotate_vectors(T_to_from, self.velocities),
        )

    def frame_from_box(self) -> np.ndarray:
        """(K, 4, 4) transforms T_<frame>_from_box of each box."""
        out = np.zeros((len(self), 4, 4))
        for k in range(len(self)):
            out[k] = make_transform(yaw_matrix(self.yaws[k]), self.centers[k])
        return out

    def box_from_frame(self) -> np.ndarray:
        """(K, 4, 4) transforms T_box_from_<frame> of each box."""
        return np.stack([invert_transform(T) for T in self.frame_from_box()]) if len(self) else np.zeros((0, 4, 4))


@dataclass
class PointCloud:
    """One LiDAR sweep. xyz (N, 3) metres in `frame` (float64 as read; float32 for a scene's ego-frame
    sweeps); intensity (N,) float32; ring (N,) int16; lidar_info (N,) int8 in 0..4 (see LIDAR_NAMES), -1
    where unknown."""

    xyz: np.ndarray
    intensity: np.ndarray
    ring: np.ndarray
    lidar_info: np.ndarray
    frame: str

    def __len__(self) -> int:
        return int(len(self.xyz))

    def transformed(self, T_to_from: np.ndarray, to_frame: str) -> "PointCloud":
        """The same points in another frame; T_to_from maps `self.frame` into `to_frame`."""
        return replace(self, xyz=transform_points(T_to_from, self.xyz), frame=to_frame)

    def subset(self, keep: np.ndarray) -> "PointCloud":
        """Points selected by a boolean mask or index array."""
        return PointCloud(self.xyz[keep], self.intensity[keep], self.ring[keep], self.lidar_info[keep], self.frame)


@dataclass
class LogMeta:
    """The single `log` row. map_name is `log.map_version` with any '.gpkg' suffix stripped."""

    token: str
    logfile: str
    vehicle_name: str
    date: str
    timestamp_us: int
    location: str
    map_name: str


@dataclass
class LidarCalibration:
    """The `lidar` row of channel MergedPointCloud. T_ego_from_lidar (4, 4): its stored extrinsic."""

    token: str
    channel: str
    model: str
    T_ego_from_lidar: np.ndarray


@dataclass
class CameraCalibration:
    """A `camera` row. K (3, 3) px; distortion [k1, k2, p1, p2, k3]; T_ego_from_camera (4, 4); size in px."""

    token: str
    channel: str
    model: str
    K: np.ndarray
    distortion: np.ndarray
    T_ego_from_camera: np.ndarray
    width: int
    height: int


@dataclass
class EgoPoseRecord:
    """An `ego_pose` row. T_global_from_ego (4, 4) of the rear axle; velocity, acceleration and
    angular_rate (3,) in the ego frame (m/s, m/s^2, rad/s)."""

    token: str
    timestamp_us: int
    T_global_from_ego: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acceleration: np.ndarray = field(default_factory=lambda: np.zeros(3))
    angular_rate: np.ndarray = field(default_factory=lambda: np.zeros(3))
    epsg: int = 0


@dataclass
class EgoPoseTable:
    """The usable `ego_pose` rows of a log as columns, in time order (one row per timestamp).

    tokens (N,) str: lowercase hex of the DB's BLOB tokens; timestamps_us (N,) int64, strictly increasing;
    xyz (N, 3) rear-axle position in the "global" frame, m; quaternions (N, 4) [w, x, y, z] of
    T_global_from_ego's rotation as stored, within the reader's tolerance of unit norm (normalised where used).
    """

    tokens: np.ndarray
    timestamps_us: np.ndarray
    xyz: np.ndarray
    quaternions: np.ndarray

    def __len__(self) -> int:
        return int(len(self.timestamps_us))

    def T_global_from_ego(self, k: int) -> np.ndarray:
        """(4, 4) pose of row k."""
        return make_transform(quaternion_to_matrix(self.quaternions[k]), self.xyz[k])

    def index_of(self, token: str) -> int:
        """Row of an ego_pose token (hex); KeyError if it is not a usable row."""
        hits = np.flatnonzero(self.tokens == token)
        if not len(hits):
            raise KeyError(token)
        return int(hits[0])


@dataclass
class SceneRecord:
    """A `scene` row. roadblock_ids are map fids (strings)."""

    token: str
    name: str
    goal_ego_pose_token: str | None = None
    roadblock_ids: list[str] = field(default_factory=list)


@dataclass
class TrackRecord:
    """A `track` row: category name and per-track size (m)."""

    token: str
    category: str
    width: float
    length: float
    height: float


@dataclass(slots=True)
class LidarFrame:
    """A `lidar_pc` row (one 20 Hz merged sweep). filename is relative to sensor_blobs/.
    index: position of the frame in the log's time order (0-based). problem: why the frame cannot be used
    (one line, set by the reader: e.g. a repeated timestamp or a filename leaving sensor_blobs), "" if none."""

    token: str
    timestamp_us: int
    filename: str
    scene_token: str
    ego_pose_token: str
    lidar_token: str
    prev_token: str | None = None
    next_token: str | None = None
    index: int = 0
    problem: str = ""


@dataclass
class ImageRecord:
    """An `image` row (10 Hz per camera). filename_jpg is relative to sensor_blobs/."""

    token: str
    timestamp_us: int
    filename_jpg: str
    camera_token: str
    ego_pose_token: str
    prev_token: str | None = None
    next_token: str | None = None


@dataclass
class ImageTable:
    """The `image` rows of a log as columns, time order: tokens, camera_tokens (N,) str (lowercase hex),
    timestamps_us (N,) int64 (-1 where NULL), filenames (N,) bytes (UTF-8, relative to sensor_blobs/)."""

    tokens: np.ndarray
    timestamps_us: np.ndarray
    camera_tokens: np.ndarray
    filenames: np.ndarray

    def __len__(self) -> int:
        return int(len(self.timestamps_us))


@dataclass
class LogContent:
    """Everything the writer puts in one log's DB (point clouds are passed to the writer separately).

    boxes maps a lidar_pc token -> Boxes in the "global" frame (their track_tokens must be in tracks).
    """

    meta: LogMeta
    lidar: LidarCalibration
    cameras: list[CameraCalibration]
    ego_poses: list[EgoPoseRecord]
    scenes: list[SceneRecord]
    frames: list[LidarFrame]
    tracks: list[TrackRecord]
    boxes: dict[str, Boxes]
    images: list[ImageRecord] = field(default_factory=list)


@dataclass
class MapLayer:
    """One vector layer of a map in the UTM frame: shapely geometries and per-feature attribute columns."""

    geometries: np.ndarray
    attributes: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(len(self.geometries))
