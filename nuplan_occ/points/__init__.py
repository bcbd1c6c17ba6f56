"""Point-cloud primitives the pipeline's steps share: a kd-tree for nearest neighbours (knn), voxel-grid
reduction of points (voxel_reduce), normals from local planes (plane_normals), statistical outlier removal
(outliers) and compiled point-in-box tests (box_kernels). Pure functions, no file I/O."""

from __future__ import annotations


class PointInputError(ValueError):
    """Arrays given to a point-cloud function that do not fit together (shapes, frames, lengths); the
    message names the argument and the problem."""
