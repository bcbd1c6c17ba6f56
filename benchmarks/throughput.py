"""`decode_throughput(root, n)`: how fast the semantics member is read and decoded (for the bench)."""

from __future__ import annotations

import time

import numpy as np

from nuplan_occ.grid import GridSpec
from nuplan_occ.storage.manifest_reader import read_manifest
from nuplan_occ.storage.metadata import read_metadata
from nuplan_occ.storage.reader import ShardReader, decode_request, request_of


def decode_throughput(root: str, n: int = 50) -> dict:
    """Frames/s of the first `n` ok frames' semantics: decode alone, and ranged read + check + decode.

    Returns {"frames", "decode_fps", "read_decode_fps", "mean_compressed_bytes", "raw_bytes"}.
    Reads are warm after the first pass (files stay open, the OS caches them).
    """
    grid = GridSpec.from_dict(read_metadata(root)["grid"])
    table = read_manifest(root)
    rows = [r for r in table.to_pylist() if r["status"] == "ok"][:n]
    if not rows:
        raise ValueError(f"{root}: no ok frames to measure")
    requests = [request_of(r, "semantics") for r in rows]
    with ShardReader(root) as reader:
        blobs = [reader.fetch([req])[0] for req in requests]
        start = time.perf_counter()
        for req in requests:
            decode_request(req, reader.fetch([req])[0], grid)
        read_decode_s = time.perf_counter() - start
    start = time.perf_counter()
    for req, blob in zip(requests, blobs):
        decode_request(req, blob, grid)
    decode_s = time.perf_counter() - start
    return {
        "frames": len(rows),
        "decode_fps": len(rows) / decode_s,
        "read_decode_fps": len(rows) / read_decode_s,
        "mean_compressed_bytes": float(np.mean([len(b) for b in blobs])),
        "raw_bytes": int(np.prod(grid.shape)),
    }
