"""nuplan-occ: dense semantic occupancy grids from nuPlan logs."""

__version__ = "0.1.0"
