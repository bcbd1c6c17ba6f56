"""Export a published dataset to the file layouts that occupancy training code reads, with its info files.

Grids are arrays indexed [x, y, z]. By default ("--frame", "--grid" unset) the occ3d export keeps our grid
(ego frame = nuPlan rear axle, x forward, y left, z up; 400 x 400 x 32 voxels of 0.25 m over x, y in
[-50, 50) m, z in [-3, 5) m) and the uniscene export moves it into the LiDAR frame, as UniScene v2's grids are
(same bounds and voxel size around the LiDAR; `regrid.to_lidar_frame`, which needs the dataset's sensor
metadata: without it the uniscene grids stay in the ego frame and the summary's "warnings" says so, while an
explicit frame "lidar" is refused). frame "ego" | "lidar" chooses explicitly; grid "occ3d" | "<size>m" coarsens afterwards
(`regrid.coarsen`: rules and the uncovered part stated there). export.json records the frame and grid written.
Besides the frame files, `<dest>/export.json` records the format, frame, grid, label remap and, per frame,
log, scene, token, timestamp and T_global_from_ego (null where the dataset does not know them, e.g. an imported
release without its logs), and an info pickle (`export.infos`: per-frame token, poses, LiDAR file and
camera records) is written next to the grids. Without sensor metadata (a dataset built before it, see
`nuplan_occ.sensors.add_sensors`) the records have no lidar_path, lidar2ego_* or cams, and the summary's
"sensors" is false.
A frame whose members cannot be read (checksum mismatch, truncated or missing shard, undecodable or
unmappable data) is skipped and listed (frame key, token, member, problem); the other frames are
written. Unreadable manifest files are skipped as `open_dataset` skips them (listed too), or refused
with strict=True.

format "occ3d": `<dest>/gts/<scene>/<token>/labels.npz` (np.savez_compressed), <scene> = `scene-<scene_token>`
  (unique across logs, unlike nuPlan's scene names, which restart in every log; `unknown_scene` when unknown),
  and `<dest>/occ_infos.pkl` = {"infos": [frame_info + occ_path], "metadata": {"version"}}; occ_path is
  `gts/<scene>/<token>`, relative to dest, the folder the loaders join "labels.npz" to; scene_name is <scene>
  too (code that groups frames by it must not merge scenes of different logs), nuplan_scene_name the log's.
  The npz holds
    semantics    uint8 [X, Y, Z], Occ3D-nuScenes id layout (classes 0-16, free = 17), remapped by OCC3D_REMAP;
    mask_lidar   uint8 0/1, when the frame has the member (omitted otherwise, never invented);
    mask_camera  uint8 0/1, likewise.
  OCC3D_REMAP (our id  name -> Occ3D id  name), injective so the export is lossless:
      0 empty          -> 17 free
      1 other          -> 15 manmade        (walls, poles, structures: nuScenes' manmade)
      2 vehicle        ->  4 car            (nuPlan has one vehicle class; bus/truck/trailer ids stay unused)
      3 bicycle        ->  2 bicycle
      4 pedestrian     ->  7 pedestrian
      5 traffic_cone   ->  8 traffic_cone
      6 barrier        ->  1 barrier
      7 czone_sign     ->  5 construction_vehicle  (no Occ3D counterpart; nuScenes files signs under manmade,
                                                    which `other` holds, so it borrows this object id,
                                                    which nuPlan data never produces)
      8 generic_object ->  0 others
     12 road           -> 11 driveable_surface
     13 other_ground   -> 13 sidewalk       (walkways and verges outside the drivable polygons)
     14 road_line      -> 12 other_flat     (painted lines; nuScenes' other_flat holds delimiters)
  Occ3D ids 3, 6, 9, 10, 14, 16 never occur. `invert_occ3d` maps back.

format "uniscene": `<dest>/nuplan_quantized_<X>_<Y>_<Z>/<token>.npy`, dense uint8 [X, Y, Z], the layout
  UniScene v2's occupancy loaders read (0 empty, background 1, object class + 1, 12 road, 14 road line), and
  `<dest>/nuplan_infos.pkl` = {"infos": [frame_info + occ_path], "scene_tokens": [[tokens of one scene in
  time order], ...], "metadata"}: what its renderer reads (`infos['infos']` by token, each with `cams`, and
  `infos['scene_tokens']`). UNISCENE_REMAP keeps every id: ours are UniScene's numbers (0 empty,
  1 background/other, objects 2-8, 12 road, 14 road line), and our 13 other_ground (walkways and verges
  outside the drivable area) stays 13, which UniScene's palette calls "sidewalk", the nearest meaning; its
  own pipeline never writes 13, so a model trained only on its data has no signal for that id (map 13 to 1
  to reproduce its label set). Masks are not part of that layout and are not exported.
"""

