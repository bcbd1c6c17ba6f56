"""Stage 1, split (FBSA): per sweep, foreground points of each track in its box frame, background
points outside every enlarged box and outside the ego vehicle; the margin shell goes to neither.

Inputs: `scene`. Outputs: `splits` (sequence aligned with scene.sweeps, None for failed sweeps; each
sweep's split is made when the filter asks for it and not cached: the filter reads only the sweeps it keeps,
every other one on long scenes, and splitting a sweep again costs less than storing and reading it back,
bench/report-scale.md's notes).
"""

from __future__ import annotations

from dataclasses import dataclass

from nuplan_occ.aggregation.split import split_frame
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.sequences import MappedSequence


@dataclass(frozen=True)
class SplitParams:
    """box_margin: scale of the enlarged boxes that background must avoid; ego_margin_m: padding of the
    ego vehicle's own footprint (nuPlan Pacifica)."""

    box_margin: float = 1.1
    ego_margin_m: float = 0.3


def run(inputs: dict, params: SplitParams) -> dict:
    scene = inputs["scene"]

    def split(sweep):
        if not sweep.has_cloud:
            return None
        return split_frame(sweep.cloud, sweep.boxes, scene.sensor_origin_ego, margin=params.box_margin,
                           ego_margin_m=params.ego_margin_m)

    return {"splits": MappedSequence(scene.sweeps, split)}


STAGE = Stage("split", inputs=("scene",), outputs=("splits",), params_type=SplitParams, run=run,
              code=("nuplan_occ.aggregation.split", "nuplan_occ.points.box_kernels"), cache=False, doc=__doc__ or "")
