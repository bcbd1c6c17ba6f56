"""Camera images of a synthetic world: the label colours of the surfaces the pixels see, shaded by depth.

Every pixel centre's ray (`cameras.pixel_rays`, lens distortion included) is cast from the camera at the
TRUE ego pose into the same meshes the LiDAR sees (static mesh and agents posed at the image time, Open3D
RaycastingScene). A pixel whose ray hits a surface within MAX_DEPTH_M gets the colour of that surface's
label (nuplan_occ/schemas/labels.json) times `shade(depth)`, depth being the hit's z in the camera frame;
a pixel that hits nothing shows the colour of label 0 (empty, white) unshaded. The ego vehicle is not in
the world, so it never appears. Images are JPEG (quality JPEG_QUALITY, no chroma subsampling, so class
colours survive at edges) written with Pillow.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
from PIL import Image

from nuplan_occ.io.types import CameraCalibration
from nuplan_occ.labels import EMPTY, LABELS
from nuplan_occ.synth.cameras import pixel_rays
from nuplan_occ.synth.lidar import cast_rays, rotate
from nuplan_occ.synth.world import World, raycasting_scene

MAX_DEPTH_M = 200.0
"""Surfaces farther than this (m along the ray) are not drawn."""
SHADE_FLOOR, SHADE_SCALE_M = 0.45, 40.0
"""shade(d) = SHADE_FLOOR + (1 - SHADE_FLOOR) * exp(-d / SHADE_SCALE_M)."""
JPEG_QUALITY = 95

PALETTE = LABELS.palette().astype(np.float64)
PALETTE_IDS = np.array(sorted(LABELS.colors), dtype=np.int64)
"""Label ids with a colour (labels.json), EMPTY included."""


def shade(depth_m: np.ndarray) -> np.ndarray:
    """Brightness factor in (SHADE_FLOOR, 1] of surfaces at depth_m (m, camera z)."""
    return SHADE_FLOOR + (1.0 - SHADE_FLOOR) * np.exp(-np.asarray(depth_m, dtype=np.float64) / SHADE_SCALE_M)


@dataclass(frozen=True)
class RigRays:
    """The pixel rays of a camera rig in the ego frame: origins (R, 3) m and unit directions (R, 3), camera
    after camera, each camera's pixels row by row; axial (R,): each direction's z in its camera frame
    (depth = distance along the ray * axial)."""

    cameras: list[CameraCalibration]
    origins: np.ndarray
    directions: np.ndarray
    axial: np.ndarray


def rig_rays(cameras: list[CameraCalibration]) -> RigRays:
    """The rays of every pixel centre of `cameras` (`cameras.pixel_rays`) in the ego frame."""
    origins, directions, axial = [np.zeros((0, 3))], [np.zeros((0, 3))], [np.zeros(0)]
    for camera in cameras:
        d_cam = pixel_rays(camera).reshape(-1, 3)
        T = np.asarray(camera.T_ego_from_camera, dtype=np.float64)
        origins.append(np.broadcast_to(T[:3, 3], d_cam.shape))
        directions.append(rotate(d_cam, T[:3, :3]))
        axial.append(d_cam[:, 2])
    return RigRays(list(cameras), np.concatenate(origins), np.concatenate(directions), np.concatenate(axial))


def render_labels(world: World, t_us: int, T_global_from_ego: np.ndarray,
                  rays: RigRays) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per camera of `rays`, (height, width) uint8 label ids of the surfaces its pixels see (EMPTY where none
    within MAX_DEPTH_M) and float64 depth (m along the optical axis; inf where none), at absolute time t_us
    from the TRUE pose T_global_from_ego (4, 4)."""
    T_local = world.local_from_global(T_global_from_ego)
    o = rotate(rays.origins, T_local[:3, :3]) + T_local[:3, 3]
    d = rotate(rays.directions, T_local[:3, :3])
    static, agents = world.static_mesh(), world.agent_mesh(float(world.seconds(t_us)))
    t_s, id_s, _ = cast_rays(world.static_scene(), o, d)
    t_a, id_a, _ = cast_rays(raycasting_scene(agents.triangles), o, d)
    use_agent = t_a < t_s
    t_hit = np.where(use_agent, t_a, t_s)
    hit = np.isfinite(t_hit) & (t_hit <= MAX_DEPTH_M)
    label = np.full(len(t_hit), EMPTY, np.uint8)
    label[hit & ~use_agent] = static.label[id_s[hit & ~use_agent]]
    label[hit & use_agent] = agents.label[id_a[hit & use_agent]]
    depth = np.where(hit, t_hit * rays.axial, np.inf)
    labels, depths, first = [], [], 0
    for camera in rays.cameras:
        n = camera.width * camera.height
        labels.append(label[first:first + n].reshape(camera.height, camera.width))
        depths.append(depth[first:first + n].reshape(camera.height, camera.width))
        first += n
    return labels, depths


def colorize(labels: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 image of label ids (H, W) and depths (H, W) m (module doc)."""
    rgb = PALETTE[labels] * np.where(np.isfinite(depth), shade(np.where(np.isfinite(depth), depth, 0.0)), 1.0)[..., None]
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def encode_jpeg(rgb: np.ndarray) -> bytes:
    """JPEG bytes of an (H, W, 3) uint8 image."""
    buffer = io.BytesIO()
    Image.fromarray(rgb, "RGB").save(buffer, format="JPEG", quality=JPEG_QUALITY, subsampling=0)
    return buffer.getvalue()


def pixel_labels(rgb: np.ndarray, depth_m: np.ndarray) -> np.ndarray:
    """Label ids (N,) of image pixels rgb (N, 3) known to show surfaces at depth_m (N,) m: the label whose
    colour shaded at that depth is nearest (the inverse of `colorize` for a consumer who knows the depth,
    e.g. of a voxel projected into the image)."""
    expected = PALETTE[PALETTE_IDS][None] * shade(depth_m)[:, None, None]  # (N, L, 3)
    distance = np.linalg.norm(np.asarray(rgb, dtype=np.float64)[:, None] - expected, axis=2)
    return PALETTE_IDS[np.argmin(distance, axis=1)]
