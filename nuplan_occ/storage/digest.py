"""`content_digests(root)`: what a dataset publishes, as sha256 per item, independent of commit ids.

Items: "dataset.json", every "shards/<key>.tar", and "manifest": the visible manifest rows in manifest
order without their commit ids, as canonical Parquet bytes. Two builds with equal inputs and params
have equal digests however their commits were split, interleaved or compacted.
"""

from __future__ import annotations

import hashlib

from nuplan_occ.storage.fragments import COMMIT_COLUMN
from nuplan_occ.storage.fsio import resolve
from nuplan_occ.storage.manifest import to_parquet_bytes
from nuplan_occ.storage.manifest_reader import read_manifest
from nuplan_occ.storage.metadata import METADATA_NAME


def content_digests(root: str) -> dict[str, str]:
    """sha256 hex of every published item of `root` (see module docstring)."""
    fs, path = resolve(root)
    try:
        shards = sorted(p for p in fs.find(f"{path}/shards") if p.endswith(".tar") and "/." not in p)
    except FileNotFoundError:
        shards = []
    out = {p[len(path) + 1:]: hashlib.sha256(fs.cat_file(p)).hexdigest() for p in shards}
    out[METADATA_NAME] = hashlib.sha256(fs.cat_file(f"{path}/{METADATA_NAME}")).hexdigest()
    table = read_manifest(root)
    out["manifest"] = hashlib.sha256(to_parquet_bytes(table.drop_columns([COMMIT_COLUMN]))).hexdigest()
    return out
