"""Map labels of the ground: the map's layers rasterized to a bird's-eye-view label grid (bev, from line
pieces of line_segments), aligned to the LiDAR's road paint first (map_align). Pure functions, no file I/O."""
