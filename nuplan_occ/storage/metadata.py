"""`dataset.json`: what a reader needs besides the manifest (grid, labels, member codecs, params).

No creation time is stored, so reruns with equal inputs publish byte-identical files.
"""

from __future__ import annotations

import json
from collections.abc import Mapping

import nuplan_occ
from nuplan_occ import schemas
from nuplan_occ.grid import GridSpec
from nuplan_occ.storage.codecs import MEMBERS
from nuplan_occ.storage.errors import DatasetFormatError, InvalidFrameError
from nuplan_occ.storage.fsio import resolve

FORMAT_NAME = "nuplan-occ-tar-shards"
SCHEMA_VERSION = 2
METADATA_NAME = "dataset.json"
LAYOUT = {
    "manifest": "manifest/**/*.parquet: one fragment per scene and commit (row per frame); per scene_token the "
                "rows of the greatest commit_id are visible; a frame exists iff its row is visible",
    "shards": "shards/<shard>.tar",
    "member_name": "<frame_key>.<suffix>",
    "frame_key": "{log}-{frame_index:06d}, characters of log outside [A-Za-z0-9_-] replaced by '_'",
    "frame_json": "<frame_key>.json: identity, pose and extra columns of the frame",
}


def label_ids(labels: Mapping) -> list[int]:
    """Sorted label ids of a label map dict (schemas/labels.json layout)."""
    return sorted(int(c["id"]) for c in labels["classes"])


def build_metadata(user: Mapping, grid: GridSpec, levels: Mapping[str, int]) -> dict:
    """The dataset.json content: `user` (must hold "params") plus the format's own keys."""
    if "params" not in user:
        raise InvalidFrameError("dataset metadata needs a 'params' entry")
    labels = schemas.load("labels")
    own = {
        "format": FORMAT_NAME,
        "schema_version": SCHEMA_VERSION,
        "software_version": nuplan_occ.__version__,
        "grid": grid.to_dict(),
        "labels": labels,
        "members": {name: spec.describe(grid, levels[name]) for name, spec in MEMBERS.items()},
        "class_hist_length": label_ids(labels)[-1] + 1,
        "layout": LAYOUT,
    }
    clash = sorted(set(user) & set(own))
    if clash:
        raise InvalidFrameError(f"dataset metadata keys {clash} are set by the writer")
    metadata = {**user, **own}
    try:
        metadata_bytes(metadata)
    except (TypeError, ValueError) as exc:
        raise InvalidFrameError(f"dataset metadata is not JSON-serialisable: {exc}") from exc
    return metadata


def metadata_bytes(metadata: Mapping) -> bytes:
    """Canonical serialisation (sorted keys, 2-space indent, trailing newline)."""
    return (json.dumps(metadata, sort_keys=True, indent=2, allow_nan=False) + "\n").encode()


def read_metadata(root: str) -> dict:
    """The dataset.json of a root."""
    fs, path = resolve(root)
    target = f"{path}/{METADATA_NAME}"
    try:
        return json.loads(fs.cat_file(target))
    except FileNotFoundError as exc:
        raise DatasetFormatError(f"{root}: no {METADATA_NAME}") from exc
    except json.JSONDecodeError as exc:
        raise DatasetFormatError(f"{target}: not JSON ({exc})") from exc
