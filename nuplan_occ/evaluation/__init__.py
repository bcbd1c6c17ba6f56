"""Quality figures against known truth: whole datasets compared frame by frame (datasets), semantic grids
(grid_metrics), reconstructed surfaces (surfaces) and the aggregation steps (step_metrics)."""
