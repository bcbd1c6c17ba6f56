"""The synth's auto-label failures and sensor artefacts (synth.auto_label, synth.sensor_artefacts): each is made
as documented, the defaults make none, and the truth never sees them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from nuplan_occ.dataset import open_dataset
from nuplan_occ.geometry import wrap_angle
from nuplan_occ.io.types import PACIFICA
from nuplan_occ.synth import synthesize
from nuplan_occ.synth.auto_label import FALSE_POSITIVE_SIZE
from nuplan_occ.synth.lidar import sweep_at
from nuplan_occ.synth.logbuild import build_log, log_start
from nuplan_occ.synth.presets import SynthOptions, get_preset, imperfect_options
from nuplan_occ.synth.sensor_artefacts import with_artefacts
from nuplan_occ.synth.world import build_world
from nuplan_occ.voxel.voxelize import in_box

SEED, SECONDS = 3, 4.0
OPTIONS = imperfect_options("realistic")


def _plan(options: SynthOptions):
    start = log_start(SEED, 0)
    world = build_world(get_preset("small"), options, SEED, 0, SECONDS, int(start.timestamp()) * 1_000_000)
    return world, build_log(world, SECONDS, SEED, 0, start)


@pytest.fixture(scope="module")
def imperfect():
    return _plan(OPTIONS)


def _track_boxes(plan, token: str) -> dict[int, tuple]:
    """frame index -> (centre, size, yaw, velocity) of the track's box there."""
    out = {}
    for f, frame in enumerate(plan.content.frames):
        b = plan.content.boxes[frame.token]
        if token in b.track_tokens:
            i = b.track_tokens.index(token)
            out[f] = (b.centers[i], b.sizes[i], b.yaws[i], b.velocities[i])
    return out


def _agent_of(world, plan, token: str):
    boxed = [a for a in world.agents if a.boxed]
    return boxed[[t.token for t in plan.content.tracks].index(token)]


def _times(world, plan) -> np.ndarray:
    return np.array([(f.timestamp_us - world.start_us) / 1e6 for f in plan.content.frames])


def test_defaults_make_no_failure_and_no_artefact():
    world, plan = _plan(SynthOptions())
    hit = plan.label_failures
    assert not (hit.flipped or hit.gaps or hit.switched or hit.false_positives or hit.undersized or hit.oversized
                or hit.duplicated)
    sweep = sweep_at(world, plan.content.frames[0].timestamp_us, plan.true_poses[0])
    assert with_artefacts(sweep, world.options, -world.options.axle_height_m, np.random.default_rng(0)) is sweep


def test_flipped_box_turns_by_half_a_turn_in_a_quarter_of_its_frames(imperfect):
    world, plan = imperfect
    (token, flipped), = plan.label_failures.flipped.items()
    agent = _agent_of(world, plan, token)
    assert agent.category == "vehicle"
    boxes = _track_boxes(plan, token)
    true_yaw = agent.state(_times(world, plan))[1]
    turned = {f for f, (_, _, yaw, _) in boxes.items() if abs(wrap_angle(yaw - true_yaw[f])) > np.pi / 2}
    assert turned == set(flipped.tolist())
    assert abs(len(turned) / len(boxes) - OPTIONS.yaw_flip_share) <= 0.05


def test_track_gap_removes_the_boxes_of_a_moving_car_for_half_a_second(imperfect):
    world, plan = imperfect
    (token, gap), = plan.label_failures.gaps.items()
    assert _agent_of(world, plan, token).moving
    boxes = _track_boxes(plan, token)
    assert len(gap) == 10 and np.all(np.diff(gap) == 1)
    assert not set(gap.tolist()) & set(boxes)
    assert gap[0] - 1 in boxes or gap[-1] + 1 in boxes  # boxed around the gap


def test_id_switch_moves_the_track_to_a_new_token_halfway(imperfect):
    world, plan = imperfect
    (old, (new, first)), = plan.label_failures.switched.items()
    before, after = _track_boxes(plan, old), _track_boxes(plan, new)
    assert before and after and max(before) < first == min(after)
    assert new in {t.token for t in plan.content.tracks}


def test_false_positive_box_stands_on_empty_drivable_ground(imperfect):
    world, plan = imperfect
    (token, frames), = plan.label_failures.false_positives.items()
    boxes = _track_boxes(plan, token)
    assert sorted(boxes) == frames.tolist() and len(frames) == round(OPTIONS.false_positive_seconds / 0.05)
    times = _times(world, plan)
    for f, (centre, size, yaw, _) in boxes.items():
        assert np.allclose(size, FALSE_POSITIVE_SIZE)
        for agent in world.agents:
            c, y, _ = agent.state(times[f:f + 1])
            corners = c[0] + np.array([[sx * agent.size[0] / 2, sy * agent.size[1] / 2, 0.0]
                                       for sx in (-1, 0, 1) for sy in (-1, 0, 1)]) @ np.array(
                [[np.cos(y[0]), np.sin(y[0]), 0], [-np.sin(y[0]), np.cos(y[0]), 0], [0, 0, 1]])
            assert not in_box(corners + world.origin, centre, float(yaw), size, 0.5).any()


