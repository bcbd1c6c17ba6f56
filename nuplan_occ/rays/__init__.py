"""What sensors see through the grid: voxel traversal of rays (traversal), LiDAR and camera visibility
masks (visibility) and free-space clearing of voxels rays crossed (free_space). Pure functions, no file I/O."""
