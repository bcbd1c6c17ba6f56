"""Writes folders in the released Nuplan-Occ layouts from grids of our ids (the tests' known truth)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nuplan_occ import schemas

SHIFT_R800_OLD = 8
"""Voxels between z = -5 m (the r800_old grid's bottom) and z = -3 m (ours)."""


def inverse_map(name: str) -> np.ndarray:
    """(256,) our id -> the release id of named map `name` (the first release id mapping to it); -1 unmapped."""
    lut = np.full(256, -1, dtype=np.int64)
    for entry in reversed(schemas.load("release_labels")["maps"][name]["classes"]):
        lut[entry["ours"]] = entry["id"]
    return lut


def to_release_z(semantics: np.ndarray, z_min: float) -> np.ndarray:
    """Our [x, y, z] grid (z in [-3, 5)) as the release grid with bottom z_min (-3 or -5); voxels the
    release grid does not cover are dropped."""
    if z_min == -3.0:
        return semantics
    assert z_min == -5.0
    out = np.zeros_like(semantics)
    out[:, :, SHIFT_R800_OLD:] = semantics[:, :, :-SHIFT_R800_OLD]
    return out


def write_sparse(root: Path, folder: str, frames: dict[str, np.ndarray], columns: int, labels: str = "raw-sparse",
                 z_min: float = -3.0) -> Path:
    """`root/dense_voxels_with_semantic/<folder>/<token>.npz` (key occ, int32 [N, 4] or [N, 2] C-order flat)."""
    lut = inverse_map(labels)
    target = root / "dense_voxels_with_semantic" / folder
    target.mkdir(parents=True, exist_ok=True)
    for token, semantics in frames.items():
        grid = to_release_z(semantics, z_min)
        voxels = np.argwhere(grid > 0)
        ids = lut[grid[tuple(voxels.T)]]
        assert (ids >= 0).all(), "a class of the truth has no id in this label map"
        if columns == 4:
            occ = np.concatenate([voxels, ids[:, None]], axis=1)
        else:
            occ = np.stack([np.ravel_multi_index(tuple(voxels.T), grid.shape), ids], axis=1)
        np.savez_compressed(target / f"{token}.npz", occ=occ.astype(np.int32))
    return target


def write_dense(root: Path, frames: dict[str, np.ndarray], z_min: float = -3.0) -> Path:
    """`root/nuplan_quantized_400_400_32/<token>.npy` dense uint8 in UniScenev2 ids (= ours)."""
    target = root / "nuplan_quantized_400_400_32"
    target.mkdir(parents=True, exist_ok=True)
    for token, semantics in frames.items():
        np.save(target / f"{token}.npy", to_release_z(semantics, z_min))
    return target


def truth_frames(n: int, seed: int = 0, classes: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 7, 8)) -> dict[str, np.ndarray]:
    """n grids of our ids with boxes of `classes` at random places below z = 3 m (inside both z conventions)."""
    rng = np.random.default_rng(seed)
    frames = {}
    for i in range(n):
        grid = np.zeros((400, 400, 32), dtype=np.uint8)
        grid[:, :, 10] = classes[0]  # a ground layer
        for label in classes:
            x, y, z = rng.integers(0, 390), rng.integers(0, 390), rng.integers(11, 20)
            grid[x: x + 6, y: y + 4, z: z + 3] = label
        frames[f"{rng.integers(0, 2**63):016x}{i:04d}"] = grid
    return frames
