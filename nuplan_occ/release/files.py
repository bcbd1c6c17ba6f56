"""The release's files: which folders hold frames, and the content of one frame file.

Layouts (what is known of the release; the hosted files could not be inspected, so readers are tolerant):
    sparse4  `dense_voxels_with_semantic/<scene or sample token>/<lidar_pc token>.npz`, key `occ`: int
             [N, 4] rows (x index, y index, z index, label) of occupied voxels;
    sparse2  the same files with [N, 2] rows (flat index, label); the flat index is C order over
             [x, y, z] of the 400 x 400 x 32 grid (x slowest: i = (x * 400 + y) * 32 + z, what
             `reshape(-1)` of our [x, y, z] arrays gives) unless told "zyx" (OpenScene's order, x fastest);
    dense    `nuplan_quantized_<X>_<Y>_<Z>/<lidar_pc token>.npy`: dense [X, Y, Z] integer ids (0 empty).
Sparse files of one folder may mix sparse4 and sparse2 under layout "auto" (detected per file by the
number of columns). Files are loaded with `allow_pickle=False`: a pickled array is a malformed file.
"""

from __future__ import annotations

import re
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nuplan_occ.release.errors import ReleaseFrameError, ReleaseImportError

SPARSE_ROOT = "dense_voxels_with_semantic"
SPARSE_SHAPE = (400, 400, 32)
LAYOUTS = ("auto", "sparse4", "sparse2", "dense")
FLAT_ORDERS = ("xyz", "zyx")
_DENSE_FOLDER = re.compile(r"^nuplan_quantized_(\d+)_(\d+)_(\d+)$")
_READ_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile)
_MAGIC = {"dense": (b"\x93NUMPY", ".npy array"), "sparse": (b"PK\x03\x04", ".npz archive")}


@dataclass(frozen=True)
class ReleaseFolder:
    """One folder of frame files: name (scene/sample token or nuplan_quantized_X_Y_Z), kind "sparse" or
    "dense", grid shape [X, Y, Z] and its files sorted by name (the file stem is the lidar_pc token)."""

    name: str
    path: Path
    kind: str
    shape: tuple[int, int, int]
    files: tuple[Path, ...]


@dataclass
class ReleaseFrame:
    """One file's content in source ids: `labels` (N,) with `voxels` (N, 3) [x, y, z] indices (sparse),
    or `labels` dense [X, Y, Z] with `voxels` None (0 = empty). `layout`: sparse4, sparse2 or dense."""

    layout: str
    labels: np.ndarray
    voxels: np.ndarray | None = None


def _dense_folders(root: Path) -> list[Path]:
    candidates = [root] if _DENSE_FOLDER.match(root.name) else sorted(root.glob("nuplan_quantized_*"))
    return [p for p in candidates if p.is_dir() and _DENSE_FOLDER.match(p.name)]


def find_folders(src: Path, layout: str) -> list[ReleaseFolder]:
    """The frame folders under `src` (a release root, its `dense_voxels_with_semantic` folder, or one
    `nuplan_quantized_X_Y_Z` folder) for `layout` (LAYOUTS). ReleaseImportError when there is none, when
    "auto" finds both kinds, or when several dense grids are present."""
    if layout not in LAYOUTS:
        raise ReleaseImportError(f"--layout {layout!r}: use one of {', '.join(LAYOUTS)}")
    src = Path(src)
    if not src.is_dir():
        raise ReleaseImportError(f"{src}: release folder not found")
    sparse_root = src if src.name == SPARSE_ROOT else src / SPARSE_ROOT
    sparse = sorted(p for p in sparse_root.iterdir() if p.is_dir()) if sparse_root.is_dir() else []
    dense = _dense_folders(src)
    if layout == "auto" and sparse and dense:
        raise ReleaseImportError(f"{src}: holds both {SPARSE_ROOT}/ and {dense[0].name}/; choose --layout")
    if layout == "dense" or (layout == "auto" and dense):
        if len(dense) != 1:
            found = ", ".join(p.name for p in dense) or "none"
            raise ReleaseImportError(f"{src}: expected one nuplan_quantized_<X>_<Y>_<Z>/ folder, found {found}")
        shape = tuple(int(v) for v in _DENSE_FOLDER.match(dense[0].name).groups())
        return [ReleaseFolder(dense[0].name, dense[0], "dense", shape, tuple(sorted(dense[0].glob("*.npy"))))]
    if not sparse:
        raise ReleaseImportError(f"{src}: no {SPARSE_ROOT}/<token>/ folders and no nuplan_quantized_<X>_<Y>_<Z>/ "
                                 f"folder (layout {layout})")
    return [ReleaseFolder(p.name, p, "sparse", SPARSE_SHAPE, tuple(sorted(p.glob("*.npz")))) for p in sparse]


