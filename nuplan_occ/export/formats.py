"""Export a published dataset to the file layouts that occupancy training code reads.

Both exports keep our grid as it is: arrays indexed [x, y, z] in the ego frame (nuPlan rear axle, x
forward, y left, z up), 400 x 400 x 32 voxels of 0.25 m over x, y in [-50, 50) m, z in [-3, 5) m. Occ3D-
nuScenes arrays are also [x, y, z] in the ego frame, but 200 x 200 x 16 at 0.4 m over [-40, 40]^2 x
[-1, 5.4] m; no resampling is done, so configs must state our shape, range and voxel size.
Besides the frame files, `<dest>/export.json` records the format, grid, label remap and, per frame,
log, scene, token, timestamp and T_global_from_ego (for building a consumer's info file; null where the
dataset does not know them, e.g. an imported release without its logs, whose occ3d folder is
`unknown_log`).
A frame whose members cannot be read (checksum mismatch, truncated or missing shard, undecodable or
unmappable data) is skipped and listed (frame key, token, member, problem); the other frames are
written. Unreadable manifest files are skipped as `open_dataset` skips them (listed too), or refused
with strict=True.

format "occ3d": `<dest>/<log>/<token>/labels.npz` (np.savez_compressed) with
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
  UniScenev2's occupancy loader reads (peers.md section 1 item 11: dense uint8 `.npy` per token under
  `nuplan_quantized_{X}_{Y}_{Z}/`, 0 empty, background 1, object class + 1). Our ids already follow that
  palette (0-8, 12 road, 14 road_line; 13 other_ground is ours), so ids are written unchanged. Masks are
  not part of that layout and are not exported.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from nuplan_occ.dataset import open_dataset
from nuplan_occ.labels import LABELS
from nuplan_occ.storage.errors import ChecksumError, StorageError

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
UNKNOWN_LOG = "unknown_log"
"""occ3d folder of frames whose log is unknown (an imported release without its logs)."""
_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]")


class ExportError(ValueError):
    """The export cannot be written (unknown format, ids outside the remap, unsafe names)."""


def _lut(mapping: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(256,) uint8 lookup table and (256,) bool 'defined' of an id mapping."""
    lut, defined = np.zeros(256, dtype=np.uint8), np.zeros(256, dtype=bool)
    for src, dst in mapping.items():
        lut[src], defined[src] = dst, True
    return lut, defined


def to_occ3d(semantics: np.ndarray, where: str = "semantics") -> np.ndarray:
    """Our uint8 ids -> Occ3D ids (OCC3D_REMAP); ExportError naming `where` for an id outside the map."""
    lut, defined = _lut(OCC3D_REMAP)
    bad = np.setdiff1d(np.unique(semantics), np.flatnonzero(defined))
    if bad.size:
        raise ExportError(f"{where}: ids {bad.tolist()} have no Occ3D mapping")
    return lut[semantics]


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


def _write_frame(frame: dict, dest: Path, fmt: str, shape: tuple[int, int, int]) -> str:
    """Write one frame's file; returns its path relative to dest."""
    token = _safe(frame["token"], "token")
    if fmt == "uniscene":
        rel = f"{uniscene_folder(shape)}/{token}.npy"
        np.save(dest / rel, np.ascontiguousarray(frame["semantics"], dtype=np.uint8))
        return rel
    rel = f"{_safe(frame['log_name'] or UNKNOWN_LOG, 'log name')}/{token}/labels.npz"
    (dest / rel).parent.mkdir(parents=True, exist_ok=True)
    arrays = {"semantics": to_occ3d(frame["semantics"], f"frame {token}")}
    arrays |= {m: frame[m].astype(np.uint8) for m in MASK_MEMBERS if m in frame}
    np.savez_compressed(dest / rel, **arrays)
    return rel


def _pose_or_none(pose: np.ndarray) -> list | None:
    """A pose as nested lists; None when unknown (NaN)."""
    return pose.tolist() if np.all(np.isfinite(pose)) else None


def _group_by_members(ds, indices: range, wanted: tuple[str, ...]) -> dict[tuple[str, ...], list[int]]:
    """Frame indices grouped by which of the `wanted` members they have (one batched read per group)."""
    groups: dict[tuple[str, ...], list[int]] = {}
    for i in indices:
        groups.setdefault(tuple(m for m in wanted if m in ds.members_of(i)), []).append(i)
    return groups


def _frame_entry(frame: dict, dest: Path, fmt: str, shape: tuple[int, int, int]) -> dict:
    """Write one frame's file; its entry in the frame list."""
    return {"file": _write_frame(frame, dest, fmt, shape), "token": frame["token"], "log_name": frame["log_name"],
            "scene_token": frame["scene_token"], "frame_index": frame["frame_index"],
            "timestamp_us": frame["timestamp_us"], "ego_to_global": _pose_or_none(frame["ego_to_global"])}


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


def export_dataset(root: str, dest: str | Path, format: str, *, strict: bool = False) -> dict:  # noqa: A002
    """Write the ok frames of the dataset at `root` under `dest` in `format` ("occ3d" | "uniscene").

    Returns {"format", "source", "dest", "frames", "frames_without": {mask member: count} (occ3d),
    "remap": remap rows (occ3d: our id -> Occ3D id; uniscene: identity), "grid", "skipped": [{"frame",
    "token", "log_name", "member", "problem"}] (frames not written), "damaged_manifest": [one line per
    unreadable manifest file skipped]}; the same plus the frame list is written to `<dest>/export.json`.
    strict: refuse a dataset with an unreadable manifest file (DatasetFormatError).
    """
    if format not in FORMATS:
        raise ExportError(f"format {format!r}: use one of {FORMATS} or mesh")
    ds = open_dataset(root, strict=strict)
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    if format == "uniscene":
        (dest / uniscene_folder(ds.grid.shape)).mkdir(exist_ok=True)
    wanted = ("semantics", *MASK_MEMBERS) if format == "occ3d" else ("semantics",)
    frames, skipped, without = [], [], {m: 0 for m in MASK_MEMBERS}
    for start in range(0, len(ds), BATCH):
        for keys, indices in _group_by_members(ds, range(start, min(start + BATCH, len(ds))), wanted).items():
            for i, frame in _read_batch(ds, indices, keys):
                if isinstance(frame, Exception):
                    skipped.append(_unreadable(ds, i, keys, frame))
                    continue
                try:
                    frames.append(_frame_entry(frame, dest, format, ds.grid.shape))
                except ExportError as exc:
                    skipped.append(_skipped(ds, i, "semantics", exc))
                    continue
                for m in MASK_MEMBERS:
                    without[m] += m not in frame
    if format == "occ3d":
        remap = remap_table()
    else:
        remap = [{"id": i, "name": name, "uniscene_id": i} for i, name in sorted(LABELS.names.items())]
    summary = {"format": format, "source": str(root), "dest": str(dest), "frames": len(frames),
               "frames_without": without if format == "occ3d" else {}, "remap": remap,
               "grid": ds.grid.to_dict(), "skipped": skipped,
               "damaged_manifest": [damaged.describe() for damaged in ds.damaged]}
    (dest / "export.json").write_text(json.dumps({**summary, "frame_list": frames}, indent=1) + "\n")
    return summary
