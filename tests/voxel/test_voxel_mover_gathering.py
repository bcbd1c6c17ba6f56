"""An unboxed mover's points of the frames around one are moved by its own motion onto where it is: on exact
box geometry, each frame's returns falling elsewhere along its scanlines, the gathered points lie on the
object's surface at the frame gathered onto, also along a flat side that slides onto itself and through a
turn."""

from __future__ import annotations

import numpy as np

from nuplan_occ.voxel.mover_gathering import GatherSettings, gather_mover, joint_velocity, supported

LENGTH, WIDTH, HEIGHT = 4.5, 1.8, 1.5


def _seen_faces(x0: float, y0: float, yaw: float, rng: np.random.Generator) -> np.ndarray:
    """Returns off a box's left side (y = +WIDTH/2) and roof along scanlines: rows every 0.3 m in z on the side
    and every 0.3 m across the roof, each with points at random spots along the length (a sweep's beams fall
    elsewhere along its rows each time); box frame placed at (x0, y0) with yaw (rad)."""
    side_z = np.arange(0.2, HEIGHT, 0.3)
    along = rng.uniform(-LENGTH / 2, LENGTH / 2, (len(side_z), 40))
    side = np.c_[along.ravel(), np.full(along.size, WIDTH / 2), np.repeat(side_z, 40)]
    roof_y = np.arange(-WIDTH / 2 + 0.15, WIDTH / 2, 0.3)
    along = rng.uniform(-LENGTH / 2, LENGTH / 2, (len(roof_y), 20))
    roof = np.c_[along.ravel(), np.repeat(roof_y, 20), np.full(along.size, HEIGHT)]
    points = np.vstack([side, roof])
    c, s = np.cos(yaw), np.sin(yaw)
    points[:, :2] = points[:, :2] @ np.array([[c, s], [-s, c]]) + [x0, y0]
    return points


def _off_surface(points: np.ndarray, x0: float, y0: float, yaw: float) -> np.ndarray:
    """(N,) m: each point's distance from the box's side and roof faces (box at (x0, y0), yaw)."""
    c, s = np.cos(yaw), np.sin(yaw)
    local = (points[:, :2] - [x0, y0]) @ np.array([[c, -s], [s, c]])
    along = np.maximum(np.abs(local[:, 0]) - LENGTH / 2, 0.0)
    to_side = np.hypot(np.hypot(local[:, 1] - WIDTH / 2, along), np.maximum(np.abs(points[:, 2] - 0.85) - 0.65, 0))
    to_roof = np.hypot(np.hypot(points[:, 2] - HEIGHT, along), np.maximum(np.abs(local[:, 1]) - WIDTH / 2, 0.0))
    return np.minimum(to_side, to_roof)


def _frames(step_m: float, turn_rad: float, steps: range, seed: int = 0) -> dict[int, np.ndarray]:
    """Frame step -> the returns of a box driving along its length at step_m per frame, turning turn_rad per
    frame about its centre's path, at frame 0 at (10, 5) heading +x."""
    rng = np.random.default_rng(seed)
    frames = {}
    for k in steps:
        yaw = turn_rad * k
        x0, y0 = 10.0 + step_m * k * np.cos(yaw / 2), 5.0 + step_m * k * np.sin(yaw / 2)
        frames[k] = _seen_faces(x0, y0, yaw, rng)
    return frames


def test_a_side_sliding_along_itself_is_gathered_where_the_object_is() -> None:
    """The mover shows one flat side along its motion (8 m/s): shifted by any amount along its length the
    side still lies on itself, so only its ends tell the motion. The gathered points stay on the box at frame
    0 and end where it ends (no smear along the motion)."""
    frames = _frames(0.8, 0.0, range(-5, 6))
    own = frames.pop(0)
    gathered = gather_mover(own, frames, GatherSettings(), 0.25)
    assert len(gathered) >= 8 * len(own)  # most of the ten frames around joined
    assert np.percentile(_off_surface(gathered, 10.0, 5.0, 0.0), 95) <= 0.1
    assert gathered[:, 0].min() >= 10.0 - LENGTH / 2 - 0.15 and gathered[:, 0].max() <= 10.0 + LENGTH / 2 + 0.15


def test_the_velocity_is_read_from_the_frames_before_and_after() -> None:
    frames = _frames(0.8, 0.0, range(-2, 3))
    own = frames.pop(0)
    velocity = joint_velocity(own, frames, GatherSettings())
    assert velocity is not None and np.allclose(velocity, [0.8, 0.0], atol=0.06)