from __future__ import annotations

import json
import pickle
import re
from pathlib import Path

import numpy as np

from nuplan_occ.dataset import open_dataset
from nuplan_occ.export.infos import frame_info
from nuplan_occ.export.regrid import (
    COARSEN_RULES, LIDAR_FRAME_RULE, GridError, coarsen, target_grid, to_lidar_frame,
)
from nuplan_occ.labels import LABELS
from nuplan_occ.storage.errors import ChecksumError, StorageError
from nuplan_occ.storage.sensors import MissingSensorsError

FORMATS = ("occ3d", "uniscene")
BATCH = 8
"""Frames fetched together (adjacent frames of a shard cost one read)."""

OCC3D_NAMES = {
    0: "others", 1: "barrier", 2: "bicycle", 3: "bus", 4: "car", 5: "construction_vehicle", 6: "motorcycle",
    7: "pedestrian", 8: "traffic_cone", 9: "trailer", 10: "truck", 11: "driveable_surface", 12: "other_flat",
    13: "sidewalk", 14: "terrain", 15: "manmade", 16: "vegetation", 17: "free",
}
OCC3D_FREE = 17
OCC3D_REMAP = {0: 17, 1: 15, 2: 4, 3: 2, 4: 7, 5: 8, 6: 1, 7: 5, 8: 0, 12: 11, 13: 13, 14: 12}
"""Our semantic id -> Occ3D-nuScenes id (see module docstring)."""
MASK_MEMBERS = ("mask_lidar", "mask_camera")
UNKNOWN_SCENE = "unknown_scene"
"""occ3d scene folder of frames whose scene is unknown (an imported release without its logs)."""
UNISCENE_REMAP = {i: i for i in (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 13, 14)}
"""Our semantic id -> UniScene v2 id: unchanged, 13 other_ground included (module docstring)."""
UNISCENE_NAMES = {13: "sidewalk"}
"""UniScene's palette names where they differ from ours."""
INFO_FILES = {"occ3d": "occ_infos.pkl", "uniscene": "nuplan_infos.pkl"}
DEFAULT_FRAME = {"occ3d": "ego", "uniscene": "lidar"}
INFO_VERSION = "nuplan-occ"
_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]")


class ExportError(ValueError):
    """The export cannot be written (unknown format, ids outside the remap, unsafe names)."""


