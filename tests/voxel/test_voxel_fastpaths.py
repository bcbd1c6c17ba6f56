"""The fast traversal / voxelization paths give exactly what the straightforward implementations give.

The references below are the straightforward (slow) formulations: every ray traversed over its whole
length with all entries generated at once; every (triangle, voxel of its bounding box) candidate tested
with the separating-axis theorem on (M, 3, 3) arrays."""

import numpy as np
import pytest

from nuplan_occ.geometry import make_transform
from nuplan_occ.grid import GridSpec
from nuplan_occ.io.types import CameraCalibration
from nuplan_occ.voxel import voxelize
from nuplan_occ.rays.traversal import grid_args, mark_visible_to_first_hit
from nuplan_occ.rays.visibility import camera_rays, camera_visibility, lidar_observation

GRID = GridSpec(x_min=-6, x_max=6, y_min=-5, y_max=5, z_min=-2, z_max=2, voxel_size=0.25)


def clip_to_box(o, d, shape):
    """Parameter range [t0, t1] within [0, 1] of segments o + t d (N, 3, voxel units) inside [0, shape]."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (0.0 - o) / d
        tb = (shape - o) / d
    t_lo = np.where(d == 0, np.where((o >= 0) & (o < shape), -np.inf, np.inf), np.minimum(ta, tb))
    t_hi = np.where(d == 0, np.where((o >= 0) & (o < shape), np.inf, -np.inf), np.maximum(ta, tb))
    return np.maximum(t_lo.max(axis=1), 0.0), np.minimum(t_hi.min(axis=1), 1.0)


def reference_entries(starts, ends, grid, t_from=None):
    """(ray, flat voxel, t) of every voxel entered by each segment over its whole length (from t_from (N,) on
    where given)."""
    shape = np.asarray(grid.shape)
    o_all = (starts - grid.lower) / grid.voxel_size
    d_all = (ends - grid.lower) / grid.voxel_size - o_all
    t0, t1 = clip_to_box(o_all, d_all, shape.astype(np.float64))
    if t_from is not None:
        t0 = np.maximum(t0, t_from)
    rays = np.flatnonzero(t0 < t1)
    o, d, t0, t1 = o_all[rays], d_all[rays], t0[rays], t1[rays]
    a, b = o + t0[:, None] * d, o + t1[:, None] * d
    first = np.floor(np.minimum(a, b)).astype(np.int64) + 1
    count = np.where(d == 0, 0, np.maximum(np.floor(np.maximum(a, b)).astype(np.int64) - first + 1, 0))
    inv_len = 1e-6 / np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    ray_ids, ts = [np.arange(len(o))], [t0]
    for axis in range(3):
        for r in np.flatnonzero(count[:, axis]):  # the reciprocal taken once per segment and axis, as documented
            k = first[r, axis] + np.arange(count[r, axis])
            ray_ids.append(np.full(len(k), r))
            ts.append((k - o[r, axis]) * (1.0 / d[r, axis]))
    ids, t = np.concatenate(ray_ids), np.concatenate(ts)
    keep = t < t1[ids]
    keep[: len(o)] = True
    ids, t = ids[keep], t[keep]
    vox = np.floor(o[ids] + (t + inv_len[ids])[:, None] * d[ids]).astype(np.int64)
    inside = np.all((vox >= 0) & (vox < shape), axis=1)
    ids, t, vox = ids[inside], t[inside], vox[inside]
    return rays[ids], np.ravel_multi_index(vox.T, grid.shape), t


def random_segments(rng, n):
    """Segments of every kind: random, leaving the grid, axis-parallel, on lattice planes, degenerate."""
    starts = rng.uniform(-7, 7, size=(n, 3)) * [1, 1, 0.4]
    ends = starts + rng.normal(size=(n, 3)) * [6, 6, 2]
    lattice = rng.random(n) < 0.3
    starts[lattice] = np.round(starts[lattice] * 4) / 4
    ends[lattice] = np.round(ends[lattice] * 4) / 4
    parallel = rng.random(n) < 0.2
    ends[parallel, 1:] = starts[parallel, 1:]
    ends[:3] = starts[:3]
    grazing = slice(3, 23)  # nearly parallel to a y plane, crossing it (the floating-point fallback)
    starts[grazing, 1], ends[grazing, 1] = 0.25 - 1e-10, 0.25 + rng.uniform(-1e-9, 1e-9, 20)
    return starts, ends


def test_lidar_observation_equals_full_traversal():
    rng = np.random.default_rng(5)
    origin = np.array([0.3, -0.2, 0.4])
    starts, ends = random_segments(rng, 400)
    ends = np.concatenate([ends, origin + rng.normal(size=(300, 3)) * [5, 5, 1]])
    expected = np.zeros(GRID.shape, np.uint8).ravel()
    _, flat, _ = reference_entries(np.broadcast_to(origin, ends.shape), ends, GRID)
    expected[flat] = 1
    idx, inside = GRID.point_to_index(ends)
    expected[np.ravel_multi_index(idx[inside].T, GRID.shape)] = 2
    assert np.array_equal(lidar_observation(ends, origin, GRID).ravel(), expected)
    per_ray = np.zeros(GRID.shape, np.uint8).ravel()
    _, flat, _ = reference_entries(starts, ends[:400], GRID)
    per_ray[flat] = 1
    idx, inside = GRID.point_to_index(ends[:400])
    per_ray[np.ravel_multi_index(idx[inside].T, GRID.shape)] = 2
    assert np.array_equal(lidar_observation(ends[:400], starts, GRID).ravel(), per_ray)


def camera(yaw, position, f=60.0):
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.stack([[s, -c, 0.0], [0.0, 0.0, -1.0], [c, s, 0.0]], axis=1)
    K = np.array([[f, 0.3, 64.0], [0.0, f * 1.1, 36.0], [0.0, 0.0, 1.0]])
    return CameraCalibration("c", "CAM", "pinhole", K, np.zeros(5), make_transform(R, position), 128, 72)


def first_hit_entries(starts, ends, occupied, t_block, t_from=None):
    """Per segment (whole, or from t_from (N,) on): the flat voxels up to its first blocking entry, whether it
    ends (t = 1) inside the grid unblocked, and where its walk stops (its first blocking entry, or where it
    leaves the grid or ends, within [0, 1]; 0 for a segment missing the grid)."""
    ids, flat, t = reference_entries(starts, ends, GRID, t_from)
    blocking = occupied.ravel()[flat] & (t >= t_block)
    t_hit = np.full(len(starts), np.inf)
    np.minimum.at(t_hit, ids[blocking], t[blocking])
    o = (starts - GRID.lower) / GRID.voxel_size
    t0, t1 = clip_to_box(o, (ends - GRID.lower) / GRID.voxel_size - o, np.asarray(GRID.shape, np.float64))
    met = t0 < t1 if t_from is None else np.maximum(t0, t_from) < t1
    stop = np.where(t0 < t1, np.minimum(t_hit, np.clip(t1, 0.0, 1.0)), 0.0)
    return flat[t <= t_hit[ids]], met & (t1 >= 1.0) & np.isinf(t_hit), stop


def scene_for_cameras(seed):
    rng = np.random.default_rng(seed)
    occupied = rng.random(GRID.shape) < 0.01
    occupied[:, :, 5] |= rng.random(GRID.shape[:2]) < 0.8  # a leaky ground layer
    cams = [camera(rng.uniform(-np.pi, np.pi), rng.uniform(-1, 1, 3) * [4, 3, 0.5]) for _ in range(3)]
    cams.append(camera(0.0, np.array([-5.9, 0.0, 0.0])))  # axis-parallel rays from near the border
    return occupied, cams


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_camera_visibility_of_one_band_equals_full_traversal(seed):
    occupied, cams = scene_for_cameras(seed)
    max_range, step, near = 14.0, 0.25 / 14.0, 0.5
    expected = np.zeros(occupied.size, bool)
    for cam in cams:
        origin, dirs = camera_rays(cam, step)
        starts = np.broadcast_to(origin, dirs.shape)
        seen, _, _ = first_hit_entries(starts, starts + dirs * max_range, occupied, near / max_range)
        expected[seen] = True
    got = camera_visibility(occupied, cams, GRID, max_range_m=max_range, near_m=near, range_bands=1)
    assert np.array_equal(got.ravel(), expected)
    assert 0 < got.sum() < got.size


def test_first_hit_walk_of_every_kind_of_segment_equals_full_traversal():
    """The merged walk counts its cell and evaluates entries in floating point only near planes, the border
    and its ends: segments of every kind, and ones starting or ending a hair before, on or after lattice
    planes, give exactly the reference's entries, outcomes and stops."""
    rng = np.random.default_rng(11)
    starts, ends = random_segments(rng, 600)
    hair = GRID.voxel_size * rng.choice([-1e-6, -1e-7, -1e-10, 0.0, 1e-10, 1e-7, 1e-6], size=(400, 3))
    on_planes = np.round(rng.uniform(-6, 6, size=(400, 3)) * [1, 0.8, 0.3] * 4) / 4 + hair
    starts = np.concatenate([starts, on_planes[:200], rng.uniform(-5, 5, size=(200, 3)) * [1, 1, 0.3]])
    ends = np.concatenate([ends, rng.uniform(-5, 5, size=(200, 3)) * [1, 1, 0.3], on_planes[200:]])
    occupied = rng.random(GRID.shape) < 0.02
    t_from = np.where(rng.random(len(starts)) < 0.3, rng.uniform(0, 0.8, len(starts)), 0.0)
    t_from[rng.random(len(starts)) < 0.05] = np.inf
    visible, reached, stop = np.zeros(occupied.size, bool), np.zeros(len(starts), bool), np.full(len(starts), -1.0)
    mark_visible_to_first_hit(starts, ends, *grid_args(GRID), occupied.ravel(), 0.1, t_from, visible, reached, stop)
    walked = np.isfinite(t_from)
    seen, reached_ref, stop_ref = first_hit_entries(starts[walked], ends[walked], occupied, 0.1, t_from[walked])
    expected = np.zeros(occupied.size, bool)
    expected[seen] = True
    assert np.array_equal(visible, expected)
    assert np.array_equal(reached[walked], reached_ref) and not reached[~walked].any()
    assert np.array_equal(stop[walked], stop_ref) and np.all(stop[~walked] == -1.0)
    assert 0 < visible.sum() < visible.size


