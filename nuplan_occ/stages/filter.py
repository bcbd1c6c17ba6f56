"""filter: statistical outlier removal on the background points of the sweeps that build the
background (`SceneData.background_positions(sweep_stride)`: every output sweep, and every sweep when the
stride is 1): sweep by sweep on short scenes; on scenes of at least `aggregate_min_sweeps` loaded sweeps the
sweeps pass through and the same test runs once on the scene's aggregate (aggregate stage), while
registration keeps only voxels holding several returns (register.unfiltered_min_voxel_points).

Inputs: `scene`, `splits`. Outputs: `background` (sequence of (n, 3) ego-frame points per sweep, None for
failed sweeps and sweeps left out by the stride; an item output, made sweep by sweep as the cache stores it,
read back one sweep per access by later stages), `background_positions` (the positions holding a background),
`outliers_removed` (count per sweep, 0 where none was filtered; complete once the cache has stored
`background`) and `aggregate_outliers` (None when the sweeps were filtered here; else the test left to the
aggregate: keyword arguments of `nuplan_occ.points.outliers.remove_statistical_outliers`).
"""

from __future__ import annotations

from dataclasses import dataclass

from nuplan_occ.pipeline.params import param
from nuplan_occ.pipeline.stage import Stage
from nuplan_occ.points.outliers import OUTLIER_METHODS, remove_statistical_outliers


@dataclass(frozen=True)
class FilterParams:
    method: str = param("range", "outlier test: neighbour distance over range to the sensor, Open3D's statistical "
                        "test, the paper's distance to the mean, or none", choices=OUTLIER_METHODS)
    nb_neighbors: int = param(8, "neighbours of each point's mean distance (range and knn tests)", low=1)
    std_ratio: float = param(2.0, "a point is an outlier beyond mean + std_ratio standard deviations (range and knn "
                             "tests)", low=0.0, low_open=True)
    k_sigma: float = param(3.0, "a point is an outlier beyond k_sigma standard deviations from the mean (global "
                           "test)", low=0.0, low_open=True)
    sweep_stride: int = param(2, "background from every output sweep and every n-th sweep in phase with them "
                              "(1: every sweep)", low=1)
    stride_min_sweeps: int = param(40, "scenes with fewer loaded sweeps take every sweep", low=0)
    aggregate_min_sweeps: int = param(40, "scenes with at least this many loaded sweeps run the test once on the "
                                      "aggregate instead of per sweep (0: always per sweep)", low=0)


def run(inputs: dict, params: FilterParams) -> dict:
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
              item_outputs=("background",), params_type=FilterParams, run=run)
