"""A frame composed of a ground plane, a moving car box and a static cone."""

import numpy as np
import pytest
import trimesh

from nuplan_occ.grid import GridSpec
from nuplan_occ.labels import OTHER, ROAD, TRAFFIC_CONE, VEHICLE
from nuplan_occ.voxel.compose import (
    FrameGrids, PlacedObject, clear_ego_box, compose_frame, crowded_or_anchored, object_voxel_indices,
    zero_emptied_objects,
)
from nuplan_occ.voxel.voxelize import VoxelizeError, in_box


GRID = GridSpec(x_min=-10, x_max=10, y_min=-10, y_max=10, z_min=-3, z_max=5, voxel_size=0.25)
GROUND_Z = -1.4  # layer 6


def box_mesh(lo, hi):
    """Closed 12-triangle box surface between corners lo and hi (metres)."""
    mesh = trimesh.creation.box(bounds=np.stack([lo, hi]))
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def frame(fill=True, ground_layer_classes=()):
    ground_v = np.array([[-12, -12, GROUND_Z], [12, -12, GROUND_Z], [12, 12, GROUND_Z], [-12, 12, GROUND_Z]])
    # the background mesh also holds a stale blob inside the car's box (to be removed)
    blob_v, blob_f = box_mesh(np.array([4.2, 1.2, -0.9]), np.array([4.8, 1.8, -0.2]))
    vertices = np.concatenate([ground_v, blob_v])
    faces = np.concatenate([np.array([[0, 1, 2], [0, 2, 3]]), blob_f + 4])
    car_v, car_f = box_mesh(np.array([-2.1, -0.85, -0.7]), np.array([2.1, 0.85, 0.7]))  # box frame
    car = PlacedObject(car_v, car_f, center=np.array([5.0, 1.0, -0.55]), yaw=np.pi / 2, size=np.array([4.4, 1.9, 1.6]),
                       class_id=VEHICLE, instance_id=7, velocity=np.array([0.0, 3.0, 0.0]))
    cone_pts = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.2]])
    cone = PlacedObject(cone_pts, np.zeros((0, 3), int), center=np.array([-3.0, -3.0, -1.1]), yaw=0.0,
                        size=np.array([0.4, 0.4, 0.6]), class_id=TRAFFIC_CONE, instance_id=9)
    bev = np.full(GRID.shape[:2], ROAD, dtype=np.uint8)
    return compose_frame(vertices, faces, [car, cone], bev, GRID, fill_objects=fill,
                         ground_layer_classes=ground_layer_classes), car


def test_moving_car_has_its_class_instance_and_flow():
    grids, car = frame()
    in_car = grids.instance == 7
    # the filled car: 4.2 x 1.7 x 1.4 m rotated by 90 deg -> x in [4.15, 5.85], y in [-1.1, 3.1],
    # z in [-1.25, 0.15] -> voxel index blocks 56..63, 35..52, 7..12 (z = -1.25 is a boundary: layer 7)
    expected = np.zeros(GRID.shape, bool)
    expected[56:64, 35:53, 7:13] = True
    assert np.array_equal(in_car, expected)
    assert np.all(grids.semantics[in_car] == VEHICLE)
    assert np.allclose(grids.flow[in_car].astype(float), [0.0, 3.0, 0.0])
    assert np.all(grids.flow[~in_car] == 0) and np.all(grids.instance[grids.semantics == ROAD] == 0)
    assert grids.semantics.dtype == np.uint8 and grids.instance.dtype == np.uint16 and grids.flow.dtype == np.float16


def test_background_in_box_removed_but_ground_kept():
    grids, _ = frame()
    assert np.all(grids.semantics[:, :, 6][grids.occupied_background[:, :, 6]] == ROAD)
    assert grids.occupied_background[:, :, 6].sum() + (grids.instance[:, :, 6] > 0).sum() == 80 * 80
    assert not np.any(grids.semantics == OTHER)  # the stale blob inside the car's box is gone
    assert not np.any(grids.occupied_background & (grids.instance > 0))


def test_points_object_and_no_fill():
    grids, _ = frame(fill=False)
    assert (grids.instance == 9).sum() == 2 and np.all(grids.semantics[grids.instance == 9] == TRAFFIC_CONE)
    shell = (grids.instance == 7).sum()
    filled, _ = frame(fill=True)
    assert (filled.instance == 7).sum() > shell


