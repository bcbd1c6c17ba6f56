"""Voxelization, ground labeling, visibility masks, instance ids and flow of one frame (pure functions,
no file I/O). All grids follow nuplan_occ/grid.py: ego frame, indexed [x, y, z]."""