def test_a_turning_mover_is_gathered_turned_back() -> None:
    """Turning 3 degrees per frame: frame 5 is 15 degrees off; gathered turned back onto frame 0's box."""
    frames = _frames(0.6, np.deg2rad(3.0), range(-5, 6), seed=1)
    own = frames.pop(0)
    gathered = gather_mover(own, frames, GatherSettings(), 0.25)
    assert len(gathered) >= 6 * len(own)
    assert np.percentile(_off_surface(gathered, 10.0, 5.0, 0.0), 95) <= 0.15


def test_other_objects_and_a_vanished_mover_are_not_gathered() -> None:
    """A pole 6 m away in every frame around is never gathered; once the mover is gone (from frame 3 on) that direction
    ends there, even though frame 4 holds points again (contiguous frames only)."""
    frames = _frames(0.8, 0.0, range(-2, 3))
    pole = np.c_[np.full(20, 16.0), np.full(20, -1.0), np.linspace(0.0, 3.0, 20)]
    own = frames.pop(0)
    frames = {k: np.vstack([points, pole]) for k, points in frames.items()}
    frames[3] = pole.copy()
    frames[4] = _frames(0.8, 0.0, range(4, 5))[4]
    gathered = gather_mover(own, frames, GatherSettings(), 0.25)
    assert not np.any(np.hypot(gathered[:, 0] - 16.0, gathered[:, 1] + 1.0) < 0.5)
    assert len(gathered) <= 5 * len(own)  # frames -2..2 at most
    assert np.percentile(_off_surface(gathered, 10.0, 5.0, 0.0), 95) <= 0.1


def test_without_neighbours_only_the_own_points_remain() -> None:
    own = _frames(0.8, 0.0, range(0, 1))[0]
    assert np.array_equal(gather_mover(own, {}, GatherSettings(), 0.25), own)


def test_gathered_points_stay_within_the_own_points_span_along_the_motion() -> None:
    """Frame 0 saw the box's rear 2 m only; the frames around saw all of it. Along the motion the gathered
    points end where the own points end (a shift read a little off along a side would leave a trail); across
    it they reach at most reach_m past them."""
    frames = _frames(0.8, 0.0, range(-5, 6))
    own = frames.pop(0)
    own = own[own[:, 0] < 10.0 - LENGTH / 2 + 2.0]
    narrow = own[own[:, 1] > 5.0 + WIDTH / 2 - 0.5]  # the side and a strip of roof beside it
    gathered = gather_mover(own, frames, GatherSettings(reach_m=1.0), 0.25)
    assert len(gathered) >= 4 * len(own)
    assert gathered[:, 0].max() <= own[:, 0].max() + 1e-9 and gathered[:, 0].min() >= own[:, 0].min() - 1e-9
    assert np.percentile(_off_surface(gathered, 10.0, 5.0, 0.0), 95) <= 0.1
    across = gather_mover(narrow, frames, GatherSettings(reach_m=1.0), 0.25)
    assert across[:, 1].min() < narrow[:, 1].min() - 0.5  # the roof seen by the frames around joins
    assert across[:, 1].min() >= narrow[:, 1].min() - 1.0 - 1e-9


def test_a_stray_return_flagged_beside_the_mover_in_one_frame_is_not_gathered() -> None:
    """Frame 2 also flagged a floater 0.6 m beside the box's side (within reach of the own points, in the cluster
    of the side's points): no other frame has a point there once placed, so it stays out, while the side's
    points, which recur, are gathered."""
    frames = _frames(0.8, 0.0, range(-5, 6))
    own = frames.pop(0)
    floater = np.array([[10.0 + 2 * 0.8, 5.0 + WIDTH / 2 + 0.6, 1.1]])
    frames[2] = np.vstack([frames[2], floater])
    gathered = gather_mover(own, frames, GatherSettings(reach_m=1.0), 0.25)
    assert len(gathered) >= 8 * len(own)
    assert not np.any(np.linalg.norm(gathered - (floater[0] - [2 * 0.8, 0.0, 0.0]), axis=1) < 0.2)


def test_supported_keeps_own_points_and_points_another_part_reaches() -> None:
    own = np.array([[0.0, 0.0, 0.0]])
    near_own = np.array([[0.2, 0.0, 0.0]])
    alone = np.array([[2.0, 2.0, 2.0]])
    pair = np.array([[5.0, 5.0, 1.0]]), np.array([[5.1, 5.1, 1.1]])
    kept = supported([own, np.vstack([near_own, alone]), pair[0], pair[1]], 0.25)
    assert {tuple(p) for p in kept} == {(0.0, 0.0, 0.0), (0.2, 0.0, 0.0), (5.0, 5.0, 1.0), (5.1, 5.1, 1.1)}
