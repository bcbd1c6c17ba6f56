"""Cars whose voxels stop above the road reach down to it, boxed or not; a gap taller than the reach, a class left out and a
column of unknown ground stay as they are."""

import numpy as np
import trimesh

from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import PEDESTRIAN, ROAD, VEHICLE
from nuplan_occ.voxel.compose import PlacedObject, compose_frame
from nuplan_occ.voxel.ground_contact import reach_down_to_ground

GRID = GridSpec(x_min=-10, x_max=10, y_min=-10, y_max=10, z_min=-3, z_max=5, voxel_size=0.25)
GROUND_Z = -1.4  # layer 6: [-1.5, -1.25)


def box_mesh(lo, hi):
    mesh = trimesh.creation.box(bounds=np.stack([lo, hi]))
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def placed(class_id, instance_id, center_xy, body_bottom_z, velocity=(0.0, 0.0, 0.0)):
    """An object whose box stands on the ground (bottom at GROUND_Z) and whose body starts at body_bottom_z
    (ego frame) and ends 1 m higher; 3 x 1.5 m footprint."""
    box_bottom, top = GROUND_Z, body_bottom_z + 1.0
    center = np.array([*center_xy, (box_bottom + top) / 2.0])
    v, f = box_mesh(np.array([-1.4, -0.7, body_bottom_z - center[2]]), np.array([1.4, 0.7, top - center[2]]))
    return PlacedObject(v, f, center=center, yaw=0.0, size=np.array([3.0, 1.5, top - box_bottom]),
                        class_id=class_id, instance_id=instance_id, velocity=np.array(velocity))


def scene():
    ground_v = np.array([[-12, -12, GROUND_Z], [12, -12, GROUND_Z], [12, 12, GROUND_Z], [-12, 12, GROUND_Z]])
    objects = [placed(VEHICLE, 1, (4.0, 4.0), -1.1, velocity=(2.0, 0.0, 0.0)),  # lowest voxel in layer 7: 0 gap
               placed(VEHICLE, 2, (4.0, -4.0), -0.85, velocity=(0.0, 1.0, 0.0)),  # layer 8: a 1-layer gap
               placed(VEHICLE, 3, (-4.0, 4.0), -0.4),  # layer 10: a 3-layer gap (0.75 m)
               placed(PEDESTRIAN, 4, (-4.0, -4.0), -0.85)]
    grids = compose_frame(ground_v, np.array([[0, 1, 2], [0, 2, 3]]), objects, np.full(GRID.shape[:2], ROAD, np.uint8),
                          GRID)
    return grids


def lowest_layer(grids, instance_id):
    mask = grids.instance == instance_id
    return np.where(mask.any(axis=2), np.argmax(mask, axis=2), -1)


def test_a_car_over_a_one_layer_gap_fills_it_with_its_class_instance_and_flow():
    grids = scene()
    before = {name: getattr(grids, name).copy() for name in ("semantics", "instance", "flow")}
    low = lowest_layer(grids, 2)
    columns = low == 8
    assert columns.sum() > 60  # the car's footprint
    assert not before["semantics"][:, :, 7][columns].any()  # the gap between the road (6) and the car (8)

    filled = reach_down_to_ground(grids, (VEHICLE,), reach_m=0.5, grid=GRID)

    changed = np.any([getattr(grids, n) != before[n] if n != "flow" else np.any(grids.flow != before["flow"], axis=3)
                      for n in before], axis=0)
    expected = np.zeros(GRID.shape, bool)
    expected[:, :, 7] = columns
    assert np.array_equal(changed, expected) and filled == columns.sum()
    assert np.all(grids.semantics[expected] == VEHICLE) and np.all(grids.instance[expected] == 2)
    assert np.allclose(grids.flow[expected].astype(float), [0.0, 1.0, 0.0])


def test_no_gap_a_taller_gap_another_class_and_unknown_ground_stay_as_they_are():
    grids = scene()
    low2 = lowest_layer(grids, 2)
    grids.ground_height[:, : GRID.shape[1] // 2] = np.nan  # car 2 (y < 0) now stands on unknown ground
    before = grids.semantics.copy()
    assert reach_down_to_ground(grids, (VEHICLE,), reach_m=0.5, grid=GRID) == 0
    assert np.array_equal(grids.semantics, before)
    assert (lowest_layer(grids, 3)[lowest_layer(grids, 3) >= 0] == 10).all()  # a 0.75 m gap is beyond the reach
    grids.ground_height[:] = 0.0  # ground far above the road voxels: their floor is not ground
    assert reach_down_to_ground(grids, (VEHICLE, PEDESTRIAN), reach_m=1.0, grid=GRID) == 0
    assert (low2 >= 0).sum() > 60


def test_a_reach_of_a_gap_fills_it_and_the_classes_choose_who_reaches():
    grids = scene()
    footprint3 = lowest_layer(grids, 3) == 10
    footprint4 = lowest_layer(grids, 4) == 8
    filled = reach_down_to_ground(grids, (VEHICLE,), reach_m=0.75, grid=GRID)
    assert np.all(grids.instance[:, :, 7:10][footprint3] == 3)  # layers 7, 8, 9 under car 3
    assert not grids.semantics[:, :, 7][footprint4].any()  # the pedestrian's class was not given
    assert filled == 3 * footprint3.sum() + (lowest_layer(grids, 2) >= 0).sum()


def test_an_unboxed_mover_reaches_down_too_without_an_instance():
    grids = scene()
    columns = lowest_layer(grids, 2) == 8
    grids.instance[grids.instance == 2] = 0  # car 2 painted as a mover: class only
    grids.flow[:] = 0
    assert reach_down_to_ground(grids, (VEHICLE,), reach_m=0.5, grid=GRID) == columns.sum()
    assert np.all(grids.semantics[:, :, 7][columns] == VEHICLE) and not grids.instance[:, :, 7][columns].any()