def test_ground_layer_classes_give_the_layer_back_to_the_road():
    ground_v = np.array([[-12, -12, GROUND_Z], [12, -12, GROUND_Z], [12, 12, GROUND_Z], [-12, 12, GROUND_Z]])
    car_v, car_f = box_mesh(np.array([-2.0, -0.8, -0.8]), np.array([2.0, 0.8, 0.8]))
    car = PlacedObject(car_v, car_f, center=np.array([5.0, 1.0, GROUND_Z + 0.8]), yaw=0.0,
                       size=np.array([4.0, 1.6, 1.6]), class_id=VEHICLE, instance_id=3)
    bev = np.full(GRID.shape[:2], ROAD, dtype=np.uint8)
    plain = compose_frame(ground_v, np.array([[0, 1, 2], [0, 2, 3]]), [car], bev, GRID)
    cleared = compose_frame(ground_v, np.array([[0, 1, 2], [0, 2, 3]]), [car], bev, GRID, ground_layer_classes=(VEHICLE,))
    layer = 6  # GROUND_Z = -1.4 lies in [-1.5, -1.25)
    under = plain.instance[:, :, layer] == 3
    assert under.sum() >= 16 * 7  # at least x 3..7 (16 voxels) by y 0.2..1.8 (7 voxels)
    assert not np.any(cleared.instance[:, :, layer] == 3)
    assert np.all(cleared.semantics[:, :, layer][under] == ROAD) and np.all(cleared.flow[:, :, layer][under] == 0)
    assert np.array_equal(cleared.instance[:, :, layer + 1:] == 3, plain.instance[:, :, layer + 1:] == 3)


def test_sparse_solid_cells_need_company_or_an_observed_cell():
    # 0.1 m cell centres in the box frame: a full 0.5 m block, plus two lone cells a rays-crossed voxel kept
    axis = np.arange(-0.2, 0.25, 0.1)
    block = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    lone = np.array([[0.6, 0.0, 0.0], [0.0, 0.6, 0.0]])
    points = np.vstack([block, lone])
    observed = np.zeros(len(points), dtype=bool)
    observed[-1] = True  # the second lone cell holds an observed point
    common = dict(faces=np.zeros((0, 3), int), center=np.array([0.1, 0.1, 0.1]), yaw=0.0,
                  size=np.array([1.6, 1.6, 1.6]), class_id=VEHICLE, instance_id=3)
    kept_all = object_voxel_indices(PlacedObject(points, **common), GRID, fill=False)
    thinned = object_voxel_indices(PlacedObject(points, **common, min_points_per_voxel=4, anchors=observed), GRID,
                                   fill=False)
    lone_voxels = {tuple(v) for v in np.floor((lone + 0.1 - GRID.lower) / 0.25).astype(int)}
    assert lone_voxels <= {tuple(v) for v in kept_all}
    kept = {tuple(v) for v in thinned}
    observed_voxel = tuple(np.floor((lone[1] + 0.1 - GRID.lower) / 0.25).astype(int))
    unobserved_voxel = tuple(np.floor((lone[0] + 0.1 - GRID.lower) / 0.25).astype(int))
    assert observed_voxel in kept and unobserved_voxel not in kept
    block_voxels = {tuple(v) for v in np.floor((block + 0.1 - GRID.lower) / 0.25).astype(int)}
    crowded = crowded_or_anchored(block + 0.1, None, 4, GRID)
    assert {tuple(v) for v in np.floor((block[crowded] + 0.1 - GRID.lower) / 0.25).astype(int)} <= kept
    assert len(kept & block_voxels) >= 1


def test_an_object_holds_its_geometry_voxels_and_the_voxels_of_its_own_points():
    # a 0.4 m cone, yawed 45 deg, with 3 x 3 x 3 points 0.12 m apart in its box frame
    axis = np.array([-0.12, 0.0, 0.12])
    points = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    common = dict(center=np.array([2.0, 2.0, -1.0]), yaw=np.pi / 4, size=np.array([0.4, 0.4, 0.7]),
                  class_id=TRAFFIC_CONE, instance_id=5, own_points=points)
    expected = {tuple(v) for v in GRID.point_to_index(PlacedObject(points, np.zeros((0, 3), int), **common)
                                                       .vertices_ego())[0]}
    empty_surface = PlacedObject(np.zeros((0, 3)), np.zeros((0, 3), int), **common)
    assert {tuple(v) for v in object_voxel_indices(empty_surface, GRID)} == expected
    sliver_v, sliver_f = box_mesh(np.array([-0.01, -0.01, -0.01]), np.array([0.01, 0.01, 0.01]))  # one voxel
    sliver = PlacedObject(sliver_v, sliver_f, **common)
    assert {tuple(v) for v in object_voxel_indices(sliver, GRID)} == expected
    # a solid that stops 0.05 m below the lowest points: it misses the voxels the points reach into
    lid_v, lid_f = box_mesh(np.array([-0.2, -0.2, -0.35]), np.array([0.2, 0.2, -0.17]))
    lid = PlacedObject(lid_v, lid_f, **common)
    lid_alone = {tuple(v) for v in object_voxel_indices(PlacedObject(lid_v, lid_f, **{**common, "own_points": None}), GRID)}
    got = object_voxel_indices(lid, GRID)
    assert len(got) == len({tuple(v) for v in got})
    assert {tuple(v) for v in got} == lid_alone | expected and not expected <= lid_alone
    grids = compose_frame(np.zeros((0, 3)), np.zeros((0, 3), int), [empty_surface], None, GRID)
    assert (grids.instance == 5).sum() == len(expected) and (grids.semantics[grids.instance == 5] == TRAFFIC_CONE).all()


