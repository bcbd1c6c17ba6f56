"""Batches of semantic clips from a dataset (`nuplan_occ.torch.OccupancyDataset`), cropped in x and y.

A crop of `crop` x `crop` cells keeps the full z range; its lower corner is (i0, j0) cells from the grid's
lower corner, i.e. at (x_min + i0*s, y_min + j0*s) metres in the ego frame.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import torch

from nuplan_occ.torch import OccupancyDataset
from occgen.configs import CLASS_IDS


class NoClipsError(ValueError):
    """A dataset holds no clip of the length (and subset) a model trains on."""


def open_clips(path: str, clip_len: int = 1, subset: str | None = None) -> OccupancyDataset:
    """Clips of `clip_len` frames; NoClipsError if the dataset has none."""
    dataset = OccupancyDataset(str(path), clip_len=clip_len, subset=subset)
    if len(dataset) == 0:
        raise NoClipsError(f"{path}: no clip of {clip_len} consecutive frames of one scene (subset {subset!r})")
    return dataset


def crop_origin(size: tuple[int, int], crop: int | None, generator: torch.Generator | None) -> tuple[int, int]:
    """Lower corner (i0, j0) of a crop: random if a generator is given, else centred."""
    if crop is None:
        return 0, 0
    if crop > min(size):
        raise ValueError(f"crop {crop} is larger than the grid {size}")
    if generator is None:
        return (size[0] - crop) // 2, (size[1] - crop) // 2
    return tuple(int(torch.randint(0, n - crop + 1, (1,), generator=generator)) for n in size)  # type: ignore


def load_clip(dataset: OccupancyDataset, index: int, crop: int | None,
              generator: torch.Generator | None = None) -> tuple[torch.Tensor, tuple[int, int]]:
    """Clip `index` as long [T, crop, crop, Z] and its crop origin (cells); ValueError on unknown ids."""
    sem = dataset[index]["semantics"]
    unknown = sorted(set(torch.unique(sem).tolist()) - set(CLASS_IDS))
    if unknown:
        raise ValueError(f"clip {index} of the dataset holds ids {unknown} outside the label map")
    i0, j0 = crop_origin(tuple(sem.shape[1:3]), crop, generator)
    if crop is not None:
        sem = sem[:, i0:i0 + crop, j0:j0 + crop]
    return sem.long(), (i0, j0)


def semantics_batches(dataset: OccupancyDataset, batch_size: int, crop: int | None,
                      generator: torch.Generator, indices: Sequence[int] | None = None) -> Iterator[torch.Tensor]:
    """Endless random batches long [B, T, crop, crop, Z] drawn from the clips `indices` (default all)."""
    pool = list(range(len(dataset))) if indices is None else list(indices)
    while True:
        picks = torch.randint(0, len(pool), (batch_size,), generator=generator)
        yield torch.stack([load_clip(dataset, pool[int(k)], crop, generator)[0] for k in picks])
