"""Unboxed movers completed from the frames around them, on exact box geometry: the points gathered onto a vehicle
outline a solid from the road up, so its roof and underside voxels (which rays graze without a return in them)
are its own; a cyclist's gathered points are painted as they are, so what the frames around saw comes back
and no solid fills the air inside it."""

from __future__ import annotations

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import BICYCLE, OTHER, VEHICLE
from nuplan_occ.voxel.mover_gathering import GatherSettings
from nuplan_occ.voxel.mover_solids import gathered_solids, gathered_traces, outline_solid
from nuplan_occ.voxel.movers import MoverVoxels

GROUND_Z = -1.6  # ego frame: the road under the box; its voxel layer is 5
BOX_LO, BOX_HI = np.array([10.1, 5.1, GROUND_Z + 0.2]), np.array([14.6, 6.85, GROUND_Z + 1.5])  # ends inside voxels


def _box_side_and_roof(x_shift: float = 0.0, seed: int = 0) -> np.ndarray:
    """Returns at random spots on the box's left side (y = BOX_HI y) and roof, 400 per square metre, the box
    moved by x_shift along x."""
    rng = np.random.default_rng(seed)
    length, width, height = BOX_HI - BOX_LO
    side = rng.uniform([0.0, 0.0], [length, height], (int(400 * length * height), 2))
    roof = rng.uniform([0.0, 0.0], [length, width], (int(400 * length * width), 2))
    side = np.c_[side[:, 0], np.full(len(side), width - 0.01), side[:, 1]]
    roof = np.c_[roof, np.full(len(roof), height - 0.01)]
    return np.vstack([side, roof]) + BOX_LO + [x_shift, 0.0, 0.0]


def _ground() -> np.ndarray:
    return np.full(DEFAULT_GRID.shape[:2], GROUND_Z)


def _box_voxels() -> set[tuple[int, int, int]]:
    """Voxels above the ground layer, up to the box's top, of the columns whose centre lies in the box's footprint."""
    lo = np.ceil((BOX_LO[:2] - DEFAULT_GRID.lower[:2]) / DEFAULT_GRID.voxel_size - 0.5).astype(int)
    hi = np.floor((BOX_HI[:2] - DEFAULT_GRID.lower[:2]) / DEFAULT_GRID.voxel_size - 0.5).astype(int)
    ground_layer = int(np.floor((GROUND_Z - DEFAULT_GRID.z_min) / DEFAULT_GRID.voxel_size))
    top = int(np.floor((BOX_HI[2] - 0.01 - DEFAULT_GRID.z_min) / DEFAULT_GRID.voxel_size))
    return {(i, j, k) for i in range(lo[0], hi[0] + 1) for j in range(lo[1], hi[1] + 1)
            for k in range(ground_layer + 1, top + 1)}


def test_the_outline_fills_the_hull_from_the_road_to_the_top() -> None:
    """Side and roof seen: every column of the box, from above the road to the roof; the random returns' hull may
    cut a corner column."""
    solid = {tuple(v) for v in outline_solid(_box_side_and_roof(), _ground(), 0.5).tolist()}
    box = _box_voxels()
    corner_columns = 4 * len({k for _, _, k in box})
    assert solid <= box and len(box - solid) <= corner_columns


def test_an_unseen_column_takes_the_lowest_top_around_it() -> None:
    """A low bonnet (0.8 m, x < 11.6 m) before a 1.5 m cabin. No return came from a hole in the cabin roof nor
    from a strip of the bonnet beside the cabin. The hole takes the roof's height; the strip, with cabin and
    bonnet columns within reach, takes the bonnet's (the lowest top around), not the cabin's."""
    points = _box_side_and_roof()
    bonnet = points[:, 0] < 11.6
    points = points[~bonnet | (points[:, 2] < GROUND_Z + 0.8)]
    rng = np.random.default_rng(1)
    bonnet_top = np.c_[rng.uniform([10.1, 5.1], [11.6, 6.85], (600, 2)), np.full(600, GROUND_Z + 0.79)]
    points = np.vstack([points, bonnet_top])
    hole = (np.abs(points[:, 0] - 13.0) < 0.3) & (np.abs(points[:, 1] - 6.0) < 0.3)
    strip = (points[:, 0] >= 11.0) & (points[:, 0] < 11.5) & (points[:, 1] < 6.5)
    points = points[~hole & ~strip]
    solid = outline_solid(points, _ground(), 0.5)
    tops = {}
    for i, j, k in solid.tolist():
        tops[(i, j)] = max(tops.get((i, j), -1), k)
    column = lambda x, y: tuple(DEFAULT_GRID.point_to_index(np.array([[x, y, 0.0]]))[0][0, :2].tolist())  # noqa: E731
    layer = lambda z: int(np.floor((z - DEFAULT_GRID.z_min) / DEFAULT_GRID.voxel_size))  # noqa: E731
    assert tops[column(13.0, 6.0)] == layer(BOX_HI[2] - 0.01)  # the hole in the roof
    assert tops[column(11.3, 5.8)] == layer(GROUND_Z + 0.79)  # the bonnet strip beside the cabin


