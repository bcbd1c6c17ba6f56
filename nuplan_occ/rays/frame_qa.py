"""The qa_ray_* columns of one output frame: its grid graded by ray consistency (`nuplan_occ.rays.consistency`)
against the loaded sweep of its scene nearest in time that is not an output frame (the 20 Hz sweeps between
10 Hz frames; ties go to the later one; in a build whose output rate is the sweep rate, the nearest other
loaded sweep; none farther than MAX_SWEEP_DT_S). `scene` arguments are SceneData (nuplan_occ.pipeline.scene:
sweeps with timestamp_us, is_output, has_cloud, xyz; sensor_origin_ego). The sweep's returns and the merged
LiDAR origin are moved into the frame's ego frame by T_frame_from_sweep = inv(pose_frame) @ pose_sweep. Used
by the build's write stage and by `nuplan-occ qa` (nuplan_occ.evaluation.ray_qa), so both give the same
figures.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.geometry import invert_transform
from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.rays.consistency import broken_rules, ray_consistency, return_stride

MAX_SWEEP_DT_S = 0.2
"""A frame is scored against a sweep at most this far from it in time (s)."""

MAX_RAYS = 20000
"""Returns scored per frame by default (evenly strided; `rays.consistency`)."""

FIGURES = {"qa_ray_agree": "agree", "qa_ray_early": "early", "qa_ray_hole": "hole", "qa_ray_other": "other",
           "qa_ray_depth_error_p90_m": "depth_error_p90_m", "qa_ray_depth_error_p99_m": "depth_error_p99_m"}
"""The figure columns and the `RayConsistency` field each holds."""


def scoring_sweep(scene, position: int) -> int | None:
    """Position of the loaded sweep the output frame at `position` is scored against (module docstring), or
    None when no loaded sweep lies within MAX_SWEEP_DT_S."""
    between = [i for i, s in enumerate(scene.sweeps) if s.has_cloud and not s.is_output]
    candidates = between or [i for i, s in enumerate(scene.sweeps) if s.has_cloud and i != position]
    t = scene.sweeps[position].timestamp_us
    best = min(candidates, key=lambda i: (abs(scene.sweeps[i].timestamp_us - t), -scene.sweeps[i].timestamp_us),
               default=None)
    if best is None or abs(scene.sweeps[best].timestamp_us - t) > MAX_SWEEP_DT_S * 1e6:
        return None
    return best


def sweep_in_frame(scene, poses: np.ndarray, frame: int, sweep: int, stride: int = 1
                   ) -> tuple[np.ndarray, np.ndarray]:
    """(origin (3,), returns (N, 3)) of every `stride`-th return of the sweep at position `sweep` in the ego
    frame of the sweep at `frame` (poses: (F, 4, 4) T_global_from_ego in scene sweep order; metres)."""
    T = invert_transform(poses[frame]) @ poses[sweep]
    xyz = scene.sweeps[sweep].xyz[::stride].astype(np.float64)
    return T[:3, :3] @ scene.sensor_origin_ego + T[:3, 3], xyz @ T[:3, :3].T + T[:3, 3]


def frame_flags(row: dict) -> list[str]:
    """Names of the flag rules (`rays.consistency.FLAG_RULES`) a sidecar row's figures break."""
    return broken_rules({name: row.get(column) for column, name in FIGURES.items()})


def frame_ray_columns(scene, position: int, poses: np.ndarray, semantics: np.ndarray,
                      background: set[int] | None, max_rays: int | None = MAX_RAYS, grid: GridSpec = DEFAULT_GRID
                      ) -> dict:
    """The qa_ray_* columns of the output frame at `position` (its grid `semantics`, uint8 [x, y, z] of
    `grid`, in the frame's ego frame): the scored sweep, its time offset (s) and background membership
    (`background`: positions whose background the grids hold, None when unknown), the counts and figures
    (FIGURES) and the flags; qa_ray_problem says why a frame has no figures. poses: (F, 4, 4)
    T_global_from_ego in scene sweep order."""
    sweep = scene.sweeps[position]
    other = scoring_sweep(scene, position)
    if other is None:
        return {"qa_ray_problem": f"no loaded sweep within {MAX_SWEEP_DT_S:g} s", "qa_ray_flags": ""}
    n_returns = len(scene.sweeps[other].stored_cloud)
    stride = return_stride(n_returns, max_rays)  # the returns ray_consistency would consider: moved alone
    figures = ray_consistency(semantics, *sweep_in_frame(scene, poses, position, other, stride), grid)
    columns = {"qa_ray_sweep_token": scene.sweeps[other].token,
               "qa_ray_sweep_dt_s": (scene.sweeps[other].timestamp_us - sweep.timestamp_us) / 1e6,
               "qa_ray_sweep_in_background": None if background is None else other in background,
               "qa_ray_returns": n_returns, "qa_ray_scored": figures.n_scored,
               **{column: getattr(figures, name) for column, name in FIGURES.items()}, "qa_ray_problem": ""}
    columns["qa_ray_flags"] = ",".join(frame_flags(columns))
    return columns
