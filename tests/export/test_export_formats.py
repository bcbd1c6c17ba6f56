"""Export to Occ3D-style labels.npz and UniScenev2-style dense .npy; round trips through the remap."""

import json

import numpy as np
import pytest

from nuplan_occ.export.formats import (
    OCC3D_FREE, OCC3D_REMAP, ExportError, export_dataset, invert_occ3d, to_occ3d, uniscene_folder,
)
from nuplan_occ.labels import LABELS
from tools_world import SMALL, small_scene, token_of, write_dataset


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """Frame 0: every label id, both masks; frame 1: lidar mask only; frame 2: no masks."""
    rng = np.random.default_rng(3)
    ids = np.array(sorted(LABELS.names), dtype=np.uint8)
    frames = []
    for i in range(3):
        arrays = {"semantics": small_scene(i)}
        if i == 0:
            arrays["semantics"] = ids[rng.integers(0, len(ids), SMALL.shape)]
        if i < 2:
            arrays["mask_lidar"] = rng.random(SMALL.shape) < 0.5
        if i == 0:
            arrays["mask_camera"] = rng.random(SMALL.shape) < 0.3
        frames.append(arrays)
    root = tmp_path_factory.mktemp("src")
    write_dataset(root, frames)
    return str(root), frames


def test_remap_is_injective_total_and_free_is_17():
    assert set(OCC3D_REMAP) == set(LABELS.names)
    assert len(set(OCC3D_REMAP.values())) == len(OCC3D_REMAP)
    assert OCC3D_REMAP[0] == OCC3D_FREE == 17 and max(OCC3D_REMAP.values()) == 17


def test_occ3d_round_trip(source, tmp_path):
    root, frames = source
    summary = export_dataset(root, tmp_path / "occ3d", "occ3d")
    assert summary["frames"] == 3
    assert summary["frames_without"] == {"mask_lidar": 1, "mask_camera": 2}
    assert {(r["id"], r["occ3d_id"]) for r in summary["remap"]} == set(OCC3D_REMAP.items())
    for i, arrays in enumerate(frames):
        with np.load(tmp_path / "occ3d" / "gts" / f"scene-{'ab' * 8}" / token_of(i) / "labels.npz") as npz:
            assert npz["semantics"].dtype == np.uint8 and npz["semantics"].shape == SMALL.shape
            assert np.array_equal(invert_occ3d(npz["semantics"]), arrays["semantics"])
            assert np.count_nonzero(npz["semantics"] == OCC3D_FREE) == np.count_nonzero(arrays["semantics"] == 0)
            for mask in ("mask_lidar", "mask_camera"):
                assert (mask in npz.files) == (mask in arrays)
                if mask in arrays:
                    assert npz[mask].dtype == np.uint8 and set(np.unique(npz[mask])) <= {0, 1}
                    assert np.array_equal(npz[mask].astype(bool), arrays[mask])
    meta = json.loads((tmp_path / "occ3d" / "export.json").read_text())
    assert [f["token"] for f in meta["frame_list"]] == [token_of(i) for i in range(3)]
    assert meta["grid"]["axis_order"] == ["x", "y", "z"] and meta["frame_list"][1]["ego_to_global"][0][3] == 1001.0


def test_uniscene_round_trip(source, tmp_path):
    root, frames = source
    summary = export_dataset(root, tmp_path / "uni", "uniscene")
    assert all(r["id"] == r["uniscene_id"] for r in summary["remap"])
    assert [r["uniscene_name"] for r in summary["remap"] if r["id"] == 13] == ["sidewalk"]
    # no sensor metadata: the grids stay in the ego frame, and the summary says so
    assert summary["frame"] == "ego" and summary["sensors"] is False and "no sensor metadata" in summary["warnings"][0]
    for i, arrays in enumerate(frames):
        dense = np.load(tmp_path / "uni" / uniscene_folder(SMALL.shape) / f"{token_of(i)}.npy")
        assert dense.dtype == np.uint8 and np.array_equal(dense, arrays["semantics"])
    with pytest.raises(ExportError, match="no sensor metadata"):
        export_dataset(root, tmp_path / "uni2", "uniscene", frame="lidar")
    assert uniscene_folder(SMALL.shape) == "nuplan_quantized_32_32_8"


def test_bad_format_and_foreign_ids_are_errors(source, tmp_path):
    with pytest.raises(ExportError, match="format"):
        export_dataset(source[0], tmp_path / "x", "kitti")
    with pytest.raises(ExportError, match=r"ids \[9\]"):
        to_occ3d(np.array([0, 9], dtype=np.uint8))
    with pytest.raises(ExportError, match=r"Occ3D ids \[3\]"):
        invert_occ3d(np.array([3, 17], dtype=np.uint8))
