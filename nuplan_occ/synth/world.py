"""A synthetic world: static scenery and ground, agents and the TRUE ego motion, placed in the UTM frame
of one nuPlan location.

Frames: "local" = global minus `World.origin` (a pure translation; local z = 0 is the ground level);
"global" = UTM metres of the location's EPSG. Times: seconds from the log start (t = 0 at start_us).
The TRUE ego pose is upright (yaw only) with its origin (rear axle) `options.axle_height_m` above the
ground under it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from nuplan_occ.synth.agents import Agent, mesh_template, posed_triangles
from nuplan_occ.synth.ground import curb_faces, ground_faces
from nuplan_occ.synth.mapgen import RoadNetwork, build_network
from nuplan_occ.synth.population import EgoRoute, ego_route, populate
from nuplan_occ.synth.presets import Preset, SynthOptions
from nuplan_occ.synth.primitives import Faces
from nuplan_occ.synth.scenery import Scenery, build_scenery

LOCATIONS: dict[str, tuple[int, str, tuple[float, float]]] = {
    "us-nv-las-vegas-strip": (32611, "9.15.1915", (664000.0, 3997000.0)),
    "us-pa-pittsburgh-hazelwood": (32617, "9.17.1937", (589000.0, 4476000.0)),
}
"""location -> (EPSG, map version, (easting, northing) of the world's local origin)."""


@dataclass
class MeshSet:
    """Triangles (T, 3, 3) local metres with per-triangle semantic id (T,) uint8 and instance id (T,) uint16."""

    triangles: np.ndarray
    label: np.ndarray
    instance: np.ndarray


@dataclass
class World:
    """Everything needed to render sensors and truth at any time of one log."""

    preset: Preset
    options: SynthOptions
    location: str
    net: RoadNetwork
    origin: np.ndarray
    faces: Faces
    crowns: np.ndarray
    agents: list[Agent]
    ego: EgoRoute
    duration: float
    start_us: int
    noise_key: tuple[int, int] = (0, 0)
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def epsg(self) -> int:
        return LOCATIONS[self.location][0]

    @property
    def map_version(self) -> str:
        return LOCATIONS[self.location][1]

    @property
    def T_global_from_local(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, 3] = self.origin
        return T

    def seconds(self, t_us: int | np.ndarray) -> np.ndarray:
        """Seconds from the log start of absolute microsecond timestamps."""
        return (np.asarray(t_us, np.int64) - self.start_us) / 1e6

    def ego_state(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """TRUE ego state at times t (T,) s: T_local_from_ego (T, 4, 4); velocity, acceleration (T, 3) in the
        ego frame (m/s, m/s^2); angular_rate (T, 3) rad/s in the ego frame."""
        t = np.atleast_1d(np.asarray(t, np.float64))
        s, v, a = self.ego.motion.sample(t)
        xy, yaw, ground = self.ego.path.at(s)
        kappa = np.interp(s, self.ego.path.s, self.ego.path.curvature())
        c, sn = np.cos(yaw), np.sin(yaw)
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, 0, 0], T[:, 0, 1], T[:, 1, 0], T[:, 1, 1] = c, -sn, sn, c
        T[:, :2, 3] = xy
        T[:, 2, 3] = ground + self.options.axle_height_m
        zeros = np.zeros_like(v)
        return {
            "T_local_from_ego": T,
            "velocity": np.stack([v, zeros, zeros], 1),
            "acceleration": np.stack([a, v * v * kappa, zeros], 1),
            "angular_rate": np.stack([zeros, zeros, v * kappa], 1),
        }

    def local_from_global(self, T_global_from_x: np.ndarray) -> np.ndarray:
        """T_local_from_x of a transform into the global frame."""
        T = np.array(T_global_from_x, dtype=np.float64)
        T[:3, 3] -= self.origin
        return T

    def true_pose(self, t_us: int) -> np.ndarray:
        """T_global_from_ego (4, 4) of the TRUE ego pose at an absolute timestamp (us)."""
        return self.T_global_from_local @ self.ego_state(self.seconds(t_us))["T_local_from_ego"][0]

    def static_mesh(self) -> MeshSet:
        """Ground, curbs, buildings, walls, poles (two triangles per face) and tree crowns; instance 0."""
        if "static" not in self._cache:
            tris = np.concatenate([self.faces.triangles(), self.crowns])
            label = np.concatenate([np.repeat(self.faces.label, 2), np.full(len(self.crowns), 1, np.uint8)])
            self._cache["static"] = MeshSet(tris, label, np.zeros(len(tris), np.uint16))
        return self._cache["static"]

    def agent_mesh(self, t: float) -> MeshSet:
        """Meshes of all agents posed at time t (s), with their box category ids and instance ids."""
        if "templates" not in self._cache:
            self._cache["templates"] = [mesh_template(a.category, a.size) for a in self.agents]
        parts, labels, inst = [], [], []
        for agent, template in zip(self.agents, self._cache["templates"]):
            center, yaw, _ = agent.state(np.array([t]))
            parts.append(posed_triangles(template, center[0], float(yaw[0])))
            labels.append(np.full(len(template), agent.label, np.uint8))
            inst.append(np.full(len(template), agent.instance, np.uint16))
        if not parts:
            return MeshSet(np.zeros((0, 3, 3)), np.zeros(0, np.uint8), np.zeros(0, np.uint16))
        return MeshSet(np.concatenate(parts), np.concatenate(labels), np.concatenate(inst))

    def static_scene(self) -> o3d.t.geometry.RaycastingScene:
        """Ray casting scene of the static mesh (built once; local frame, float32)."""
        if "scene" not in self._cache:
            self._cache["scene"] = raycasting_scene(self.static_mesh().triangles)
        return self._cache["scene"]


def raycasting_scene(triangles: np.ndarray) -> o3d.t.geometry.RaycastingScene:
    """An open3d ray casting scene of triangles (T, 3, 3) (one geometry; primitive id = triangle index)."""
    scene = o3d.t.geometry.RaycastingScene()
    if len(triangles):
        verts = np.ascontiguousarray(triangles.reshape(-1, 3), dtype=np.float32)
        index = np.arange(len(verts), dtype=np.uint32).reshape(-1, 3)
        scene.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(index))
    return scene


def build_static(preset: Preset, seed: int) -> tuple[RoadNetwork, Faces, Scenery]:
    """The map-bound part of a world (shared by all logs of a seed): network, all static faces (ground,
    curbs, scenery) and the scenery (crowns, keepout)."""
    rng = np.random.default_rng([seed, 0x5CE7E])
    net = build_network(preset.layout)
    scenery = build_scenery(net, preset, rng)
    faces = Faces.concat([ground_faces(net), curb_faces(net), scenery.faces])
    return net, faces, scenery


def build_world(preset: Preset, options: SynthOptions, seed: int, log_index: int, duration: float, start_us: int,
                location: str = "us-nv-las-vegas-strip") -> World:
    """The world of log `log_index`: static part from `seed`, ego route and agents from (seed, log_index)."""
    if location not in LOCATIONS:
        raise ValueError(f"unknown location {location!r}; known: {sorted(LOCATIONS)}")
    net, faces, scenery = build_static(preset, seed)
    rng = np.random.default_rng([seed, log_index, 0xA6E7])
    ego = ego_route(net, rng, duration)
    agents = populate(net, scenery, preset, options, ego, rng, duration)
    east, north = LOCATIONS[location][2]
    origin = np.array([east, north, options.ground_z])
    return World(preset, options, location, net, origin, faces, scenery.crowns, agents, ego, duration, start_us,
                 (seed, log_index))
