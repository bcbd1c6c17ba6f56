"""Synthetic frames with known content, for tests and the storage bench (not nuPlan data).

Each frame: a ground slab (road for y < 0, other_ground for y >= 0, a road_line row) at z index
`ground_k`, and `n_agents` vehicle boxes whose x position moves with the frame index; the ego drives
along global x at `ego_speeds[i]` m/s (10 Hz frames). Masks, instance ids and flow are consistent with
the boxes. Arrays are [x, y, z] in the ego frame on `grid`.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence

import numpy as np

from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import OTHER_GROUND, ROAD, ROAD_LINE, VEHICLE
from nuplan_occ.storage.records import FrameRecord

FRAME_PERIOD_US = 100_000


def synthetic_arrays(grid: GridSpec, frame: int, members: Sequence[str], n_agents: int = 3,
                     agent_speed: float = 5.0) -> dict[str, np.ndarray]:
    """The requested members of synthetic frame `frame` (see module docstring)."""
    nx, ny, nz = grid.shape
    ground_k = max(nz // 4, 0)
    sem = np.zeros(grid.shape, dtype=np.uint8)
    sem[:, : ny // 2, ground_k] = ROAD
    sem[:, ny // 2:, ground_k] = OTHER_GROUND
    sem[:, ny // 2, ground_k] = ROAD_LINE
    inst = np.zeros(grid.shape, dtype=np.uint16)
    flow = np.zeros((*grid.shape, 3), dtype=np.float16)
    size = max(nx // 16, 1)
    for a in range(n_agents):
        x0 = (a * nx // max(n_agents, 1) + frame * (1 + a)) % (nx - size)
        y0 = (ny // 4 + a * size * 2) % (ny - size)
        box = (slice(x0, x0 + size), slice(y0, y0 + size), slice(ground_k + 1, min(ground_k + 1 + size, nz)))
        sem[box] = VEHICLE
        inst[box] = a + 1
        flow[box] = np.array([agent_speed, 0.0, 0.0], dtype=np.float16)
    xs = np.arange(nx)[:, None, None]
    out = {
        "semantics": sem,
        "mask_lidar": np.broadcast_to((xs + frame) % 7 != 0, grid.shape).copy() & (sem > 0),
        "mask_camera": np.broadcast_to(xs >= nx // 2, grid.shape).copy(),
        "instance": inst,
        "flow": flow,
    }
    return {m: out[m] for m in members}


def synthetic_log(grid: GridSpec, log: str, log_id: int, scene_lengths: Sequence[int],
                  ego_speeds: Sequence[float] | None = None, max_agent_speeds: Sequence[float] | None = None,
                  members: Sequence[str] = ("semantics",), failed: Sequence[int] = ()) -> list[FrameRecord]:
    """Records of one log: consecutive scenes of the given lengths; frames in `failed` are failed.

    ego_speeds / max_agent_speeds (m/s, one per frame) become the manifest columns `ego_speed`,
    `max_agent_speed`; the ego pose integrates ego_speeds along global x.
    """
    n = int(sum(scene_lengths))
    ego_speeds = np.full(n, 5.0) if ego_speeds is None else np.asarray(ego_speeds, dtype=np.float64)
    max_agent_speeds = np.full(n, 5.0) if max_agent_speeds is None else np.asarray(max_agent_speeds, dtype=np.float64)
    scene_of = np.repeat(np.arange(len(scene_lengths)), scene_lengths)
    x = np.concatenate([[0.0], np.cumsum(ego_speeds[:-1] * FRAME_PERIOD_US * 1e-6)])
    records = []
    for i in range(n):
        pose = np.eye(4)
        pose[:3, 3] = [664_000.0 + x[i], 3_997_000.0, 0.0]
        scene = int(scene_of[i])
        token = hashlib.sha256(f"{log}/{i}".encode()).hexdigest()[:32]
        common = dict(
            log=log, log_id=log_id, scene_token=hashlib.md5(f"{log}/scene{scene}".encode()).hexdigest(),
            scene_name=f"{log}-scene{scene}", frame_index=i, token=token,
            timestamp_us=1_620_000_000_000_000 + i * FRAME_PERIOD_US, ego_to_global=pose,
            columns={"ego_speed": float(ego_speeds[i]), "max_agent_speed": float(max_agent_speeds[i]),
                     "n_moving_agents": 3},
        )
        if i in failed:
            records.append(FrameRecord(**common, status="failed", failure_reason="synthetic failure"))
        else:
            records.append(FrameRecord(**common, arrays=synthetic_arrays(grid, i, members)))
    return records
