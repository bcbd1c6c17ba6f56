"""Cropping a tiled surface gives exactly the crop of the whole surface moved into the box frame."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nuplan_occ.geometry import make_transform, transform_points
from nuplan_occ.voxel.surface_tiles import build_surface_tiles, transform_rows

LOWER, UPPER = np.array([-26.0, -26.0, -4.0]), np.array([26.0, 26.0, 6.0])


def reference_crop(vertices_box, faces):
    """Triangles (or points) with a vertex in [LOWER, UPPER), from every vertex moved into the box frame."""
    near = np.all((vertices_box >= LOWER) & (vertices_box < UPPER), axis=1)
    if len(faces) == 0:
        return vertices_box[near], faces
    kept = faces[near[faces].any(axis=1)]
    used, remapped = np.unique(kept, return_inverse=True)
    return vertices_box[used], remapped.reshape(-1, 3)


def scene_mesh(rng):
    """A scene-frame mesh along a 300 m drive (vertices in random order): a 1 m lattice sheet, 50 triangles
    spanning the scene and a giant one reaching beyond it."""
    x, y = np.meshgrid(np.arange(0.0, 300.0), np.arange(-40.0, 40.0), indexing="ij")
    sheet = np.stack([x.ravel(), y.ravel(), rng.uniform(-3, 5, x.size)], axis=1)
    corner = np.arange(x.size).reshape(x.shape)[:-1, :-1].ravel()
    ny = x.shape[1]
    cells = np.concatenate([np.stack([corner, corner + ny, corner + 1], 1),
                            np.stack([corner + ny, corner + ny + 1, corner + 1], 1)])
    n = len(sheet)
    faces = np.concatenate([cells, rng.integers(0, n, size=(50, 3)), [[n, n + 1, 0]]])
    vertices = np.concatenate([sheet, [[-50, -50, 0], [400, 60, 1]]])
    shuffle = rng.permutation(len(vertices))
    return vertices[shuffle], np.argsort(shuffle)[faces]


def poses(rng, count):
    for _ in range(count):
        R = Rotation.from_euler("zyx", [rng.uniform(-np.pi, np.pi), *rng.normal(0, 0.03, 2)]).as_matrix()
        yield make_transform(R, [rng.uniform(-20, 320), rng.uniform(-30, 30), rng.normal(0, 1)])


@pytest.mark.parametrize("points", [False, True])
def test_tiled_crop_equals_crop_of_the_whole_surface(points):
    rng = np.random.default_rng(7)
    vertices, faces = scene_mesh(rng)
    if points:
        faces = np.zeros((0, 3), dtype=np.int64)
    tiles = build_surface_tiles(vertices, faces, tile_m=7.0)
    assert np.array_equal(tiles.vertices[tiles.faces], vertices[faces])  # renumbered, the same triangles
    for T_scene_from_box in poses(rng, 12):
        T_box_from_scene = np.linalg.inv(T_scene_from_box)
        got_vertices, got_faces = tiles.crop(T_box_from_scene, LOWER, UPPER)
        want_vertices, want_faces = reference_crop(transform_rows(T_box_from_scene, vertices), faces)
        if points:
            assert np.array_equal(got_vertices, want_vertices) and got_faces.shape == (0, 3)
        else:  # the same triangles, in the same order, each vertex once and used
            assert np.array_equal(got_vertices[got_faces], want_vertices[want_faces])
            assert np.array_equal(np.unique(got_faces), np.arange(len(got_vertices)))
            assert len(np.unique(got_vertices, axis=0)) == len(got_vertices)
        assert len(got_vertices) > 0


def test_candidates_skip_far_tiles_and_an_empty_surface_crops_to_nothing():
    rng = np.random.default_rng(8)
    vertices, faces = scene_mesh(rng)
    tiles = build_surface_tiles(vertices, faces, tile_m=10.0)
    ids = tiles.candidates(LOWER, UPPER, make_transform(np.eye(3), [150.0, 0.0, 0.0]))
    assert 0 < len(ids) < 0.3 * len(faces)  # a 52 m box over a 300 m sheet
    assert len(faces) - 1 in ids  # the giant triangle, wider than any tile, spans it
    empty = build_surface_tiles(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    got_vertices, got_faces = empty.crop(np.eye(4), LOWER, UPPER)
    assert got_vertices.shape == (0, 3) and got_faces.shape == (0, 3)


def test_transform_rows_does_not_depend_on_the_other_rows():
    rng = np.random.default_rng(9)
    points = rng.uniform(-500, 500, size=(1000, 3))
    T = make_transform(Rotation.random(random_state=2).as_matrix(), [1234.5, -333.3, 12.1])
    whole = transform_rows(T, points)
    assert all(np.array_equal(transform_rows(T, points[k:k + 1]), whole[k:k + 1]) for k in range(0, 1000, 97))
    np.testing.assert_allclose(whole, transform_points(T, points), atol=1e-9)
