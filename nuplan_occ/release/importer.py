"""`import_release(src, out, options)`: the paper's released Nuplan-Occ folder -> our dataset format.

Each release file (see `nuplan_occ.release.files`) becomes one frame: its ids are mapped to ours by the
chosen label map (an id outside the map stops the import with one line naming the file, after
committing what was done), its grid is moved onto ours (z in [-3, 5) m: a release made with z in
[-5, 3) m is shifted by whole voxels; with frame "lidar" and the log's extrinsic at hand it is
resampled into the ego frame, otherwise kept in the LiDAR frame and marked so), and it is written with
`DatasetWriter` into `shards/release/<folder>/part-NNNNN.tar`, `chunk_frames` frames per shard.
A malformed file gets a failed row with its reason (in the manifest, rows of its chunk's shard). The identity (log, scene, frame index, timestamp,
ego_to_global) and filter columns come from the nuPlan DBs when `logs_root` is given; otherwise they
are null. Extra columns per frame: release_folder, release_layout (sparse4 | sparse2 | dense),
release_frame (the frame the stored grid is in: ego | lidar), release_log_matched (null without logs).

Streaming: files are read one at a time; a chunk of at most `chunk_frames` decoded grids (5.1 MB each
at 400 x 400 x 32) is held until its shard is written. Resumable: a rerun into the same OUT with the
same conventions skips tokens already imported (status ok) and retries failed ones. The manifest's unit
is the shard (`storage.fragments`), so a chunk holding a failed frame is redone whole, its frames
read again and written under the same shard key, and its new rows supersede the old; frames of chunks
without failures are skipped. Rows are committed every `commit_every_s` seconds (whole chunks only)
and when the import ends or stops.
"""

from __future__ import annotations

import re
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from nuplan_occ.geometry import invert_transform
from nuplan_occ.io.errors import NuplanFormatError
from nuplan_occ.release.errors import ReleaseFrameError, ReleaseImportError
from nuplan_occ.release.files import FLAT_ORDERS, ReleaseFolder, densify, find_folders, read_frame
from nuplan_occ.release.label_maps import DEFAULT_BY_LAYOUT, ReleaseLabelMap, load_label_map
from nuplan_occ.release.logs import FrameMeta, LogIndex
from nuplan_occ.release.regrid import output_grid, resample, source_grid
from nuplan_occ.storage import DatasetWriter, FrameRecord, read_manifest, read_metadata, shard_exists
from nuplan_occ.storage.errors import DatasetFormatError
from nuplan_occ.storage.records import STATUS_FAILED, STATUS_OK

FRAMES = ("ego", "lidar")
SOURCE = "UniScenev2 Nuplan-Occ release (import-release)"
_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]")


@dataclass(frozen=True)
class ImportOptions:
    """layout: auto | sparse4 | sparse2 | dense. z_min: lower z bound of the release grid, m (-3; -5 for
    the mini split's r800_old). frame: ego | lidar (the release grid's frame). labels: a label map name
    or FILE.json (None: raw-sparse for sparse files, uniscene for dense). logs_root: nuPlan data root
    whose DBs give identity and poses (None: they stay null). flat_order: xyz | zyx, the [N, 2] files'
    flat index order."""

    layout: str = "auto"
    z_min: float = -3.0
    frame: str = "ego"
    labels: str | None = None
    logs_root: str | None = None
    flat_order: str = "xyz"
    chunk_frames: int = 32
    commit_every_s: float = 10.0


@dataclass
class ImportSummary:
    """Counts of one run: frames imported (ok), failed (with reasons), skipped (already imported)."""

    folders: int = 0
    imported: int = 0
    failed: int = 0
    skipped: int = 0
    failure_reasons: Counter = field(default_factory=Counter)