def test_emptied_object_voxels_lose_their_instance_id_and_flow_and_the_rest_keep_theirs():
    rng = np.random.default_rng(7)
    shape = (6, 5, 4)
    instance = rng.integers(0, 3, shape).astype(np.uint16)
    flow = rng.normal(size=(*shape, 3)).astype(np.float16)
    semantics = rng.integers(0, 2, shape).astype(np.uint8) * 7
    grids = FrameGrids(semantics, instance.copy(), flow.copy(), np.zeros(shape, bool))
    emptied = (instance != 0) & (semantics == 0)
    assert 0 < emptied.sum() < (instance != 0).sum()  # some object voxels emptied, some kept
    zero_emptied_objects(grids, semantics)
    assert np.array_equal(grids.instance, np.where(emptied, 0, instance))
    assert np.array_equal(grids.flow, np.where(emptied[..., None], np.float16(0), flow))
    with pytest.raises(VoxelizeError, match="C-contiguous"):
        zero_emptied_objects(FrameGrids(semantics, instance.T.copy().T, flow, np.zeros(shape, bool)), semantics)


def test_the_ego_box_ends_empty_above_the_ground_layer_and_nothing_outside_it_changes():
    ground_v = np.array([[-12, -12, GROUND_Z], [12, -12, GROUND_Z], [12, 12, GROUND_Z], [-12, 12, GROUND_Z]])
    bump_v, bump_f = box_mesh(np.array([0.0, -0.5, -1.4]), np.array([1.0, 0.5, -0.9]))  # a bump of the surface
    vertices = np.concatenate([ground_v, bump_v])
    faces = np.concatenate([np.array([[0, 1, 2], [0, 2, 3]]), bump_f + 4])
    cone_v, cone_f = box_mesh(np.array([-0.3, -0.3, -0.45]), np.array([0.3, 0.3, 0.45]))
    cone = PlacedObject(cone_v, cone_f, center=np.array([3.9, 0.0, -0.95]), yaw=0.0, size=np.array([0.6, 0.6, 0.9]),
                        class_id=TRAFFIC_CONE, instance_id=9, velocity=np.array([1.0, 0.0, 0.0]))
    grids = compose_frame(vertices, faces, [cone], np.full(GRID.shape[:2], ROAD, np.uint8), GRID)
    before = {name: getattr(grids, name).copy() for name in ("semantics", "instance", "flow", "occupied_background")}
    center, size = np.array([1.5, 0.0, -0.5]), np.array([5.0, 2.3, 1.8])  # bottom at -1.4 m: the ground's height
    inside = in_box(GRID.voxel_centers().reshape(-1, 3), center, 0.0, size).reshape(GRID.shape)
    inside[:, :, :7] = False  # layer 6 holds the ground
    assert np.count_nonzero(before["semantics"][inside] == OTHER) > 0  # the bump is there
    assert np.count_nonzero(before["instance"][inside] == 9) > 0  # and the part of the cone inside the box

    emptied = clear_ego_box(grids, center, size, GRID)

    assert emptied == np.count_nonzero(before["semantics"][inside])
    assert not grids.semantics[inside].any() and not grids.instance[inside].any()
    assert not grids.flow[inside].any() and not grids.occupied_background[inside].any()
    for name, grid in before.items():
        assert np.array_equal(getattr(grids, name)[~inside], grid[~inside])
    under = inside.any(axis=2)
    assert np.all(grids.semantics[:, :, 6][under & (before["instance"][:, :, 6] == 0)] == ROAD)  # the road under the ego
    assert np.count_nonzero(grids.instance == 9) > 0  # the cone's part beyond the box's front (x > 4.0 m) stays
