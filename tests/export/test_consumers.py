"""Sensor metadata and the consumers' layouts on a real build of the shared synthetic log (8 cameras with
rendered images): UniScene v2's info pickle and LiDAR-frame grids, Occ3D-style gts/<scene>/<token>/labels.npz
with its info file, and the round trip: voxels projected with the exported calibration land on image pixels of
their class. Conventions checked are the consumers' documented ones (file names, keys, dtypes, frames)."""

import os
import pickle
import shutil
from pathlib import Path

import duckdb
import numpy as np
import pyarrow.parquet as pq
import pytest
from PIL import Image

from nuplan_occ.dataset import open_dataset
from nuplan_occ.export.formats import OCC3D_FREE, export_dataset, invert_occ3d
from nuplan_occ.export.infos import nearest_per_pixel, project_to_image
from nuplan_occ.geometry import make_transform, quaternion_to_matrix
from nuplan_occ.grid import GridSpec
from nuplan_occ.io.reader import NuplanLog
from nuplan_occ.io.types import CAMERA_CHANNELS
from nuplan_occ.sensors import add_sensors
from nuplan_occ.storage.sensors import MissingSensorsError
from nuplan_occ.synth.camera_render import pixel_labels
from nuplan_occ.synth.lidar import T_EGO_FROM_LIDAR

BLOBS = Path("nuplan-v1.1") / "sensor_blobs"


@pytest.fixture(scope="module")
def built(synthetic_root, tmp_path_factory):
    """(data root, the build as a dataset built before sensors (its sensors/ removed), the build (sensors
    written by it), the old one with sensors added by add_sensors, add_sensors' summary)."""
    from nuplan_occ.pipeline.build import run_build
    from nuplan_occ.stages import PIPELINE
    from pipeline_helpers import build_params

    base = tmp_path_factory.mktemp("consumers")
    new = base / "new"
    assert run_build(synthetic_root, str(new), build_params(), pipeline=PIPELINE).sensor_problems == []
    old = base / "old"
    shutil.copytree(new, old, ignore=shutil.ignore_patterns("work"))
    shutil.rmtree(old / "sensors")
    added = base / "added"
    shutil.copytree(old, added)
    return synthetic_root, str(old), str(new), str(added), add_sensors(str(added), synthetic_root)


@pytest.fixture(scope="module")
def exports(built, tmp_path_factory):
    new = built[2]
    base = tmp_path_factory.mktemp("exports")
    return {name: (base / name, export_dataset(new, base / name, fmt, **kw)) for name, fmt, kw in (
        ("uniscene", "uniscene", {}), ("occ3d", "occ3d", {}), ("occ3d_coarse", "occ3d", {"grid": "occ3d"}),
        ("uniscene_ego", "uniscene", {"frame": "ego"}))}


def _pose(translation, quaternion) -> np.ndarray:
    return make_transform(quaternion_to_matrix(np.asarray(quaternion)), np.asarray(translation))


def test_sensor_metadata_per_frame(built):
    data_root, old, new, added, summary = built
    ds = open_dataset(new)
    assert ds.has_sensors  # written by the build
    assert summary["problems"] == [] and summary["frames"] == len(ds) and summary["without_image"] == 0
    assert summary["rows"] == 8 * len(ds)
    # added to the older dataset: the same tables the build wrote
    for path in sorted((Path(new) / "sensors").rglob("*.parquet")):
        assert pq.read_table(path).equals(pq.read_table(Path(added) / path.relative_to(new)))
    db = next((data_root / "nuplan-v1.1" / "splits" / "mini").glob("*.db"))
    with NuplanLog(db) as log:
        cameras = {c.channel: c for c in log.cameras}
        filenames = {f.token: f.filename for f in log.frames}
    for i in (0, len(ds) - 1):
        identity, sensors = ds.identity(i), ds.sensors(i)
        assert np.allclose(sensors["lidar_to_ego"], T_EGO_FROM_LIDAR)
        assert sensors["lidar_filename"] == filenames[identity["token"]]
        assert sorted(sensors["cameras"]) == sorted(CAMERA_CHANNELS)
        for channel, cam in sensors["cameras"].items():
            truth = cameras[channel]
            assert np.array_equal(cam["intrinsic"], truth.K) and np.array_equal(cam["distortion"], truth.distortion)
            assert np.array_equal(cam["camera_to_ego"], truth.T_ego_from_camera)
            # synthetic images are taken at the sweep's time, so the nearest one is at the frame's time
            assert cam["image_timestamp_us"] == identity["timestamp_us"]
            assert np.allclose(cam["image_ego_to_frame_ego"], np.eye(4))
            assert (data_root / cam["image_path"]).is_file()
            assert cam["image_path"] == f"{BLOBS.as_posix()}/{cam['image_filename']}"
    # DuckDB reads the sidecars as they are
    rows = duckdb.sql(f"SELECT count(*), count(DISTINCT token) FROM read_parquet('{new}/sensors/*/*.parquet') "
                      "WHERE channel = 'CAM_F0' AND image_path IS NOT NULL").fetchall()
    assert rows == [(len(ds), len(ds))]
    # a dataset built before sensors: a clear answer
    before = open_dataset(old)
    assert not before.has_sensors
    with pytest.raises(MissingSensorsError, match="no sensor metadata"):
        before.sensors(0)


def test_uniscene_layout(built, exports):
    data_root, new = built[0], built[2]
    dest, summary = exports["uniscene"]
    ds = open_dataset(new)
    assert summary["frame"] == "lidar" and summary["sensors"] and summary["frames"] == len(ds)
    assert summary["frames_without_cameras"] == 0 and summary["warnings"] == []
    with open(dest / "nuplan_infos.pkl", "rb") as f:
        infos = pickle.load(f)
    records = infos["infos"]
    assert len(records) == len(ds)
    # scene_tokens: every token once, grouped by scene, in time order
    assert sorted(t for scene in infos["scene_tokens"] for t in scene) == sorted(r["token"] for r in records)
    by_token = {r["token"]: r for r in records}
    for scene in infos["scene_tokens"]:
        assert len({by_token[t]["scene_token"] for t in scene}) == 1
        assert [by_token[t]["timestamp"] for t in scene] == sorted(by_token[t]["timestamp"] for t in scene)
    for r in records:
        occ = np.load(dest / "nuplan_quantized_400_400_32" / f"{r['token']}.npy")
        assert occ.dtype == np.uint8 and occ.shape == (400, 400, 32) and r["occ_path"].endswith(f"{r['token']}.npy")
        assert (data_root / BLOBS / r["lidar_path"]).is_file()
        assert np.allclose(_pose(r["lidar2ego_translation"], r["lidar2ego_rotation"]), T_EGO_FROM_LIDAR)
        assert np.allclose(_pose(r["ego2global_translation"], r["ego2global_rotation"]), r["ego2global"])
        assert list(r["cams"]) == list(CAMERA_CHANNELS) or sorted(r["cams"]) == sorted(CAMERA_CHANNELS)
        for channel, cam in r["cams"].items():
            assert (data_root / BLOBS / cam["data_path"]).is_file() and cam["type"] == channel
            assert cam["cam_intrinsic"].shape == (3, 3) and cam["distortion"].shape == (5,)
            R, t = cam["sensor2lidar_rotation"], cam["sensor2lidar_translation"]
            assert R.shape == (3, 3) and t.shape == (3,) and np.allclose(R @ R.T, np.eye(3))
            # sensor2lidar = inverse(lidar2ego) @ sensor2ego (image at the sweep's time)
            expected = np.linalg.inv(T_EGO_FROM_LIDAR) @ _pose(cam["sensor2ego_translation"], cam["sensor2ego_rotation"])
            assert np.allclose(make_transform(R, t), expected, atol=1e-9)
    assert all(row["id"] == row["uniscene_id"] for row in summary["remap"])


def test_occ3d_layout(built, exports):
    new = built[2]
    ds = open_dataset(new)
    for name, shape in (("occ3d", (400, 400, 32)), ("occ3d_coarse", (200, 200, 16))):
        dest, summary = exports[name]
        assert summary["frame"] == "ego" and summary["grid"]["shape"] == list(shape)
        with open(dest / "occ_infos.pkl", "rb") as f:
            records = pickle.load(f)["infos"]
        assert len(records) == len(ds)
        for r in records:
            # loaders join "labels.npz" to occ_path; the folder is gts/<scene>/<token>
            assert r["occ_path"] == f"gts/scene-{r['scene_token']}/{r['token']}" == f"gts/{r['scene_name']}/{r['token']}"
            assert r["nuplan_scene_name"].startswith("scene-")
            with np.load(os.path.join(dest, r["occ_path"], "labels.npz")) as npz:
                assert sorted(npz.files) == ["mask_camera", "mask_lidar", "semantics"]
                for key in npz.files:
                    assert npz[key].dtype == np.uint8 and npz[key].shape == shape
                assert set(np.unique(npz["mask_camera"])) <= {0, 1} and OCC3D_FREE in npz["semantics"]
                if name == "occ3d_coarse":  # Occ3D's top layer lies above our grid: free and never observed
                    assert not npz["mask_lidar"][..., 15].any() and np.all(npz["semantics"][..., 15] == OCC3D_FREE)
            assert np.allclose(_pose(r["ego2global_translation"], r["ego2global_rotation"]), r["ego2global"])
            assert np.allclose(_pose(r["lidar2ego_translation"], r["lidar2ego_rotation"]), T_EGO_FROM_LIDAR)
            assert sorted(r["cams"]) == sorted(CAMERA_CHANNELS)
            # grids in the ego frame: sensor2lidar places the cameras in the ego frame
            for cam in r["cams"].values():
                placed = make_transform(cam["sensor2lidar_rotation"], cam["sensor2lidar_translation"])
                assert np.allclose(placed, _pose(cam["sensor2ego_translation"], cam["sensor2ego_rotation"]))


def _agreement(dest: Path, record: dict, semantics: np.ndarray, grid: GridSpec, blobs: Path) -> tuple[float, int]:
    """Share of the voxels each camera sees (nearest per pixel) whose class the image shows at that pixel."""
    idx = np.argwhere(semantics > 0)
    centres, labels = grid.index_to_center(idx), semantics[tuple(idx.T)]
    agree = seen_total = 0
    for cam in record["cams"].values():
        uv, depth = project_to_image(centres, cam)
        seen = nearest_per_pixel(uv, depth, cam["width"], cam["height"])
        rgb = np.asarray(Image.open(blobs / cam["data_path"]).convert("RGB"))
        cells = np.floor(uv[seen] + 0.5).astype(np.int64)
        shown = pixel_labels(rgb[cells[:, 1], cells[:, 0]], depth[seen])
        agree += int(np.count_nonzero(shown == labels[seen]))
        seen_total += len(seen)
    return agree / seen_total, seen_total


def test_round_trip_voxels_land_on_pixels_of_their_class(built, exports):
    data_root = built[0]
    dest, _ = exports["uniscene"]
    ego_dest, _ = exports["uniscene_ego"]
    with open(dest / "nuplan_infos.pkl", "rb") as f:
        record = pickle.load(f)["infos"][0]
    with open(ego_dest / "nuplan_infos.pkl", "rb") as f:
        ego_record = pickle.load(f)["infos"][0]
    grid = GridSpec()  # UniScene's grid: [-50, 50]^2 x [-3, 5] m at 0.25 m, here around the LiDAR
    lidar_grid = np.load(dest / record["occ_path"])
    share, seen = _agreement(dest, record, lidar_grid, grid, data_root / BLOBS)
    assert seen > 10_000 and share > 0.75
    # the ego-frame export with its own (ego-frame) camera placement agrees as well ...
    ego_grid = np.load(ego_dest / ego_record["occ_path"])
    assert _agreement(ego_dest, ego_record, ego_grid, grid, data_root / BLOBS)[0] > 0.75
    # ... but the ego-frame grid read as if it were in the LiDAR frame (the shift the issue describes) does not
    assert _agreement(dest, record, ego_grid, grid, data_root / BLOBS)[0] < 0.5


def test_occ3d_export_keeps_ids_invertible(exports):
    dest, _ = exports["occ3d"]
    with open(dest / "occ_infos.pkl", "rb") as f:
        record = pickle.load(f)["infos"][0]
    with np.load(dest / record["occ_path"] / "labels.npz") as npz:
        ours = invert_occ3d(npz["semantics"])
    assert ours.max() <= 14 and np.count_nonzero(ours) > 0


def test_torch_dataset_returns_cameras_and_decoded_images(built):
    from nuplan_occ.torch import OccupancyDataset

    data_root, old, new = built[:3]
    clips = OccupancyDataset(new, clip_len=2, data_root=str(data_root))
    item = clips[0]
    ds = open_dataset(new)
    first = ds.sensors(int(clips.frame_indices(0)[0]))
    assert item["lidar_to_ego"].shape == (2, 4, 4) and np.allclose(item["lidar_to_ego"][0].numpy(), T_EGO_FROM_LIDAR)
    assert sorted(item["cams"]) == sorted(CAMERA_CHANNELS) == sorted(item["images"])
    front = item["cams"]["CAM_F0"]
    assert front["intrinsic"].shape == (2, 3, 3) and np.array_equal(front["intrinsic"][0].numpy(),
                                                                     first["cameras"]["CAM_F0"]["intrinsic"])
    image = item["images"]["CAM_F0"]
    assert image.dtype.is_floating_point is False and tuple(image.shape) == (2, 270, 480, 3)
    on_disk = np.asarray(Image.open(data_root / front["image_path"][0]).convert("RGB"))
    assert np.array_equal(image[0].numpy(), on_disk)
    with pytest.raises(MissingSensorsError, match="no sensor metadata"):
        OccupancyDataset(old, cameras=True)
