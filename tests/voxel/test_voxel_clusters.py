"""Sparse Chebyshev clusters: the partition dilating the voxels by a cube and labeling with 26-connectivity gives."""

import numpy as np
import pytest
from scipy import ndimage

from nuplan_occ.voxel.voxel_clusters import chebyshev_clusters


def _dilated_labels(indices: np.ndarray, half_width: int) -> np.ndarray:
    """Reference: label of each voxel after dilating by a cube of half_width (dense volume, scipy)."""
    low = indices.min(axis=0) - half_width
    volume = np.zeros(tuple(indices.max(axis=0) + half_width - low + 1), dtype=bool)
    volume[tuple((indices - low).T)] = True
    cube = np.ones((3, 3, 3), dtype=bool)
    if half_width:
        volume = ndimage.binary_dilation(volume, cube, iterations=half_width)
    labels, _ = ndimage.label(volume, structure=cube)
    return labels[tuple((indices - low).T)]


def _same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    pairs = np.unique(np.c_[a, b], axis=0)
    return len(pairs) == len(np.unique(a)) == len(np.unique(b))


@pytest.mark.parametrize("half_width", [0, 1, 2])
def test_clusters_equal_dilated_labeling(half_width):
    rng = np.random.default_rng(half_width)
    for _ in range(10):
        centres = rng.integers(0, 120, size=(rng.integers(1, 30), 3))
        indices = np.unique(centres[rng.integers(0, len(centres), 600)] + rng.integers(-4, 5, size=(600, 3)), axis=0)
        labels, count = chebyshev_clusters(indices, 2 * half_width + 1)
        assert count == len(np.unique(labels)) and labels.min() == 0 and labels.max() == count - 1
        assert _same_partition(labels, _dilated_labels(indices, half_width))


def test_reach_is_per_axis_and_transitive():
    indices = np.array([[0, 0, 0], [3, 3, 3], [6, 0, 3], [10, 0, 0], [0, 20, 0]])
    labels, count = chebyshev_clusters(indices, 3)
    # (0,0,0)-(3,3,3)-(6,0,3) chain at distance 3; (10,0,0) is 4 from (6,0,3); (0,20,0) is alone
    assert count == 3 and labels.tolist() == [0, 0, 0, 1, 2]
    assert chebyshev_clusters(np.zeros((0, 3), np.int64), 3)[1] == 0
