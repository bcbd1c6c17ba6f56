"""Preview picture of a synthesized frame, read back from disk: the truth (dataset format) and the written
sweep (PCD via the DB's lidar extrinsic), both in the ego frame of the truth frame.

Panels: BEV of the truth (top-most occupied voxel per column, label palette) with the sweep on top; BEV
of mask_lidar (observed voxels per column); side view (x-z) of the |y| < 1.5 m slab with its points.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from nuplan_occ.dataset import open_dataset  # noqa: E402
from nuplan_occ.io.reader import NuplanLog, points_to_ego  # noqa: E402
from nuplan_occ.io.writer import log_db_path  # noqa: E402
from nuplan_occ.labels import LABELS  # noqa: E402


def _top_label(semantics: np.ndarray) -> np.ndarray:
    """(nx, ny) label of the highest occupied voxel of each column (0 where empty)."""
    occupied = semantics > 0
    top = semantics.shape[2] - 1 - np.argmax(occupied[:, :, ::-1], axis=2)
    out = np.take_along_axis(semantics, top[:, :, None], axis=2)[:, :, 0]
    return np.where(occupied.any(axis=2), out, 0)


def _truth_item(ds, out_root: Path, frame: int, log: int) -> tuple[dict, list[str]]:
    """Truth frame number `frame` of log number `log` (sorted log names) and the sorted log names."""
    logs = ds.manifest["log"].to_pylist()
    names = sorted(set(logs))
    if not 0 <= log < len(names):
        raise ValueError(f"render_preview: {out_root / 'truth'} has {len(names)} logs, asked for log {log}")
    rows = [i for i, name in enumerate(logs) if name == names[log]]
    if not 0 <= frame < len(rows):
        raise ValueError(f"render_preview: log {names[log]} has {len(rows)} truth frames, asked for frame {frame}")
    return ds.get(rows[frame], ["semantics", "mask_lidar"]), names


def render_preview(out_root: Path, png_path: Path, frame: int = 0, log: int = 0, split: str = "mini") -> Path:
    """Write a PNG of truth frame number `frame` (0-based, among the truth frames of log number `log`)."""
    out_root = Path(out_root)
    ds = open_dataset(str(out_root / "truth"))
    try:
        item, names = _truth_item(ds, out_root, frame, log)
    finally:
        ds.close()
    grid = ds.grid
    with NuplanLog(log_db_path(out_root, split, names[log])) as nlog:
        lidar_frame = next(f for f in nlog.frames if f.token == item["token"])
        cloud = points_to_ego(nlog.load_points(lidar_frame), nlog)
    pts = cloud.xyz
    palette = LABELS.palette() / 255.0
    extent = (grid.y_max, grid.y_min, grid.x_min, grid.x_max)  # BEV: x up, y to the left
    fig, axes = plt.subplots(1, 3, figsize=(21, 7))
    bev = palette[_top_label(item["semantics"])]
    axes[0].imshow(bev, origin="lower", extent=extent)
    inside = (np.abs(pts[:, 0]) < grid.x_max) & (np.abs(pts[:, 1]) < grid.y_max)
    axes[0].scatter(pts[inside, 1], pts[inside, 0], s=0.05, c="k", alpha=0.5)
    axes[0].set_title(f"truth (top label) + sweep, {names[log]} frame {item['frame_index']}")
    axes[1].imshow(item["mask_lidar"].mean(axis=2), origin="lower", extent=extent, cmap="viridis")
    axes[1].set_title("mask_lidar: observed fraction per column")
    for ax in axes[:2]:
        ax.set_xlim(grid.y_max, grid.y_min)
        ax.set_xlabel("y (m, left)")
        ax.set_ylabel("x (m, forward)")
    j0, j1 = np.searchsorted((np.arange(grid.shape[1]) + 0.5) * grid.voxel_size + grid.y_min, [-1.5, 1.5])
    slab = item["semantics"][:, j0:j1, :]
    side_label = np.zeros((grid.shape[0], grid.shape[2]), np.uint8)
    for j in range(slab.shape[1]):
        side_label = np.where(slab[:, j, :] > 0, slab[:, j, :], side_label)
    axes[2].imshow(palette[side_label].transpose(1, 0, 2), origin="lower", aspect="auto",
                   extent=(grid.x_min, grid.x_max, grid.z_min, grid.z_max))
    sel = inside & (np.abs(pts[:, 1]) < 1.5)
    axes[2].scatter(pts[sel, 0], pts[sel, 2], s=0.3, c="k")
    axes[2].set_ylim(grid.z_min, grid.z_max)
    axes[2].set_xlabel("x (m)")
    axes[2].set_ylabel("z (m)")
    axes[2].set_title("side view |y| < 1.5 m: truth + points")
    fig.tight_layout()
    png_path = Path(png_path)
    png_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png_path, dpi=90)
    plt.close(fig)
    return png_path