def _lut(mapping: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(256,) uint8 lookup table and (256,) bool 'defined' of an id mapping."""
    lut, defined = np.zeros(256, dtype=np.uint8), np.zeros(256, dtype=bool)
    for src, dst in mapping.items():
        lut[src], defined[src] = dst, True
    return lut, defined


def _remap(semantics: np.ndarray, mapping: dict[int, int], where: str, consumer: str) -> np.ndarray:
    """uint8 ids mapped by `mapping`; ExportError naming `where` for an id outside the map."""
    lut, defined = _lut(mapping)
    bad = np.setdiff1d(np.unique(semantics), np.flatnonzero(defined))
    if bad.size:
        raise ExportError(f"{where}: ids {bad.tolist()} have no {consumer} mapping")
    return lut[semantics]


def to_occ3d(semantics: np.ndarray, where: str = "semantics") -> np.ndarray:
    """Our uint8 ids -> Occ3D ids (OCC3D_REMAP); ExportError naming `where` for an id outside the map."""
    return _remap(semantics, OCC3D_REMAP, where, "Occ3D")


def invert_occ3d(semantics: np.ndarray, where: str = "semantics") -> np.ndarray:
    """Occ3D ids written by `to_occ3d` -> our uint8 ids; ExportError for ids the export never writes."""
    lut, defined = _lut({dst: src for src, dst in OCC3D_REMAP.items()})
    bad = np.setdiff1d(np.unique(semantics), np.flatnonzero(defined))
    if bad.size:
        raise ExportError(f"{where}: Occ3D ids {bad.tolist()} are not produced by this export")
    return lut[semantics]


def remap_table() -> list[dict]:
    """The Occ3D remap as rows {"id", "name", "occ3d_id", "occ3d_name"} (in export.json and the result)."""
    return [{"id": src, "name": LABELS.names[src], "occ3d_id": dst, "occ3d_name": OCC3D_NAMES[dst]}
            for src, dst in sorted(OCC3D_REMAP.items())]


def _safe(name: str, what: str) -> str:
    if not name or name in (".", "..") or _UNSAFE.search(name):
        raise ExportError(f"{what} {name!r} cannot be used as a folder/file name")
    return name


def uniscene_folder(shape: tuple[int, int, int]) -> str:
    """`nuplan_quantized_<X>_<Y>_<Z>` for a grid shape."""
    return "nuplan_quantized_{}_{}_{}".format(*shape)


def scene_folder(scene_token: str | None) -> str:
    """occ3d scene folder: `scene-<scene_token>` (`unknown_scene` when unknown)."""
    return f"scene-{_safe(scene_token, 'scene token')}" if scene_token else UNKNOWN_SCENE


def _write_frame(frame: dict, dest: Path, fmt: str, shape: tuple[int, int, int]) -> tuple[str, str]:
    """Write one frame's file; returns (its path relative to dest, the info record's occ_path)."""
    token = _safe(frame["token"], "token")
    if fmt == "uniscene":
        rel = f"{uniscene_folder(shape)}/{token}.npy"
        np.save(dest / rel, _remap(frame["semantics"], UNISCENE_REMAP, f"frame {token}", "UniScene"))
        return rel, rel
    folder = f"gts/{scene_folder(frame['scene_token'])}/{token}"
    (dest / folder).mkdir(parents=True, exist_ok=True)
    arrays = {"semantics": to_occ3d(frame["semantics"], f"frame {token}")}
    arrays |= {m: frame[m].astype(np.uint8) for m in MASK_MEMBERS if m in frame}
    np.savez_compressed(dest / folder / "labels.npz", **arrays)
    return f"{folder}/labels.npz", folder


def _pose_or_none(pose: np.ndarray) -> list | None:
    """A pose as nested lists; None when unknown (NaN)."""
    return pose.tolist() if np.all(np.isfinite(pose)) else None


def _group_by_members(ds, indices: range, wanted: tuple[str, ...]) -> dict[tuple[str, ...], list[int]]:
    """Frame indices grouped by which of the `wanted` members they have (one batched read per group)."""
    groups: dict[tuple[str, ...], list[int]] = {}
    for i in indices:
        groups.setdefault(tuple(m for m in wanted if m in ds.members_of(i)), []).append(i)
    return groups


def _frame_entry(frame: dict, dest: Path, fmt: str, shape: tuple[int, int, int]) -> tuple[dict, str]:
    """Write one frame's file; (its entry in the frame list, its occ_path)."""
    rel, occ_path = _write_frame(frame, dest, fmt, shape)
    entry = {"file": rel, "token": frame["token"], "log_name": frame["log_name"], "scene_token": frame["scene_token"],
             "frame_index": frame["frame_index"], "timestamp_us": frame["timestamp_us"],
             "ego_to_global": _pose_or_none(frame["ego_to_global"])}
    return entry, occ_path


READ_ERRORS = (StorageError, OSError)
"""What reading one frame's members may raise for damaged data (checksum, truncated or missing shard)."""


def _skipped(ds, i: int, member: str, exc: Exception) -> dict:
    """The skipped-frame entry of frame i: `member` could not be read or converted (`exc`)."""
    identity = ds.identity(i)
    frame = exc.frame_key if isinstance(exc, ChecksumError) else ds.frame_key(i)
    return {"frame": frame, "token": identity["token"], "log_name": identity["log_name"], "member": member,
            "problem": str(exc)}


