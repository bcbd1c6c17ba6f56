"""Stage 4, aggregate (FBSA): the scene's background in one scene-local frame with the refined poses;
each track's foreground accumulated in its box frame (rigid classes over the whole scene, pedestrians
over a short window around each frame). Per-point sensor origins are kept for normal orientation.

Inputs: `scene`, `splits`, `background`, `registration`.
Outputs: `background_aggregate` (BackgroundAggregate, scene frame), `objects` (track -> ObjectAggregate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.fbsa.aggregate import aggregate_background, aggregate_objects
from nuplan_occ.pipeline.stage import Stage


@dataclass(frozen=True)
class AggregateParams:
    """voxel_downsample_m: thin the background aggregate to one point per cube of this edge (0 = keep all).
    rigid_categories: classes aggregated over the whole scene; others use a window of frames."""

    voxel_downsample_m: float = 0.05
    rigid_categories: tuple[str, ...] = ("vehicle", "bicycle", "traffic_cone", "barrier", "czone_sign", "generic_object")


def run(inputs: dict, params: AggregateParams) -> dict:
    scene = inputs["scene"]
    ok = scene.ok_indices()
    poses = inputs["registration"].poses
    background = aggregate_background(
        [inputs["background"][i] for i in ok],
        np.repeat(scene.sensor_origin_ego[None], len(ok), axis=0),
        poses[ok],
        T_global_from_scene=poses[ok[0]] if ok else None,
        voxel_downsample_m=params.voxel_downsample_m or None,
    )
    objects = aggregate_objects([inputs["splits"][i] for i in ok], [scene.sweeps[i].boxes for i in ok],
                                rigid_categories=params.rigid_categories)
    return {"background_aggregate": background, "objects": objects}


STAGE = Stage("aggregate", inputs=("scene", "splits", "background", "registration"),
              outputs=("background_aggregate", "objects"), params_type=AggregateParams, run=run,
              code=("nuplan_occ.fbsa.aggregate",), doc=__doc__ or "")
