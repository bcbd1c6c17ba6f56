"""One frame's occupied voxels projected into a camera image with the calibration of the UniScene export.

    python -m benchmarks.camera_projection DATASET DATA_ROOT --png docs/camera_projection.png [--index 0]
        [--camera CAM_F0] [--work /tmp/projection]

Exports the dataset (`export --format uniscene`: LiDAR-frame grids and nuplan_infos.pkl; sensor metadata
added first to a copy's sidecars when the dataset has none), reads the frame's grid and camera record back
from the info file as a consumer would, projects the voxel centres (the nearest voxel per pixel, what the
camera sees) and draws three panels: the camera image, the projected voxels in their class colours over it (dimmed),
and per pixel whether the image shows the voxel's class (green) or another (red; the synthetic images are
label colours shaded by depth, `synth.camera_render.pixel_labels` reads them back). Prints the agreement.
"""

from __future__ import annotations

import argparse
import pickle
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from nuplan_occ.dataset import open_dataset
from nuplan_occ.export.formats import export_dataset
from nuplan_occ.export.infos import nearest_per_pixel, project_to_image
from nuplan_occ.grid import GridSpec
from nuplan_occ.io.data_root import resolve_logs, sensor_root_for
from nuplan_occ.labels import LABELS
from nuplan_occ.sensors import add_sensors
from nuplan_occ.synth.camera_render import pixel_labels


def projection_panels(dest: Path, blobs: Path, index: int, channel: str) -> tuple[np.ndarray, float, int]:
    """(H, 3 W, 3) uint8 panels of frame `index` of the export at dest, share of seen voxels whose class the
    image shows, number of seen voxels."""
    with open(dest / "nuplan_infos.pkl", "rb") as f:
        record = pickle.load(f)["infos"][index]
    occ = np.load(dest / record["occ_path"])
    grid = GridSpec()  # the export's grid: our bounds around the LiDAR
    idx = np.argwhere(occ > 0)
    labels = occ[tuple(idx.T)]
    camera = record["cams"][channel]
    uv, depth = project_to_image(grid.index_to_center(idx), camera)
    seen = nearest_per_pixel(uv, depth, camera["width"], camera["height"])
    image = np.asarray(Image.open(blobs / camera["data_path"]).convert("RGB"))
    cells = np.floor(uv[seen] + 0.5).astype(np.int64)
    rows, cols = cells[:, 1], cells[:, 0]
    shown = pixel_labels(image[rows, cols], depth[seen])
    agree = shown == labels[seen]
    overlay = (image * 0.3).astype(np.uint8)
    overlay[rows, cols] = LABELS.palette()[labels[seen]]
    check = (image * 0.4).astype(np.uint8)
    check[rows, cols] = np.where(agree[:, None], [40, 200, 40], [230, 40, 40])
    return np.concatenate([image, overlay, check], axis=1), float(agree.mean()), len(seen)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset")
    parser.add_argument("data_root", type=Path)
    parser.add_argument("--png", type=Path, default=Path("docs/camera_projection.png"))
    parser.add_argument("--index", type=int, default=0)
    parser.add_argument("--camera", default="CAM_F0")
    parser.add_argument("--work", type=Path, default=Path("/tmp/camera_projection"))
    args = parser.parse_args()
    dataset = args.dataset
    if not open_dataset(dataset).has_sensors:
        copy = args.work / "dataset"
        shutil.rmtree(copy, ignore_errors=True)
        shutil.copytree(dataset, copy, ignore=shutil.ignore_patterns("work"))
        add_sensors(str(copy), args.data_root)
        dataset = str(copy)
    dest = args.work / "uniscene"
    shutil.rmtree(dest, ignore_errors=True)
    export_dataset(dataset, dest, "uniscene")
    log = open_dataset(dataset).identity(args.index)["log_name"]
    db = resolve_logs(args.data_root, split=None, log_names=[log])[0]
    panels, share, seen = projection_panels(dest, sensor_root_for(db, args.data_root), args.index, args.camera)
    args.png.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(panels).save(args.png)
    print(f"{args.png}: frame {args.index}, {args.camera}: {seen} voxels seen, {share:.1%} on pixels of their class")


if __name__ == "__main__":
    main()