def _unreadable(ds, i: int, keys: tuple[str, ...], exc: Exception) -> dict:
    """The skipped-frame entry of frame i whose members `keys` could not be read together (`exc`): the
    first member that fails on its own is named."""
    if isinstance(exc, ChecksumError):
        return _skipped(ds, i, exc.member, exc)
    for member in keys:
        try:
            ds.get(i, keys=(member,))
        except READ_ERRORS as own:
            return _skipped(ds, i, member, own)
    return _skipped(ds, i, keys[0], exc)


def _read_batch(ds, indices: list[int], keys: tuple[str, ...]) -> list[tuple[int, dict | Exception]]:
    """(index, frame or the error reading it) of frames `indices`, read together; when that fails, one
    frame at a time, so that only the bad frames fail."""
    try:
        return list(zip(indices, ds.get_many(indices, keys=keys)))
    except READ_ERRORS:
        pass
    out: list[tuple[int, dict | Exception]] = []
    for i in indices:
        try:
            out.append((i, ds.get(i, keys=keys)))
        except READ_ERRORS as exc:
            out.append((i, exc))
    return out


class _Placement:
    """How frames are placed: grid frame ("ego" | "lidar"), optional coarser target grid, output grid."""

    def __init__(self, ds, fmt: str, frame: str | None, grid: str | None):
        self.frame = frame or DEFAULT_FRAME[fmt]
        self.warnings: list[str] = []
        if self.frame not in ("ego", "lidar"):
            raise ExportError(f"frame {self.frame!r}: use ego or lidar")
        if self.frame == "lidar" and not ds.has_sensors:
            if frame is not None:
                raise ExportError(f"{ds.root}: --frame lidar needs the LiDAR-to-ego transform, and the dataset has no "
                                  "sensor metadata (add it with `nuplan-occ sensors <dataset> <nuPlan data root>`)")
            self.frame = "ego"
            self.warnings.append(f"{ds.root} has no sensor metadata: grids left in the ego (rear-axle) frame, not "
                                 f"the LiDAR frame {fmt} uses (add it with `nuplan-occ sensors <dataset> <data root>`)")
        try:
            self.target = target_grid(grid, ds.grid) if grid else None
        except GridError as exc:
            raise ExportError(str(exc)) from None
        self.source = ds.grid
        self.shape = (self.target or ds.grid).shape

    def place(self, frame: dict, sensors: dict | None) -> dict:
        """The frame's members in the export's frame and grid."""
        if self.frame == "lidar":
            frame = to_lidar_frame(frame, self.source, sensors["lidar_to_ego"])
        return coarsen(frame, self.source, self.target) if self.target else frame

    def grid_dict(self) -> dict:
        """The output grid as export.json records it."""
        out = (self.target or self.source).to_dict()
        out["frame"] = ("LiDAR (the log's MergedPointCloud frame): bounds around the LiDAR" if self.frame == "lidar"
                        else out["frame"])
        return out


def _sensors_or_none(ds, i: int) -> dict | None:
    try:
        return ds.sensors(i)
    except MissingSensorsError:
        return None


def _info_file(fmt: str, infos: list[dict]) -> dict:
    """The info pickle's content: {"infos", "metadata"} (+ "scene_tokens" for uniscene, scenes in order of first
    frame, tokens in time order)."""
    content = {"infos": infos, "metadata": {"version": INFO_VERSION}}
    if fmt == "uniscene":
        scenes: dict[object, list[dict]] = {}
        for info in infos:
            scenes.setdefault(info["scene_token"] or info["token"], []).append(info)
        content["scene_tokens"] = [[i["token"] for i in sorted(frames, key=lambda i: i["timestamp"] or 0)]
                                   for frames in scenes.values()]
    return content


