"""Objects placed at one frame: each of the frame's boxes with the geometry that stands for its object there.

A box-filled category is a regular lattice filling its box; else a carved solid (cell samples), else a
reconstructed surface, else the object's raw points (windowed around the frame for non-rigid objects).
Geometry is in the object's BOX frame (origin at the box centre, x along the heading, z up; metres); the
box (centre, yaw, size, velocity) is in the frame's EGO frame, as the frame's boxes give it.
"""

from __future__ import annotations

import numpy as np

from nuplan_occ.io.types import Boxes
from nuplan_occ.labels import LABELS
from nuplan_occ.voxel.compose import PlacedObject


def box_lattice_points(size: np.ndarray, spacing_m: float) -> np.ndarray:
    """(N, 3) points of a regular lattice filling a box [-size/2, size/2] (box frame, m), faces included,
    at most spacing_m apart."""
    axes = [np.linspace(-h, h, max(2, int(np.ceil(2 * h / spacing_m)) + 1)) for h in np.asarray(size, np.float64) / 2]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def placed_objects(instance_ids: dict[str, int], boxes: Boxes, ok_position: int, objects: dict, surfaces: dict,
                   solids: dict, window: int, box_fill_categories: tuple[str, ...] = (), box_fill_spacing_m: float = 0.05,
                   sparse_solid_categories: tuple[str, ...] = (), solid_min_cells: int = 1) -> list[PlacedObject]:
    """The frame's boxes (ego frame) with their object geometry in the box frame (objects: track ->
    ObjectAggregate, surfaces: track -> Surface, solids: track -> SolidSamples): a lattice of points at most
    box_fill_spacing_m apart for box_fill_categories, else solid cell samples (for sparse_solid_categories a
    voxel needs solid_min_cells of them or an observed one), else the surface, else the points within
    `window` sweeps of the frame (ok_position: the frame's index among the scene's loaded sweeps); each with
    the object's own points, whose voxels are the object's too (`PlacedObject.own_points`). Boxes of a track
    with no geometry are left out; instance ids come from instance_ids (track -> id, 0 when absent)."""
    placed = []
    for k, track in enumerate(boxes.track_tokens):
        min_points, anchors = 1, None
        if boxes.categories[k] in box_fill_categories:
            vertices, faces = box_lattice_points(boxes.sizes[k], box_fill_spacing_m), np.zeros((0, 3), dtype=np.int64)
        elif track in solids:
            vertices, faces = solids[track].points, np.zeros((0, 3), dtype=np.int64)
            if boxes.categories[k] in sparse_solid_categories:
                min_points, anchors = solid_min_cells, solids[track].observed
        elif track in surfaces:
            vertices, faces = surfaces[track].vertices, surfaces[track].faces
        elif track in objects:
            vertices, _ = objects[track].points_for_frame(ok_position, window)
            faces = np.zeros((0, 3), dtype=np.int64)
        else:
            continue
        own = objects[track].points_for_frame(ok_position, window)[0] if track in objects else None
        placed.append(PlacedObject(
            vertices=vertices, faces=faces, center=boxes.centers[k], yaw=float(boxes.yaws[k]), size=boxes.sizes[k],
            class_id=LABELS.box_category_to_id[boxes.categories[k]], instance_id=instance_ids.get(track, 0),
            velocity=boxes.velocities[k], min_points_per_voxel=min_points, anchors=anchors, own_points=own))
    return placed
