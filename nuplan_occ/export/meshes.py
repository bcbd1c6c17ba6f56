"""`nuplan-occ export --format mesh`: a scene's reconstructed surfaces as meshes for MeshLab or Blender.

For every scene of a built dataset, the background surface and each rigid object's surface (the
reconstruct stage's `background_surface` and `object_surfaces`) are written in the SCENE frame (the
frame the background was reconstructed in, metres), each object placed by its corrected box at the
scene's first ok output frame (or at the frame given by token):
    <dest>/<log>/<scene>.glb   one node per mesh, named "background" or "<class>_<instance id>",
                               vertex colours from the label palette (background: `other`);
    <dest>/<log>/<scene>.ply   the same meshes merged, vertex colours only (MeshLab);
    <dest>/mesh_export.json    per scene: the frame, T_global_from_scene and the vertex / face count
                               of every mesh.
The surfaces come from the build's stage cache (OUT/work) through `run_stages`, which recomputes any
stage whose output is missing; this needs the source logs (`data_root`), since a stage's cache key
includes its input files. Objects that have no surface (pedestrians, objects under the point threshold,
which the build keeps as points or solids) are not written.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import trimesh

from nuplan_occ.dataset import open_dataset
from nuplan_occ.geometry import invert_transform, transform_points
from nuplan_occ.labels import LABELS, OTHER
from nuplan_occ.storage.metadata import read_metadata

SURFACE_ARTIFACTS = ("scene", "registration", "object_boxes", "scene_frame", "background_surface",
                     "object_surfaces")


def box_to_frame(vertices_box: np.ndarray, center: np.ndarray, yaw: float) -> np.ndarray:
    """(V, 3) box-frame points (m) -> the frame the box is given in (rotation by yaw about +z, then centre)."""
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return vertices_box @ rotation.T + np.asarray(center, dtype=np.float64)


def _colored(vertices: np.ndarray, faces: np.ndarray, class_id: int) -> trimesh.Trimesh:
    rgb = np.array(LABELS.colors[class_id], dtype=np.uint8)
    colors = np.tile(np.append(rgb, 255), (len(vertices), 1))
    return trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=colors, process=False)


def scene_meshes(artifacts: dict, token: str | None) -> tuple[dict[str, trimesh.Trimesh], dict]:
    """Named meshes of one scene in its scene frame (see module docstring) and the frame they show."""
    scene, poses = artifacts["scene"], artifacts["registration"].poses
    T_global_from_scene = artifacts["scene_frame"]
    ok = set(scene.ok_indices())
    outputs = [i for i, sweep in enumerate(scene.sweeps) if sweep.is_output and i in ok]
    position = next((i for i in outputs if scene.sweeps[i].token == token), outputs[0])
    T_scene_from_ego = invert_transform(T_global_from_scene) @ poses[position]
    background = artifacts["background_surface"]
    meshes = {"background": _colored(background.vertices, background.faces, OTHER)}
    boxes = artifacts["object_boxes"][position]
    for k, track in enumerate(boxes.track_tokens):
        surface = artifacts["object_surfaces"].get(track)
        if surface is None or not surface.is_mesh:
            continue
        class_id = LABELS.box_category_to_id[boxes.categories[k]]
        vertices_ego = box_to_frame(surface.vertices, boxes.centers[k], float(boxes.yaws[k]))
        name = f"{LABELS.names[class_id]}_{scene.instance_ids.get(track, 0)}"
        meshes[name] = _colored(transform_points(T_scene_from_ego, vertices_ego), surface.faces, class_id)
    frame = {"token": scene.sweeps[position].token, "T_global_from_scene": T_global_from_scene.tolist()}
    return meshes, frame


def _scene_tasks(root: str, pipeline: list, data_root: Path, maps_root: str | None) -> list:
    """The build's scene tasks of the dataset at `root` (its params from dataset.json, its work cache)."""
    from nuplan_occ.io.data_root import maps_root_for, resolve_logs
    from nuplan_occ.pipeline.build import default_work_root, plan_tasks
    from nuplan_occ.pipeline.params import apply_overrides, default_params

    params = apply_overrides(default_params(pipeline), read_metadata(root)["params"], f"{root}/dataset.json")
    logs = sorted(set(open_dataset(root).column("log").to_pylist()))
    dbs = resolve_logs(data_root, split=None, log_names=logs)
    return plan_tasks(dbs, Path(data_root), maps_root_for(data_root, maps_root), root, default_work_root(root),
                      params)


def export_meshes(root: str, dest: str | Path, data_root: str | Path, pipeline: list, maps_root: str | None = None,
                  token: str | None = None) -> dict:
    """Write the meshes of every scene of the dataset at `root` (only the scene holding `token`, placed
    at that frame, when given) under `dest`, running the stages of `pipeline` up to the surfaces (from the
    work cache when kept); returns the mesh_export.json content."""
    from nuplan_occ.pipeline.runner import run_stages

    ds = open_dataset(root)
    scenes = set(ds.column("scene_token").to_pylist())
    if token is not None:
        scenes = {ds.get(ds.index_of_token(token), keys=())["scene_token"]}
    dest = Path(dest)
    summary = {"format": "mesh", "source": str(root), "frame": "scene", "scenes": []}
    for task in _scene_tasks(root, pipeline, Path(data_root), maps_root):
        if task.scene_token not in scenes:
            continue
        meshes, frame = scene_meshes(run_stages(task, pipeline, SURFACE_ARTIFACTS), token)
        folder = dest / task.log_name
        folder.mkdir(parents=True, exist_ok=True)
        trimesh.Scene(meshes).export(folder / f"{task.scene_name}.glb")
        trimesh.util.concatenate(list(meshes.values())).export(folder / f"{task.scene_name}.ply")
        summary["scenes"].append({
            "log": task.log_name, "scene": task.scene_name, "glb": f"{task.log_name}/{task.scene_name}.glb",
            "ply": f"{task.log_name}/{task.scene_name}.ply", **frame,
            "meshes": {name: {"vertices": len(m.vertices), "faces": len(m.faces)} for name, m in meshes.items()}})
    dest.mkdir(parents=True, exist_ok=True)
    (dest / "mesh_export.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary
