"""Summary figures of a published dataset, computed from its manifest and dataset.json alone (no shard reads).

- frames: ok / failed counts, failure reasons counted, logs and scenes (unknown, null ones not counted);
- classes: voxel totals per label id over the ok frames (the manifest's `class_hist`), with fractions
  of all voxels and of occupied voxels;
- bytes: stored (compressed) bytes per frame of each member (`<member>_nbytes`), over the frames that
  have the member: frames, mean, median, max, total;
- qa: every `qa_*` column over the ok frames: numeric -> n, median, min, max; bool -> n, fraction
  true; string -> value counts. Nulls (e.g. NaN coverage of an empty sweep) are counted apart;
- damaged: the manifest files skipped as unreadable (`manifest_reader.DamagedFile`): the figures above
  cover the readable rows only, and each entry says whether its shard's frames are missing.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import asdict

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from nuplan_occ.storage.codecs import MEMBERS
from nuplan_occ.storage.manifest_reader import ManifestIndex
from nuplan_occ.storage.metadata import read_metadata
from nuplan_occ.storage.records import STATUS_FAILED, STATUS_OK


def _class_totals(ok: pa.Table, labels: dict) -> list[dict]:
    hist = ok["class_hist"].combine_chunks()
    if len(hist) == 0:
        return []
    counts = hist.values.to_numpy(zero_copy_only=False).reshape(len(hist), -1).sum(axis=0)
    names = {int(c["id"]): c["name"] for c in labels["classes"]}
    total, occupied = int(counts.sum()), int(counts.sum() - counts[0])
    return [
        {"id": i, "name": names.get(i, f"id {i}"), "voxels": int(counts[i]),
         "fraction": counts[i] / total if total else float("nan"),
         "fraction_of_occupied": (counts[i] / occupied if occupied else float("nan")) if i else None}
        for i in np.flatnonzero(counts).tolist()
    ]


def _member_bytes(ok: pa.Table) -> dict[str, dict]:
    out = {}
    for member in MEMBERS:
        column = f"{member}_nbytes"
        if column not in ok.column_names:
            continue
        values = ok[column].drop_null().to_numpy().astype(np.int64)
        if values.size:
            out[member] = {"frames": int(values.size), "mean": float(values.mean()),
                           "median": float(np.median(values)), "max": int(values.max()), "total": int(values.sum())}
    return out


def _qa_summary(ok: pa.Table) -> dict[str, dict]:
    out = {}
    for name in sorted(n for n in ok.column_names if n.startswith("qa_")):
        column = ok[name]
        values = column.drop_null()
        entry: dict = {"n": len(values), "null": column.null_count}
        if pa.types.is_boolean(column.type):
            entry["fraction_true"] = float(pc.mean(values.cast(pa.float64())).as_py()) if len(values) else None
        elif pa.types.is_integer(column.type) or pa.types.is_floating(column.type):
            array = values.to_numpy().astype(np.float64)
            array = array[np.isfinite(array)]
            entry["null"] += len(values) - array.size
            entry["n"] = int(array.size)
            if array.size:
                entry |= {"median": float(np.median(array)), "min": float(array.min()), "max": float(array.max())}
        else:
            entry["counts"] = dict(Counter(str(v) for v in values.to_pylist()).most_common())
        out[name] = entry
    return out


def dataset_stats(root: str, *, strict: bool = False) -> dict:
    """The summary of the dataset at `root` (see module docstring); strict: raise DatasetFormatError on
    an unreadable manifest file instead of skipping it.

    Returns {"root", "frames": {"total", "ok", "failed", "logs", "scenes"}, "failure_reasons": {reason:
    count}, "classes": [{"id", "name", "voxels", "fraction", "fraction_of_occupied"}], "bytes": {member:
    {...}}, "bytes_per_frame": mean stored bytes of an ok frame (all members), "qa": {column: {...}},
    "damaged": [{"path", "problem", "shard_folder", "commit_id", "outcome", "fallback_commit", "line"}]}.
    """
    metadata = read_metadata(root)
    index = ManifestIndex(root, strict=strict)
    table = index.table()
    ok = table.filter(pc.equal(table["status"], STATUS_OK))
    failed = table.filter(pc.equal(table["status"], STATUS_FAILED))
    member_bytes = _member_bytes(ok)
    return {
        "root": root,
        "frames": {"total": table.num_rows, "ok": ok.num_rows, "failed": failed.num_rows,
                   "logs": pc.count_distinct(table["log"]).as_py(),
                   "scenes": pc.count_distinct(table["scene_token"]).as_py()},
        "failure_reasons": dict(Counter(failed["failure_reason"].to_pylist()).most_common()),
        "classes": _class_totals(ok, metadata["labels"]),
        "bytes": member_bytes,
        "bytes_per_frame": (sum(m["total"] for m in member_bytes.values()) / ok.num_rows) if ok.num_rows else 0.0,
        "qa": _qa_summary(ok),
        "damaged": [asdict(d) | {"line": d.describe()} for d in index.damaged],
    }