def export_dataset(root: str, dest: str | Path, format: str, *, strict: bool = False,  # noqa: A002
                   frame: str | None = None, grid: str | None = None) -> dict:
    """Write the ok frames of the dataset at `root` under `dest` in `format` ("occ3d" | "uniscene").

    frame: "ego" | "lidar" (None: the format's, DEFAULT_FRAME); grid: None (ours), "occ3d" or "<size>m".
    Returns {"format", "source", "dest", "frames", "frame" (written), "grid" (written), "source_grid",
    "frames_without": {mask member: count} (occ3d), "remap": rows (our id -> the consumer's id), "info_file",
    "sensors": whether camera / LiDAR records were written, "frames_without_cameras", "warnings", "skipped":
    [{"frame", "token", "log_name", "member", "problem"}] (frames not written), "damaged_manifest": [one line per
    unreadable manifest file skipped]}; the same plus the frame list is written to `<dest>/export.json`.
    strict: refuse a dataset with an unreadable manifest file (DatasetFormatError).
    """
    if format not in FORMATS:
        raise ExportError(f"format {format!r}: use one of {FORMATS} or mesh")
    ds = open_dataset(root, strict=strict)
    placement = _Placement(ds, format, frame, grid)
    scene_names = ds.column("scene_name").to_pylist() if ds.has_column("scene_name") else [None] * len(ds)
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    if format == "uniscene":
        (dest / uniscene_folder(placement.shape)).mkdir(exist_ok=True)
    wanted = ("semantics", *MASK_MEMBERS) if format == "occ3d" else ("semantics",)
    frames, infos, skipped, without = [], [], [], {m: 0 for m in MASK_MEMBERS}
    no_cameras = 0
    for start in range(0, len(ds), BATCH):
        for keys, indices in _group_by_members(ds, range(start, min(start + BATCH, len(ds))), wanted).items():
            for i, data in _read_batch(ds, indices, keys):
                if isinstance(data, Exception):
                    skipped.append(_unreadable(ds, i, keys, data))
                    continue
                sensors = _sensors_or_none(ds, i) if ds.has_sensors else None
                if placement.frame == "lidar" and sensors is None:
                    skipped.append(_skipped(ds, i, "sensors", MissingSensorsError(
                        f"frame {data['token']!r} has no sensor metadata (LiDAR-to-ego transform)")))
                    continue
                try:
                    entry, occ_path = _frame_entry(placement.place(data, sensors), dest, format, placement.shape)
                except ExportError as exc:
                    skipped.append(_skipped(ds, i, "semantics", exc))
                    continue
                frames.append(entry)
                info = frame_info(data, scene_names[i], sensors, placement.frame) | {"occ_path": occ_path}
                if format == "occ3d":  # the gts folder: unique, where nuPlan's scene names repeat across logs
                    info |= {"scene_name": scene_folder(data["scene_token"]), "nuplan_scene_name": scene_names[i]}
                infos.append(info)
                no_cameras += len(info.get("cams", {})) < len(sensors["cameras"]) if sensors else 1
                for m in MASK_MEMBERS:
                    without[m] += m not in data
    if format == "occ3d":
        remap = remap_table()
    else:
        remap = [{"id": i, "name": LABELS.names[i], "uniscene_id": j,
                  "uniscene_name": UNISCENE_NAMES.get(j, LABELS.names[i])} for i, j in sorted(UNISCENE_REMAP.items())]
    with open(dest / INFO_FILES[format], "wb") as f:
        pickle.dump(_info_file(format, infos), f, protocol=4)
    summary = {"format": format, "source": str(root), "dest": str(dest), "frames": len(frames),
               "frame": placement.frame, "grid": placement.grid_dict(), "source_grid": ds.grid.to_dict(),
               "grid_rules": {"frame": LIDAR_FRAME_RULE if placement.frame == "lidar" else None,
                              "coarsen": COARSEN_RULES if placement.target else None},
               "frames_without": without if format == "occ3d" else {}, "remap": remap,
               "info_file": INFO_FILES[format], "sensors": ds.has_sensors, "frames_without_cameras": no_cameras,
               "warnings": placement.warnings, "skipped": skipped,
               "damaged_manifest": [damaged.describe() for damaged in ds.damaged]}
    (dest / "export.json").write_text(json.dumps({**summary, "frame_list": frames}, indent=1) + "\n")
    return summary
