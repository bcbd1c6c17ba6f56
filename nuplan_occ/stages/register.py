"""register: refine the logged ego poses by ICP of the filtered background against a local map of the
previous sweeps, with the logged relative motion as the prior (nuplan_occ.registration.register). Every
correction is gated: a poor fit or an implausible jump keeps the logged pose, with the reason recorded.
Only the sweeps of `SceneData.background_positions(sweep_stride, stride_min_sweeps)` are registered; the
others (and failed sweeps, or sweeps the filter left without a background) get poses interpolated between
their neighbours' refined poses at their timestamps. Scenes with fewer loaded sweeps than `stride_min_sweeps`
fit every point in every ICP stage. Sweeps the filter stage passed through unfiltered (the outlier test left
to the aggregate) are registered on the voxels holding at least `unfiltered_min_voxel_points` of their returns.

Inputs: `scene`, `background`, `aggregate_outliers`. Outputs: `registration` (RegistrationResult: poses
T_global_from_ego (F, 4, 4) in scene sweep order, with each sweep's fit figures and the reason of a rejection).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from nuplan_occ.pipeline.params import param
from nuplan_occ.pipeline.settings import settings_from
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.registration.register import ANCHORS, RegistrationParams, refine_poses
from nuplan_occ.sequences import MappedSequence

ICP = RegistrationParams  # the library's defaults


@dataclass(frozen=True)
class RegisterParams:
    voxel_size_m: float = param(ICP.voxel_size_m, "downsampling voxel of each sweep's background", unit="m",
                                low=0.01, high=5.0)
    map_voxel_m: float = param(ICP.map_voxel_m, "downsampling voxel of the local map", unit="m", low=0.01, high=5.0)
    window: int = param(ICP.window, "previous trusted sweeps making the local map", low=1)
    max_correspondence_m: tuple[float, ...] = param(
        ICP.max_correspondence_m, "correspondence distance of each coarse-to-fine ICP stage (the first must exceed "
        "the prior's error)", unit="m", low=0.0, low_open=True)
    tukey_ratio: float = param(ICP.tukey_ratio, "Tukey kernel width as a fraction of the stage's correspondence "
                               "distance", low=0.0, low_open=True)
    max_iterations: int = param(ICP.max_iterations, "Gauss-Newton iterations per ICP stage", low=1)
    coarse_stride: int = param(ICP.coarse_stride, "the widest ICP stage fits every n-th source point", low=1)
    normal_radius_m: float = param(ICP.normal_radius_m, "search radius of the map normals", unit="m",
                                   low=0.0, low_open=True)
    normal_max_nn: int = param(ICP.normal_max_nn, "most neighbours of a map normal", low=3)
    normal_reuse_frames: int = param(ICP.normal_reuse_frames, "frames a map voxel's normal is reused before it is "
                                     "estimated again (0: every frame)", low=0)
    min_points: int = param(ICP.min_points, "gate: fewest downsampled source points", low=1)
    min_fitness: float = param(ICP.min_fitness, "gate: least share of source points with a correspondence",
                               low=0.0, high=1.0)
    max_rmse_m: float = param(ICP.max_rmse_m, "gate: largest point-to-plane RMSE", unit="m", low=0.0, low_open=True)
    min_conditioning: float = param(ICP.min_conditioning, "gate: least smallest/largest eigenvalue ratio of the "
                                    "point-to-plane information (0 accepts degenerate geometry)", low=0.0, high=1.0)
    max_translation_m: float = param(ICP.max_translation_m, "gate: largest correction with respect to the prior",
                                     unit="m", low=0.0)
    max_rotation_deg: float = param(ICP.max_rotation_deg, "gate: largest rotation with respect to the prior",
                                    unit="deg", low=0.0, high=180.0)
    anchor: str = param(ICP.anchor, "how the refined chain is placed: one rigid fit to every logged pose, or "
                        "the first sweep at its logged pose", choices=ANCHORS)
    log_sigma_xy_m: float = param(ICP.log_sigma_xy_m, "weight of the logged x, y in the 'fit' anchor (1 sigma)",
                                  unit="m", low=0.0, low_open=True)
    log_sigma_deg: float = param(ICP.log_sigma_deg, "weight of the logged heading in the 'fit' anchor (1 sigma)",
                                 unit="deg", low=0.0, low_open=True)
    sweep_stride: int = param(2, "register every output sweep and every n-th sweep in phase with them "
                              "(1: every sweep); the others are interpolated", low=1)
    stride_min_sweeps: int = param(40, "scenes with fewer loaded sweeps register every sweep, fitting all points",
                                   low=0)
    min_voxel_points: int = param(ICP.min_voxel_points, "source and map keep only voxels holding at least this "
                                  "many returns of a filtered sweep", low=1)
    unfiltered_min_voxel_points: int = param(2, "the same for sweeps the filter stage passed through unfiltered",
                                             low=1)


def run(inputs: dict, params: RegisterParams) -> dict:
    scene = inputs["scene"]
    icp = settings_from(RegistrationParams, params)
    if inputs["aggregate_outliers"] is not None:
        icp = replace(icp, min_voxel_points=params.unfiltered_min_voxel_points)
    if len(scene.ok_indices()) < params.stride_min_sweeps:  # a short scene keeps all its evidence
        icp = replace(icp, coarse_stride=1)
    registered = set(scene.background_positions(params.sweep_stride, params.stride_min_sweeps))
    clouds = MappedSequence(list(range(len(scene.sweeps))),
                            lambda position: inputs["background"][position] if position in registered else None)
    logged = np.stack([sweep.logged_pose for sweep in scene.sweeps])
    times = np.array([sweep.timestamp_us for sweep in scene.sweeps], dtype=np.float64)
    return {"registration": refine_poses(clouds, logged, icp, times)}


STAGE = Stage("register", inputs=("scene", "background", "aggregate_outliers"), outputs=("registration",),
              params_type=RegisterParams, run=run, kept=True)
