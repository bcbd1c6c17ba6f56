"""`nuplan-occ report` on the shared e2e builds: a page per scene, every picture referenced exists and
decodes, every local link resolves, flag rules fire where a frame failed and where a box got no voxel,
and a rerun renders only the scenes whose rows changed."""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from urllib.parse import unquote

import matplotlib.image
import numpy as np
import pytest
from typer.testing import CliRunner

from nuplan_occ.cli import app
from nuplan_occ.report import write_report
from nuplan_occ.report.scenes import page_id
from nuplan_occ.storage import DatasetWriter, read_manifest, read_metadata

pytestmark = pytest.mark.slow

_REF = re.compile(r'(?:src|href)="([^"#]*)(?:#[^"]*)?"')


def local_refs(report: Path) -> dict[Path, list[Path]]:
    """Every html page of the report -> the local files its src/href attributes name."""
    refs = {}
    for page in report.rglob("*.html"):
        text = page.read_text()
        assert "http://" not in text and "https://" not in text, f"{page} references the network"
        refs[page] = [(page.parent / unquote(target)).resolve() for target in _REF.findall(text) if target]
    return refs


def scene_names(root: Path) -> set[str]:
    rows = read_manifest(str(root)).select(["log", "scene_name"]).to_pylist()
    return {page_id(r["log"], r["scene_name"]) for r in rows}


def test_report_of_the_reference_build_has_every_scene_and_picture(reference_build, tmp_path):
    report = tmp_path / "report"
    result = CliRunner().invoke(app, ["report", str(reference_build), "--out", str(report), "--every", "2"])
    assert result.exit_code == 0, result.output
    assert f"report written to {report / 'index.html'}" in result.output

    scenes = scene_names(reference_build)
    assert {p.name for p in (report / "scenes").iterdir()} == scenes
    refs = local_refs(report)
    assert all(report / "scenes" / s / "index.html" in refs for s in scenes)
    images = set()
    for page, targets in refs.items():
        for target in targets:
            assert target.exists(), f"{page} links to missing {target}"
            if target.suffix == ".png":
                images.add(target)
    for image in images:
        pixels = matplotlib.image.imread(image)
        assert pixels.ndim == 3 and min(pixels.shape[:2]) >= 100, image
    ok_frames = len([s for s in read_manifest(str(reference_build))["status"].to_pylist() if s == "ok"])
    thumbnails = [p for p in images if p.name.startswith("top-")]
    assert len(thumbnails) >= ok_frames // 2  # every other frame of each scene, at least
    # a thumbnail is the grid seen from above: mostly ground colours, the ego marked in white at the centre
    picture = matplotlib.image.imread(sorted(thumbnails)[0])
    assert np.allclose(picture[200, 200, :3], 1.0)
    assert (picture[..., :3].reshape(-1, 3).std(axis=0) > 0.05).all()
    assert "No frame failed." in (report / "index.html").read_text()

    again = write_report(str(reference_build), report, every=2)
    assert (again.rendered, again.reused) == (0, len(scenes))
    assert again.rule_frames["failed"] == 0 and "unlabeled_boxes" in again.rule_frames  # the build has its columns


def test_report_flags_the_failed_frames_of_a_damaged_build(bad_blobs_build, tmp_path):
    result = write_report(str(bad_blobs_build.out), tmp_path / "report")
    gallery = (tmp_path / "report" / "gallery-001.html").read_text()
    index = (tmp_path / "report" / "index.html").read_text()
    for frame in (bad_blobs_build.corrupt, bad_blobs_build.missing):
        assert frame.token in gallery
    assert result.rule_frames["failed"] == 2
    assert "truncated PCD" in index
    assert re.search(r'badge failed">failed</span></td><td>[^<]*</td><td class="n" data-v="2.0">2<', index)
    for page, targets in local_refs(tmp_path / "report").items():
        assert all(t.exists() for t in targets), page


def _recommit(root: Path, change) -> None:
    """Publish the rows of `root` again with `change(rows)` applied, through the dataset writer."""
    rows = read_manifest(str(root)).to_pylist()
    change(rows)
    metadata = read_metadata(str(root))
    DatasetWriter(str(root), {"params": metadata["params"], "software": metadata["software"]}).commit(rows)


def test_report_flags_a_box_without_voxels_and_renders_only_changed_scenes(reference_build, tmp_path):
    root = tmp_path / "dataset"
    shutil.copytree(reference_build, root, ignore=shutil.ignore_patterns("work"))
    rows = read_manifest(str(root)).to_pylist()
    boxed = [r for r in rows if r["status"] == "ok" and r["qa_boxes_with_points"]]
    first, other = boxed[0], next(r for r in boxed if r["scene_token"] != boxed[0]["scene_token"])
    already = sum(r["qa_boxes_with_points"] > r["qa_boxes_labeled"] for r in rows if r["status"] == "ok")

    def lose_a_box(tokens):
        def change(rows):
            for r in rows:
                if r["token"] in tokens:
                    r["qa_boxes_labeled"] = r["qa_boxes_with_points"] - 1
        return change

    report = tmp_path / "report"
    write_report(str(root), report)
    _recommit(root, lose_a_box({first["token"]}))
    result = write_report(str(root), report)
    assert result.rendered == 1  # only the scene whose rows changed
    gallery = (report / "gallery-001.html").read_text()
    assert result.rule_frames["unlabeled_boxes"] == already + 1 and first["token"] in gallery
    scene_page = (report / "scenes" / page_id(first["log"], first["scene_name"]) / "index.html").read_text()
    assert "unlabeled_boxes" in scene_page

    _recommit(root, lose_a_box({first["token"], other["token"]}))
    result = write_report(str(root), report)
    assert result.rendered == 1 and result.rule_frames["unlabeled_boxes"] == already + 2
    assert other["token"] in (report / "gallery-001.html").read_text()
