"""PyTorch view of a dataset: `OccupancyDataset` yields clips of consecutive frames of one scene.

A clip is T = clip_len ok frames of one scene with consecutive `output_index` (the build's rate: 0.1 s
steps at 10 Hz); a failed or missing frame breaks the run. Item of a clip:
    <key> for key in `keys`: tensor [T, X, Y, Z] (flow [T, X, Y, Z, 3]), dtype as stored
          (semantics uint8, masks bool, instance uint16, flow float16 m/s), each frame in its own ego frame;
    poses: float64 [T, 4, 4], T_first_from_t = inv(ego_to_global[0]) @ ego_to_global[t], i.e. frame t's
           ego frame expressed in the clip's first ego frame (poses[0] = identity);
    ego_to_global: float64 [T, 4, 4]; timestamp_us, frame_index: int64 [T];
    tokens: list of T lidar_pc tokens; scene_token, log_name: str.
With cameras=True (the dataset's sensor metadata, `nuplan_occ.sensors`; MissingSensorsError without it):
    lidar_to_ego: float64 [T, 4, 4]; cams: {channel: {"intrinsic" [T, 3, 3], "distortion" [T, 5],
          "camera_to_ego" [T, 4, 4] (float64), "image_timestamp_us" int64 [T] (-1: no image within 50 ms),
          "image_path": list of T paths relative to the data root (None: no image)}};
    and with data_root given, images: {channel: uint8 [T, H, W, 3]} decoded RGB (MissingSensorsError naming
          the frame when a camera has no image).
Unknown identity (an imported release without its logs): poses NaN, timestamp_us / frame_index -1,
scene_token / log_name None; frames of unknown scene only form clips of length 1.
Clips and subsets are chosen from manifest columns only (see `nuplan_occ.storage.clips`).
Works with DataLoader workers: each worker reopens its shard handles after the fork.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import torch
from PIL import Image

from nuplan_occ.dataset import OccDataset
from nuplan_occ.geometry import invert_transform
from nuplan_occ.storage import clips
from nuplan_occ.storage.errors import DatasetFormatError
from nuplan_occ.storage.sensors import MissingSensorsError


def _index_columns(ds: OccDataset, subset: str | None) -> dict[str, np.ndarray]:
    """Per frame: output_index where stored (-1 elsewhere) and, for a subset, the speeds (NaN where
    null), read in one pass."""
    speeds = ("ego_speed", "max_agent_speed") if subset is not None else ()
    missing = [name for name in speeds if not ds.has_column(name)]
    if missing:
        raise DatasetFormatError(f"{ds.root}: manifest has no {missing[0]!r} column, needed for subsets")
    stored = ("output_index",) if ds.has_column("output_index") else ()
    if not stored + speeds:
        return {"output_index": np.full(len(ds), -1, dtype=np.int64)}
    table = ds.columns([*stored, *speeds])
    columns = {name: table[name].cast(pa.float64()).fill_null(np.nan).to_numpy() for name in speeds}
    columns["output_index"] = (table["output_index"].cast(pa.int64()).fill_null(-1).to_numpy() if stored
                               else np.full(len(ds), -1, dtype=np.int64))
    return columns


def _output_index(ds: OccDataset, scenes: np.ndarray, stored: np.ndarray) -> np.ndarray:
    """The manifest's output_index; derived from frame_index for scenes written without it."""
    if np.all(stored >= 0):
        return stored
    return np.where(stored >= 0, stored, clips.output_index_from_frame_index(scenes, ds.frame_index))


