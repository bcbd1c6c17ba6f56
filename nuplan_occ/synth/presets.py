"""Presets (world size, sensor density, population) and the options that make logs imperfect on purpose."""

from __future__ import annotations

from dataclasses import dataclass, replace

from nuplan_occ.synth.mapgen import RoadLayout


@dataclass(frozen=True)
class SynthOptions:
    """How the written log deviates from the exact world (all figures are 1-sigma unless stated).

    Ego poses: logged = true composed with a slow drift (sum of sinusoids with period ~drift_period_s,
    amplitudes drift_*) and white noise (noise_*); z, roll and pitch included. Boxes: centre, yaw and
    relative size noise per frame. LiDAR: Gaussian range noise, random ray drop (plus grazing / range
    dependent drop). ego_pose rows are written at ego_pose_hz (the 20 Hz frames link the nearest row).
    The auto-label failures (box_velocity_sigma .. duplicate_*) and sensor artefacts (floater_share ..
    self_hits) are off by default; `IMPERFECTIONS["realistic"]` turns them on together. They change only
    the log (synth.auto_label, synth.sensor_artefacts): the truth never contains an artefact and always
    contains every object, whatever its box.
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
    box_velocity_sigma: float = 0.0
    """Noise (m/s, per axis in x and y) on the logged box velocities, which nuPlan's auto-labeller estimates."""
    yaw_flip_tracks: int = 0
    """Vehicle tracks (parked ones within 20 m of the ego first, then the nearest) whose box is turned by 180 deg in
    yaw_flip_share of their frames, in runs of yaw_flip_run_s."""
    yaw_flip_share: float = 0.25
    yaw_flip_run_s: float = 0.5
    gap_tracks: int = 0
    """Moving tracks (nearest the ego first) whose box is missing for gap_seconds around their closest
    approach to the ego (the object stays in the world and in the truth)."""
    gap_seconds: float = 0.5
    id_switch_tracks: int = 0
    """Moving tracks whose boxes carry a new track token from the middle of their boxed frames on."""
    false_positive_boxes: int = 0
    """Vehicle boxes of a track of their own on empty drivable ground 10-30 m from the ego, each for
    false_positive_seconds (no object, no LiDAR return inside them but the road's)."""
    false_positive_seconds: float = 0.3
    undersized_tracks: int = 0
    """Pedestrian tracks (nearest the ego first) whose boxes, track size included, are undersized_scale of
    the object's size in every dimension (on top of the noise)."""
    undersized_scale: float = 0.75
    oversized_tracks: int = 0
    """Vehicle tracks (parked ones nearest the ego first) whose boxes are oversized_scale of the object."""
    oversized_scale: float = 1.25
    duplicate_tracks: int = 0
    """Moving vehicles that get a second track on the same object for duplicate_seconds around their closest
    approach (its box offset by duplicate_offset_m sideways): two boxes on one object."""
    duplicate_seconds: float = 1.0
    duplicate_offset_m: float = 0.4
    floater_share: float = 0.0
    """Returns added per sweep, as a share of the sweep's returns, as floaters: points in the air along a
    returned ray, at 15-85 % of its range and at least 0.5 m above the ground under the ego."""
    ghost_share: float = 0.0
    """Returns added per sweep, as a share of the sweep's returns, as multipath ghosts: a ground return
    repeated further along its ray so that it lies ghost_depth_m (uniform) below the ground."""
    ghost_depth_m: tuple[float, float] = (1.0, 3.0)
    self_hits: int = 0
    """Returns added per sweep on the ego's own body (its roof and the upper half of its sides)."""
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
    "suburb": Preset("suburb", RoadLayout(xs=(-70.0, 70.0), ys=(0.0,), extent=190.0, lane_width=3.2, walkway_width=2.5,
                                          curb_height=0.2, carpark=(-40.0, 20.0, -55.0, -16.0), driveway=(-12.0, -6.0)),
                     scene_seconds=20.0, top_azimuths=2200, side_azimuths=1600,
                     n_vehicles=18, n_pedestrians=20, n_cyclists=4, n_parked=20, n_static_objects=16,
                     n_buildings=30, tree_spacing=8.0, pole_spacing=32.0),
}
"""small: a 2 s test world at one intersection; city: the real-scale 3 x 3 grid of roads (the scale bench's);
small_objects: voxel-sized objects along the route; suburb: another road layout for held-out checks (one
east-west road crossed by two north-south ones 140 m apart, narrower lanes and walkways, higher curbs, denser
trees, fewer agents)."""


def get_preset(name: str) -> Preset:
    """The preset called `name`; ValueError naming the known ones otherwise."""
    if name not in PRESETS:
        raise ValueError(f"unknown synth preset {name!r}; known: {sorted(PRESETS)}")
    return PRESETS[name]


IMPERFECTIONS: dict[str, dict] = {
    "none": {},
    "realistic": {
        "box_center_sigma": 0.15, "box_yaw_sigma_deg": 3.0, "box_size_sigma_rel": 0.08, "box_velocity_sigma": 0.2,
        "yaw_flip_tracks": 1, "yaw_flip_share": 0.25, "gap_tracks": 1, "gap_seconds": 0.5, "id_switch_tracks": 1,
        "false_positive_boxes": 1, "false_positive_seconds": 0.3, "undersized_tracks": 1, "undersized_scale": 0.75,
        "oversized_tracks": 1, "oversized_scale": 1.25, "duplicate_tracks": 1,
        "floater_share": 0.003, "ghost_share": 0.002, "self_hits": 200,
    },
}
"""Imperfection profiles: SynthOptions overrides. "realistic": the failure modes of auto-labelled boxes and
merged real sweeps at magnitudes seen in real auto-labelled logs (box centre 0.15 m, yaw 3 deg, size bias 8 %, one
flipped parked car a quarter of the time, a 0.5 s track gap, an id switch, a 0.3 s false-positive vehicle, a
pedestrian box 25 % small, 0.3 % floaters, 0.2 % multipath ghosts, 200 self-hits per sweep) plus an oversized
box, a duplicate track and velocity noise."""


def imperfect_options(profile: str, base: SynthOptions | None = None) -> SynthOptions:
    """`base` (default SynthOptions()) with the overrides of imperfection profile `profile`; ValueError
    naming the known profiles otherwise."""
    if profile not in IMPERFECTIONS:
        raise ValueError(f"unknown imperfection profile {profile!r}; known: {sorted(IMPERFECTIONS)}")
    return replace(base or SynthOptions(), **IMPERFECTIONS[profile])
