"""Surface reconstruction: NKSR-lite (torch), Open3D Poisson, or raw points.

Public API:
- `reconstruct(points, sensor_origins, method="nksr", params=None, frame="scene") -> Surface`
- `Surface` (vertices, faces, frame; `sample_points(spacing)`), `ReconParams`, `ReconError`
- `surface_metrics(pred_points, truth_points, thresholds)`, `voxel_iou(pred, truth, grid, mask)`
"""

from nuplan_occ.recon.api import METHODS, reconstruct
from nuplan_occ.evaluation.surfaces import surface_metrics, voxel_iou
from nuplan_occ.recon.params import ReconError, ReconParams
from nuplan_occ.recon.surface import Surface

__all__ = ["METHODS", "ReconError", "ReconParams", "Surface", "reconstruct", "surface_metrics", "voxel_iou"]
