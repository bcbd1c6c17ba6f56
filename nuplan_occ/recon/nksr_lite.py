"""NKSR-lite: the neural-kernel surface solver (NKSR, Huang et al., CVPR 2023) without learned weights.

Units and frames: input points are metres in the caller's frame; the solver works in level-0
voxel units u = (x - anchor) / voxel_size, where `anchor` is a lattice-aligned corner shared by
all chunks of one reconstruction.

Field: f(u) = sum_l sum_{j in level l} alpha_j B((u - c_j) / 2**l) with the quadratic B-spline
basis of `basis` on the sparse hierarchy of `hierarchy` (feature factor beta = 0: no per-point
features enter the kernel). Sign convention: f > 0 on the sensor
side (free space), f < 0 behind the surface, grad f = the unit normal oriented toward the sensor,
so f approximates a signed distance in voxel units near the data.

Energy (gradient fitting, per occupied level-0 voxel v with point count c_v):
    w_v * sum_{s in sub-voxels(v)} (c_s / c_v) f(ybar_s)^2         zero value at the points
  + w_g * sum_v k_v || grad f(ybar_v) - nbar_v ||^2                gradient = oriented normal
  + w_o * sum_v k_v (f(ybar_v + nbar_v) - 1)^2                     front offset (free space)
  + lambda * alpha^T K alpha                                       ridge, K_ij = B(c_i - c_j)
ybar are centroids (of half-size sub-voxels and of voxels), nbar_v the normalised mean normal and
k_v = |mean normal| its consistency. The front-offset term is this module's addition to NKSR's
energy (in the spirit of NKSR's optional free-space term, but along the normal,
where the target t is the signed distance of a plane): without it the ridge term lets the field
sag to slightly negative values beyond convex edges (a box seen from outside), and marching cubes
then continues each face as a sheet up to the mask distance. Each voxel counts once, so the fit does not depend on the
LiDAR density. The normal equations (G^T W G + lambda K) alpha = G^T W y are assembled by the
numba kernels of `gram` and solved with Jacobi PCG on a torch CSR (int32) matrix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
import torch

from nuplan_occ.recon.basis import gram_weights
from nuplan_occ.recon.design import design_matrix, field_values
from nuplan_occ.recon.gram import normal_equations
from nuplan_occ.recon.hierarchy import FlatLevels, VoxelHierarchy, unique_voxels
from nuplan_occ.recon.params import ReconParams
from nuplan_occ.recon.pcg import PCGResult, jacobi_pcg, to_torch_csr

FRONT_OFFSETS = (1.0,)
"""Distances t (level-0 voxels) of the front-offset constraints f(ybar + t nbar) = t."""


@dataclass
class ImplicitField:
    """The solved field; `evaluate` takes level-0 voxel units relative to `anchor` (metres). levels: the
    hierarchy's index volumes as `FlatLevels`; coefficients (n,) float32."""

    hierarchy: VoxelHierarchy
    levels: FlatLevels
    coefficients: torch.Tensor
    anchor: np.ndarray
    voxel_size: float

    def evaluate(self, u: torch.Tensor) -> torch.Tensor:
        """f at query points u (K, 3) float64 (level-0 voxel units) -> (K,) float32 voxel units (`design.field_values`)."""
        levels = self.levels
        return torch.from_numpy(field_values(np.ascontiguousarray(u.numpy(), dtype=np.float64),
                                             self.coefficients.numpy(), levels.volumes, levels.starts, levels.shapes,
                                             levels.los, levels.sizes))


@dataclass(frozen=True)
class SolveStats:
    """Sizes and convergence of one solve."""

    points: int
    voxels: int
    unknowns: int
    nnz: int
    iterations: int
    relative_residual: float


