"""The track stage on a moving car seen through auto-label noise, and through a scene pose that sits turned and
shifted against the global frame: its boxes end up on its points (the exact synthetic truth)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from vehicle_surface import surface_samples

from nuplan_occ.geometry import yaw_matrix
from nuplan_occ.io.types import Boxes
from nuplan_occ.map_labels.map_align import MapAlignment
from nuplan_occ.stages.track import TrackParams, run

SIZE = np.array([4.7, 1.9, 1.6])
SWEEPS = 60  # 3 s at 20 Hz


def _true_poses(t: np.ndarray) -> np.ndarray:
    """(T, 4) x, y, z, yaw of a car driving at 8 m/s along a gentle left curve, ego frame = global frame."""
    yaw = 0.1 * t
    return np.c_[8.0 * np.sin(yaw) / 0.1 + 5.0, 8.0 * (1 - np.cos(yaw)) / 0.1 - 6.0, np.full_like(t, 0.8), yaw]


def _scene(seed: int, scene_error: np.ndarray = np.eye(4)):
    """(scene, registration, true poses (SWEEPS, 4)): the ego stands at the global origin; the registration's
    poses are scene_error (4, 4; T_global_from_ego as registered, the truth being the identity)."""
    rng = np.random.default_rng(seed)
    t = np.arange(SWEEPS) * 0.05
    truth = _true_poses(t)
    sweeps = []
    ground = np.c_[rng.uniform(-10, 60, (4000, 2)), np.zeros(4000)]
    for f in range(SWEEPS):
        body = surface_samples(rng, 3000, SIZE)
        body = body[(body[:, 1] > 0.3) | (body[:, 0] < -1.5) | (body[:, 2] > 0.5)][:800]  # its left, rear and top
        body = body @ yaw_matrix(truth[f, 3]).T + truth[f, :3] + rng.normal(0, 0.01, body.shape)
        noisy = truth[f] + np.r_[rng.normal(0, 0.15, 2), rng.normal(0, 0.05), np.radians(rng.normal(0, 3.0))]
        boxes = Boxes("global", noisy[None, :3], SIZE[None].copy(), noisy[3:4], np.array([[8.0, 0.0, 0.0]]),
                      ["vehicle"], ["car"], [f"box{f}"])
        sweeps.append(SimpleNamespace(timestamp_us=int(t[f] * 1e6), boxes_global=boxes, xyz=np.vstack([body, ground])))
    scene = SimpleNamespace(sweeps=sweeps, sensor_origin_ego=np.array([0.0, 0.0, 1.8]),
                            ok_indices=lambda: list(range(SWEEPS)))
    registration = SimpleNamespace(poses=np.repeat(scene_error[None], SWEEPS, axis=0))
    return scene, registration, truth


def _box_errors(out: dict, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centre error (SWEEPS,) m, heading error (SWEEPS,) deg) of the track stage's boxes against the truth."""
    boxes = [out["object_boxes"][f] for f in range(SWEEPS)]
    centre = np.array([b.centers[0] for b in boxes])
    yaw = np.array([b.yaws[0] for b in boxes])
    return (np.linalg.norm(centre[:, :2] - truth[:, :2], axis=1),
            np.degrees(np.abs(np.angle(np.exp(1j * (yaw - truth[:, 3]))))))


def test_a_moving_cars_noisy_boxes_end_on_its_points():
    """Boxes off by 0.15 m and 3 deg per frame (the realistic profile's auto-label noise) end, over three
    draws, within a sixth of that position error and a fifth of that heading error of the truth."""
    position, raw_position, heading = [], [], []
    for seed in range(3):
        scene, registration, truth = _scene(seed)
        err, dyaw = _box_errors(run({"scene": scene, "registration": registration, "map_alignment": None},
                                    TrackParams()), truth)
        logged = np.array([s.boxes_global.centers[0] for s in scene.sweeps])
        raw = np.linalg.norm(logged[:, :2] - truth[:, :2], axis=1)
        position.append(np.sqrt((err ** 2).mean()))
        raw_position.append(np.sqrt((raw ** 2).mean()))
        heading.append(np.sqrt((dyaw ** 2).mean()))
    assert np.mean(position) < np.mean(raw_position) / 6, (position, raw_position)
    assert np.mean(heading) < 3.0 / 5, heading


def test_boxes_are_placed_with_the_poses_the_map_corrected():
    """A scene registered 0.4 deg turned and 0.1 m shifted against the global frame (the map shows it, the boxes
    share the global frame): with the map's correction the boxes land on the car; with the registered poses alone
    (boxes_on_map off, or no alignment) they keep the scene's error, which no per-track ICP can see."""
    turn = np.radians(0.4)
    error = np.eye(4)
    error[:2, :2] = [[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]]
    error[:2, 3] = [0.1, -0.05]
    scene, registration, truth = _scene(0, error)
    inverse = np.linalg.inv(error)
    alignment = MapAlignment(dx=float(inverse[0, 3]), dy=float(inverse[1, 3]), dyaw=-turn, pivot=(0.0, 0.0),
                             n_points=1000, rms_before=0.1, rms_after=0.02, applied=True)
    inputs = {"scene": scene, "registration": registration}
    on_map, _ = _box_errors(run({**inputs, "map_alignment": alignment}, TrackParams()), truth)
    registered, _ = _box_errors(run({**inputs, "map_alignment": alignment}, TrackParams(boxes_on_map=False)), truth)
    unaligned, _ = _box_errors(run({**inputs, "map_alignment": None}, TrackParams()), truth)
    assert np.sqrt((on_map ** 2).mean()) < 0.04
    assert np.sqrt((registered ** 2).mean()) > 0.1 and np.sqrt((unaligned ** 2).mean()) > 0.1
