"""Stage 2, filter (FBSA): statistical outlier removal on the background points of the sweeps that build the
background (`SceneData.background_positions(sweep_stride)`: every output sweep, and every sweep when the
stride is 1): sweep by sweep on short scenes; on scenes of at least `aggregate_min_sweeps` loaded sweeps the
sweeps pass through and the same test runs once on the scene's aggregate (aggregate stage), while
registration keeps only voxels holding several returns (RegistrationParams.min_voxel_points).

Inputs: `scene`, `splits`. Outputs: `background` (sequence of (n, 3) ego-frame points per sweep, None for
failed sweeps and sweeps left out by the stride; an item output, made sweep by sweep as the cache stores it,
read back one sweep per access by later stages), `background_positions` (the positions holding a background),
`outliers_removed` (count per sweep, 0 where none was filtered; complete once the cache has stored
`background`) and `aggregate_outliers` (None when the sweeps were filtered here; else the test left to the
aggregate: keyword arguments of `nuplan_occ.points.outliers.remove_statistical_outliers`).
"""

from __future__ import annotations

from dataclasses import dataclass

from nuplan_occ.points.outliers import remove_statistical_outliers
from nuplan_occ.pipeline.stage import Stage


@dataclass(frozen=True)
class FilterParams:
    """method: "range" (neighbour distance divided by range to the sensor; the default, chosen by
    measurement: 84 % of injected outliers caught for 0.0 % real points lost on single sweeps, against
    67 % / 1.1 % for "knn" and 30 % / 1.1 % for "global"), "knn" (Open3D statistical outlier removal) or
    "global" (the paper's ||p - mu|| < k sigma). nb_neighbors: 8 rather than 20 (nuplan_occ.points.outliers:
    more outliers caught, fewer real points lost, half the kNN search; the scale bench rows are in
    bench/report-scale.md's notes).
    sweep_stride: the background is taken from every output sweep, every n-th sweep in phase with them and the
    first and last sweeps (`SceneData.background_positions`; 1: every sweep). nuPlan's LiDAR sweeps at 20 Hz
    and the dataset's frames are 10 Hz, so 2 takes the output sweeps; the sweeps in between repeat the same
    static scene from ~0.5 m further along (measured in bench/report-scale.md: faster and smaller on long
    scenes, a little less background on the sub-2 s scenes of the small bench).
    stride_min_sweeps: scenes with fewer loaded sweeps than this take every sweep whatever the stride (a
    short scene has little evidence to spare; bench/report-scale.md's notes).
    aggregate_min_sweeps: scenes with at least this many loaded sweeps are not filtered sweep by sweep: the
    test runs once on the scene's downsampled aggregate, each point scored against its own sweep's sensor
    (0: always sweep by sweep). One kNN pass over the scene instead of one per sweep; measured side by side on
    the scale scenes (faster, higher IoU and mIoU) and the small bench (its <= 17-sweep scenes lost vehicle
    IoU to it) in bench/report-scale.md's notes. method "none" keeps every point everywhere."""

    method: str = "range"
    nb_neighbors: int = 8
    std_ratio: float = 2.0
    k_sigma: float = 3.0
    sweep_stride: int = 2
    stride_min_sweeps: int = 40
    aggregate_min_sweeps: int = 40


def run(inputs: dict, params: FilterParams) -> dict:
    if params.sweep_stride < 1:
        raise ValueError(f"filter: sweep_stride must be >= 1, got {params.sweep_stride}")
    positions = inputs["scene"].background_positions(params.sweep_stride, params.stride_min_sweeps)
    used = set(positions)
    removed: list[int] = []
    test = {"method": params.method, "nb_neighbors": params.nb_neighbors, "std_ratio": params.std_ratio,
            "k_sigma": params.k_sigma}
    deferred = 0 < params.aggregate_min_sweeps <= len(inputs["scene"].ok_indices()) and params.method != "none"

    def filtered():
        splits = inputs["splits"]
        for position in range(len(splits)):
            split = splits[position] if position in used else None  # a split is made only where it is used
            if split is None:
                removed.append(0)
                yield None
                continue
            points = split.background.xyz
            if deferred:
                removed.append(0)
                yield points
                continue
            keep = remove_statistical_outliers(points, origin=inputs["scene"].sensor_origin_ego, **test)
            removed.append(int((~keep).sum()))
            yield points[keep]

    return {"background": filtered(), "background_positions": positions, "outliers_removed": removed,
            "aggregate_outliers": test if deferred else None}


STAGE = Stage("filter", inputs=("scene", "splits"),
              outputs=("background", "background_positions", "outliers_removed", "aggregate_outliers"),
              item_outputs=("background",), params_type=FilterParams, run=run,
              code=("nuplan_occ.points.outliers", "nuplan_occ.points.knn"), doc=__doc__ or "")
