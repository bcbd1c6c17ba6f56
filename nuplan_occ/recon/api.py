"""`reconstruct`: points with sensor origins -> Surface, by NKSR-lite, Open3D Poisson or raw points."""

from __future__ import annotations

import dataclasses
from contextlib import contextmanager
from typing import Callable, Iterator

import numpy as np
import torch
from scipy.spatial import cKDTree

from nuplan_occ.recon.chunking import nksr_mesh
from nuplan_occ.recon.cleanup import clean_mesh
from nuplan_occ.recon.normals import estimate_normals
from nuplan_occ.recon.params import ReconError, ReconParams
from nuplan_occ.recon.poisson import poisson_mesh
from nuplan_occ.recon.surface import Surface

METHODS = ("nksr", "poisson", "none")


@contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Run the block with `count` torch intra-op threads (0: unchanged), then restore."""
    previous = torch.get_num_threads()
    if count > 0:
        torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _validate(points: np.ndarray, sensor_origins: np.ndarray, origin_ids: np.ndarray | None, method: str,
              params: ReconParams) -> tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """float64 points and the function giving the sensor origins of the points at given indices."""
    if method not in METHODS:
        raise ReconError(f"reconstruct: unknown method {method!r}; expected one of {METHODS}")
    pts = np.asarray(points, dtype=np.float64)
    origins = np.asarray(sensor_origins, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ReconError(f"reconstruct: points must have shape (N, 3), got {pts.shape}")
    if origin_ids is None and origins.shape != pts.shape:
        raise ReconError(f"reconstruct: sensor_origins shape {origins.shape} must equal points shape {pts.shape}")
    if origin_ids is not None:
        ids = np.asarray(origin_ids)
        if origins.ndim != 2 or origins.shape[1] != 3 or ids.shape != (len(pts),):
            raise ReconError(f"reconstruct: with origin_ids, sensor_origins must be (F, 3) and origin_ids "
                             f"({len(pts)},), got {origins.shape} and {ids.shape}")
        if len(ids) and (ids.min() < 0 or ids.max() >= len(origins)):
            raise ReconError(f"reconstruct: origin_ids must index the {len(origins)} sensor_origins")
    if not (np.isfinite(pts).all() and np.isfinite(origins).all()):
        raise ReconError("reconstruct: points and sensor_origins must be finite")
    if method != "none" and len(pts) < params.normal_knn:
        raise ReconError(f"reconstruct: {len(pts)} points are fewer than normal_knn = {params.normal_knn}")
    if origin_ids is None:
        return pts, lambda index: origins[index]
    return pts, lambda index: origins[ids[index]]


def reconstruct(
    points: np.ndarray,
    sensor_origins: np.ndarray,
    method: str = "nksr",
    params: ReconParams | None = None,
    frame: str = "scene",
    origin_ids: np.ndarray | None = None,
) -> Surface:
    """Surface of `points` (N, 3) seen from `sensor_origins` (N, 3), both metres in `frame`; or, with
    origin_ids (N,) int, seen from sensor_origins (F, 3), point i from sensor_origins[origin_ids[i]] (one
    origin per sweep, say, instead of a copy per point).

    method "nksr": NKSR-lite (chunked torch solver, marching cubes, distance mask); "poisson":
    Open3D screened Poisson, density- and distance-trimmed; "none": the raw points. Meshes are
    cleaned with pymeshlab (see `cleanup`). The returned surface is in the same frame; its `info`
    holds per-method diagnostics (solver sizes and iterations).
    """
    params = params or ReconParams()
    pts, origins_at = _validate(points, sensor_origins, origin_ids, method, params)
    if method == "none":
        return Surface(vertices=pts.copy(), faces=np.zeros((0, 3), dtype=np.int64), frame=frame)
    info: dict = {"method": method, "points": len(pts)}
    if method == "poisson":
        vertices, faces = poisson_mesh(
            pts, estimate_normals(pts, origins_at(np.arange(len(pts))), params.normal_knn, params.normal_cell_m), params.poisson_depth,
            params.poisson_density_quantile, params.mask_distance, cKDTree(pts),
            threads=params.threads or -1,
        )
    else:
        with torch_threads(params.threads):
            vertices, faces, stats = nksr_mesh(pts, origins_at, params)
        info["chunks"] = [dataclasses.asdict(s) for s in stats]
    vertices, faces = clean_mesh(vertices, faces, params.min_component_faces, params.max_hole_edges)
    return Surface(vertices=vertices, faces=faces, frame=frame, info=info)
