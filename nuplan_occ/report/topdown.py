"""Top-down pictures of a semantic grid (pure numpy): each column shows the label of its highest occupied
voxel in the label palette, shaded by that voxel's height, with the ego path drawn over it.

Image convention: row 0 is the grid's front edge (+x), column 0 its left edge (+y), so up in the picture
is forward and left is left, as seen from above. One pixel per voxel column (0.25 m).
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.geometry import invert_transform, transform_points
from nuplan_occ.grid import GridSpec

EMPTY_RGB = np.array([24, 24, 28], dtype=np.uint8)
PATH_RGB = np.array([255, 40, 200], dtype=np.uint8)
EGO_RGB = np.array([255, 255, 255], dtype=np.uint8)
SHADE_LOW = 0.55
"""Brightness of a column whose top voxel is the grid's lowest layer (the top layer is full brightness)."""


def top_labels(semantics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y) label of the highest non-empty voxel of each column (0 where the column is empty) and
    (X, Y) its z index (-1 where empty), of a [x, y, z] uint8 grid."""
    occupied = semantics > 0
    from_top = np.argmax(occupied[:, :, ::-1], axis=2)
    z = semantics.shape[2] - 1 - from_top
    has = occupied.any(axis=2)
    labels = np.take_along_axis(semantics, z[:, :, None], axis=2)[:, :, 0]
    return np.where(has, labels, 0), np.where(has, z, -1)


def to_image(grid_xy: np.ndarray) -> np.ndarray:
    """An [x, y, ...] array turned into picture orientation (rows = -x, columns = -y)."""
    return grid_xy[::-1, ::-1]


def render_topdown(semantics: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """(X, Y, 3) uint8 RGB picture (picture orientation) of a semantic grid; palette: (256, 3) uint8."""
    labels, z = top_labels(semantics)
    shade = SHADE_LOW + (1.0 - SHADE_LOW) * np.clip(z, 0, None) / max(semantics.shape[2] - 1, 1)
    rgb = (palette[labels].astype(np.float32) * shade[:, :, None]).astype(np.uint8)
    rgb[labels == 0] = EMPTY_RGB
    return to_image(rgb)


def path_pixels(poses_global: np.ndarray, ego_to_global: np.ndarray, grid: GridSpec,
                step_m: float = 0.1) -> np.ndarray:
    """(P, 2) picture (row, column) of the ego path: the positions of `poses_global` (F, 4, 4) moved into the
    ego frame of `ego_to_global`, joined by straight segments sampled every step_m, clipped to the grid."""
    xyz = transform_points(invert_transform(ego_to_global), poses_global[:, :3, 3])
    xyz[:, 2] = (grid.z_min + grid.z_max) / 2.0  # the picture is top-down: height plays no part
    if len(xyz) > 1:
        lengths = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
        xyz = np.concatenate([np.linspace(a, b, max(2, int(np.ceil(d / step_m)) + 1))
                              for a, b, d in zip(xyz[:-1], xyz[1:], lengths)])
    index, inside = grid.point_to_index(xyz)
    index = index[inside]
    return np.stack([grid.shape[0] - 1 - index[:, 0], grid.shape[1] - 1 - index[:, 1]], axis=1)


def draw_path(image: np.ndarray, pixels: np.ndarray, width: int = 1) -> np.ndarray:
    """The picture with the path's pixels (and `width` pixels around them) painted in PATH_RGB, and the ego
    (picture centre) marked by a small white square."""
    out = image.copy()
    h, w = out.shape[:2]
    for dr in range(-width, width + 1):
        for dc in range(-width, width + 1):
            r, c = pixels[:, 0] + dr, pixels[:, 1] + dc
            keep = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            out[r[keep], c[keep]] = PATH_RGB
    cr, cc = h // 2, w // 2
    out[cr - 3:cr + 3, cc - 2:cc + 2] = EGO_RGB
    return out
