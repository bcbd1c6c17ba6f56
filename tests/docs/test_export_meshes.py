"""`export --format mesh` on the shared README build: the GLB / PLY load back with trimesh and hold the
reconstruct stage's cached surfaces, objects placed inside their boxes in the scene frame."""

from __future__ import annotations

import json

import numpy as np
import trimesh

from nuplan_occ.dataset import open_dataset
from nuplan_occ.geometry import invert_transform, transform_points
from nuplan_occ.labels import LABELS
from nuplan_occ.export.meshes import SURFACE_ARTIFACTS, _scene_tasks, box_to_frame, export_meshes
from nuplan_occ.pipeline.runner import run_stages
from nuplan_occ.stages import PIPELINE


def test_mesh_export_holds_the_cached_surfaces(workspace, tmp_path):
    folder, env = workspace
    out, data_root = str(folder / "out"), env["NUPLAN_DATA_ROOT"]
    ds = open_dataset(out)
    frame = ds.get(len(ds) - 1, keys=())  # a scene's last frame: objects placed away from its first
    summary = export_meshes(out, tmp_path, data_root, PIPELINE, token=frame["token"])
    assert json.loads((tmp_path / "mesh_export.json").read_text()) == summary
    tasks = {t.scene_name: t for t in _scene_tasks(out, PIPELINE, data_root, None)}
    assert [(tasks[s["scene"]].scene_token, s["token"]) for s in summary["scenes"]] == [
        (frame["scene_token"], frame["token"])]
    objects_checked = 0
    for entry in summary["scenes"]:
        artifacts = run_stages(tasks[entry["scene"]], PIPELINE, SURFACE_ARTIFACTS)
        glb = trimesh.load(tmp_path / entry["glb"], force="scene")
        background = artifacts["background_surface"]
        assert len(glb.geometry["background"].vertices) == len(background.vertices) > 0
        assert len(glb.geometry["background"].faces) == len(background.faces)
        np.testing.assert_allclose(glb.geometry["background"].vertices, background.vertices, atol=1e-3)
        scene, poses = artifacts["scene"], artifacts["registration"].poses
        position = next(i for i, s in enumerate(scene.sweeps) if s.token == entry["token"])
        T_scene_from_ego = invert_transform(np.asarray(entry["T_global_from_scene"])) @ poses[position]
        boxes = artifacts["object_boxes"][position]
        for k, track in enumerate(boxes.track_tokens):
            surface = artifacts["object_surfaces"].get(track)
            if surface is None or not surface.is_mesh:
                continue
            mesh = glb.geometry[f"{LABELS.names[LABELS.box_category_to_id[boxes.categories[k]]]}_"
                                f"{scene.instance_ids[track]}"]
            assert len(mesh.vertices) == len(surface.vertices) and len(mesh.faces) == len(surface.faces)
            # back into the box frame: within the box (plus the surface's mask distance) around its centre
            ego = transform_points(invert_transform(T_scene_from_ego), mesh.vertices)
            in_box = box_to_frame(ego - boxes.centers[k], 0.0, -float(boxes.yaws[k]))
            assert np.all(np.abs(in_box) <= boxes.sizes[k] / 2 + 0.5)
            objects_checked += 1
        ply = trimesh.load(tmp_path / entry["ply"], force="mesh", process=False)  # as written: no vertex merging
        assert len(ply.vertices) == sum(m["vertices"] for m in entry["meshes"].values())
    assert objects_checked > 0