def pixel_cells(cam, step):
    """Pixel lattice (u, v centres) of a camera at angular step `step`, and its cell sizes."""
    su, sv = max(1.0, cam.K[0, 0] * step), max(1.0, cam.K[1, 1] * step)
    return np.arange(su / 2, cam.width, su), np.arange(sv / 2, cam.height, sv), su, sv


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_camera_visibility_by_range_bands_follows_the_band_rule(seed):
    """Bands end at 3.5, 7 and 14 m; a ray resumes at its band's near end when the previous band's 3 x 3 rays
    around its pixel all reached it unblocked, is skipped when none did, and otherwise is walked from one voxel
    before the least distance those rays are known unblocked to (a skipped ray: the least of its own 3 x 3)."""
    occupied, cams = scene_for_cameras(seed)
    max_range, near = 14.0, 0.5
    expected = np.zeros(occupied.size, bool)
    edges = 0
    for cam in cams:
        reached, unblocked_m, previous = None, None, None
        for far in (3.5, 7.0, 14.0):
            step = 0.25 / far
            origin, dirs = camera_rays(cam, step)
            starts = np.broadcast_to(origin, dirs.shape)
            u, v, _, _ = pixel_cells(cam, step)
            if reached is None:
                walk = np.ones(len(dirs), bool)
                t_from = np.zeros(len(dirs))
                least_m = np.zeros(len(dirs))
            else:
                pu, pv, psu, psv = previous
                cell_u = np.minimum(np.floor(u / psu).astype(int), len(pu) - 1)  # the last cell holds the image's edge
                cell_v = np.minimum(np.floor(v / psv).astype(int), len(pv) - 1)
                iu = np.clip(cell_u[:, None, None, None] + np.arange(-1, 2)[:, None], 0, len(pu) - 1)
                iv = np.clip(cell_v[None, :, None, None] + np.arange(-1, 2), 0, len(pv) - 1)
                around = (iu * len(pv) + iv).reshape(len(dirs), 9)
                walk = reached[around].any(axis=1)
                least_m = unblocked_m[around].min(axis=1)
                edge = walk & ~reached[around].all(axis=1)
                edges += int(edge.sum())
                t_from = np.where(reached[around].all(axis=1), 0.5, np.maximum(least_m - 0.25, 0.0) / far)
            seen, reached_now, stop_now = first_hit_entries(starts[walk], starts[walk] + dirs[walk] * far, occupied,
                                                            near / far, t_from[walk])
            expected[seen] = True
            reached = np.zeros(len(dirs), bool)
            reached[walk] = reached_now
            unblocked_m = least_m.copy()
            unblocked_m[walk] = stop_now * far
            previous = (u, v, *pixel_cells(cam, step)[2:])
    assert edges > 100
    got = camera_visibility(occupied, cams, GRID, max_range_m=max_range, near_m=near, range_bands=3)
    assert np.array_equal(got.ravel(), expected)
    whole = camera_visibility(occupied, cams, GRID, max_range_m=max_range, near_m=near, range_bands=1)
    assert (got ^ whole).sum() < 0.05 * whole.sum()