def _integer_array(array: np.ndarray, what: str) -> np.ndarray:
    if not np.issubdtype(array.dtype, np.integer):
        raise ReleaseFrameError(f"{what} has dtype {array.dtype}, expected integers")
    return array.astype(np.int64)


def _sparse_voxels(occ: np.ndarray, layout: str, shape: tuple[int, int, int], flat_order: str) -> ReleaseFrame:
    columns = occ.shape[1] if occ.ndim == 2 else None
    detected = {4: "sparse4", 2: "sparse2"}.get(columns)
    if detected is None or layout not in ("auto", detected):
        expected = {"auto": "[N, 4] or [N, 2]", "sparse4": "[N, 4]", "sparse2": "[N, 2]"}[layout]
        raise ReleaseFrameError(f"occ has shape {list(occ.shape)}, expected {expected}")
    occ = _integer_array(occ, "occ")
    if detected == "sparse4":
        voxels = occ[:, :3]
        outside = np.any((voxels < 0) | (voxels >= np.array(shape)), axis=1)
        if outside.any():
            raise ReleaseFrameError(f"{int(outside.sum())} voxel indices outside the {shape} grid")
        return ReleaseFrame(detected, occ[:, 3], voxels)
    flat, size = occ[:, 0], int(np.prod(shape))
    outside = (flat < 0) | (flat >= size)
    if outside.any():
        raise ReleaseFrameError(f"{int(outside.sum())} flat indices outside [0, {size})")
    if flat_order == "xyz":
        voxels = np.stack(np.unravel_index(flat, shape), axis=1)
    else:
        voxels = np.stack(np.unravel_index(flat, shape[::-1]), axis=1)[:, ::-1]
    return ReleaseFrame(detected, occ[:, 1], voxels)


def read_frame(path: Path, folder: ReleaseFolder, layout: str, flat_order: str = "xyz") -> ReleaseFrame:
    """The content of one frame file of `folder`; ReleaseFrameError (the failure reason) if it is malformed."""
    if flat_order not in FLAT_ORDERS:
        raise ReleaseImportError(f"flat index order {flat_order!r}: use one of {FLAT_ORDERS}")
    magic, what = _MAGIC[folder.kind]
    try:
        with open(path, "rb") as handle:
            head = handle.read(len(magic))
        if head != magic:
            raise ReleaseFrameError(f"not an {what} (starts with {head!r})")
        if folder.kind == "dense":
            array = np.load(path, allow_pickle=False)
            if not isinstance(array, np.ndarray) or array.shape != folder.shape:
                raise ReleaseFrameError(f"array has shape {list(getattr(array, 'shape', []))}, "
                                        f"expected {list(folder.shape)}")
            return ReleaseFrame("dense", _integer_array(array, "array"))
        loaded = np.load(path, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise ReleaseFrameError("not an .npz archive")
        with loaded as npz:
            if "occ" not in npz.files:
                raise ReleaseFrameError(f"no 'occ' array (holds {npz.files})")
            occ = npz["occ"]
        return _sparse_voxels(occ, layout, folder.shape, flat_order)
    except ReleaseFrameError:
        raise
    except _READ_ERRORS as exc:
        raise ReleaseFrameError(f"cannot read ({type(exc).__name__}: {exc})") from None


def densify(frame: ReleaseFrame, our_ids: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """uint8 [X, Y, Z] grid of our ids: `our_ids` (the frame's labels mapped, same shape) placed at its
    voxels (sparse; a voxel listed twice keeps its last row) or as is (dense)."""
    if frame.voxels is None:
        return np.ascontiguousarray(our_ids, dtype=np.uint8)
    grid = np.zeros(shape, dtype=np.uint8)
    grid[frame.voxels[:, 0], frame.voxels[:, 1], frame.voxels[:, 2]] = our_ids
    return grid
