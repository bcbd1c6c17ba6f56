"""3D view of one occupancy frame with pyvista: voxels in the label palette, the ego box, LiDAR points.

Everything is drawn in the ego frame of the frame (nuPlan rear axle: x forward, y left, z up, metres),
the frame the grid is indexed in ([x, y, z], see `nuplan_occ.grid`). Only the exposed faces of occupied
voxels are built (a face whose neighbour in that direction is also drawn is hidden), so a frame of
~200k occupied voxels is a few hundred thousand quads and renders interactively.
With `screenshot` the plotter is off-screen (works headless through VTK's EGL/OSMesa window).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nuplan_occ.grid import DEFAULT_GRID, GridSpec
from nuplan_occ.io.types import PACIFICA, VehicleFootprint
from nuplan_occ.labels import EMPTY, LABELS, VEHICLE, LabelMap

MASK_MEMBERS = {"lidar": "mask_lidar", "camera": "mask_camera"}
"""`--mask` choice -> dataset member."""

CAMERA_BEHIND_ABOVE = ((-62.0, -22.0, 58.0), (8.0, 0.0, -4.0), (0.0, 0.0, 1.0))
"""Camera (position, focal point, view-up) in the ego frame, metres: behind and above the ego, looking ahead."""

UNKNOWN_RGB = (90, 100, 150)
POINTS_RGB = (30, 30, 30)
BACKGROUND_RGB = (235, 238, 242)

# For each face direction (axis, side): the axes spanning the face, ordered so the quad's corners run
# counter-clockwise seen from outside (normal = side * e_axis).
_TANGENTS = {(0, 1): (1, 2), (0, -1): (2, 1), (1, 1): (2, 0), (1, -1): (0, 2), (2, 1): (0, 1), (2, -1): (1, 0)}


def exposed_faces(visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The faces of `visible` voxels that border a non-visible voxel (or the grid's edge).

    visible: (X, Y, Z) bool, indexed [x, y, z]. Returns (corners (F, 4, 3) int64 in voxel-corner index
    units, counter-clockwise seen from outside; owner (F, 3) int64 voxel index of each face).
    """
    visible = np.asarray(visible, dtype=bool)
    padded = np.pad(visible, 1)
    corners, owners = [], []
    for (axis, side), (b, c) in _TANGENTS.items():
        neighbour = np.roll(padded, -side, axis=axis)[1:-1, 1:-1, 1:-1]
        owner = np.argwhere(visible & ~neighbour)
        base = owner.copy()
        if side > 0:
            base[:, axis] += 1
        eb, ec = np.eye(3, dtype=np.int64)[b], np.eye(3, dtype=np.int64)[c]
        quad = np.stack([base, base + eb, base + eb + ec, base + ec], axis=1)
        corners.append(quad)
        owners.append(owner)
    return np.concatenate(corners), np.concatenate(owners)


def voxel_surface(visible: np.ndarray, colors: np.ndarray | None, grid: GridSpec = DEFAULT_GRID):
    """pyvista PolyData of the exposed faces of `visible` (ego frame, metres).

    colors: (X, Y, Z, 3) uint8 RGB per voxel, stored per face as cell data "rgb"; None for no colors.
    """
    import pyvista as pv

    corners, owner = exposed_faces(visible)
    points = grid.lower + corners.reshape(-1, 3) * grid.voxel_size
    n = len(corners)
    faces = np.hstack([np.full((n, 1), 4, dtype=np.int64), np.arange(4 * n, dtype=np.int64).reshape(n, 4)])
    mesh = pv.PolyData(points, faces=faces.reshape(-1))
    if colors is not None:
        mesh.cell_data["rgb"] = colors[owner[:, 0], owner[:, 1], owner[:, 2]]
    return mesh


def ego_box(footprint: VehicleFootprint = PACIFICA):
    """pyvista Box of the ego vehicle in the ego frame (rear axle at the origin, wheels on z = 0)."""
    import pyvista as pv

    center, size = footprint.box_center_and_size()
    lo, hi = center - size / 2.0, center + size / 2.0
    return pv.Box(bounds=(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]))


def _hex(rgb) -> str:
    return "#{:02x}{:02x}{:02x}".format(*(int(v) for v in rgb))


def legend_entries(semantics: np.ndarray, labels: LabelMap = LABELS) -> list[tuple[str, str]]:
    """(name with voxel count, hex color) of every non-empty class present in `semantics`, by id."""
    counts = np.bincount(np.asarray(semantics).reshape(-1), minlength=256)
    return [
        (f"{labels.names.get(i, f'id {i}')} ({counts[i]:,})", _hex(labels.colors.get(i, (0, 0, 0))))
        for i in np.flatnonzero(counts)
        if i != EMPTY
    ]