def _conventions(options: ImportOptions, kind: str, label_map: ReleaseLabelMap) -> dict:
    """The dataset.json "release" entry: what a reader must know about where the frames came from."""
    return {
        "source": SOURCE,
        "layout": options.layout,
        "file_kind": kind,
        "label_map": label_map.to_dict(),
        "source_z_range_m": [options.z_min, options.z_min + 8.0],
        "source_frame": options.frame,
        "stored_frame": "ego, except frames whose release_frame column says lidar (no LiDAR extrinsic found)",
        "flat_index_order": options.flat_order if kind == "sparse" else None,
        "identity_from_logs": options.logs_root is not None,
        "unknown_fields": "null (log, scene, frame_index, timestamp_us, ego_to_global without the logs)",
        "pose": "logged ego pose at the lidar_pc timestamp (not refined)" if options.logs_root else None,
    }


def _check_options(options: ImportOptions) -> None:
    if options.frame not in FRAMES:
        raise ReleaseImportError(f"--frame {options.frame!r}: use ego or lidar")
    if options.flat_order not in FLAT_ORDERS:
        raise ReleaseImportError(f"--flat-order {options.flat_order!r}: use one of {', '.join(FLAT_ORDERS)}")
    if options.chunk_frames < 1:
        raise ReleaseImportError(f"chunk_frames must be >= 1, got {options.chunk_frames}")


@dataclass
class _Previous:
    """What an earlier run left in OUT: `done`, tokens of chunks without failures (skipped); `redo`,
    per release folder the chunks holding a failed frame, as shard key -> its tokens."""

    done: set[str] = field(default_factory=set)
    redo: dict[str, dict[str, set[str]]] = field(default_factory=dict)


def _previous(out: str, conventions: dict) -> _Previous:
    """The earlier runs' chunks in `out`; ReleaseImportError if `out` holds another kind of data."""
    try:
        metadata = read_metadata(out)
    except DatasetFormatError:
        return _Previous()
    if metadata.get("release") != conventions:
        raise ReleaseImportError(f"{out}: already holds a dataset not imported with these options "
                                 f"(layout, z, frame, labels, logs); import into a new OUT")
    rows = read_manifest(out, ["token", "status", "shard", "release_folder"]).to_pylist()
    failed_shards = {row["shard"] for row in rows if row["status"] != STATUS_OK}
    previous = _Previous()
    for row in rows:
        if row["shard"] in failed_shards:
            previous.redo.setdefault(row["release_folder"], {}).setdefault(row["shard"], set()).add(row["token"])
        else:
            previous.done.add(row["token"])
    return previous


