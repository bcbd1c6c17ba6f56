"""Ego-pose refinement: multi-stage point-to-plane ICP of each sweep's background against its neighbours,
with the logged motion as the prior (register), its linearised solve (point_to_plane) and the nearest-
neighbour queries that follow a converging pose (tracked_nearest). Pure functions, no file I/O."""
