"""Stage 5, reconstruct: surfaces from the aggregates with the neural-kernel-style torch solver
(default), Open3D screened Poisson, or "none" (raw points).

The background is reconstructed in the scene frame. Each rigid object is reconstructed in its box
frame from its aggregate; non-rigid objects (pedestrians) keep their raw windowed points, since their
shape changes from frame to frame. Objects with fewer than `min_object_points` points keep raw points.

Inputs: `background_aggregate`, `objects`.
Outputs: `background_surface` (Surface, scene frame), `object_surfaces` (track -> Surface, box frame).
"""

from __future__ import annotations

from dataclasses import dataclass

from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.recon import reconstruct


@dataclass(frozen=True)
class ReconstructParams:
    """method / object_method: "nksr" | "poisson" | "none"."""

    method: str = "nksr"
    object_method: str = "nksr"
    min_object_points: int = 200


def run(inputs: dict, params: ReconstructParams) -> dict:
    background = inputs["background_aggregate"]
    background_surface = reconstruct(background.points, background.sensor_origins, method=params.method, frame="scene")
    object_surfaces = {}
    for track, aggregate in inputs["objects"].items():
        if not aggregate.rigid or len(aggregate.points) < params.min_object_points:
            continue
        object_surfaces[track] = reconstruct(aggregate.points, aggregate.sensor_origins,
                                             method=params.object_method, frame="box")
    return {"background_surface": background_surface, "object_surfaces": object_surfaces}


STAGE = Stage("reconstruct", inputs=("background_aggregate", "objects"),
              outputs=("background_surface", "object_surfaces"), params_type=ReconstructParams, run=run,
              code=("nuplan_occ.recon",), doc=__doc__ or "")