def reference_triangle_voxels(tri):
    """Test each (triangle, voxel of its bounding box) candidate by SAT on the closed cube [v-EPS, v+1-EPS]."""
    eps, h = voxelize.EPS, 0.5
    first = np.floor(tri.min(axis=1) + eps).astype(np.int64)
    last = np.floor(tri.max(axis=1) + eps).astype(np.int64)
    t_idx, vox = [], []
    for t in range(len(tri)):
        axes = [np.arange(a, b + 1) for a, b in zip(first[t], last[t])]
        box = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        t_idx.append(np.full(len(box), t))
        vox.append(box)
    t_idx, vox = np.concatenate(t_idx), np.concatenate(vox)
    u = tri[t_idx] - (vox + (h - eps))[:, None, :]
    ok = np.all((u.min(axis=1) <= h) & (u.max(axis=1) >= -h), axis=1)
    normal = np.cross(u[:, 1] - u[:, 0], u[:, 2] - u[:, 0])
    ok &= np.abs((normal * u[:, 0]).sum(axis=1)) <= h * np.abs(normal).sum(axis=1)
    for f in (u[:, 1] - u[:, 0], u[:, 2] - u[:, 1], u[:, 0] - u[:, 2]):
        for a, b in ((1, 2), (2, 0), (0, 1)):
            p = u[:, :, b] * f[:, None, a] - u[:, :, a] * f[:, None, b]
            r = h * (np.abs(f[:, a]) + np.abs(f[:, b]))
            ok &= (p.min(axis=1) <= r) & (p.max(axis=1) >= -r)
    single = np.all(first == last, axis=1)[t_idx]  # a triangle inside one voxel touches it
    return np.unique(vox[ok | single], axis=0)


@pytest.mark.parametrize("scale, count", [(0.4, 300), (1.0, 300), (3.0, 300), (12.0, 200)])
def test_triangle_voxels_equal_candidate_sat(scale, count):
    rng = np.random.default_rng(int(scale * 10))
    tri = rng.uniform(-1, 1, size=(count, 3, 3)) * scale + rng.uniform(-4, 4, size=(count, 1, 3))
    tri[:100] = np.round(tri[:100] * 2) / 2  # vertices on the lattice and on half voxels: touching cases
    tri[100:150, :, 2] = np.round(tri[100:150, :1, 2])  # flat triangles on a lattice plane
    tri[150:160, 1] = tri[150:160, 0]  # degenerate (segments)
    assert np.array_equal(voxelize.triangle_voxel_indices(tri), reference_triangle_voxels(tri))
