"""Presets (world size, sensor density, population) and the options that make logs imperfect on purpose."""

from __future__ import annotations

from dataclasses import dataclass

from nuplan_occ.synth.mapgen import RoadLayout


@dataclass(frozen=True)
class SynthOptions:
    """How the written log deviates from the exact world (all figures are 1-sigma unless stated).

    Ego poses: logged = true composed with a slow drift (sum of sinusoids with period ~drift_period_s,
    amplitudes drift_*) and white noise (noise_*); z, roll and pitch included. Boxes: centre, yaw and
    relative size noise per frame. LiDAR: Gaussian range noise, random ray drop (plus grazing / range
    dependent drop). ego_pose rows are written at ego_pose_hz (the 20 Hz frames link the nearest row).
    """

    pose_noise_xy: float = 0.02
    pose_noise_z: float = 0.02
    pose_noise_yaw_deg: float = 0.05
    pose_noise_rollpitch_deg: float = 0.05
    drift_xy: float = 0.25
    drift_z: float = 0.12
    drift_yaw_deg: float = 0.15
    drift_period_s: float = 25.0
    box_center_sigma: float = 0.08
    box_yaw_sigma_deg: float = 1.0
    box_size_sigma_rel: float = 0.03
    unboxed_moving_object: bool = True
    box_range_m: float = 80.0
    range_noise: float = 0.015
    ray_drop: float = 0.03
    ego_pose_hz: float = 100.0
    ground_z: float = 2.5
    """Height of the world's ground in the global frame (m); non-zero so that a dropped z shows."""
    axle_height_m: float = 0.36
    """Height of the rear axle (the ego origin) above the ground: about a Pacifica wheel's radius. It also
    keeps the ground off the grid's voxel boundaries (ego z = -0.36 lies inside layer 10), so truth and
    builds are not decided by which side of a boundary a surface falls on."""


@dataclass(frozen=True)
class StaticKind:
    """A kind of static boxed object: nuPlan box category, box size [length, width, height] m, and inset m:
    how far beyond the curb (towards the walkway) it stands."""

    category: str
    size: tuple[float, float, float]
    inset: float


DEFAULT_STATIC_KINDS = (
    StaticKind("traffic_cone", (0.4, 0.4, 0.7), 0.5),
    StaticKind("barrier", (2.0, 0.5, 1.0), 5.0),
    StaticKind("czone_sign", (0.8, 0.25, 1.6), 1.2),
    StaticKind("generic_object", (0.6, 0.6, 1.05), 3.4),
)

SMALL_OBJECT_KINDS = (
    StaticKind("traffic_cone", (0.4, 0.4, 0.7), 0.5),      # cone at the road edge
    StaticKind("traffic_cone", (0.3, 0.3, 0.5), 0.3),      # small cone
    StaticKind("barrier", (0.2, 0.2, 0.9), 0.4),           # bollard
    StaticKind("generic_object", (0.25, 0.25, 1.2), 0.6),  # post
    StaticKind("generic_object", (0.5, 0.5, 0.6), 0.8),    # small box
)
"""Objects near a voxel in size (0.2 - 0.5 m footprints), placed close to the road."""


@dataclass(frozen=True)
class Preset:
    """World size and sensor density. Azimuth counts are per full 360 degrees of each LiDAR.
    static_kinds: the static boxed objects, placed in turn within static_route_distance_m of the ego route
    (with static_on_driven_route, of the part of it the ego drives within the log, so that every object
    is passed)."""

    name: str
    layout: RoadLayout
    scene_seconds: float
    top_azimuths: int
    side_azimuths: int
    n_vehicles: int
    n_pedestrians: int
    n_cyclists: int
    n_parked: int
    n_static_objects: int
    n_buildings: int
    tree_spacing: float
    pole_spacing: float
    static_kinds: tuple[StaticKind, ...] = DEFAULT_STATIC_KINDS
    static_route_distance_m: float = 45.0
    static_on_driven_route: bool = False


PRESETS: dict[str, Preset] = {
    "small": Preset("small", RoadLayout(), scene_seconds=2.0, top_azimuths=800, side_azimuths=480,
                    n_vehicles=8, n_pedestrians=8, n_cyclists=2, n_parked=12, n_static_objects=10,
                    n_buildings=14, tree_spacing=14.0, pole_spacing=28.0),
    "city": Preset("city", RoadLayout(xs=(-110.0, 0.0, 110.0), ys=(-110.0, 0.0, 110.0), extent=200.0,
                                      carpark=(22.0, 88.0, -92.0, -18.0)),
                   scene_seconds=20.0, top_azimuths=2200, side_azimuths=1600,
                   n_vehicles=30, n_pedestrians=30, n_cyclists=6, n_parked=30, n_static_objects=24,
                   n_buildings=60, tree_spacing=11.0, pole_spacing=25.0),
    "small_objects": Preset("small_objects", RoadLayout(), scene_seconds=2.0, top_azimuths=800, side_azimuths=480,
                            n_vehicles=2, n_pedestrians=0, n_cyclists=0, n_parked=0, n_static_objects=15,
                            n_buildings=4, tree_spacing=30.0, pole_spacing=60.0, static_kinds=SMALL_OBJECT_KINDS,
                            static_route_distance_m=15.0, static_on_driven_route=True),
}


def get_preset(name: str) -> Preset:
    """The preset called `name`; ValueError naming the known ones otherwise."""
    if name not in PRESETS:
        raise ValueError(f"unknown synth preset {name!r}; known: {sorted(PRESETS)}")
    return PRESETS[name]
