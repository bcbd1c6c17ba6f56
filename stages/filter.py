"""Stage 2, filter (FBSA): statistical outlier removal on the background points of the sweeps that build the
background (`SceneData.background_positions(sweep_stride)`: every output sweep, and every sweep when the
stride is 1).

Inputs: `scene`, `splits`. Outputs: `background` (sequence of (n, 3) ego-frame points per sweep, None for
failed sweeps and sweeps left out by the stride; an item output, made sweep by sweep as the cache stores it,
read back one sweep per access by later stages), `background_positions` (the positions holding a background)
and `outliers_removed` (count per sweep, 0 where none was filtered; complete once the cache has stored
`background`).
"""

from __future__ import annotations

from dataclasses import dataclass

from nuplan_occ.fbsa.outliers import remove_statistical_outliers
from nuplan_occ.pipeline.stage import Stage


@dataclass(frozen=True)
class FilterParams:
    """method: "range" (neighbour distance divided by range to the sensor; the default, chosen by
    measurement: 84 % of injected outliers caught for 0.0 % real points lost on single sweeps, against
    67 % / 1.1 % for "knn" and 30 % / 1.1 % for "global"), "knn" (Open3D statistical outlier removal) or
    "global" (the paper's ||p - mu|| < k sigma). nb_neighbors: 8 rather than 20 (nuplan_occ.fbsa.outliers:
    more outliers caught, fewer real points lost, half the kNN search; the scale bench rows are in
    bench/report-scale.md's notes).
    sweep_stride: the background is taken from every output sweep, every n-th sweep in phase with them and the
    first and last sweeps (`SceneData.background_positions`; 1: every sweep). nuPlan's LiDAR sweeps at 20 Hz
    and the dataset's frames are 10 Hz, so 2 takes the output sweeps; the sweeps in between repeat the same
    static scene from ~0.5 m further along (measured in bench/report-scale.md: faster and smaller on long
    scenes, a little less background on the sub-2 s scenes of the small bench).
    stride_min_sweeps: scenes with fewer loaded sweeps than this take every sweep whatever the stride (a
    short scene has little evidence to spare; bench/report-scale.md's notes).
    method "none" keeps every point: the filter can then run once on the scene's aggregate instead
    (AggregateParams.outlier_method), with registration gated by RegistrationParams.min_voxel_points: the
    README's scale profile. It is faster with higher IoU and mIoU but lower vehicle IoU (bench/report-scale.md's
    notes), hence not the default."""

    method: str = "range"
    nb_neighbors: int = 8
    std_ratio: float = 2.0
    k_sigma: float = 3.0
    sweep_stride: int = 2
    stride_min_sweeps: int = 40


def run(inputs: dict, params: FilterParams) -> dict:
    if params.sweep_stride < 1:
        raise ValueError(f"filter: sweep_stride must be >= 1, got {params.sweep_stride}")
    positions = inputs["scene"].background_positions(params.sweep_stride, params.stride_min_sweeps)
    used = set(positions)
    removed: list[int] = []

    def filtered():
        for position, split in enumerate(inputs["splits"]):
            if split is None or position not in used:
                removed.append(0)
                yield None
                continue
            points = split.background.xyz
            keep = remove_statistical_outliers(points, method=params.method, nb_neighbors=params.nb_neighbors,
                                               std_ratio=params.std_ratio, k_sigma=params.k_sigma,
                                               origin=inputs["scene"].sensor_origin_ego)
            removed.append(int((~keep).sum()))
            yield points[keep]

    return {"background": filtered(), "background_positions": positions, "outliers_removed": removed}


STAGE = Stage("filter", inputs=("scene", "splits"), outputs=("background", "background_positions", "outliers_removed"),
              item_outputs=("background",), params_type=FilterParams, run=run,
              code=("nuplan_occ.fbsa.outliers", "nuplan_occ.fbsa.knn"), doc=__doc__ or "")
