"""Parameters of the surface reconstruction methods, with documented defaults.

All lengths are metres in the frame of the input points; solver weights are dimensionless and
refer to the NKSR-lite energy written in level-0 voxel units (see `nksr_lite`).
"""

from __future__ import annotations

from dataclasses import dataclass


class ReconError(ValueError):
    """Bad input or parameters for a surface reconstruction (the message names the problem)."""


@dataclass(frozen=True)
class ReconParams:
    """Settings of `reconstruct`. Defaults target the 0.25 m occupancy grid of nuplan-occ.

    Shared by every method:
    - mask_distance: surface farther than this from every input point is removed (m). NKSR trims
      at 2 voxels; this is the analytic distance-to-points version. The default keeps hole filling for
      generic scans; the build sets its own (the reconstruct stage's mask_distance_m and
      object_mask_distance_m), trimming closer where far LiDAR rings leave the aggregate sparse.
    - normal_knn: neighbours of the PCA normal estimate (`normals.estimate_normals`); normals are flipped
      to face each point's sensor origin.
    - normal_cell_m: one normal is estimated per cube of this edge, at its points' centroid, and shared by
      them (0 = one per point).
    - min_component_faces: connected mesh components with fewer faces are removed (pymeshlab).
    - max_hole_edges: holes bounded by at most this many edges are closed (pymeshlab); 0 = off.
    - threads: torch intra-op threads during the solve (restored afterwards) and Open3D Poisson
      threads; 0 keeps torch's current setting.

    NKSR-lite ("nksr"):
    - voxel_size: finest hierarchy level (m); the output grid's voxel or finer.
    - levels: number of hierarchy levels (voxel_size * 2**l); coarse levels fill holes.
    - degree: B-spline degree of the basis; only 2 (quadratic, 3-voxel support) is implemented.
    - ridge_weight: lambda of the regulariser alpha^T K alpha.
    - value_weight / gradient_weight: w_v (zero value at the points) and w_g (gradient = the
      oriented normal at each voxel's centroid); both are per occupied level-0 voxel.
    - offset_weight: w_o of the front-offset constraint f(ybar + nbar) = 1 voxel (keeps the field
      positive in free space beyond convex edges; see `nksr_lite`).
      The value constraints of a level-0 voxel are the centroids of its occupied half-size
      sub-voxels (at most 8), weighted by their point counts (a Nystrom-style cap on N).
    - coarse_first: solve the coarsest level's coefficients alone first, then the finer levels' against what
      the coarse field leaves of the targets (two smaller systems; the joint system's cross-level products
      are most of its assembly), instead of all levels in one system.
    - pcg_tolerance / pcg_max_iter: Jacobi-PCG stop rule ||r|| <= tol ||b||, at most pcg_max_iter
      iterations.
    - chunk_size / chunk_overlap: xy tiles (m) solved independently, with this margin of extra
      points on every side; chunk_size <= 0 disables chunking. chunk_max_points: a chunk holding more
      points (overlap included) is halved across its longer side until each part fits (0 = no budget):
      the solve's memory grows with its points, and a long scene fills its tiles densely.
    docs/measurements.md (recon.params) holds the measurements behind these defaults.

    Poisson ("poisson", Open3D screened Poisson):
    - poisson_depth: octree depth; poisson_density_quantile: vertices whose Poisson density is
      below this quantile are removed (then the distance mask is applied too).
    """

    mask_distance: float = 0.5
    normal_knn: int = 30
    normal_cell_m: float = 0.1
    min_component_faces: int = 50
    max_hole_edges: int = 0
    threads: int = 1
    voxel_size: float = 0.25
    levels: int = 3
    degree: int = 2
    ridge_weight: float = 1e-2
    value_weight: float = 1.0
    gradient_weight: float = 1.0
    offset_weight: float = 0.1
    coarse_first: bool = False
    pcg_tolerance: float = 1e-3
    pcg_max_iter: int = 2000
    chunk_size: float = 50.0
    chunk_overlap: float = 1.5
    chunk_max_points: int = 600_000
    poisson_depth: int = 10
    poisson_density_quantile: float = 0.05

    def __post_init__(self) -> None:
        positive = {
            "mask_distance": self.mask_distance,
            "voxel_size": self.voxel_size,
            "pcg_tolerance": self.pcg_tolerance,
        }
        for name, value in positive.items():
            if not value > 0:
                raise ReconError(f"ReconParams.{name} must be > 0, got {value}")
        if self.degree != 2:
            raise ReconError(f"ReconParams.degree: only quadratic B-splines (2) are implemented, got {self.degree}")
        if self.levels < 1 or self.normal_knn < 3 or self.pcg_max_iter < 1 or self.threads < 0:
            raise ReconError("ReconParams: levels >= 1, normal_knn >= 3, pcg_max_iter >= 1 and threads >= 0 are required")
        if min(self.ridge_weight, self.value_weight, self.gradient_weight, self.offset_weight) < 0:
            raise ReconError("ReconParams: ridge, value, gradient and offset weights must be >= 0")
        if not 0 <= self.poisson_density_quantile < 1:
            raise ReconError(f"ReconParams.poisson_density_quantile must be in [0, 1), got {self.poisson_density_quantile}")
        if self.normal_cell_m < 0:
            raise ReconError(f"ReconParams.normal_cell_m must be >= 0, got {self.normal_cell_m}")
        if self.chunk_size > 0 and self.chunk_overlap < 0:
            raise ReconError(f"ReconParams.chunk_overlap must be >= 0, got {self.chunk_overlap}")
