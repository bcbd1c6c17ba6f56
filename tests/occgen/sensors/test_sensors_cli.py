import json

import typer
from typer.testing import CliRunner

from occgen.cli_sensors import register


def test_cli_lidar_and_eval(tmp_path, street_dataset):
    root = street_dataset
    app = typer.Typer()
    register(app)
    runner = CliRunner()
    res = runner.invoke(app, ["lidar", root, "--out", str(tmp_path / "gen"), "--density", "0.1"])
    assert res.exit_code == 0, res.output
    assert len(list((tmp_path / "gen").glob("*.pcd"))) == 2
    res = runner.invoke(app, ["eval-lidar", str(tmp_path / "gen"), str(tmp_path / "gen")])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    assert out["jsd"] == 0.0 and out["chamfer_m"] == 0.0 and out["n_paired"] == 2
    res = runner.invoke(app, ["lidar", root, "--out", str(tmp_path / "x"), "--model", "learned"])
    assert res.exit_code != 0 and "--ckpt" in res.output
