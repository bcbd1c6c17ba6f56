"""A scene's surface indexed on x-y tiles of its own frame, so that cropping it to one frame's grid box only
touches the surface near that frame (the cost of a crop does not grow with the scene's length).

The surface is a triangle mesh (vertices (V, 3) metres in the scene frame, faces (F, 3)) or, without
faces, a point set. Its elements (triangles, or points) are sorted by the tile holding the lower x-y
corner of their bounding box; elements wider than a tile are listed apart with their bounding boxes. A
crop selects the tiles that can hold an element meeting the box's footprint and the wide elements that
meet it, then applies the exact test to those elements only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from nuplan_occ.geometry import invert_transform

TILE_M = 10.0
"""Edge (m) of the x-y tiles."""

_SLACK_M = 1e-3
"""Growth (m) of a crop's footprint in the scene frame: covers the rounding of moving the box there."""


def transform_rows(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) points moved by the 4x4 transform T, each row computed on its own (the same bits whichever
    other rows are moved with it, unlike a BLAS matrix product)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    return np.stack([T[a, 0] * x + T[a, 1] * y + T[a, 2] * z + T[a, 3] for a in range(3)], axis=1)


@numba.njit(cache=True)
def _moved_triangles_near(vertices: np.ndarray, faces: np.ndarray, ids: np.ndarray, T: np.ndarray, lower: np.ndarray,
                          upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The triangles faces[ids] that have a vertex v, moved by T (as `transform_rows`, same bits), with
    lower <= v < upper, in the order of ids, as a mesh: (vertices (K', 3): those the kept triangles use, in
    order of first use, faces (K, 3) into them). Each vertex is moved once however many triangles share it."""
    slot = np.full(len(vertices), -1, dtype=np.int64)  # vertex -> row of `moved`
    moved = np.empty((3 * len(ids), 3))
    inside = np.empty(3 * len(ids), dtype=np.bool_)
    kept_faces = np.empty((len(ids), 3), dtype=np.int64)
    n_moved, kept = 0, 0
    for e in ids:
        near = False
        for n in range(3):
            v = faces[e, n]
            s = slot[v]
            if s < 0:
                s, slot[v] = n_moved, n_moved
                n_moved += 1
                x, y, z = vertices[v, 0], vertices[v, 1], vertices[v, 2]
                within = True
                for a in range(3):
                    c = T[a, 0] * x + T[a, 1] * y + T[a, 2] * z + T[a, 3]
                    moved[s, a] = c
                    within = within and lower[a] <= c < upper[a]
                inside[s] = within
            near = near or inside[s]
            kept_faces[kept, n] = s
        kept += near
    renumbered = np.full(n_moved, -1, dtype=np.int64)
    used = 0
    for f in range(kept):
        for n in range(3):
            s = kept_faces[f, n]
            if renumbered[s] < 0:
                renumbered[s] = used
                used += 1
            kept_faces[f, n] = renumbered[s]
    out = np.empty((used, 3))
    for s in range(n_moved):
        if renumbered[s] >= 0:
            out[renumbered[s]] = moved[s]
    return out, kept_faces[:kept]


@dataclass(frozen=True)
class SurfaceTiles:
    """The index (see the module doc). vertices (V, 3) float64 m, scene frame (of a mesh, numbered in the order
    the tile-sorted triangles first use them); faces (F, 3) int64 ((0, 3): a point set; face ids are the
    input's); order: ids of the elements at most tile_m wide (x and y), sorted by tile key (ascending ids
    within a tile); keys: their tile keys (tile (tx, ty) -> tx * n_tiles[1] + ty, tiles of tile_m counted
    from `origin` (2,) m); wide: ids of the other elements, wide_low / wide_high (W, 2): their x-y
    bounding boxes (m)."""

    vertices: np.ndarray
    faces: np.ndarray
    order: np.ndarray
    keys: np.ndarray
    origin: np.ndarray
    n_tiles: tuple[int, int]
    wide: np.ndarray
    wide_low: np.ndarray
    wide_high: np.ndarray
    tile_m: float = TILE_M

    def candidates(self, lower: np.ndarray, upper: np.ndarray, T_scene_from_box: np.ndarray) -> np.ndarray:
        """Sorted ids of elements whose x-y bounding box may meet the x-y footprint of the box [lower, upper]
        (3,) moved by T_scene_from_box: a superset of the elements with a vertex inside the box."""
        corners = np.stack(np.meshgrid(*zip(lower, upper), indexing="ij"), axis=-1).reshape(-1, 3)
        xy = transform_rows(T_scene_from_box, corners)[:, :2]
        low, high = xy.min(axis=0) - _SLACK_M, xy.max(axis=0) + _SLACK_M
        found = np.zeros(len(self.order) + len(self.wide), dtype=bool)  # the lists are disjoint: mark, then read in order
        found[self.wide[np.all((self.wide_low <= high) & (self.wide_high >= low), axis=1)]] = True
        first = np.maximum(np.floor((low - self.tile_m - self.origin) / self.tile_m).astype(np.int64), 0)
        last = np.minimum(np.floor((high - self.origin) / self.tile_m).astype(np.int64), np.asarray(self.n_tiles) - 1)
        if np.all(first <= last):
            rows = np.arange(first[0], last[0] + 1) * self.n_tiles[1]
            starts = np.searchsorted(self.keys, rows + first[1], side="left")
            stops = np.searchsorted(self.keys, rows + last[1], side="right")
            for a, b in zip(starts, stops):
                found[self.order[a:b]] = True
        return np.flatnonzero(found)

    def crop(self, T_box_from_scene: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The surface moved into the box frame (T_box_from_scene, see `transform_rows`) and cut to the
        triangles with a vertex v in lower <= v < upper (3,), in their order: (vertices (K', 3) m in the box
        frame, the ones those triangles use in order of first use, faces (K, 3) into them); for a point set,
        those points in their order and faces (0, 3)."""
        T = np.ascontiguousarray(T_box_from_scene, dtype=np.float64)
        lower, upper = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
        ids = self.candidates(lower, upper, invert_transform(T))
        if len(self.faces) == 0:
            moved = transform_rows(T, self.vertices[ids])
            return moved[np.all((moved >= lower) & (moved < upper), axis=1)], self.faces
        return _moved_triangles_near(self.vertices, self.faces, ids, T, lower, upper)


def build_surface_tiles(vertices: np.ndarray, faces: np.ndarray, tile_m: float = TILE_M) -> SurfaceTiles:
    """Index a surface: vertices (V, 3) metres (scene frame), faces (F, 3) int ((0, 3): a point set)."""
    v = np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f):
        low, high = np.empty((len(f), 2)), np.empty((len(f), 2))
        for a in range(2):
            c = [v[f[:, n], a] for n in range(3)]
            low[:, a], high[:, a] = np.minimum(np.minimum(c[0], c[1]), c[2]), np.maximum(np.maximum(c[0], c[1]), c[2])
    else:
        low = high = v[:, :2]
    is_wide = np.any(high - low > tile_m, axis=1)
    wide, narrow = np.flatnonzero(is_wide), np.flatnonzero(~is_wide)
    origin = low[narrow].min(axis=0) if len(narrow) else np.zeros(2)
    tile = np.floor((low[narrow] - origin) / tile_m).astype(np.int64)
    n_tiles = (int(tile[:, 0].max()) + 1, int(tile[:, 1].max()) + 1) if len(narrow) else (0, 0)
    keys = tile[:, 0] * n_tiles[1] + tile[:, 1]
    order = np.argsort(keys, kind="stable")
    if len(f):
        v, f = _numbered_by_first_use(v, f, np.concatenate([narrow[order], wide]))
    return SurfaceTiles(v, f, narrow[order], keys[order], origin, n_tiles, wide, low[wide], high[wide], tile_m)


def _numbered_by_first_use(vertices: np.ndarray, faces: np.ndarray, sequence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same mesh with its vertices renumbered in the order the faces `sequence` (every face id once) first use
    them (unused vertices last, in their order): a crop then reads the vertices of neighbouring triangles from
    neighbouring rows."""
    new_of_old = _first_use_numbers(faces, sequence, len(vertices))
    old_of_new = np.empty_like(new_of_old)
    old_of_new[new_of_old] = np.arange(len(new_of_old))
    return vertices[old_of_new], new_of_old[faces]


@numba.njit(cache=True)
def _first_use_numbers(faces: np.ndarray, sequence: np.ndarray, n_vertices: int) -> np.ndarray:
    """New number of each vertex: its rank by first use in faces[sequence] (unused ones after, in order)."""
    number = np.full(n_vertices, -1, dtype=np.int64)
    used = 0
    for e in sequence:
        for n in range(3):
            if number[faces[e, n]] < 0:
                number[faces[e, n]] = used
                used += 1
    for v in range(n_vertices):
        if number[v] < 0:
            number[v] = used
            used += 1
    return number
