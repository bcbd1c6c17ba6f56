"""A folder of model predictions, read as semantic grids on a dataset's grid.

Files (found anywhere below the folder): `<token>.npy` (a dense array) or `<token>.npz` with the array
under the key `semantics` (our and Occ3D's labels.npz name) or, failing that, `pred` (the name Occ3D-style
submission scripts use); other keys are ignored. A file named `labels.npz` / `labels.npy` takes its token
from its folder (the `<log>/<token>/labels.npz` layout `nuplan-occ export --format occ3d` writes). Arrays
are integer (X, Y, Z) label ids indexed [x, y, z] in the frame's ego frame (nuPlan rear axle), in our ids
(0 = free; `nuplan_occ/schemas/labels.json`) or, with labels="occ3d", in the Occ3D ids our occ3d export
writes (free = 17), mapped back to ours. Files are read without unpickling.

Grid: the dataset's own, or a stated one (`parse_grid`: "occ3d" = Occ3D-nuScenes' 200 x 200 x 16 voxels
of 0.4 m over x, y in [-40, 40) m, z in [-1, 5.4) m; or "x_min,x_max,y_min,y_max,z_min,z_max,voxel_size"
in metres, same ego frame). A prediction on another grid is resampled to the dataset's: each voxel takes
the label of the prediction voxel holding its centre; voxels whose centre lies outside the prediction's
box are not covered, and the scoring leaves them out of truth and prediction alike.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from nuplan_occ.evaluation.datasets import EvaluationError
from nuplan_occ.grid import GridSpec

ARRAY_KEYS = ("semantics", "pred")
"""The .npz keys read, in order of preference."""

TOKEN_FROM_FOLDER = "labels"
"""A file of this stem takes its token from its folder's name."""

NAMED_GRIDS = {"occ3d": GridSpec(x_min=-40.0, x_max=40.0, y_min=-40.0, y_max=40.0, z_min=-1.0, z_max=5.4,
                                 voxel_size=0.4)}
"""Grids a prediction may be stated on by name."""

LABEL_SPACES = ("ours", "occ3d")
"""The label ids a prediction may be written in: ours, or those of our occ3d export."""


def parse_grid(text: str | None, default: GridSpec) -> GridSpec:
    """The grid named by `text`: None or "ours" -> `default`, a name of NAMED_GRIDS, or seven comma-separated
    numbers x_min,x_max,y_min,y_max,z_min,z_max,voxel_size (metres); EvaluationError otherwise."""
    if text is None or text == "ours":
        return default
    if text in NAMED_GRIDS:
        return NAMED_GRIDS[text]
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 7 or values[6] <= 0 or values[0] >= values[1] or values[2] >= values[3] or values[4] >= values[5]:
        raise EvaluationError(f"prediction grid {text!r}: use ours, {', '.join(NAMED_GRIDS)} or "
                              "x_min,x_max,y_min,y_max,z_min,z_max,voxel_size (metres, min < max, voxel > 0)")
    return GridSpec(*values)


def find_predictions(folder: Path) -> dict[str, Path]:
    """token -> prediction file below `folder` (module docstring); EvaluationError if the folder holds
    none or two files claim the same token."""
    folder = Path(folder)
    if not folder.is_dir():
        raise EvaluationError(f"{folder}: not a folder of predictions")
    found: dict[str, Path] = {}
    for path in sorted(p for p in folder.rglob("*") if p.suffix in (".npz", ".npy") and p.is_file()):
        token = path.parent.name if path.stem == TOKEN_FROM_FOLDER else path.stem
        if token in found:
            raise EvaluationError(f"{path}: token {token} also predicted by {found[token]}")
        found[token] = path
    if not found:
        raise EvaluationError(f"{folder}: no .npz or .npy prediction files")
    return found


def load_prediction(path: Path, shape: tuple[int, int, int], labels: str = "ours") -> np.ndarray:
    """uint8 (X, Y, Z) label ids (ours) of one prediction file of grid shape `shape`; EvaluationError
    naming the file for a missing key, another shape, a non-integer array or ids outside 0-255."""
    from nuplan_occ.export.formats import ExportError, invert_occ3d

    path = Path(path)
    try:
        loaded = np.load(path, allow_pickle=False)
        if isinstance(loaded, np.ndarray):
            array = loaded
        else:
            with loaded:
                key = next((k for k in ARRAY_KEYS if k in loaded.files), None)
                if key is None:
                    raise EvaluationError(f"{path}: no array named {' or '.join(ARRAY_KEYS)} "
                                          f"(keys: {', '.join(loaded.files) or 'none'})")
                array = loaded[key]
    except (ValueError, zipfile.BadZipFile) as exc:  # unreadable, or an object array that needs unpickling
        raise EvaluationError(f"{path}: not a readable numpy file ({exc})") from None
    if tuple(array.shape) != tuple(shape):
        raise EvaluationError(f"{path}: shape {tuple(array.shape)}, the prediction grid has {tuple(shape)}")
    if array.dtype.kind not in "iub" or (array.size and (array.min() < 0 or array.max() > 255)):
        raise EvaluationError(f"{path}: label ids must be integers 0-255 (dtype {array.dtype})")
    array = array.astype(np.uint8, copy=False)
    if labels not in LABEL_SPACES:
        raise EvaluationError(f"labels {labels!r} is not one of {', '.join(LABEL_SPACES)}")
    if labels == "occ3d":
        try:
            return invert_occ3d(array, where=str(path))
        except ExportError as exc:
            raise EvaluationError(str(exc)) from None
    return array


def resample(pred: np.ndarray, pred_grid: GridSpec, grid: GridSpec) -> tuple[np.ndarray, np.ndarray | None]:
    """(uint8 grid.shape semantics, covered bool grid.shape or None when the grids are the same): each
    voxel of `grid` takes the label of the `pred_grid` voxel holding its centre; uncovered voxels are 0."""
    if pred_grid == grid:
        return pred, None
    index, inside = [], []
    for lo, n, p_lo, p_size, p_n in zip(grid.lower, grid.shape, pred_grid.lower, [pred_grid.voxel_size] * 3,
                                       pred_grid.shape):
        centres = lo + (np.arange(n) + 0.5) * grid.voxel_size
        j = np.floor((centres - p_lo) / p_size).astype(np.int64)
        inside.append((j >= 0) & (j < p_n))
        index.append(np.clip(j, 0, p_n - 1))
    covered = inside[0][:, None, None] & inside[1][None, :, None] & inside[2][None, None, :]
    out = np.asarray(pred)[np.ix_(*index)]
    out[~covered] = 0
    return out, covered
