"""Datasets written out for other tools: grids in the layouts of Occ3D-style and UniScene code (formats) and
reconstructed surfaces as mesh files (meshes)."""
