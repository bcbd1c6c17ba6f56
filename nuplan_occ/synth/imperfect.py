"""Deliberate imperfections of a written log relative to the exact world (pure functions).

Logged ego pose = TRUE pose with a 6-DOF error: a slow drift (per degree of freedom, a sum of three
sinusoids with periods around `drift_period_s` and random phases, scaled to the drift amplitude) plus
white noise. Translation errors are in the global frame; rotation errors are applied on the ego side
(T_logged = [R_true @ R_err | p_true + dp]).
Logged boxes = true boxes with Gaussian noise on centre, yaw and size (a per-track size bias plus a
smaller per-frame jitter).
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.geometry import rotation_from_euler, wrap_angle
from nuplan_occ.synth.presets import SynthOptions


def pose_errors(times: np.ndarray, options: SynthOptions, rng: np.random.Generator) -> np.ndarray:
    """(T, 6) errors [dx, dy, dz (m, global), droll, dpitch, dyaw (rad)] at times (T,) seconds."""
    times = np.asarray(times, np.float64)
    drift_amp = np.array([options.drift_xy, options.drift_xy, options.drift_z, 0.0, 0.0, np.radians(options.drift_yaw_deg)])
    noise = np.array([options.pose_noise_xy, options.pose_noise_xy, options.pose_noise_z,
                      *np.radians([options.pose_noise_rollpitch_deg, options.pose_noise_rollpitch_deg, options.pose_noise_yaw_deg])])
    periods = options.drift_period_s * rng.uniform(0.5, 1.5, (6, 3))
    phases = rng.uniform(0, 2 * np.pi, (6, 3))
    weights = rng.uniform(0.5, 1.0, (6, 3))
    wave = np.einsum("dk,tdk->td", weights, np.sin(2 * np.pi * times[:, None, None] / periods + phases))
    wave /= weights.sum(axis=1)
    return drift_amp * wave + noise * rng.standard_normal((len(times), 6))


def logged_poses(T_true: np.ndarray, errors: np.ndarray) -> np.ndarray:
    """(T, 4, 4) logged T_global_from_ego from TRUE poses (T, 4, 4) and errors (T, 6) of `pose_errors`."""
    out = np.array(T_true, dtype=np.float64, copy=True)
    for k, e in enumerate(errors):
        out[k, :3, :3] = T_true[k, :3, :3] @ rotation_from_euler(e[3], e[4], e[5])
        out[k, :3, 3] = T_true[k, :3, 3] + e[:3]
    return out


def noisy_boxes(centers: np.ndarray, sizes: np.ndarray, yaws: np.ndarray, size_bias: np.ndarray,
                options: SynthOptions, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Logged (centers (K, 3), sizes (K, 3), yaws (K,)) from true ones; size_bias (K, 3) is the per-track
    relative size error (drawn once per track with `track_size_bias`)."""
    k = len(centers)
    c = centers + options.box_center_sigma * rng.standard_normal((k, 3)) * [1.0, 1.0, 0.5]
    jitter = 1.0 + size_bias + 0.3 * options.box_size_sigma_rel * rng.standard_normal((k, 3))
    y = np.asarray(wrap_angle(yaws + np.radians(options.box_yaw_sigma_deg) * rng.standard_normal(k)), np.float64).reshape(-1)
    return c, sizes * np.maximum(jitter, 0.5), y


def track_size_bias(n: int, options: SynthOptions, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) relative size errors, one per track."""
    return options.box_size_sigma_rel * rng.standard_normal((n, 3))