def test_unknown_ground_gives_no_solid() -> None:
    assert outline_solid(_box_side_and_roof(), np.full(DEFAULT_GRID.shape[:2], np.nan), 0.5).shape == (0, 3)


def test_each_vehicle_cluster_gathers_its_neighbours_and_other_classes_are_left() -> None:
    """Frame 0 saw the box's side and the half of its roof beside it; the frames around (moving 0.5 m per frame
    along x) saw all of the roof. The vehicle cluster's solid covers the whole box; an `other` cluster is not
    gathered."""
    full = {k: _box_side_and_roof(0.5 * k, seed=k + 3) for k in range(-3, 4)}
    own = full[0][full[0][:, 1] > (BOX_LO[1] + BOX_HI[1]) / 2]
    stray = np.c_[np.full(10, -20.1), np.linspace(-10.1, -9.0, 10), np.full(10, 0.1)]
    index = DEFAULT_GRID.point_to_index(np.vstack([own, stray]))[0]
    voxels = np.unique(index, axis=0)
    classes = np.where(voxels[:, 0] < DEFAULT_GRID.point_to_index(np.array([[0.0, 0.0, 0.0]]))[0][0, 0],
                       OTHER, VEHICLE).astype(np.uint8)
    movers = MoverVoxels(voxels, classes, np.zeros(len(voxels), bool))
    neighbours = {k: points for k, points in full.items() if k}
    solids = gathered_solids(movers, np.vstack([own, stray]), neighbours, _ground(), (VEHICLE,), GatherSettings(), 0.5)
    assert set(solids.class_ids.tolist()) == {VEHICLE}
    painted = {tuple(v) for v in solids.indices.tolist()}
    box = _box_voxels()
    assert len(painted & box) >= 0.95 * len(box)
    assert len(painted - box) <= 0.05 * len(box)


RIDER_LO, RIDER_HI = np.array([10.1, 5.1, GROUND_Z + 0.2]), np.array([11.9, 5.85, GROUND_Z + 1.7])


def _rider_faces(x_shift: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(left side, front): returns, 400 per square metre, on the left side (y = RIDER_HI y) and on the front
    (x = RIDER_HI x) of a 1.8 x 0.75 x 1.5 m rider box, moved by x_shift along x."""
    rng = np.random.default_rng(seed)
    (x0, y0, z0), (x1, y1, z1) = RIDER_LO, RIDER_HI
    side = rng.uniform([x0, z0], [x1, z1], (int(400 * (x1 - x0) * (z1 - z0)), 2))
    front = rng.uniform([y0, z0], [y1, z1], (int(400 * (y1 - y0) * (z1 - z0)), 2))
    return (np.c_[side[:, 0] + x_shift, np.full(len(side), y1 - 0.01), side[:, 1]],
            np.c_[np.full(len(front), x1 - 0.01 + x_shift), front])


def _voxel_set(points: np.ndarray) -> set[tuple[int, int, int]]:
    return {tuple(v) for v in np.unique(DEFAULT_GRID.point_to_index(points)[0], axis=0).tolist()}


def test_a_cyclist_takes_what_the_frames_around_saw_and_no_solid() -> None:
    """This frame saw the rider's left side only; the frames just before and after (0.5 m per frame along x)
    saw its front too. The trace paints the front where the rider is now and nothing inside the rider (no
    solid); a vehicle cluster is left to gathered_solids."""
    own, front_now = _rider_faces(0.0, seed=1)
    neighbours = {k: np.vstack(_rider_faces(0.5 * k, seed=k + 5)) for k in (-1, 1)}
    voxels = np.unique(DEFAULT_GRID.point_to_index(own)[0], axis=0)
    movers = MoverVoxels(voxels, np.full(len(voxels), BICYCLE, np.uint8), np.zeros(len(voxels), bool))
    traces = gathered_traces(movers, own, neighbours, (BICYCLE,), GatherSettings(), 2)
    assert set(traces.class_ids.tolist()) == {BICYCLE}
    painted = {tuple(v) for v in traces.indices.tolist()}
    front, side = _voxel_set(front_now), _voxel_set(own)
    assert len(painted & front) >= 0.9 * len(front - side)
    assert len(painted - front - side) <= 0.05 * len(painted)
    centres = DEFAULT_GRID.index_to_center(np.array(sorted(painted)))
    inside = np.all((centres > RIDER_LO + DEFAULT_GRID.voxel_size) & (centres < RIDER_HI - DEFAULT_GRID.voxel_size), axis=1)
    assert not inside.any()
    assert len(gathered_traces(movers, own, neighbours, (VEHICLE,), GatherSettings(), 2).indices) == 0