def render_arrays(
    semantics: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    show_unknown: bool = False,
    points_ego: np.ndarray | None = None,
    grid: GridSpec = DEFAULT_GRID,
    labels: LabelMap = LABELS,
    title: str = "",
    screenshot: Path | None = None,
    window_size: tuple[int, int] = (1600, 1000),
) -> None:
    """Draw one frame; interactive window, or a PNG at `screenshot` rendered off-screen.

    semantics: (X, Y, Z) uint8 label ids indexed [x, y, z] on `grid` (ego frame). mask: optional
    (X, Y, Z) bool observability mask; only occupied voxels inside it are drawn, and with
    `show_unknown` the unobserved space (mask False) is drawn as a translucent shell. points_ego:
    optional (N, 3) metres in the ego frame; those inside the grid's bounds are drawn as small dark spheres.
    """
    import pyvista as pv

    semantics = np.asarray(semantics)
    if semantics.shape != grid.shape:
        raise ValueError(f"semantics has shape {semantics.shape}, the grid is {grid.shape}")
    if mask is not None and np.shape(mask) != grid.shape:
        raise ValueError(f"mask has shape {np.shape(mask)}, the grid is {grid.shape}")
    visible = semantics != EMPTY
    if mask is not None:
        visible &= mask
    shown = np.where(visible, semantics, EMPTY)

    plotter = pv.Plotter(off_screen=screenshot is not None, window_size=list(window_size))
    plotter.set_background(_hex(BACKGROUND_RGB))
    if visible.any():
        plotter.add_mesh(voxel_surface(visible, labels.palette()[shown], grid), scalars="rgb", rgb=True,
                         ambient=0.35, diffuse=0.7, specular=0.0)
    if mask is not None and show_unknown and not np.all(mask):
        plotter.add_mesh(voxel_surface(~np.asarray(mask, dtype=bool), None, grid), color=_hex(UNKNOWN_RGB),
                         opacity=0.25)
    plotter.add_mesh(ego_box(), color=_hex(labels.colors[VEHICLE]), show_edges=True, edge_color="black",
                     line_width=2)
    points = None if points_ego is None else np.asarray(points_ego, dtype=np.float32).reshape(-1, 3)
    if points is not None:
        points = points[np.all((points >= grid.lower) & (points < grid.upper), axis=1)]
    if points is not None and len(points):
        plotter.add_points(points, color=_hex(POINTS_RGB), point_size=2.0, render_points_as_spheres=True)
    entries = legend_entries(shown, labels) + [("ego vehicle", _hex(labels.colors[VEHICLE]))]
    plotter.add_legend(labels=[list(e) for e in entries], bcolor="white", border=True,
                       size=(0.17, 0.032 * len(entries)), loc="lower right", face="rectangle")
    if title:
        plotter.add_text(title, position="upper_left", font_size=10, color="black")
    plotter.add_axes()
    plotter.camera_position = [tuple(v) for v in CAMERA_BEHIND_ABOVE]
    if screenshot is not None:
        Path(screenshot).parent.mkdir(parents=True, exist_ok=True)
        plotter.show(screenshot=str(screenshot), auto_close=True)
    else:
        plotter.show()


class PointsUnavailable(RuntimeError):
    """The LiDAR sweep of a frame cannot be loaded (data root, log DB or blob not reachable)."""


def label_map_of(labels: dict) -> LabelMap:
    """A LabelMap from an `OccDataset.labels` dict (id -> {"name", "color"})."""
    return LabelMap(names={int(i): c["name"] for i, c in labels.items()},
                    colors={int(i): tuple(c["color"]) for i, c in labels.items()}, box_category_to_id={})


def frame_points_ego(data_root: str | Path, log_name: str, token: str) -> np.ndarray:
    """(N, 3) metres in the ego frame: the merged LiDAR sweep of lidar_pc `token` of log `log_name`,
    read from the nuPlan data root. Raises PointsUnavailable saying what is missing."""
    from nuplan_occ.io.data_root import resolve_logs, sensor_root_for
    from nuplan_occ.io.errors import NuplanFormatError
    from nuplan_occ.io.reader import NuplanLog, points_to_ego

    try:
        db_path = resolve_logs(data_root, split=None, log_names=[log_name])[0]
        with NuplanLog(db_path, sensor_root_for(db_path, data_root)) as log:
            frame = next((f for f in log.frames if f.token == token), None)
            if frame is None:
                raise PointsUnavailable(f"{db_path}: no lidar_pc with token {token}")
            return points_to_ego(log.load_points(frame), log).xyz
    except NuplanFormatError as exc:
        raise PointsUnavailable(str(exc)) from exc


def render_frame(
    root: str,
    index: int | None = None,
    token: str | None = None,
    mask: str | None = None,
    points: np.ndarray | None = None,
    screenshot: Path | None = None,
    window_size: tuple[int, int] = (1600, 1000),
    show_unknown: bool = False,
) -> None:
    """Draw frame `index` (or the frame of lidar_pc `token`; default the first) of the dataset at `root`.

    mask: None, "lidar" or "camera" (the frame's mask_lidar / mask_camera member; MissingMemberError if
    the frame has none). points: optional (N, 3) ego-frame metres to overlay. See `render_arrays`.
    """
    from nuplan_occ.dataset import open_dataset

    if index is not None and token is not None:
        raise ValueError("give index or token, not both")
    if mask is not None and mask not in MASK_MEMBERS:
        raise ValueError(f"mask {mask!r}: use one of {sorted(MASK_MEMBERS)}")
    ds = open_dataset(root)
    i = ds.index_of_token(token) if token is not None else (index or 0)
    keys = ("semantics",) + ((MASK_MEMBERS[mask],) if mask else ())
    frame = ds.get(i, keys=keys)
    title = f"{frame['log_name']}  frame {frame['frame_index']}  token {frame['token']}"
    render_arrays(frame["semantics"], mask=frame[MASK_MEMBERS[mask]] if mask else None, show_unknown=show_unknown,
                  points_ego=points, grid=ds.grid, labels=label_map_of(ds.labels), title=title,
                  screenshot=screenshot, window_size=window_size)
