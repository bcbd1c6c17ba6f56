"""Quality figures of the FBSA steps against known truth (synthetic scenes, benchmarks). Pure numpy."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nuplan_occ.points import PointInputError
from nuplan_occ.geometry import invert_transform, rotation_angle_deg, wrap_angle


@dataclass
class PoseErrors:
    """Per-frame errors of estimated vs true T_global_from_ego: translation_m (F,) 3D distance, horizontal_m (F,),
    z_m (F,) signed (estimate - truth), yaw_deg (F,) signed, tilt_deg (F,) angle between the two z axes
    (roll/pitch error); relative_translation_m / relative_rotation_deg (F-1,): error of the motion between
    consecutive frames (independent of where the whole trajectory is anchored)."""

    translation_m: np.ndarray
    horizontal_m: np.ndarray
    z_m: np.ndarray
    yaw_deg: np.ndarray
    tilt_deg: np.ndarray
    relative_translation_m: np.ndarray
    relative_rotation_deg: np.ndarray

    def medians(self) -> dict[str, float]:
        """Median of the absolute value of every per-frame error."""
        return {name: float(np.median(np.abs(value))) if len(value) else float("nan")
                for name, value in vars(self).items()}


def pose_errors(estimated: np.ndarray, truth: np.ndarray) -> PoseErrors:
    """Errors of estimated (F, 4, 4) against truth (F, 4, 4), both T_global_from_ego (metres, degrees)."""
    est, tru = np.asarray(estimated, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    if est.shape != tru.shape or est.ndim != 3 or est.shape[1:] != (4, 4):
        raise PointInputError(f"pose_errors: estimated {est.shape} and truth {tru.shape} must both be (F, 4, 4)")
    d = est[:, :3, 3] - tru[:, :3, 3]
    yaw = np.arctan2(est[:, 1, 0], est[:, 0, 0]) - np.arctan2(tru[:, 1, 0], tru[:, 0, 0])
    tilt = np.degrees(np.arccos(np.clip(np.sum(est[:, :3, 2] * tru[:, :3, 2], axis=1), -1.0, 1.0)))
    rel_est = np.stack([invert_transform(a) @ b for a, b in zip(est[:-1], est[1:])]) if len(est) > 1 else est[:0]
    rel_tru = np.stack([invert_transform(a) @ b for a, b in zip(tru[:-1], tru[1:])]) if len(tru) > 1 else tru[:0]
    rel_err = np.stack([invert_transform(a) @ b for a, b in zip(rel_tru, rel_est)]) if len(rel_est) else rel_est
    return PoseErrors(
        translation_m=np.linalg.norm(d, axis=1), horizontal_m=np.linalg.norm(d[:, :2], axis=1), z_m=d[:, 2],
        yaw_deg=np.degrees(np.asarray(wrap_angle(yaw), dtype=np.float64).reshape(-1)), tilt_deg=tilt,
        relative_translation_m=np.linalg.norm(rel_err[:, :3, 3], axis=1),
        relative_rotation_deg=rotation_angle_deg(rel_err[:, :3, :3]),
    )


@dataclass
class OutlierScores:
    """caught: share of the true outliers that were removed; lost: share of the real points that were removed."""

    caught: float
    lost: float
    n_outliers: int
    n_real: int


def outlier_scores(keep: np.ndarray, is_outlier: np.ndarray) -> OutlierScores:
    """Score a keep mask (N,) bool against the truth (N,) bool (True = injected outlier)."""
    keep, bad = np.asarray(keep, dtype=bool), np.asarray(is_outlier, dtype=bool)
    if keep.shape != bad.shape:
        raise PointInputError(f"outlier_scores: keep {keep.shape} and is_outlier {bad.shape} differ in shape")
    n_bad, n_real = int(bad.sum()), int((~bad).sum())
    caught = float((~keep & bad).sum() / n_bad) if n_bad else float("nan")
    lost = float((~keep & ~bad).sum() / n_real) if n_real else float("nan")
    return OutlierScores(caught, lost, n_bad, n_real)


def moving_leak_fraction(background_instance_ids: np.ndarray, input_instance_ids: np.ndarray,
                         moving_ids: np.ndarray | list[int]) -> float:
    """Share of the moving objects' points that ended up in a background aggregate.

    background_instance_ids (M,): the true instance id of every background point; input_instance_ids (N,): the
    true instance id of every input point (all frames); moving_ids: the ids of the moving objects."""
    moving = np.asarray(moving_ids)
    n_input = int(np.isin(input_instance_ids, moving).sum())
    return float(np.isin(background_instance_ids, moving).sum() / n_input) if n_input else 0.0


@dataclass
class GroundLayering:
    """Heights of aggregated road points against the true ground height (metres).

    offset: median(z - z_true); spread: std of z - z_true; p95_abs: 95th percentile of |z - z_true|;
    p95_layer: 95th percentile of |z - z_true - offset| (layering once the common offset is removed);
    within_tol: share of points with |z - z_true| <= tol."""

    offset: float
    spread: float
    p95_abs: float
    p95_layer: float
    within_tol: float


def ground_layering(z: np.ndarray, ground_z: np.ndarray | float, tol: float = 0.05) -> GroundLayering:
    """z (M,): heights of road points in the frame where the true ground height is ground_z (scalar or (M,))."""
    dz = np.asarray(z, dtype=np.float64) - np.asarray(ground_z, dtype=np.float64)
    if dz.ndim != 1 or len(dz) == 0:
        raise PointInputError(f"ground_layering: z must be a non-empty (M,) array, got shape {np.shape(z)}")
    offset = float(np.median(dz))
    return GroundLayering(offset, float(dz.std()), float(np.percentile(np.abs(dz), 95)),
                          float(np.percentile(np.abs(dz - offset), 95)), float(np.mean(np.abs(dz) <= tol)))
