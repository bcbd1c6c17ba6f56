"""Procedural synthetic worlds with exact occupancy truth, written as nuPlan logs.

Frames used throughout the package:
- "global": UTM metres of the map's location (EPSG of the location, e.g. 32611 for Las Vegas).
- "local":  the world's working frame = global translated by `World.origin` (no rotation). Meshes, ray
  casting and the map generator work here so that float32 ray casting keeps millimetre precision.
- "ego":    nuPlan rear axle (x forward, y left, z up); the TRUE ego pose puts its origin axle_height_m above the ground.
- "sensor": one physical LiDAR's own frame (x forward, z up), see `lidar.py`.
- "lidar":  the MergedPointCloud frame written to the PCD files (T_ego_from_lidar is not identity).
"""

from nuplan_occ.synth.generate import SynthResult, synthesize
from nuplan_occ.synth.preview import render_preview
from nuplan_occ.synth.truth import truth_for_frame

__all__ = ["SynthResult", "synthesize", "render_preview", "truth_for_frame"]