class OccupancyDataset(torch.utils.data.Dataset):
    """Clips of `clip_len` consecutive output frames of one scene (consecutive `output_index`), starts
    `stride` frames apart within a run.

    subset: None (all clips), "spatial" (ego_speed > theta_e) or "temporal" (ego_speed < theta_e and
    max_agent_speed > theta_o), speeds in m/s from the manifest; a clip is in a subset iff all its
    frames are. keys: members to load (each must exist for every frame, never faked). cameras: add each frame's
    camera calibration and LiDAR-to-ego transform; data_root (implies cameras): also the decoded images.
    """

    def __init__(
        self,
        path: str,
        clip_len: int = 1,
        stride: int = 1,
        subset: str | None = None,
        keys: tuple[str, ...] = ("semantics",),
        theta_e: float = 1.0,
        theta_o: float = 2.0,
        cameras: bool = False,
        data_root: str | None = None,
    ):
        self.ds = OccDataset(path)
        self.clip_len, self.stride, self.subset, self.keys = clip_len, stride, subset, tuple(keys)
        self.cameras, self.data_root = cameras or data_root is not None, data_root
        if self.cameras and not self.ds.has_sensors:
            raise MissingSensorsError(f"{path}: no sensor metadata (dataset built before sensors; add it with "
                                      "`nuplan-occ sensors <dataset> <nuPlan data root>`)")
        scenes = self.ds.scene_codes
        columns = _index_columns(self.ds, subset)
        frames = _output_index(self.ds, scenes, columns["output_index"])
        self._order = clips.clip_order(scenes, frames)
        starts = clips.clip_starts(scenes, frames, self._order, clip_len, stride)
        if subset is not None:
            flags = clips.subset_flags(subset, columns["ego_speed"], columns["max_agent_speed"], theta_e, theta_o)
            starts = starts[clips.clips_all_flagged(flags, self._order, starts, clip_len)]
        self._starts = starts

    def __len__(self) -> int:
        return len(self._starts)

    def frame_indices(self, i: int) -> np.ndarray:
        """Indices into the underlying `OccDataset` of clip i's frames, in time order."""
        if not 0 <= i < len(self):
            raise IndexError(f"clip {i} out of range for {len(self)} clips")
        start = self._starts[i]
        return self._order[start: start + self.clip_len]

    def __getitem__(self, i: int) -> dict:
        frames = self.ds.get_many(self.frame_indices(i).tolist(), self.keys)
        ego_to_global = np.stack([f["ego_to_global"] for f in frames])
        first_from_global = invert_transform(ego_to_global[0])
        item = {key: torch.from_numpy(np.stack([f[key] for f in frames])) for key in self.keys}
        item["poses"] = torch.from_numpy(np.einsum("ij,tjk->tik", first_from_global, ego_to_global))
        item["ego_to_global"] = torch.from_numpy(ego_to_global)
        for name in ("timestamp_us", "frame_index"):
            item[name] = torch.tensor([-1 if f[name] is None else f[name] for f in frames], dtype=torch.int64)
        item["tokens"] = [f["token"] for f in frames]
        item["scene_token"] = frames[0]["scene_token"]
        item["log_name"] = frames[0]["log_name"]
        if self.cameras:
            item |= self._camera_items(self.frame_indices(i).tolist(), item["tokens"])
        return item

    def _camera_items(self, indices: list[int], tokens: list[str]) -> dict:
        """lidar_to_ego, cams and (with a data root) images of a clip's frames (class doc)."""
        sensors = [self.ds.sensors(j) for j in indices]
        channels = list(sensors[0]["cameras"])
        cams = {}
        for channel in channels:
            per_frame = [s["cameras"][channel] for s in sensors]
            cams[channel] = {name: torch.from_numpy(np.stack([c[name] for c in per_frame]))
                             for name in ("intrinsic", "distortion", "camera_to_ego")}
            cams[channel]["image_timestamp_us"] = torch.tensor(
                [-1 if c["image_timestamp_us"] is None else c["image_timestamp_us"] for c in per_frame], dtype=torch.int64)
            cams[channel]["image_path"] = [c["image_path"] for c in per_frame]
        out = {"lidar_to_ego": torch.from_numpy(np.stack([s["lidar_to_ego"] for s in sensors])), "cams": cams}
        if self.data_root is not None:
            out["images"] = {channel: torch.from_numpy(np.stack([self._image(cams[channel]["image_path"][t], tokens[t],
                                                                              channel) for t in range(len(indices))]))
                             for channel in channels}
        return out

    def _image(self, path: str | None, token: str, channel: str) -> np.ndarray:
        """The decoded RGB image (H, W, 3) uint8 at `path` under the data root."""
        if path is None:
            raise MissingSensorsError(f"{self.ds.root}: frame {token!r} has no {channel} image within 50 ms")
        with Image.open(Path(self.data_root) / path) as image:
            return np.asarray(image.convert("RGB"))
