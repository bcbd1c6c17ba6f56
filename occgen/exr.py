"""OpenEXR files of rendered camera maps (OpenEXR python package 3.x, `OpenEXR.File`).

Channels of one file (scanline image, ZIP compression, all full resolution):
    "depth"    FLOAT  metres along the camera's optical axis (camera z), 0 where nothing was rendered;
    "alpha"    FLOAT  accumulated opacity A of the composited Gaussians, in [0, 1];
    "semantic" UINT   semantic id (nuplan_occ.labels), 0 (empty) where nothing was rendered.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR

CHANNELS = ("depth", "alpha", "semantic")


class MapFileError(ValueError):
    """An EXR map file that lacks a channel or whose channels disagree; names the file."""

    def __init__(self, path: str | Path, problem: str):
        super().__init__(f"{path}: {problem}")


def write_maps_exr(path: str | Path, depth: np.ndarray, alpha: np.ndarray, semantic: np.ndarray) -> None:
    """Write one camera's (H, W) maps to `path`."""
    shapes = {np.shape(depth), np.shape(alpha), np.shape(semantic)}
    if len(shapes) != 1 or len(np.shape(depth)) != 2:
        raise MapFileError(path, f"maps must share one (H, W) shape, got {sorted(shapes)}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    channels = {
        "depth": np.ascontiguousarray(depth, dtype=np.float32),
        "alpha": np.ascontiguousarray(alpha, dtype=np.float32),
        "semantic": np.ascontiguousarray(semantic, dtype=np.uint32),
    }
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))


def read_maps_exr(path: str | Path) -> dict[str, np.ndarray]:
    """The (H, W) maps of a file written by `write_maps_exr`: depth, alpha float32; semantic uint8."""
    if not Path(path).is_file():
        raise MapFileError(path, "no such EXR file")
    with OpenEXR.File(str(path)) as f:
        channels = {name: np.array(ch.pixels) for name, ch in f.channels().items()}
    missing = [c for c in CHANNELS if c not in channels]
    if missing:
        raise MapFileError(path, f"EXR lacks channel(s) {', '.join(missing)}")
    return {
        "depth": channels["depth"].astype(np.float32),
        "alpha": channels["alpha"].astype(np.float32),
        "semantic": channels["semantic"].astype(np.uint8),
    }
