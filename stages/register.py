"""Stage 3, register (FBSA): refine the logged ego poses by ICP on the filtered background, with
the logged relative motion as the prior; every correction is gated (poor fit or implausible jump ->
keep the logged pose, with the reason recorded). Sweeps without a background (failed, or left out by the
filter's sweep stride) get poses interpolated between their neighbours' refined poses at their timestamps.

Inputs: `scene`, `background`. Outputs: `registration` (RegistrationResult; poses are T_global_from_ego).
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.fbsa.register import RegistrationParams, refine_poses
from nuplan_occ.pipeline.stage import Stage


def run(inputs: dict, params: RegistrationParams) -> dict:
    scene = inputs["scene"]
    logged = np.stack([sweep.logged_pose for sweep in scene.sweeps])
    times = np.array([sweep.timestamp_us for sweep in scene.sweeps], dtype=np.float64)
    return {"registration": refine_poses(inputs["background"], logged, params, times)}


STAGE = Stage("register", inputs=("scene", "background"), outputs=("registration",),
              params_type=RegistrationParams, run=run,
              code=("nuplan_occ.fbsa.register", "nuplan_occ.fbsa.knn", "nuplan_occ.fbsa.tracked_nearest",
                    "nuplan_occ.fbsa.plane_normals", "nuplan_occ.fbsa.point_to_plane", "nuplan_occ.fbsa.voxel_reduce"),
              doc=__doc__ or "")
