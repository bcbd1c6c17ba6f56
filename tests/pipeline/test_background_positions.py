"""Which sweeps are registered and build the background (SceneData.background_positions): every output sweep,
the sweeps in phase with them at the stride, the first and last loaded sweeps, never a sweep that failed to load;
and which sweeps align the map (SceneData.spread_positions): a stride, thinned evenly to a limit."""

from __future__ import annotations

import numpy as np

from nuplan_occ.pipeline.scene import SceneData, Sweep


def _scene(outputs: list[bool], loaded: list[bool]) -> SceneData:
    sweeps = [Sweep(token=f"s{i}", index=i, timestamp_us=50_000 * i, logged_pose=np.eye(4),
                    stored_cloud=object() if ok else None, boxes=None, boxes_global=None, is_output=out)
              for i, (out, ok) in enumerate(zip(outputs, loaded))]
    return SceneData(task=None, meta=None, sweeps=sweeps, sensor_origin_ego=np.zeros(3), cameras=[], map_path=None,
                     instance_ids={}, track_categories={})


def test_stride_two_keeps_the_output_sweeps_in_phase_with_them():
    # one context sweep before the outputs, outputs every other sweep from position 1, sweep 5 failed to load
    outputs = [False, True, False, True, False, True, False, False]
    loaded = [True, True, True, True, True, False, True, True]
    scene = _scene(outputs, loaded)
    assert scene.background_positions(1) == [0, 1, 2, 3, 4, 6, 7]
    assert scene.background_positions(2) == [0, 1, 3, 7]
    assert scene.background_positions(3) == [0, 1, 3, 4, 7]


def test_an_output_sweep_out_of_phase_is_still_used():
    outputs = [True, False, True, True, False, True, False]  # an irregular output step (a dropped sweep in the log)
    scene = _scene(outputs, [True] * len(outputs))
    assert scene.background_positions(2) == [0, 2, 3, 4, 5, 6]


def test_a_scene_shorter_than_min_sweeps_keeps_every_sweep():
    outputs = [False, True, False, True, False, True, False, False]
    scene = _scene(outputs, [True] * len(outputs))
    every = list(range(len(outputs)))
    assert scene.background_positions(2, min_sweeps=9) == every
    assert scene.background_positions(2, min_sweeps=8) == [0, 1, 3, 5, 7]


def test_spread_positions_thin_evenly_and_keep_both_ends():
    scene = _scene([True] * 11, [True] * 10 + [False])
    assert scene.spread_positions(2) == [0, 2, 4, 6, 8]
    assert scene.spread_positions(1, limit=4) == [0, 3, 6, 9]
    assert scene.spread_positions(2, limit=3) == [0, 4, 8]
    assert scene.spread_positions(2, limit=5) == scene.spread_positions(2, limit=0) == [0, 2, 4, 6, 8]
