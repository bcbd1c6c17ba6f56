"""nuplan-occ: dense semantic occupancy grids from nuPlan logs.

Public dataset API: `nuplan_occ.open_dataset(path_or_url)` and `nuplan_occ.torch.OccupancyDataset`.
"""

__version__ = "0.1.0"


def open_dataset(path_or_url: str):
    """Open a built dataset (local path or fsspec URL); see `nuplan_occ.dataset.OccDataset`."""
    from nuplan_occ.dataset import open_dataset as _open

    return _open(path_or_url)


__all__ = ["__version__", "open_dataset"]