class _Importer:
    """One run: the writer, the chunk being filled and the rows not yet committed."""

    def __init__(self, out: str, options: ImportOptions, folders: list[ReleaseFolder], label_map: ReleaseLabelMap):
        self.options, self.label_map = options, label_map
        try:
            self.src_grid = source_grid(options.z_min, folders[0].shape)
        except ValueError as exc:
            raise ReleaseImportError(f"{folders[0].path}: {exc}") from None
        self.out_grid = output_grid(self.src_grid)
        self.conventions = _conventions(options, folders[0].kind, label_map)
        self.previous = _previous(out, self.conventions)
        self.writer = DatasetWriter(out, {"params": {"import_release": asdict(options)}, "release": self.conventions},
                                    grid=self.out_grid)
        self.out = out
        try:
            self.logs = LogIndex(options.logs_root) if options.logs_root else None
        except NuplanFormatError as exc:
            raise ReleaseImportError(f"--logs-root: {exc}") from None
        self.summary = ImportSummary()
        self.records: list[FrameRecord] = []
        self.pending: list[dict] = []
        self.last_commit = time.monotonic()
        self.part = 0
        self.folder: ReleaseFolder | None = None

    def frame_record(self, path: Path, folder: ReleaseFolder) -> FrameRecord:
        token = path.stem
        meta: FrameMeta | None = self.logs.lookup(token, folder.name) if self.logs else None
        record = FrameRecord(
            log=meta.log if meta else None, log_id=meta.log_id if meta else None,
            scene_token=meta.scene_token if meta else None, scene_name=meta.scene_name if meta else None,
            frame_index=meta.frame_index if meta else None, token=token,
            timestamp_us=meta.timestamp_us if meta else None, ego_to_global=meta.ego_to_global if meta else None,
            columns={"release_folder": folder.name, "release_layout": None, "release_frame": None,
                     "release_log_matched": (meta is not None) if self.logs else None, **(meta.columns if meta else {})})
        try:
            frame = read_frame(path, folder, self.options.layout, self.options.flat_order)
        except ReleaseFrameError as exc:
            record.status, record.failure_reason = STATUS_FAILED, f"{path.name}: {exc}"
            return record
        semantics = densify(frame, self.label_map.to_ours(frame.labels, str(path)), folder.shape)
        converted = self.options.frame == "lidar" and meta is not None
        T_src_from_out = invert_transform(meta.T_ego_from_lidar) if converted else np.eye(4)
        record.arrays = {"semantics": resample(semantics, self.src_grid, self.out_grid, T_src_from_out)}
        record.columns["release_layout"] = frame.layout
        record.columns["release_frame"] = "lidar" if self.options.frame == "lidar" and not converted else "ego"
        return record

    def next_shard_key(self, folder: ReleaseFolder) -> str:
        while True:
            key = f"release/{_UNSAFE.sub('_', folder.name)}/part-{self.part:05d}"
            self.part += 1
            if not shard_exists(self.out, key):
                return key

    def flush(self, force_commit: bool = False, shard_key: str | None = None) -> None:
        """Write the chunk being filled (to `shard_key`, None: the folder's next unused key) and commit
        the pending rows when due."""
        records, self.records = self.records, []
        if records:
            self.pending += self.writer.write_shard(shard_key or self.next_shard_key(self.folder), records)
        if self.pending and (force_commit or time.monotonic() - self.last_commit >= self.options.commit_every_s):
            self.writer.commit(self.pending)
            self.pending, self.last_commit = [], time.monotonic()

    def add_frame(self, path: Path, folder: ReleaseFolder, on_frame: Callable[[str], None]) -> None:
        record = self.frame_record(path, folder)
        self.records.append(record)
        if record.status == STATUS_OK:
            self.summary.imported += 1
        else:
            self.summary.failed += 1
            self.summary.failure_reasons[record.failure_reason.split(": ", 1)[1]] += 1
        on_frame(record.status)

    def run_folder(self, folder: ReleaseFolder, on_frame: Callable[[str], None]) -> None:
        self.folder, self.part = folder, 0
        files = self.logs.order_by_log(folder.files) if self.logs and folder.kind == "dense" else folder.files
        redo = self.previous.redo.get(folder.name, {})
        for shard_key, tokens in sorted(redo.items()):  # chunks with failed frames, rewritten whole
            for path in files:
                if path.stem in tokens:
                    self.add_frame(path, folder, on_frame)
            self.flush(shard_key=shard_key)
        redone = set().union(*redo.values())
        for path in files:
            if path.stem in self.previous.done:
                self.summary.skipped += 1
                on_frame("skipped")
            elif path.stem not in redone:
                self.add_frame(path, folder, on_frame)
                if len(self.records) >= self.options.chunk_frames:
                    self.flush()
        self.flush()
        self.summary.folders += 1


def import_release(
    src: str | Path,
    out: str,
    options: ImportOptions = ImportOptions(),
    on_folder: Callable[[ReleaseFolder], None] = lambda folder: None,
    on_frame: Callable[[str], None] = lambda status: None,
) -> ImportSummary:
    """Import the release at `src` into the dataset root `out` (see module docstring).

    on_folder(folder) is called before each folder, on_frame(status) after each file ("ok", "failed",
    "skipped"). Raises ReleaseImportError (one line naming the file or folder) when the import cannot go
    on; rows of frames done before are committed first.
    """
    _check_options(options)
    folders = find_folders(Path(src), options.layout)
    kind = folders[0].kind
    label_map = load_label_map(options.labels or DEFAULT_BY_LAYOUT["dense" if kind == "dense" else "sparse4"])
    run = _Importer(out, options, folders, label_map)
    try:
        for folder in folders:
            on_folder(folder)
            run.run_folder(folder, on_frame)
    finally:
        run.flush(force_commit=True)  # the frames finished before a stop are written and committed
        if run.logs is not None:
            run.logs.close()
    return run.summary
