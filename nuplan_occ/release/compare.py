"""A side-by-side top-down picture of one frame of two datasets: release | ours | difference.

Top-down view: each (x, y) column shows the label of its highest occupied voxel in the label palette;
x (forward) points up, y (left) points left. Difference: per column, the most frequent disagreement
among its voxels - only in the first grid, only in the second, both occupied with different classes -
else grey where both agree on occupied voxels, white where both are empty.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nuplan_occ.labels import LabelMap

DIFF_COLORS = {
    "empty": (255, 255, 255), "agree": (190, 190, 190),
    "only_first": (214, 39, 40), "only_second": (31, 119, 180), "class_differs": (255, 127, 14),
}


def top_down(semantics: np.ndarray) -> np.ndarray:
    """(X, Y) uint8: the label of the highest occupied voxel of each column of an [x, y, z] grid (0: none)."""
    occupied = semantics > 0
    top = semantics.shape[2] - 1 - np.argmax(occupied[:, :, ::-1], axis=2)
    labels = np.take_along_axis(semantics, top[:, :, None], axis=2)[:, :, 0]
    return np.where(occupied.any(axis=2), labels, 0).astype(np.uint8)


def difference_image(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """(X, Y, 3) uint8 RGB of the per-column difference of two [x, y, z] grids (see module docstring)."""
    a, b = first > 0, second > 0
    counts = np.stack([(a & ~b).sum(axis=2), (~a & b).sum(axis=2), (a & b & (first != second)).sum(axis=2)], -1)
    names = np.array(["only_first", "only_second", "class_differs"])
    category = np.where(counts.max(axis=2) > 0, names[np.argmax(counts, axis=2)],
                        np.where((a & b).any(axis=2), "agree", "empty"))
    image = np.zeros((*category.shape, 3), dtype=np.uint8)
    for name, rgb in DIFF_COLORS.items():
        image[category == name] = rgb
    return image


def _upright(image: np.ndarray) -> np.ndarray:
    """An [x, y] image turned so x points up and y left."""
    return image[::-1, ::-1]


def render_comparison(first: np.ndarray, second: np.ndarray, labels: LabelMap, path: Path,
                      names: tuple[str, str] = ("release", "ours"), title: str = "") -> Path:
    """Write the three-panel PNG of two [x, y, z] grids of our ids to `path`; returns `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.patches as mpatches
    import matplotlib.pyplot as plt

    palette = labels.palette()
    panels = [palette[top_down(first)], palette[top_down(second)], difference_image(first, second)]
    fig, axes = plt.subplots(1, 3, figsize=(16, 6.2))
    for ax, image, name in zip(axes, panels, (*names, "difference")):
        ax.imshow(_upright(image), interpolation="nearest")
        ax.set_title(name)
        ax.set_xticks([])
        ax.set_yticks([])
    present = sorted((set(np.unique(first)) | set(np.unique(second))) - {0})
    class_patches = [mpatches.Patch(color=np.array(labels.colors[i]) / 255, label=labels.names.get(i, str(i)))
                     for i in present if i in labels.colors]
    diff_names = {"only_first": f"only {names[0]}", "only_second": f"only {names[1]}",
                  "class_differs": "class differs", "agree": "agree"}
    diff_patches = [mpatches.Patch(color=np.array(DIFF_COLORS[k]) / 255, label=v) for k, v in diff_names.items()]
    axes[1].legend(handles=class_patches, loc="upper center", bbox_to_anchor=(0.5, -0.02), ncol=5, fontsize=8)
    axes[2].legend(handles=diff_patches, loc="upper center", bbox_to_anchor=(0.5, -0.02), ncol=2, fontsize=8)
    fig.suptitle(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def render_frame_pair(first_root: str, second_root: str, token: str, path: Path) -> Path:
    """The picture of the frame of lidar_pc `token` in two dataset roots (names: their folder names)."""
    from nuplan_occ.dataset import open_dataset
    from nuplan_occ.viewer import label_map_of

    first, second = open_dataset(first_root), open_dataset(second_root)
    a = first.get(first.index_of_token(token), keys=("semantics",))["semantics"]
    b = second.get(second.index_of_token(token), keys=("semantics",))["semantics"]
    names = (Path(str(first_root)).name or "first", Path(str(second_root)).name or "second")
    return render_comparison(a, b, label_map_of(first.labels), path, names=names, title=f"token {token}")
