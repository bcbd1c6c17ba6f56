"""Simulated manifest rows at dataset scale (for the manifest bench and reader tests; no shards exist).

`simulated_manifest(n_scenes, frames_per_scene)` is a manifest table in manifest order with every base
and member column and the usual filter columns and `output_index`: scene s of log s // 4 holds frames_per_scene ok frames
at 10 Hz (every 50th frame failed), distinct 32-hex tokens, one commit id per scene. Built vectorised
(strings from fixed-width byte buffers), so 3.6 M rows take seconds.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from nuplan_occ.storage.manifest import STORED_MEMBERS, base_schema

SCENES_PER_LOG = 4


def _strings(values: np.ndarray) -> pa.Array:
    """A string array from a numpy fixed-width bytes array (no Python objects)."""
    width = values.dtype.itemsize
    offsets = np.arange(len(values) + 1, dtype=np.int32) * width
    return pa.StringArray.from_buffers(len(values), pa.py_buffer(offsets.tobytes()), pa.py_buffer(values.tobytes()))


def _choice(which: np.ndarray, values: list[str]) -> pa.Array:
    """values[which[i]] per row, as a plain string array."""
    return pa.DictionaryArray.from_arrays(pa.array(which.astype(np.int32)), pa.array(values)).cast(pa.string())


def _hex(rng: np.random.Generator, n: int) -> np.ndarray:
    """n random 32-character hex strings as a numpy S32 array."""
    digits = np.frombuffer(b"0123456789abcdef", dtype="S1")
    return digits[rng.integers(0, 16, size=(n, 32))].view("S32").reshape(n)


def _formatted(pattern: str, numbers: np.ndarray) -> np.ndarray:
    return np.char.mod(pattern, numbers).astype("S")


def simulated_manifest(n_scenes: int, frames_per_scene: int = 190, hist_len: int = 15, seed: int = 0) -> pa.Table:
    """The simulated manifest (see module docstring)."""
    rng = np.random.default_rng(seed)
    n = n_scenes * frames_per_scene
    scene = np.repeat(np.arange(n_scenes), frames_per_scene)
    log_no = scene // SCENES_PER_LOG
    frame = (scene % SCENES_PER_LOG) * frames_per_scene * 2 + np.tile(np.arange(frames_per_scene) * 2, n_scenes)
    logs = _formatted("2021.05.12.22.00.38_veh-35_%05d", np.arange(log_no.max() + 1 if n else 0))
    scene_names = _formatted("scene-%04d", np.arange(SCENES_PER_LOG))
    log_of_row = logs[log_no]
    keys = np.char.add(np.char.replace(log_of_row, b".", b"_"), _formatted("-%06d", frame))
    poses = np.zeros((n, 16))
    poses[:, [0, 5, 10, 15]] = 1.0
    poses[:, 3] = 664_000.0 + frame * 0.5
    poses[:, 7] = 3_997_000.0 + log_no
    ok = np.arange(n) % 50 != 49
    columns: dict[str, pa.Array] = {
        "key": _strings(keys),
        "log": _strings(log_of_row),
        "log_id": pa.array(log_no.astype(np.int64)),
        "scene_token": _strings(_hex(rng, n_scenes)[scene]),
        "scene_name": _strings(scene_names[scene % SCENES_PER_LOG]),
        "frame_index": pa.array(frame.astype(np.int64)),
        "token": _strings(_hex(rng, n)),
        "timestamp_us": pa.array(1_620_000_000_000_000 + log_no * 10**9 + frame * 50_000),
        "ego_to_global": pa.FixedSizeListArray.from_arrays(pa.array(poses.reshape(-1)), 16),
        "shard": _strings(np.char.add(np.char.add(log_of_row, b"/"), scene_names[scene % SCENES_PER_LOG])),
        "status": _choice(~ok, ["ok", "failed"]),
        "failure_reason": _choice(~ok, ["", "simulated failure"]),
        "class_hist": pa.FixedSizeListArray.from_arrays(
            pa.array(rng.integers(0, 5000, size=n * hist_len)), hist_len, mask=pa.array(~ok)),
        "commit_id": _strings(np.char.add(_formatted("%019d", 1_796_000_000_000_000_000 + np.arange(n_scenes)),
                                          _formatted("-%016x", np.arange(n_scenes)))[scene]),
    }
    sizes = {"semantics": 36_000, "mask_lidar": 20_000, "mask_camera": 20_000, "instance": 4_000, "flow": 8_000,
             "json": 400}
    offset = np.zeros(n, dtype=np.int64)
    for name in STORED_MEMBERS:
        nbytes = np.where(ok, sizes[name] + rng.integers(0, 1000, n), 0)
        columns[f"{name}_offset"] = pa.array(offset + 512, mask=~ok)
        columns[f"{name}_nbytes"] = pa.array(nbytes, mask=~ok)
        columns[f"{name}_crc32"] = pa.array(rng.integers(0, 2**32, n, dtype=np.uint32), mask=~ok)
        offset = offset + 512 + nbytes
    speed = rng.gamma(2.0, 3.0, n)
    columns["ego_speed"] = pa.array(speed)
    columns["max_agent_speed"] = pa.array(rng.gamma(2.0, 2.0, n))
    columns["n_moving_agents"] = pa.array(rng.integers(0, 12, n))
    columns["output_index"] = pa.array(np.tile(np.arange(frames_per_scene, dtype=np.int64), n_scenes))
    schema = base_schema(hist_len)
    fields = list(schema) + [pa.field(k, columns[k].type) for k in ("ego_speed", "max_agent_speed", "n_moving_agents",
                                                                        "output_index")]
    return pa.Table.from_arrays([columns[f.name].cast(f.type) for f in fields], schema=pa.schema(fields))
