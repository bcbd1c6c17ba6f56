"""Stage 3, register (FBSA): refine the logged ego poses by ICP on the filtered background, with
the logged relative motion as the prior; every correction is gated (poor fit or implausible jump ->
keep the logged pose, with the reason recorded). Only the sweeps of `SceneData.background_positions(sweep_stride)`
are registered; the others (and failed sweeps, or sweeps the filter left without a background) get poses
interpolated between their neighbours' refined poses at their timestamps. Scenes with fewer loaded sweeps than
`stride_min_sweeps` register every sweep and fit every point in every ICP stage (`coarse_stride` 1). Sweeps
that the filter stage passed through unfiltered (it left its test to the aggregate: `aggregate_outliers`) are
registered on the voxels holding at least `unfiltered_min_voxel_points` of their returns.

Inputs: `scene`, `background`, `aggregate_outliers`. Outputs: `registration` (RegistrationResult; poses are T_global_from_ego).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from nuplan_occ.registration.register import RegistrationParams, refine_poses
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.sequences import MappedSequence


def run(inputs: dict, params: RegistrationParams) -> dict:
    scene = inputs["scene"]
    if params.sweep_stride < 1:
        raise ValueError(f"register: sweep_stride must be >= 1, got {params.sweep_stride}")
    if inputs["aggregate_outliers"] is not None:
        params = replace(params, min_voxel_points=params.unfiltered_min_voxel_points)
    if len(scene.ok_indices()) < params.stride_min_sweeps:  # a short scene keeps all its evidence
        params = replace(params, coarse_stride=1)
    registered = set(scene.background_positions(params.sweep_stride, params.stride_min_sweeps))
    clouds = MappedSequence(list(range(len(scene.sweeps))),
                            lambda position: inputs["background"][position] if position in registered else None)
    logged = np.stack([sweep.logged_pose for sweep in scene.sweeps])
    times = np.array([sweep.timestamp_us for sweep in scene.sweeps], dtype=np.float64)
    return {"registration": refine_poses(clouds, logged, params, times)}


STAGE = Stage("register", inputs=("scene", "background", "aggregate_outliers"), outputs=("registration",),
              params_type=RegistrationParams, run=run,
              code=("nuplan_occ.registration.register", "nuplan_occ.points.knn", "nuplan_occ.registration.tracked_nearest",
                    "nuplan_occ.points.plane_normals", "nuplan_occ.registration.point_to_plane", "nuplan_occ.points.voxel_reduce"),
              doc=__doc__ or "")
