"""nuplan_occ.stages.reconstruct: the background rays through a box that the aggregate kept for an object carve its solid."""

from types import SimpleNamespace

import numpy as np

from nuplan_occ.aggregation.aggregate import ObjectAggregate
from nuplan_occ.stages.reconstruct import ReconstructParams, run

SIZE = np.array([2.0, 1.0, 1.0])


def inputs():
    # the object's own points: its face x = -1 seen from a sensor 5 m in front of it
    y, z = np.meshgrid(np.linspace(-0.45, 0.45, 10), np.linspace(-0.45, 0.45, 10))
    points = np.stack([np.full(y.size, -1.0), y.ravel(), z.ravel()], axis=1)
    car = ObjectAggregate("t1", "vehicle", SIZE, points, np.tile([-6.0, 0.0, 0.0], (len(points), 1)),
                          np.zeros(len(points), np.int32), rigid=True)
    # a background ray drawn straight through the box along y (its origin misplaced, as the merged
    # LiDAR frame's origin is for the rig's other sensors)
    through = (np.array([[0.32, -5.0, 0.05]]), np.array([[0.32, 5.0, 0.05]]))
    background = SimpleNamespace(points=np.zeros((4, 3)), frame_origins=np.zeros((1, 3)),
                                 frame_ids=np.zeros(4, np.int32), T_global_from_scene=np.eye(4))
    return {"background_aggregate": background, "objects": {"t1": car}, "object_through_rays": {"t1": through}}


def test_background_rays_kept_for_an_object_carve_its_solid():
    params = ReconstructParams(method="none", object_method="none", ground_fill=False)
    default = run({**inputs(), "object_through_rays": {}}, params)["object_solids"]["t1"].points
    listed = run(inputs(), params)["object_solids"]["t1"].points
    assert len(default) == 2000  # nothing in front of the observed face, so the whole box stays solid
    carved = {tuple(np.round(p, 3)) for p in default} - {tuple(np.round(p, 3)) for p in listed}
    assert carved and all(abs(p[0] - 0.35) < 1e-6 and abs(p[2] - 0.05) < 1e-6 for p in carved)
