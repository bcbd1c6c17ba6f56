"""split: per sweep, each track's foreground points in its box frame, and the background: the points outside
every enlarged box and outside the ego vehicle; the margin shell between the two goes to neither.

Inputs: `scene`. Outputs: `splits` (sequence aligned with scene.sweeps, None for failed sweeps). Not cached:
each sweep is split when the filter stage asks for it (it reads only the sweeps it keeps), which costs less
than storing every split and reading it back.
"""

from __future__ import annotations

from dataclasses import dataclass

from nuplan_occ.aggregation.split import split_frame
from nuplan_occ.pipeline.params import param
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.sequences import MappedSequence


@dataclass(frozen=True)
class SplitParams:
    box_margin: float = param(1.1, "scale of the enlarged boxes that background points must avoid", low=1.0)
    ego_margin_m: float = param(0.3, "padding around the ego vehicle's own footprint (nuPlan Pacifica)",
                                unit="m", low=0.0)


def run(inputs: dict, params: SplitParams) -> dict:
    scene = inputs["scene"]

    def split(sweep):
        if not sweep.has_cloud:
            return None
        return split_frame(sweep.cloud, sweep.boxes, scene.sensor_origin_ego, margin=params.box_margin,
                           ego_margin_m=params.ego_margin_m)

    return {"splits": MappedSequence(scene.sweeps, split)}


STAGE = Stage("split", inputs=("scene",), outputs=("splits",), params_type=SplitParams, run=run, cache=False)
