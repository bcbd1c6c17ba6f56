"""Refinement of logged ego poses by registering background sweeps to a local map (KISS-ICP-style point-to-plane ICP against a local map).

Procedure (all in the "local" frame = the ego frame of logged frame 0, to keep coordinates small):
1. Frame k's prior is the refined pose of frame k-1 times the LOGGED relative motion k-1 -> k.
2. Its voxel-downsampled background is registered, coarse to fine, to a local map made of the last
   `window` trusted sweeps (point-to-plane Gauss-Newton ICP with a Tukey kernel, kd-tree (points.knn)
   correspondences re-queried only where they can have changed (tracked_nearest), map voxel means updated
   as sweeps enter and leave the window, PCA map normals computed only for the map points matched
   (points.plane_normals) and kept by map voxel for the next frames (normal_reuse_frames); deterministic,
   unlike Open3D's parallel ICP). Sweeps and map are downsampled to
   voxel centroids on grids aligned with their frame's origin (points.voxel_reduce). This refines all six
   degrees of freedom, z, roll and pitch included, so that the ground does not layer.
3. The result is gated: too few points, empty map, low fitness, high RMSE, degenerate geometry (a direction
   without point-to-plane constraint, e.g. a featureless plane) or an implausibly large correction with respect
   to the prior rejects it; the frame then keeps its prior (the logged pose chain) and stays out of the map.
4. Anchoring. The refined chain is consistent but its absolute placement is only as good as the logged poses.
   anchor="fit" (default) moves the whole chain by ONE rigid transform fitted to the logged poses of all frames:
   rotation and x, y from the logged x, y positions and orientations (robust least squares), then z as the median
   z offset. Logged z is deliberately left out of the rotation fit, so a slow drift in logged z can neither tilt
   the scene nor layer it; the absolute height of the scene is then the log's median z error (unknowable without
   an external reference). anchor="first" keeps frame 0 at its logged pose instead.
Poses are T_global_from_ego (4, 4); clouds are background points (n, 3) in each frame's ego frame (metres).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from nuplan_occ.points import PointInputError
from nuplan_occ.points.knn import KdTree
from nuplan_occ.points.plane_normals import LazyNormals
from nuplan_occ.registration.point_to_plane import normal_equations
from nuplan_occ.registration.tracked_nearest import TrackedNearest
from nuplan_occ.points.voxel_reduce import KeyIndex, accumulate, voxel_centroids, voxel_keys
from nuplan_occ.geometry import invert_transform, make_transform, rotation_angle_deg, transform_points


ANCHORS = ("fit", "first")
NEAREST_MARGIN_M = 0.1
"""Search radius beyond the correspondence distance of each kd-tree query (TrackedNearest margin_m)."""
COMPACT_RATIO = 3
"""The local map re-numbers its voxels once it has named more than this many times the voxels it holds."""
CONVERGED_STEP = 1e-5
"""An ICP stage stops after a Gauss-Newton step shorter than this (norm of rotation vector, rad, and translation, m)."""


@dataclass
class RegistrationParams:
    """Settings of `refine_poses` (the register stage declares each one's meaning, unit and range).

    voxel_size_m / map_voxel_m: downsampling of the source sweep / the local map (m); window: previous trusted
    sweeps in the local map; max_correspondence_m: correspondence distance of each coarse-to-fine ICP stage
    (m); tukey_ratio: Tukey kernel width as a fraction of it; max_iterations: per stage; coarse_stride: the
    first of several stages fits every n-th source point, the finer ones all of them from its estimate;
    normal_radius_m / normal_max_nn: map normals; normal_reuse_frames: frames a map voxel's normal serves
    before it is estimated again (0: every frame). Gates on the last stage: min_points (after downsampling),
    min_fitness (share of source points with a correspondence), max_rmse_m (point-to-plane RMSE, m),
    min_conditioning (smallest / largest eigenvalue of the point-to-plane information, rotation scaled by the
    points' RMS range), max_translation_m / max_rotation_deg (the correction with respect to the prior).
    anchor: "fit" or "first" (module docstring); log_sigma_xy_m / log_sigma_deg: weights of the "fit" anchor.
    min_voxel_points: the downsampled sweep and its map contribution keep only voxels holding at least this
    many of its points (1: all).
    """

    voxel_size_m: float = 0.3
    map_voxel_m: float = 0.2
    window: int = 10
    max_correspondence_m: tuple[float, ...] = (1.5, 0.6, 0.25)
    tukey_ratio: float = 0.5
    max_iterations: int = 30
    coarse_stride: int = 4
    normal_radius_m: float = 1.0
    normal_max_nn: int = 20
    normal_reuse_frames: int = 10
    min_points: int = 100
    min_fitness: float = 0.4
    max_rmse_m: float = 0.1
    min_conditioning: float = 0.02
    max_translation_m: float = 1.5
    max_rotation_deg: float = 4.0
    anchor: str = "fit"
    log_sigma_xy_m: float = 0.3
    log_sigma_deg: float = 1.0
    min_voxel_points: int = 1


@dataclass
class RegistrationResult:
    """poses (F, 4, 4) refined T_global_from_ego; corrections (F, 4, 4) = refined @ inv(logged);
    accepted (F,) whether the ICP result was kept; fitness (F,) and rmse (F,) m of the last ICP stage (NaN when
    ICP did not run; frame 0 is the reference and is accepted without ICP); reasons: "" when accepted, else why."""

    poses: np.ndarray
    corrections: np.ndarray
    accepted: np.ndarray
    fitness: np.ndarray
    rmse: np.ndarray
    reasons: list[str]


def plane_conditioning(points: np.ndarray, normals: np.ndarray, center: np.ndarray) -> float:
    """Smallest / largest eigenvalue of the point-to-plane information sum J^T J, J = [(p - c) x n / L, n].

    points (n, 3) registered source points, normals (n, 3) of their map correspondences, center (3,) the sweep's
    position, all in one frame; L = RMS distance of the points to the centre (makes rotation and translation
    comparable). Near 0 when some motion leaves every point on its plane (flat ground, a straight corridor)."""
    if len(points) < 6:
        return 0.0
    arm = points - center
    scale = np.sqrt(np.mean(np.sum(arm**2, axis=1))) or 1.0
    J = np.hstack([np.cross(arm, normals) / scale, normals])
    eig = np.linalg.eigvalsh(J.T @ J)
    return float(max(eig[0], 0.0) / eig[-1]) if eig[-1] > 0 else 0.0


@dataclass
class _Target:
    """The local map as ICP target, built for frame `frame`: points (m, 3) local frame, their kd-tree and
    normals, `voxels` (m,) the map voxel id of each point (_LocalMap.index) and `adopted` (m,) whether its
    normal was known before (not computed for this frame)."""

    points: np.ndarray
    tree: KdTree
    normals: LazyNormals
    voxels: np.ndarray
    adopted: np.ndarray
    frame: int


class _LocalMap:
    """The last `window` trusted sweeps (local frame, each with the ids of its map voxels) and the
    normal-carrying cloud made of them: one point per map voxel, the mean of the sweeps' points in it, kept
    up to date as sweeps enter and leave (`sums`, `counts` per voxel id, 0 for ids not named yet). `index` names the map voxels (ids in
    order of first appearance; re-numbered once it names far more than the window holds, `_compact`);
    `normal` and `born` keep per voxel id the last normal computed and the frame it was computed for (-1: none)."""

    def __init__(self, params: RegistrationParams):
        self.params = params
        self.sweeps: list[tuple[np.ndarray, np.ndarray]] = []
        self.index = KeyIndex()
        self.sums, self.counts = np.zeros((0, 3)), np.zeros(0)
        self.normal, self.born = np.zeros((0, 3)), np.zeros(0, np.int64)

    def add(self, points_local: np.ndarray) -> None:
        ids = self.index.add(voxel_keys(points_local, self.params.map_voxel_m))
        self._grow(len(self.index.keys))
        accumulate(ids, points_local, 1.0, self.sums, self.counts)
        self.sweeps.append((points_local, ids))
        if len(self.sweeps) > self.params.window:
            accumulate(self.sweeps[0][1], self.sweeps[0][0], -1.0, self.sums, self.counts)
            self.sweeps.pop(0)
        if len(self.index.keys) > COMPACT_RATIO * np.count_nonzero(self.counts):
            self._compact()

    def target(self, frame: int) -> _Target:
        """The map as target for registering frame `frame`, with the normals computed at most
        `normal_reuse_frames` frames before (see RegistrationParams)."""
        p = self.params
        voxels = np.flatnonzero(self.counts > 0)
        voxels = voxels[np.argsort(self.index.keys[voxels])]  # key order: neighbours in space stay near in memory
        points = self.sums[voxels] / self.counts[voxels, None]
        tree = KdTree(points)
        born = self.born[voxels]
        adopted = (born >= 0) & (frame - born <= p.normal_reuse_frames)
        normals = LazyNormals(tree, p.normal_radius_m, p.normal_max_nn)
        normals.adopt(np.flatnonzero(adopted), self.normal[voxels[adopted]])
        return _Target(points, tree, normals, voxels, adopted, frame)

    def keep_normals(self, target: _Target) -> None:
        """Remember the normals computed for target's frame."""
        computed = target.normals.known & ~target.adopted
        self.normal[target.voxels[computed]] = target.normals.normals[computed]
        self.born[target.voxels[computed]] = target.frame

    def _grow(self, size: int) -> None:
        """Per-voxel arrays for at least `size` voxel ids (grown by doubling; new ids empty)."""
        if size <= len(self.counts):
            return
        grown = max(size, 2 * len(self.counts)) - len(self.counts)
        self.sums, self.counts = np.vstack([self.sums, np.zeros((grown, 3))]), np.r_[self.counts, np.zeros(grown)]
        self.normal = np.vstack([self.normal, np.zeros((grown, 3))])
        self.born = np.r_[self.born, np.full(grown, -1, np.int64)]

    def _compact(self) -> None:
        """Re-number the map voxels to those the window holds (dropping the others' normals)."""
        held = np.flatnonzero(self.counts > 0)
        renumber = np.full(len(self.counts), -1, np.int64)
        renumber[held] = np.arange(len(held))
        self.index = KeyIndex(self.index.keys[held])
        self.sums, self.counts = self.sums[held], self.counts[held]
        self.normal, self.born = self.normal[held], self.born[held]
        self.sweeps = [(points, renumber[ids]) for points, ids in self.sweeps]


def _point_to_plane_icp(source: np.ndarray, target: np.ndarray, normals: LazyNormals, nearest: TrackedNearest,
                        init: np.ndarray, max_distance: float, tukey_k: float, max_iterations: int
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton point-to-plane ICP with a Tukey kernel (normal equations: registration.point_to_plane; deterministic:
    Open3D's ICP is not bit-reproducible between runs, and the build must give identical bytes).

    source (n, 3) points in their own frame; target (m, 3) and its normals in the map frame; `nearest` the
    correspondence search over target for these n source points (kept across calls, see TrackedNearest).
    Returns (T_map_from_source, source indices, target indices) of the last correspondences."""
    T = init.copy()
    for _ in range(max_iterations):
        moved = source @ T[:3, :3].T + T[:3, 3]
        match = nearest.query(moved, max_distance)
        matched = match[match >= 0]
        if len(matched) < 6:
            break
        normals.ensure(matched)
        A, b = normal_equations(moved, match, target, normals.normals, tukey_k)
        step = np.linalg.lstsq(A, -b, rcond=None)[0]
        update = np.eye(4)
        update[:3, :3] = Rotation.from_rotvec(step[:3]).as_matrix()
        update[:3, 3] = step[3:]
        T = update @ T
        if np.linalg.norm(step) < CONVERGED_STEP:
            break
    moved = source @ T[:3, :3].T + T[:3, 3]
    match = nearest.query(moved, max_distance)
    src = np.flatnonzero(match >= 0)
    return T, src, match[src]


def _register(source: np.ndarray, target: _Target, init: np.ndarray,
              params: RegistrationParams) -> tuple[np.ndarray, float, float, float]:
    """Coarse-to-fine point-to-plane ICP of source points (n, 3, ego frame) against the local map; returns
    (T_local_from_ego, fitness = share of source points with a correspondence, point-to-plane RMSE of the last
    stage's correspondences in m, conditioning)."""
    points, normals = target.points, target.normals
    T, distances = init, params.max_correspondence_m
    if len(distances) > 1 and params.coarse_stride > 1:  # the widest stage on every coarse_stride-th point
        thinned = source[::params.coarse_stride]
        coarse_nearest = TrackedNearest(target.tree, len(thinned), NEAREST_MARGIN_M)
        T, _, _ = _point_to_plane_icp(thinned, points, normals, coarse_nearest, T, distances[0],
                                      params.tukey_ratio * distances[0], params.max_iterations)
        distances = distances[1:]
    nearest = TrackedNearest(target.tree, len(source), NEAREST_MARGIN_M)
    for dist in distances:
        T, src, tgt = _point_to_plane_icp(source, points, normals, nearest, T, dist, params.tukey_ratio * dist,
                                          params.max_iterations)
    moved = transform_points(T, source[src])
    tgt_normals = normals.of(tgt)
    residual = np.sum(tgt_normals * (moved - points[tgt]), axis=1)
    rmse = float(np.sqrt(np.mean(residual**2))) if len(residual) else float("nan")
    fitness = len(src) / max(len(source), 1)
    return T, fitness, rmse, plane_conditioning(moved, tgt_normals, T[:3, 3])


def _gate(prior: np.ndarray, T: np.ndarray, fitness: float, rmse: float, conditioning: float,
          params: RegistrationParams) -> str:
    """"" if the ICP result is plausible, else the reason."""
    step = invert_transform(prior) @ T
    shift, turn = float(np.linalg.norm(step[:3, 3])), rotation_angle_deg(step[:3, :3])
    if fitness < params.min_fitness:
        return f"fitness {fitness:.2f} < {params.min_fitness}"
    if rmse > params.max_rmse_m:
        return f"rmse {rmse:.3f} m > {params.max_rmse_m} m"
    if conditioning < params.min_conditioning:
        return f"degenerate geometry (conditioning {conditioning:.1e} < {params.min_conditioning:.0e})"
    if shift > params.max_translation_m:
        return f"translation correction {shift:.2f} m > {params.max_translation_m} m"
    if turn > params.max_rotation_deg:
        return f"rotation correction {turn:.2f} deg > {params.max_rotation_deg} deg"
    return ""


def fit_anchor(chain: np.ndarray, logged: np.ndarray, sigma_xy_m: float = 0.3, sigma_deg: float = 1.0) -> np.ndarray:
    """One rigid A (4, 4) such that A @ chain[i] ~ logged[i] (both (F, 4, 4) in one frame).

    Rotation and x, y: robust (soft L1) least squares on the x, y positions (weight 1 / sigma_xy_m) and the
    orientations (weight 1 / sigma_deg), rotating about the chain's centroid. z: the median z residual after that
    rotation. Logged z never influences the rotation, so z drift cannot tilt the scene."""
    p_chain, p_log = chain[:, :3, 3], logged[:, :3, 3]
    center = p_chain.mean(axis=0)
    R_chain, R_log = Rotation.from_matrix(chain[:, :3, :3]), Rotation.from_matrix(logged[:, :3, :3])
    sigma_rad = np.radians(sigma_deg)

    def residuals(x: np.ndarray) -> np.ndarray:
        R = Rotation.from_rotvec(x[:3])
        moved = R.apply(p_chain - center) + center
        r_pos = (moved[:, :2] + x[3:5] - p_log[:, :2]) / sigma_xy_m
        r_rot = ((R * R_chain) * R_log.inv()).as_rotvec() / sigma_rad
        return np.concatenate([r_pos.ravel(), r_rot.ravel()])

    x = least_squares(residuals, np.zeros(5), loss="soft_l1", f_scale=2.0).x
    R = Rotation.from_rotvec(x[:3]).as_matrix()
    t = center - R @ center
    t[:2] += x[3:5]
    t[2] += float(np.median(p_log[:, 2] - (p_chain @ R.T + t)[:, 2]))
    return make_transform(R, t)


def _check_inputs(clouds_ego: Sequence[np.ndarray], logged_poses: np.ndarray, params: RegistrationParams) -> np.ndarray:
    logged = np.asarray(logged_poses, dtype=np.float64)
    if logged.ndim != 3 or logged.shape[1:] != (4, 4):
        raise PointInputError(f"refine_poses: logged_poses must be (F, 4, 4), got {logged.shape}")
    if len(clouds_ego) != len(logged):
        raise PointInputError(f"refine_poses: {len(clouds_ego)} clouds but {len(logged)} logged poses")
    if params.anchor not in ANCHORS:
        raise PointInputError(f"refine_poses: anchor must be one of {ANCHORS}, got {params.anchor!r}")
    if params.coarse_stride < 1:
        raise PointInputError(f"refine_poses: coarse_stride must be >= 1, got {params.coarse_stride}")
    return logged


def _checked_cloud(clouds_ego: Sequence[np.ndarray | None], k: int) -> np.ndarray | None:
    cloud = clouds_ego[k]
    if cloud is None:
        return None
    if np.ndim(cloud) != 2 or np.shape(cloud)[1] != 3:
        raise PointInputError(f"refine_poses: cloud {k} must be (n, 3), got shape {np.shape(cloud)}")
    return cloud


def interpolate_gaps(chain: np.ndarray, known: np.ndarray, times: np.ndarray) -> np.ndarray:
    """chain (F, 4, 4) with every pose that is not `known` (F,) bool but lies between two known ones replaced
    by their interpolation at its time (times (F,), any unit): rotation along the shortest arc, translation
    linear. Poses before the first or after the last known one are kept."""
    out = chain.copy()
    index = np.flatnonzero(known)
    for a, b in zip(index[:-1], index[1:]):
        if b - a < 2:
            continue
        between = np.arange(a + 1, b)
        alpha = (times[between] - times[a]) / (times[b] - times[a])
        turn = Rotation.from_matrix(chain[a, :3, :3].T @ chain[b, :3, :3]).as_rotvec()
        out[between, :3, :3] = chain[a, :3, :3] @ Rotation.from_rotvec(alpha[:, None] * turn).as_matrix()
        out[between, :3, 3] = chain[a, :3, 3] + alpha[:, None] * (chain[b, :3, 3] - chain[a, :3, 3])
    return out


def refine_poses(clouds_ego: Sequence[np.ndarray | None], logged_poses: np.ndarray,
                 params: RegistrationParams | None = None, times: np.ndarray | None = None) -> RegistrationResult:
    """Refined T_global_from_ego of every frame (see the module docstring for the procedure and anchoring).
    clouds_ego: any sequence; each cloud is read once, in frame order. A frame whose cloud is None (a failed
    sweep, or one left out of registration) is not registered (reason "no cloud"): between frames with clouds
    its pose is interpolated from theirs at its time (times (F,), any unit; default: the frame index), since
    the motion over a few sweeps is smooth while a logged pose may be off by its own noise; before the first
    or after the last it follows the logged motion from its neighbour."""
    params = params or RegistrationParams()
    logged = _check_inputs(clouds_ego, logged_poses, params)
    F = len(logged)
    origin = logged[0] if F else np.eye(4)
    local_log = np.einsum("ij,fjk->fik", invert_transform(origin), logged)  # T_local_from_ego, logged
    chain = np.empty_like(local_log)
    accepted = np.zeros(F, dtype=bool)
    has_cloud = np.ones(F, dtype=bool)
    fitness, rmse = np.full(F, np.nan), np.full(F, np.nan)
    reasons = [""] * F
    local_map = _LocalMap(params)
    for k in range(F):
        prior = local_log[0] if k == 0 else chain[k - 1] @ invert_transform(local_log[k - 1]) @ local_log[k]
        chain[k] = prior
        cloud = _checked_cloud(clouds_ego, k)
        if cloud is None:
            has_cloud[k] = False
            accepted[k] = k == 0
            reasons[k] = "" if k == 0 else "no cloud"
            continue
        source = voxel_centroids(cloud, params.voxel_size_m, params.min_voxel_points)
        n_src = len(source)
        if k == 0:
            accepted[k] = True
        elif n_src < params.min_points:
            reasons[k] = f"too few points ({n_src} < {params.min_points})"
        elif not local_map.sweeps:
            reasons[k] = "empty local map"
        else:
            target = local_map.target(k)
            T, fitness[k], rmse[k], cond = _register(source, target, prior, params)
            local_map.keep_normals(target)
            reasons[k] = _gate(prior, T, fitness[k], rmse[k], cond, params)
            accepted[k] = reasons[k] == ""
            if accepted[k]:
                chain[k] = T
        if n_src >= params.min_points and (accepted[k] or not local_map.sweeps):
            local_map.add(transform_points(chain[k], voxel_centroids(cloud, params.map_voxel_m, params.min_voxel_points)))
    chain = interpolate_gaps(chain, has_cloud, np.arange(F, dtype=np.float64) if times is None
                             else np.asarray(times, dtype=np.float64))
    anchor = fit_anchor(chain, local_log, params.log_sigma_xy_m, params.log_sigma_deg) \
        if params.anchor == "fit" and F else np.eye(4)
    poses = np.einsum("ij,jk,fkl->fil", origin, anchor, chain)
    corrections = np.einsum("fij,fjk->fik", poses, np.stack([invert_transform(T) for T in logged]) if F else logged)
    return RegistrationResult(poses, corrections, accepted, fitness, rmse, reasons)