@numba.njit(cache=True)
def _neighbour_entries(coords, lo, volume, shape, weights, cols, data, counts):
    """Row r of one level's block of K: for the voxel coords[r] (level units), the ids (cols[27 r:], ascending)
    and weights (data[27 r:]) of the voxels among its 27 neighbours (`basis.OFFSETS` order) present in the level's
    index volume (flat int32 `volume` of `shape`, entry 0 = voxel lo); counts[r] = how many."""
    for r in range(len(coords)):
        c = 0
        for o in range(27):
            i = coords[r, 0] - lo[0] + o // 9 - 1
            j = coords[r, 1] - lo[1] + (o // 3) % 3 - 1
            k = coords[r, 2] - lo[2] + o % 3 - 1
            if i < 0 or i >= shape[0] or j < 0 or j >= shape[1] or k < 0 or k >= shape[2]:
                continue
            found = volume[(i * shape[1] + j) * shape[2] + k]
            if found >= 0:
                cols[27 * r + c] = found
                data[27 * r + c] = weights[o]
                c += 1
        counts[r] = c


def ridge_matrix(hierarchy: VoxelHierarchy, weight: float) -> sp.csr_matrix:
    """weight * K, float32 CSR with ascending column ids: K is the same-level 27-neighbour Gram matrix with entries
    B(c_i - c_j) (`basis.gram_weights`), rows level after level (a level's ids follow its voxels' order)."""
    weights = gram_weights(torch.float32).numpy()
    indices, values, counts = [], [], []
    for level in hierarchy.levels:
        m = len(level.coords)
        cols, data, count = np.empty(27 * m, np.int32), np.empty(27 * m, np.float32), np.empty(m, np.int64)
        _neighbour_entries(level.coords.numpy(), level.lo.numpy(), level.volume.numpy().reshape(-1),
                           np.asarray(level.volume.shape, dtype=np.int64), weights, cols, data, count)
        used = (np.arange(27) < count[:, None]).reshape(-1)
        indices.append(cols[used])
        values.append(data[used])
        counts.append(count)
    n = hierarchy.num_unknowns
    indptr = np.concatenate([[0], np.cumsum(np.concatenate(counts))])
    return sp.csr_matrix((np.concatenate(values) * weight, np.concatenate(indices), indptr), shape=(n, n))


def _voxel_means(index: torch.Tensor, count: int, values: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """Per-group means of `values` (K, 3) grouped by `index` (K,) into `count` groups."""
    return torch.zeros(count, 3, dtype=values.dtype).index_add_(0, index, values) / counts.unsqueeze(1)


@dataclass
class VoxelStatistics:
    """What the solve keeps of a chunk's points, per occupied level-0 voxel v (M of them; level-0 voxel
    units): occupied (M, 3) int64 voxel indices, centroid (M, 3), unit_normal (M, 3)
    the normalised mean normal, confidence (M,) its length k_v; per occupied half-size sub-voxel s:
    sub_centroid (S, 3) and sub_weight (S,) c_s / c_v."""

    occupied: torch.Tensor
    centroid: torch.Tensor
    unit_normal: torch.Tensor
    confidence: torch.Tensor
    sub_centroid: torch.Tensor
    sub_weight: torch.Tensor


def voxel_statistics(points: np.ndarray, normals: np.ndarray, anchor: np.ndarray, voxel_size: float) -> VoxelStatistics:
    """The voxel statistics of points (N, 3) with oriented unit normals (N, 3), metres, on the lattice of
    `anchor` (3,) m and `voxel_size` m. The per-point arrays live only inside this call: the solve after it
    holds memory in proportion to voxels, not points."""
    u = torch.from_numpy((np.asarray(points, dtype=np.float64) - anchor) / voxel_size)
    n = torch.from_numpy(np.asarray(normals, dtype=np.float64))
    occupied, inverse, counts = unique_voxels(torch.floor(u).to(torch.int64))
    m0 = len(occupied)
    centroid = _voxel_means(inverse, m0, u, counts)
    mean_normal = _voxel_means(inverse, m0, n, counts)
    del n
    confidence = torch.linalg.vector_norm(mean_normal, dim=1)
    unit_normal = mean_normal / confidence.clamp_min(1e-12).unsqueeze(1)
    sub_voxel, sub_inverse, sub_counts = unique_voxels(torch.floor(2.0 * u).to(torch.int64))
    sub_centroid = _voxel_means(sub_inverse, len(sub_voxel), u, sub_counts)
    parent_count = torch.zeros(len(sub_voxel), dtype=counts.dtype).index_put_((sub_inverse,), counts[inverse])
    sub_weight = sub_counts.to(torch.float64) / parent_count.to(torch.float64)
    return VoxelStatistics(occupied, centroid, unit_normal, confidence, sub_centroid, sub_weight)


def _solve(design: list[sp.csr_matrix], targets: np.ndarray, ridge: sp.spmatrix,
           params: ReconParams) -> tuple[PCGResult, int]:
    """(PCG solution, matrix entries) of min ||G a - y||^2 + a^T ridge a for G = design[0] (taken out of the list,
    see `normal_equations`) and targets y (float32)."""
    matrix, rhs = normal_equations(design, targets, ridge)
    diagonal = torch.from_numpy(matrix.diagonal().astype(np.float32))
    return jacobi_pcg(to_torch_csr(matrix), diagonal, torch.from_numpy(rhs), params.pcg_tolerance,
                      params.pcg_max_iter), int(matrix.nnz)


def _solve_coarse_first(hierarchy: VoxelHierarchy, levels: FlatLevels, parts: list, targets: np.ndarray,
                        ridge: sp.csr_matrix, params: ReconParams) -> tuple[torch.Tensor, int, int, float]:
    """`ReconParams.coarse_first`: the coarsest level's coefficients fit alone, then the finer levels' fit to
    the targets minus the coarse field; (coefficients (n,) float32, matrix entries, PCG iterations of both, the
    fine solve's relative residual). A level's ids are contiguous and the coarsest come last."""
    split, n = hierarchy.levels[-1].offset, hierarchy.num_unknowns
    coarse = design_matrix(levels.subset(slice(-1, None)), n, parts)
    coarse = sp.csr_matrix((coarse.data, coarse.indices - np.int32(split), coarse.indptr), shape=(coarse.shape[0], n - split))
    coarse_result, coarse_nnz = _solve([coarse], targets, ridge[split:, split:], params)
    remaining = (targets - coarse @ coarse_result.x.numpy()).astype(np.float32)
    del coarse
    fine_result, fine_nnz = _solve([design_matrix(levels.subset(slice(0, -1)), split, parts)], remaining,
                                   ridge[:split, :split], params)
    return (torch.cat([fine_result.x, coarse_result.x]), coarse_nnz + fine_nnz,
            coarse_result.iterations + fine_result.iterations, fine_result.relative_residual)


def fit_field(points: np.ndarray, normals: np.ndarray, anchor: np.ndarray, params: ReconParams) -> tuple[ImplicitField, SolveStats]:
    """Solve the NKSR-lite field for points (N, 3) and oriented unit normals (N, 3), metres in the
    same frame; `anchor` (3,) metres is the lattice corner (a multiple of the coarsest voxel)."""
    voxels = voxel_statistics(points, normals, anchor, params.voxel_size)
    occupied, centroid, unit_normal, confidence = voxels.occupied, voxels.centroid, voxels.unit_normal, voxels.confidence
    sub_centroid = voxels.sub_centroid
    m0 = len(occupied)
    value_scale = torch.sqrt(params.value_weight * voxels.sub_weight)
    grad_scale = torch.sqrt(params.gradient_weight * confidence)
    del voxels

    hierarchy = VoxelHierarchy.build(occupied, params.levels)
    steps = torch.tensor(FRONT_OFFSETS, dtype=torch.float64)
    front = (centroid.unsqueeze(0) + steps[:, None, None] * unit_normal.unsqueeze(0)).reshape(-1, 3)
    front_scale = torch.sqrt(params.offset_weight * confidence).repeat(len(FRONT_OFFSETS))
    levels, n = FlatLevels.of(hierarchy), hierarchy.num_unknowns
    targets = np.concatenate([np.zeros(len(sub_centroid), np.float32),
                              (grad_scale.unsqueeze(1) * unit_normal).T.reshape(-1).numpy().astype(np.float32),
                              (front_scale * steps.repeat_interleave(m0)).numpy().astype(np.float32)])
    parts = [(sub_centroid, value_scale, False), (centroid, grad_scale, True), (front, front_scale, False)]
    ridge = ridge_matrix(hierarchy, params.ridge_weight)
    if params.coarse_first and len(hierarchy.levels) > 1:
        coefficients, nnz, iterations, residual = _solve_coarse_first(hierarchy, levels, parts, targets, ridge, params)
    else:
        result, nnz = _solve([design_matrix(levels, n, parts)], targets, ridge, params)
        coefficients, iterations, residual = result.x, result.iterations, result.relative_residual
    field = ImplicitField(hierarchy=hierarchy, levels=levels, coefficients=coefficients,
                          anchor=np.asarray(anchor, dtype=np.float64), voxel_size=params.voxel_size)
    stats = SolveStats(points=len(points), voxels=m0, unknowns=n, nnz=nnz, iterations=iterations,
                       relative_residual=residual)
    return field, stats
