"""Data-root resolution and the per-log summary."""

from __future__ import annotations

import numpy as np
import pytest
from rich.console import Console

from nuplan_io_logfactory import build_log, write_built
from nuplan_occ.io.data_root import maps_root_for, resolve_logs, sensor_root_for
from nuplan_occ.io.errors import MissingLogError
from nuplan_occ.io.summary import render_summary, summarize_log


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("nuplan")
    built = build_log(seed=3, n_frames=6)
    db_path = write_built(built, root)
    with_missing = build_log(seed=4, n_frames=6)
    with_missing.content.meta.logfile = "2021.06.01.10.00.00_veh-12_00001_00002"
    for frame in with_missing.content.frames:
        frame.filename = frame.filename.replace(built.content.meta.logfile, with_missing.content.meta.logfile)
    write_built(with_missing, root)
    (root / "nuplan-v1.1" / "sensor_blobs" / with_missing.content.frames[0].filename).unlink()
    (root / "nuplan-v1.1" / "splits" / "trainval").mkdir(parents=True)
    return root, db_path, built


def test_resolve_logs(data_root):
    root, db_path, _ = data_root
    logs = resolve_logs(root)
    assert [p.stem for p in logs] == sorted(p.stem for p in logs) and len(logs) == 2 and db_path in logs
    assert resolve_logs(root, log_names=[db_path.stem + ".db"]) == [db_path]
    assert resolve_logs(root, split=None) == logs  # glob under the root
    assert resolve_logs(root, db_paths=[str(db_path)]) == [db_path]
    with pytest.raises(MissingLogError, match="nope") as err:
        resolve_logs(root, log_names=["nope"])
    assert err.value.path == str(root / "nuplan-v1.1" / "splits" / "mini")
    with pytest.raises(MissingLogError, match="no \\*.db"):
        resolve_logs(root, split="trainval")
    with pytest.raises(MissingLogError, match="not found"):
        resolve_logs(root, db_paths=[str(root / "x.db")])


def test_sensor_and_maps_roots(data_root, monkeypatch, tmp_path):
    root, db_path, _ = data_root
    assert sensor_root_for(db_path, root) == root / "nuplan-v1.1" / "sensor_blobs"
    monkeypatch.delenv("NUPLAN_MAPS_ROOT", raising=False)
    assert maps_root_for(root) == root / "maps"
    monkeypatch.setenv("NUPLAN_MAPS_ROOT", str(tmp_path))
    assert maps_root_for(root) == tmp_path
    assert maps_root_for(root, "/explicit") == type(tmp_path)("/explicit")


def test_summary_counts(data_root):
    root, _, built = data_root
    rows = [summarize_log(p) for p in resolve_logs(root)]
    full = next(r for r in rows if r["log"] == built.content.meta.logfile)
    assert full["scenes"] == 5 and full["frames"] == 6 and full["duration_s"] == pytest.approx(0.25)
    assert full["boxes"]["vehicle"] == 6 and full["boxes"]["traffic_cone"] == 6 and full["boxes"]["bicycle"] == 0
    total = sum(len(c) for c in built.clouds.values())
    assert sum(full["points"].values()) == total and full["points"]["top"] == sum(
        int(np.sum(c.lidar_info == 0)) for c in built.clouds.values())
    other = next(r for r in rows if r is not full)
    assert other["missing_blobs"] == 1 and other["blobs_read"] == 5 and other["failures"] == []
    text = Console(width=200, record=True)
    text.print(render_summary(rows))
    assert built.content.meta.logfile in text.export_text()


def test_summary_of_a_broken_log(tmp_path):
    bad = tmp_path / "broken.db"
    bad.write_bytes(b"x" * 100)
    row = summarize_log(bad)
    assert row["log"] == "broken" and len(row["failures"]) == 1 and str(bad) in row["failures"][0]
