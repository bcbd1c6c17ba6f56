"""`nuplan-occ qa` on a synthetic build: a row per ok frame from the sweep between frames and the refined poses,
sidecar files one table keyed by token, reruns reuse them; the build's own qa_ray_* columns are the same
figures and the report judges them; a grid with an injected slab ends rays early, one with its walls removed
has holes; the sweep choice on hand-made sweep lists."""

from types import SimpleNamespace

import numpy as np
import pyarrow.dataset
import pytest
from typer.testing import CliRunner

from nuplan_occ.cli.errors import CliApp
from nuplan_occ.cli.qa import register
from nuplan_occ.dataset import open_dataset
from nuplan_occ.evaluation.ray_qa import (QA_FOLDER, matches_manifest, qa_dataset, scene_frames, scene_tasks,
                                          score_scene, sidecar_columns)
from nuplan_occ.rays.frame_qa import FIGURES, MAX_RAYS, scoring_sweep
from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import EMPTY, OTHER
from nuplan_occ.pipeline.build import run_build
from nuplan_occ.rays.consistency import GROUND_IDS
from nuplan_occ.stages import PIPELINE
from pipeline_helpers import build_params


@pytest.fixture(scope="module")
def built(synthetic_root, tmp_path_factory):
    out = tmp_path_factory.mktemp("qa") / "out"
    run_build(synthetic_root, str(out), build_params(), pipeline=PIPELINE)
    return synthetic_root, out


def test_every_ok_frame_is_scored_from_the_sweep_between_frames_with_refined_poses(built):
    data_root, out = built
    result = qa_dataset(str(out), data_root, PIPELINE, max_rays=5000)
    ds = open_dataset(str(out))
    assert sorted(r["token"] for r in result.rows) == sorted(ds.column("token").to_pylist())
    assert result.scored == 5 and result.reused == 0
    for row in result.rows:
        assert row["qa_ray_problem"] == "" and row["qa_ray_poses"] == "refined"
        assert abs(row["qa_ray_sweep_dt_s"]) == pytest.approx(0.05, abs=0.002)
        assert row["qa_ray_sweep_token"] != row["token"] and 0 < row["qa_ray_scored"] <= 5000
        shares = [row[c] for c in ("qa_ray_agree", "qa_ray_early", "qa_ray_hole", "qa_ray_other")]
        assert sum(shares) == pytest.approx(1.0) and row["qa_ray_agree"] > 0.8
    table = pyarrow.dataset.dataset(str(out / QA_FOLDER), format="parquet").to_table()
    assert sorted(table["token"].to_pylist()) == sorted(r["token"] for r in result.rows)
    again = qa_dataset(str(out), data_root, PIPELINE, max_rays=5000)
    assert (again.scored, again.reused) == (0, 5) and again.rows == result.rows
    assert qa_dataset(str(out), data_root, PIPELINE, max_rays=4000).scored == 5  # another setting: scored again


def _slab_in_front(grid: np.ndarray) -> np.ndarray:
    """A 1-voxel slab of `other` across the road 8 m ahead: x in [8, 8.25), |y| < 6 m, z in [-1, 3) m."""
    out = grid.copy()
    (x, y0, z0), (_, y1, z1) = DEFAULT_GRID.point_to_index(np.array([[8.0, -6.0, -1.0], [8.0, 6.0, 3.0]]))[0]
    out[x, y0:y1, z0:z1] = OTHER
    return out


def _walls_removed(grid: np.ndarray) -> np.ndarray:
    """Every occupied voxel that is not ground removed."""
    out = grid.copy()
    out[(out != EMPTY) & ~np.isin(out, GROUND_IDS)] = EMPTY
    return out


def test_a_slab_ends_rays_early_and_removed_walls_are_holes(built):
    data_root, out = built
    ds = open_dataset(str(out))
    task = scene_tasks(str(out), PIPELINE, data_root, None, None)[0]
    mine = scene_frames(ds)[(task.log_name, task.scene_token)]

    def scores(damage):
        rows = score_scene(task, PIPELINE, mine, lambda token: damage(
            ds.get(ds.index_of_token(token), keys=("semantics",))["semantics"]), 5000)
        return {c: np.mean([r[c] for r in rows]) for c in ("qa_ray_agree", "qa_ray_early", "qa_ray_hole")}

    clean, slab, holes = scores(lambda g: g), scores(_slab_in_front), scores(_walls_removed)
    assert slab["qa_ray_early"] > clean["qa_ray_early"] + 0.03
    assert slab["qa_ray_agree"] < clean["qa_ray_agree"] - 0.03
    assert slab["qa_ray_hole"] <= clean["qa_ray_hole"] + 0.002
    assert holes["qa_ray_hole"] > clean["qa_ray_hole"] + 0.05
    assert holes["qa_ray_agree"] < clean["qa_ray_agree"] - 0.05
    assert holes["qa_ray_early"] <= clean["qa_ray_early"] + 0.002


def test_the_cli_prints_the_summary_and_names_a_missing_data_root(built, tmp_path, capsys):
    data_root, out = built
    app = CliApp("nuplan-occ", add_completion=False)
    register(app)
    app.command("noop")(lambda: None)
    run = CliRunner().invoke(app, ["qa", str(out), "--data-root", str(data_root), "--max-rays", "5000"])
    assert run.exit_code == 0, run.output
    assert "qa_ray_agree" in run.output and "rays_early" in run.output and "5 scenes scored" in run.output
    with pytest.raises(SystemExit) as missing:
        app(["qa", str(out), "--data-root", str(tmp_path / "nowhere")], prog_name="nuplan-occ")
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert missing.value.code == 1
    assert lines == [f"nuplan-occ: error: {tmp_path / 'nowhere'}: data root folder not found"]


def _scene(*sweeps):
    """A stand-in scene: (timestamp s, is_output, loaded) per sweep."""
    return SimpleNamespace(sweeps=[SimpleNamespace(timestamp_us=int(t * 1e6), is_output=o, has_cloud=c)
                                   for t, o, c in sweeps])


def test_the_sweep_between_frames_nearest_in_time_later_on_a_tie():
    scene = _scene((0.0, True, True), (0.05, False, True), (0.1, True, True), (0.15, False, True))
    assert scoring_sweep(scene, 0) == 1 and scoring_sweep(scene, 2) == 3
    assert scoring_sweep(_scene((0.0, True, True), (0.05, False, False), (0.1, True, True), (0.15, False, True)), 0) \
        == 3  # 0.15 s away, a failed sweep is skipped
    assert scoring_sweep(_scene((0.0, True, True), (0.25, False, True)), 0) is None  # beyond MAX_SWEEP_DT_S
    every = _scene((0.0, True, True), (0.05, True, True), (0.1, True, True))
    assert scoring_sweep(every, 1) == 2  # every sweep an output: the nearest other one, the later on a tie


def test_the_build_writes_the_columns_qa_computes_and_the_report_judges_them(built):
    """The write stage's qa_ray_* manifest columns equal `nuplan-occ qa`'s figures at the same max_rays (same
    sweep, same refined poses); the report reads them and flags a frame whose rays end early."""
    from nuplan_occ.report.flags import evaluate_rules
    from nuplan_occ.report.frames import load_frames

    data_root, out = built
    rows = {r["token"]: r for r in qa_dataset(str(out), data_root, PIPELINE, max_rays=MAX_RAYS).rows}
    ds = open_dataset(str(out))
    manifest = ds.columns(["token", *FIGURES, "qa_ray_sweep_token", "qa_ray_flags"]).to_pylist()
    assert len(manifest) == len(rows)
    for frame in manifest:
        assert frame == {key: rows[frame["token"]][key] for key in frame}
    frames = load_frames(str(out))
    flags = evaluate_rules(frames.columns, frames.ok)
    assert {"rays_early", "rays_holes", "rays_disagree"} <= set(flags.masks)
    early = frames.columns["qa_ray_early"].copy()
    early[0] = 0.5  # a frame whose rays end early is flagged by that rule alone
    flags = evaluate_rules({**frames.columns, "qa_ray_early": early}, frames.ok)
    assert np.flatnonzero(flags.masks["rays_early"]).tolist() == [0]


def test_sidecar_columns_join_by_token_and_commit(built):
    """A build without the manifest columns gets them from the sidecar files; a frame rebuilt since (another
    commit) or never scored gets NaN."""
    data_root, out = built
    rows = qa_dataset(str(out), data_root, PIPELINE, max_rays=5000).rows
    tokens = np.array([r["token"] for r in rows] + ["unknown"], dtype=object)
    commits = np.array([r["commit_id"] for r in rows] + ["x"], dtype=object)
    commits[1] = "a later commit"
    joined = sidecar_columns(str(out), tokens, commits)
    expected = np.array([r["qa_ray_agree"] for r in rows] + [np.nan])
    expected[1] = np.nan
    np.testing.assert_array_equal(joined["qa_ray_agree"], expected)


def test_a_registration_matches_the_manifest_only_up_to_a_rigid_correction_on_the_left():
    rng = np.random.default_rng(0)
    poses = np.repeat(np.eye(4)[None], 5, axis=0)
    poses[:, :3, 3] = rng.normal(size=(5, 3)) * 10
    correction = np.eye(4)
    correction[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]
    correction[:3, 3] = [3.0, -2.0, 0.5]
    published = list(correction @ poses[[1, 2, 4]])
    assert matches_manifest(poses, [1, 2, 4], published)
    moved = poses.copy()
    moved[2, 0, 3] += 1e-3  # one frame 1 mm elsewhere: another registration
    assert not matches_manifest(moved, [1, 2, 4], published)


def test_an_imported_release_is_scored_with_the_logged_poses(built, tmp_path):
    """The build exported as UniScenev2-style grids and imported as a release (its logs found by token): every
    frame is scored, with the logged poses, its background membership unknown, and agrees about as well."""
    from nuplan_occ.export.formats import export_dataset
    from nuplan_occ.release.importer import ImportOptions, import_release

    data_root, out = built
    export_dataset(str(out), tmp_path / "release", "uniscene", frame="ego")
    import_release(tmp_path / "release", str(tmp_path / "rel"),
                   ImportOptions(layout="dense", labels="nuplan-occ", logs_root=str(data_root)))
    release = qa_dataset(str(tmp_path / "rel"), data_root, PIPELINE, max_rays=5000).rows
    own = {r["token"]: r for r in qa_dataset(str(out), data_root, PIPELINE, max_rays=5000).rows}
    assert sorted(r["token"] for r in release) == sorted(own)
    for row in release:
        assert row["qa_ray_poses"] == "logged" and row["qa_ray_sweep_in_background"] is None
        assert row["qa_ray_agree"] == pytest.approx(own[row["token"]]["qa_ray_agree"], abs=0.03)