def test_size_failures_scale_the_box_and_the_track(imperfect):
    """Against the same log without the size failures (same noise draws): exactly scaled, track size included."""
    world, plan = imperfect
    _, plain = _plan(replace(OPTIONS, undersized_tracks=0, oversized_tracks=0))
    for tokens, scale, category in ((plan.label_failures.undersized, OPTIONS.undersized_scale, "pedestrian"),
                                    (plan.label_failures.oversized, OPTIONS.oversized_scale, "vehicle")):
        (token,) = tokens
        assert _agent_of(world, plan, token).category == category
        scaled, unscaled = _track_boxes(plan, token), _track_boxes(plain, token)
        assert scaled and sorted(scaled) == sorted(unscaled)
        for f in scaled:
            assert np.allclose(scaled[f][1], scale * unscaled[f][1])
        track = {t.token: t for t in plan.content.tracks}[token]
        plain_track = {t.token: t for t in plain.content.tracks}[token]
        assert np.isclose(track.length, scale * plain_track.length) and np.isclose(track.height, scale * plain_track.height)


def test_duplicate_track_boxes_the_same_object_twice(imperfect):
    world, plan = imperfect
    (token, (twin, frames)), = plan.label_failures.duplicated.items()
    original, copy = _track_boxes(plan, token), _track_boxes(plan, twin)
    assert sorted(copy) == frames.tolist() and len(frames) == 20
    for f in frames:
        assert np.isclose(np.linalg.norm(copy[f][0] - original[f][0]), OPTIONS.duplicate_offset_m)


@pytest.fixture(scope="module")
def artefact_sweep():
    options = replace(SynthOptions(), floater_share=0.01, ghost_share=0.01, self_hits=300)
    world, plan = _plan(SynthOptions())
    sweep = sweep_at(world, plan.content.frames[5].timestamp_us, plan.true_poses[5])
    return sweep, with_artefacts(sweep, options, -options.axle_height_m, np.random.default_rng(5)), options


def test_artefacts_are_added_to_the_sweep_and_leave_its_returns(artefact_sweep):
    sweep, dirty, options = artefact_sweep
    n = len(sweep.points)
    assert np.array_equal(dirty.points[:n], sweep.points)
    extra = dirty.points[n:]
    assert abs(len(extra) - (0.02 * n + 300)) < 6 * np.sqrt(0.02 * n) + 0.003 * n  # floaters may be fewer: kept above ground
    assert not dirty.label[n:].any() and not dirty.instance[n:].any()


def test_self_hits_lie_on_the_ego_body(artefact_sweep):
    sweep, dirty, options = artefact_sweep
    center, size = PACIFICA.box_center_and_size()
    on_body = in_box(dirty.points[len(sweep.points):], center, 0.0, size, 1e-6)
    assert on_body.sum() == options.self_hits


def test_ghosts_lie_one_to_three_metres_below_the_road_and_floaters_in_the_air(artefact_sweep):
    sweep, dirty, options = artefact_sweep
    extra = dirty.points[len(sweep.points):]
    ground = -options.axle_height_m
    ghosts = extra[:, 2] < ground - 0.5
    assert abs(ghosts.sum() - 0.01 * len(sweep.points)) < 6 * np.sqrt(0.01 * len(sweep.points))
    assert np.all(extra[ghosts, 2] >= ground - 3.0 - 0.2) and np.all(extra[ghosts, 2] <= ground - 1.0 + 0.2)
    center, size = PACIFICA.box_center_and_size()
    floaters = extra[~ghosts & ~in_box(extra, center, 0.0, size, 1e-6)]
    assert len(floaters) and np.all(floaters[:, 2] >= ground + 0.5)


def test_truth_never_contains_the_imperfections(tmp_path):
    """Same world with and without every failure and artefact: identical truth grids and masks."""
    roots = {}
    for name, options in (("clean", SynthOptions()), ("imperfect", OPTIONS)):
        roots[name] = tmp_path / name
        synthesize(roots[name], seconds=0.1, seed=SEED, preset="small", options=options, camera_rate_hz=0.0,
                   camera_mask=False)
    clean, dirty = open_dataset(str(roots["clean"] / "truth")), open_dataset(str(roots["imperfect"] / "truth"))
    assert len(clean) == len(dirty) == 2
    for i in range(len(clean)):
        a, b = clean.get(i, keys=("semantics", "instance", "mask_lidar")), dirty.get(i, keys=("semantics", "instance", "mask_lidar"))
        for key in ("semantics", "instance", "mask_lidar"):
            assert np.array_equal(a[key], b[key]), key
