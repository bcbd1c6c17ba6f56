"""Viewer: exposed-face surface and off-screen screenshots (headless VTK)."""

import numpy as np
from PIL import Image

from nuplan_occ.grid import DEFAULT_GRID
from nuplan_occ.labels import LABELS, VEHICLE
from nuplan_occ.viewer import exposed_faces, render_frame, voxel_surface
from tools_world import street_scene, write_dataset


def test_exposed_faces_of_one_and_two_voxels():
    grid = np.zeros((3, 3, 3), dtype=bool)
    grid[1, 1, 1] = True
    corners, owner = exposed_faces(grid)
    assert len(corners) == 6 and np.all(owner == 1)
    # each face is a unit square whose corners lie on the voxel's boundary, normals point outwards
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 3] - corners[:, 0])
    centres = corners.mean(axis=1) - 1.5
    assert np.allclose(normals, 2 * centres)
    grid[2, 1, 1] = True
    assert len(exposed_faces(grid)[0]) == 10


def test_voxel_surface_is_in_ego_metres_with_face_colors():
    visible = np.zeros(DEFAULT_GRID.shape, dtype=bool)
    visible[200, 200, 12] = True  # voxel x, y in [0, 0.25), z in [0, 0.25)
    colors = np.zeros((*DEFAULT_GRID.shape, 3), dtype=np.uint8)
    colors[200, 200, 12] = (1, 2, 3)
    mesh = voxel_surface(visible, colors)
    assert np.allclose(mesh.bounds, (0, 0.25, 0, 0.25, 0, 0.25))
    assert mesh.n_cells == 6 and np.all(mesh.cell_data["rgb"] == (1, 2, 3))


def _near(rgb: np.ndarray, target, tol: int = 40) -> np.ndarray:
    """Pixels whose hue matches `target` up to shading (scaled colour within tol)."""
    rgb = rgb.astype(np.float64)
    target = np.asarray(target, dtype=np.float64)
    scale = (rgb @ target) / (target @ target)
    return (scale > 0.3) & (np.abs(rgb - scale[:, None] * target).max(axis=1) < tol)


def test_screenshot_shows_vehicles_and_ego(tmp_path):
    sem = street_scene()
    mask = np.ones(DEFAULT_GRID.shape, dtype=bool)
    mask[:, :200] = False  # right half (y < 0) unobserved
    write_dataset(tmp_path / "ds", [{"semantics": sem, "mask_lidar": mask}], grid=DEFAULT_GRID)
    png = tmp_path / "shots" / "frame.png"
    render_frame(str(tmp_path / "ds"), index=0, mask="lidar", screenshot=png, window_size=(800, 500),
                 points=np.array([[5.0, 0.0, 1.0], [10.0, -3.0, 0.5]]))
    image = np.asarray(Image.open(png).convert("RGB"))
    assert image.shape == (500, 800, 3)
    pixels = image.reshape(-1, 3)
    orange = _near(pixels, LABELS.colors[VEHICLE])
    assert orange.sum() > 500  # the ego box and the vehicle ahead on the observed left half
    assert len(np.unique(pixels, axis=0)) > 20  # a real picture, not a blank canvas


def test_cli_view_overlays_the_points_of_the_source_log(tmp_path):
    """A synthetic nuPlan log and its truth dataset: --points finds the log's sweep by log name and token."""
    import typer
    from typer.testing import CliRunner

    from nuplan_occ.cli.dataset import register
    from nuplan_occ.dataset import open_dataset
    from nuplan_occ.synth.generate import synthesize
    from nuplan_occ.viewer import frame_points_ego

    result = synthesize(tmp_path / "data", seconds=0.2, truth_rate_hz=10.0)
    ds = open_dataset(str(result.truth_root))
    frame = ds.get(1, keys=())
    points = frame_points_ego(tmp_path / "data", frame["log_name"], frame["token"])
    assert points.shape[1] == 3 and len(points) > 1000
    assert abs(np.median(points[:, 2])) < 3.0  # ego frame: returns around the ground, not in the sensor frame
    app = typer.Typer()
    register(app)
    png = tmp_path / "p.png"
    out = CliRunner().invoke(app, ["view", str(result.truth_root), "--token", frame["token"], "--points",
                                   "--data-root", str(tmp_path / "data"), "--screenshot", str(png)])
    assert out.exit_code == 0, out.output
    assert "skipped" not in out.output and png.stat().st_size > 1000
