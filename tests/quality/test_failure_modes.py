"""The build survives the failure modes of real logs: one small synthetic log with every
auto-label failure and sensor artefact of the `realistic` profile (synth.presets.IMPERFECTIONS), built once with
the default params, each mode checked against the exact truth where it happens."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.quality_matrix import MatrixWorld, below_ground_mask, evaluate_world
from nuplan_occ.dataset import open_dataset
from nuplan_occ.geometry import invert_transform
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import EMPTY, GENERIC_OBJECT, LABELS, VEHICLE
from nuplan_occ.pipeline.build import run_build
from nuplan_occ.pipeline.params import default_params
from nuplan_occ.stages import PIPELINE
from nuplan_occ.synth.logbuild import build_log, log_start
from nuplan_occ.synth.presets import get_preset, imperfect_options
from nuplan_occ.synth.world import build_world
from nuplan_occ.voxel.voxelize import box_voxel_indices, indices_to_grid

pytestmark = pytest.mark.slow

WORLD = MatrixWorld("failure-modes", "small", 35, "test", "realistic")
SECONDS = 2.0


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    """(world, plan, truth, build, quality figures) of the imperfect log; plan.label_failures says which track
    each failure hit (frame indices among the log's 20 Hz sweeps)."""
    from nuplan_occ.synth.generate import synthesize

    base = tmp_path_factory.mktemp("failure_modes")
    options = imperfect_options(WORLD.imperfections)
    synthesize(base / "data", seconds=SECONDS, seed=WORLD.seed, preset=WORLD.preset, options=options,
               truth_rate_hz=10.0, scene_seconds=SECONDS, camera_rate_hz=0.0, camera_mask=False)
    run_build(base / "data", str(base / "out"), default_params(PIPELINE), pipeline=PIPELINE)
    start = log_start(WORLD.seed, 0)
    world = build_world(get_preset(WORLD.preset), options, WORLD.seed, 0, SECONDS, int(start.timestamp()) * 1_000_000)
    plan = build_log(world, SECONDS, WORLD.seed, 0, start, SECONDS)
    figures = evaluate_world(WORLD, SECONDS, base / "data", base / "out")
    return world, plan, open_dataset(str(base / "data" / "truth")), open_dataset(str(base / "out")), figures


def _frames(log, indices) -> list[tuple[int, dict, dict]]:
    """(sweep index, truth frame, built frame) of the built frames among the given sweep indices."""
    _, plan, truth, built, _ = log
    out = []
    for f in indices:
        token = plan.content.frames[int(f)].token
        try:
            b = built.get(built.index_of_token(token), keys=("semantics", "instance"))
            t = truth.get(truth.index_of_token(token), keys=("semantics", "instance", "mask_lidar"))
        except KeyError:
            continue
        out.append((int(f), t, b))
    return out


def _agent(log, token: str):
    world, plan = log[0], log[1]
    boxed = [a for a in world.agents if a.boxed]
    return boxed[[t.token for t in plan.content.tracks].index(token)]


def _true_box_mask(log, agent, f: int, truth_frame: dict, margin_m: float) -> np.ndarray:
    """Voxels whose centre lies in the agent's TRUE box at sweep f (grown by margin_m), in the truth frame's grid."""
    world, plan = log[0], log[1]
    t = (plan.content.frames[f].timestamp_us - world.start_us) / 1e6
    center, yaw, _ = agent.state(np.array([t]))
    T = invert_transform(truth_frame["ego_to_global"])
    c = T[:3, :3] @ (center[0] + world.origin) + T[:3, 3]
    yaw_ego = float(yaw[0]) + np.arctan2(T[1, 0], T[0, 0])
    return indices_to_grid(box_voxel_indices(c, yaw_ego, agent.size, DEFAULT_GRID, margin_m))


def _object_figures(log, agent, frames) -> tuple[float, float]:
    """(recall: the agent's observed truth voxels built with its class, share over the frames; precision: built
    voxels of its class within 1 m of its true box that lie within one voxel of it)."""
    label = LABELS.box_category_to_id[agent.category]
    hit = seen = inside = near = 0
    for f, t, b in _frames(log, frames):
        own = (t["instance"] == agent.instance) & t["mask_lidar"]
        hit += int(np.count_nonzero(own & (b["semantics"] == label)))
        seen += int(np.count_nonzero(own))
        built = b["semantics"] == label
        near += int(np.count_nonzero(built & _true_box_mask(log, agent, f, t, 1.0)))
        inside += int(np.count_nonzero(built & _true_box_mask(log, agent, f, t, DEFAULT_GRID.voxel_size)))
    assert seen > 50, "the failure's object must be seen for the test to mean anything"
    return hit / seen, inside / max(near, 1)


def test_a_box_with_no_points_gets_no_voxels(log):
    plan = log[1]
    (token, frames), = plan.label_failures.false_positives.items()
    checked = 0
    for f, t, b in _frames(log, frames):
        box = plan.content.boxes[plan.content.frames[f].token]
        k = box.track_tokens.index(token)
        T = invert_transform(t["ego_to_global"])
        c = T[:3, :3] @ box.centers[k] + T[:3, 3]
        inside = indices_to_grid(box_voxel_indices(c, float(box.yaws[k]) + np.arctan2(T[1, 0], T[0, 0]), box.sizes[k],
                                                   DEFAULT_GRID, DEFAULT_GRID.voxel_size))
        objects = (b["semantics"] >= VEHICLE) & (b["semantics"] <= GENERIC_OBJECT)
        assert not np.any(inside & objects), f"sweep {f}: {np.count_nonzero(inside & objects)} object voxels in an empty box"
        checked += 1
    assert checked


def _reference_recall(log) -> float:
    """Median recall of the log's moving boxed vehicles that no failure hit: what box noise alone leaves."""
    world, plan = log[0], log[1]
    failures = plan.label_failures
    hit = {*failures.flipped, *failures.gaps, *failures.switched, *failures.duplicated, *failures.oversized,
           *failures.undersized}
    recalls = []
    agents = [a for a in world.agents if a.boxed]  # the log's first tracks, in order; later ones are failures'
    for track, agent in zip(plan.content.tracks, agents):
        if track.token not in hit and agent.category == "vehicle" and agent.moving:
            try:
                recalls.append(_object_figures(log, agent, range(len(plan.content.frames)))[0])
            except AssertionError:  # not seen
                continue
    assert recalls
    return float(np.median(recalls))


def test_a_flipped_box_neither_smears_nor_drops_its_car(log):
    (token, _), = log[1].label_failures.flipped.items()
    recall, precision = _object_figures(log, _agent(log, token), range(len(log[1].content.frames)))
    assert recall >= 0.9 * _reference_recall(log) and precision >= 0.95, (recall, precision)


def test_a_car_whose_box_is_missing_keeps_its_voxels_without_a_trail(log):
    (token, gap), = log[1].label_failures.gaps.items()
    agent = _agent(log, token)
    recall, precision = _object_figures(log, agent, gap)
    boxed_recall, _ = _object_figures(log, agent, sorted(set(range(len(log[1].content.frames))) - set(gap.tolist())))
    assert recall >= 0.9 * boxed_recall and precision >= 0.95, (recall, boxed_recall, precision)
    assert _trail(log, agent, gap) == 0


def _trail(log, agent, frames) -> int:
    """Built occupied voxels, empty in the truth, that the agent's TRUE box (its lowest 0.3 m left out) covers at
    another sweep but not (grown by a voxel) at the frame, summed over the built frames among `frames`."""
    world, plan = log[0], log[1]
    times = [(frame.timestamp_us - world.start_us) / 1e6 for frame in plan.content.frames]
    total = 0
    for f, t, b in _frames(log, frames):
        T = invert_transform(t["ego_to_global"])
        swept = np.zeros(DEFAULT_GRID.shape, dtype=bool)
        for time in times[::2]:
            center, yaw, _ = agent.state(np.array([time]))
            c = T[:3, :3] @ (center[0] + world.origin) + T[:3, 3] + [0.0, 0.0, 0.15]
            index = box_voxel_indices(c, float(yaw[0]) + np.arctan2(T[1, 0], T[0, 0]), agent.size - [0.0, 0.0, 0.3])
            swept[tuple(index.T)] = True
        now = _true_box_mask(log, agent, f, t, DEFAULT_GRID.voxel_size)
        total += int(np.count_nonzero(swept & ~now & (t["semantics"] == EMPTY) & (b["semantics"] != EMPTY)))
    return total


def test_an_id_switch_and_a_duplicate_track_keep_one_car(log):
    failures = log[1].label_failures
    reference = _reference_recall(log)
    for token in [*failures.switched, *failures.duplicated]:
        recall, precision = _object_figures(log, _agent(log, token), range(len(log[1].content.frames)))
        assert recall >= 0.75 * reference and precision >= 0.9, (token, recall, reference, precision)


def test_an_undersized_box_keeps_its_whole_pedestrian(log):
    (token,) = log[1].label_failures.undersized
    agent = _agent(log, token)
    hit = seen = 0
    for _, t, b in _frames(log, range(len(log[1].content.frames))):
        own = (t["instance"] == agent.instance) & t["mask_lidar"]
        hit += int(np.count_nonzero(own & (b["semantics"] != EMPTY)))
        seen += int(np.count_nonzero(own))
    assert seen > 20 and hit / seen >= 0.7, (hit, seen)


def test_no_voxel_below_the_ground_or_inside_the_ego_and_few_floaters(log):
    figures = log[4]
    assert figures["below_ground_voxels"] == 0
    assert figures["inside_ego_voxels"] == 0
    assert figures["floater_share"] <= 1e-4


def test_below_ground_mask_counts_voxels_under_the_lowest_truth_voxel():
    truth = np.zeros(DEFAULT_GRID.shape, np.uint8)
    truth[:, :, 10] = 12
    truth[0, 0, :] = 0  # a column without truth: nothing is below its ground
    below = below_ground_mask(truth)
    assert below[5, 5, :8].all() and not below[5, 5, 8:].any() and not below[0, 0].any()
