"""Paths on the road network and smooth longitudinal motion along them (local frame, metres, seconds).

A `Path` is a densely sampled planar curve with arc length; turns are circular arcs joined to the
straights, and the whole polyline is smoothed with a Gaussian along its length so that heading and yaw
rate are continuous (lane changes become gentle S-curves). `drive` integrates a
jerk-limited speed controller that respects a cruise speed, lateral acceleration in curves and stops
(with dwell times); the result is a `Motion` sampled every 10 ms that is exact by definition.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import gaussian_filter1d

from nuplan_occ.synth.mapgen import RoadLayout

STEP_S = 0.01
"""Integration and sampling step of every motion (s); 100 Hz, so 20 Hz frames fall on samples."""


@dataclass
class Path:
    """Planar curve through xy (N, 2) local metres; s (N,) arc length; yaw (N,) unwrapped heading rad;
    ground (N,) height of the ground under each sample relative to the world ground level (m)."""

    xy: np.ndarray
    s: np.ndarray
    yaw: np.ndarray
    ground: np.ndarray

    @classmethod
    def through(cls, xy: np.ndarray, spacing: float = 0.1, smooth: float = 1.5) -> "Path":
        """Resample a polyline (M, 2) at ~`spacing` metres, smoothed by a Gaussian of `smooth` m (arc
        length) so lane changes and kinks get a continuous heading; the ends are kept fixed."""
        xy = np.asarray(xy, np.float64)
        keep = np.r_[True, np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-9]
        xy = xy[keep]
        seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        s = np.r_[0.0, np.cumsum(seg)]
        n = max(2, int(np.ceil(s[-1] / spacing)) + 1)
        s_new = np.linspace(0.0, s[-1], n)
        pts = np.stack([np.interp(s_new, s, xy[:, 0]), np.interp(s_new, s, xy[:, 1])], axis=1)
        if smooth > 0 and n > 3:
            pts = gaussian_filter1d(pts, smooth / (s_new[1] - s_new[0]), axis=0, mode="nearest")
            return cls.through(pts, spacing, smooth=0.0)
        d = np.gradient(pts, axis=0)
        yaw = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        return cls(pts, s_new, yaw, np.zeros(n))

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def curvature(self) -> np.ndarray:
        """(N,) signed curvature 1/m."""
        return np.gradient(self.yaw, self.s)

    def project(self, xy: np.ndarray) -> np.ndarray:
        """Arc lengths (K,) of the path samples nearest to local points xy (K, 2)."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        d2 = ((self.xy[None, :, :] - xy[:, None, :]) ** 2).sum(axis=2)
        return self.s[np.argmin(d2, axis=1)]

    def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(xy (K, 2), yaw (K,), ground height (K,)) at arc lengths s (K,), clamped to the path."""
        s = np.clip(np.asarray(s, np.float64), 0.0, self.length)
        xy = np.stack([np.interp(s, self.s, self.xy[:, 0]), np.interp(s, self.s, self.xy[:, 1])], axis=-1)
        idx = np.clip(np.searchsorted(self.s, s, side="right") - 1, 0, len(self.s) - 1)
        return xy, np.interp(s, self.s, self.yaw), self.ground[idx]


def _right(d: np.ndarray) -> np.ndarray:
    return np.array([d[1], -d[0]])


@dataclass
class LaneRoute:
    """A lane-following route: polyline points (local xy), where the reference point stops before each
    intersection (local xy), and the turns taken."""

    points: np.ndarray
    stop_points: list[np.ndarray] = field(default_factory=list)
    turns: list[str] = field(default_factory=list)


TURN_RADIUS = {"right": 6.0, "left": 10.0}
"""Arc radius (m) of the lane-centre path through an intersection. A right turn goes from the outer lane to
the inner lane with a tight arc, so that a car's body stays clear of the square curb corner; a left turn
goes from inner lane to inner lane."""


def lane_route(layout: RoadLayout, start: np.ndarray, direction: np.ndarray, lane: int, turns: list[str],
               stop_margin: float, max_length: float) -> LaneRoute:
    """Route on lane centres from `start` (local xy on a lane of the road it drives along) heading along the
    axis unit vector `direction`; at each intersection ahead the next entry of `turns` ('left', 'right',
    'straight') is taken, cycling. lane: 0 inner, 1 outer (right turns leave from the outer lane, left
    turns from the inner one; both end in the inner lane; lane changes happen on the straights).
    stop_margin: distance from the reference point to the vehicle's front, so stop points put the front
    at the stop polygon. Stops are recorded at every intersection."""
    d = np.asarray(direction, np.float64)
    pos = np.asarray(start, np.float64)
    pts = [pos.copy()]
    stops, taken = [], []
    hw, lw = layout.half_width, layout.lane_width
    straight_reach = hw + 7.0  # where a straight crossing's waypoints sit before / after the centre
    lo_x, hi_x, lo_y, hi_y = layout.bounds()
    travelled, k = 0.0, 0
    while travelled < max_length:
        axis = 0 if abs(d[0]) > 0.5 else 1
        crossing = layout.xs if axis == 0 else layout.ys
        ahead = sorted(c for c in crossing if (c - pos[axis]) * d[axis] > straight_reach + 1.0)
        if d[axis] < 0:
            ahead = ahead[::-1]
        if not ahead:
            end = pos.copy()
            end[axis] = (hi_x if d[0] > 0 else lo_x) if axis == 0 else (hi_y if d[1] > 0 else lo_y)
            end[axis] -= d[axis] * 5.0
            pts.append(end)
            break
        right = _right(d)
        centre = pos.copy()
        centre[axis] = ahead[0]
        centre[1 - axis] = pos[1 - axis] - right[1 - axis] * (lane + 0.5) * lw
        turn = turns[k % len(turns)] if turns else "straight"
        k += 1
        lane_now = {"left": 0, "right": 1, "straight": lane}[turn]
        new_lane = 0 if turn != "straight" else lane
        a_in, a_out = (lane_now + 0.5) * lw, (new_lane + 0.5) * lw
        stops.append(centre - d * (layout.approach + 0.5 + stop_margin) + right * a_in)
        if turn == "straight":
            p0, p5 = centre - d * straight_reach + right * a_in, centre + d * straight_reach + right * a_in
            arc = [p0]
            new_d = d
        else:
            R = TURN_RADIUS[turn]
            sign = 1.0 if turn == "right" else -1.0
            C = centre + d * (-a_out - R if turn == "right" else a_out - R) + right * (a_in + sign * R)
            p0 = C - sign * right * R
            ang0 = np.arctan2(*(p0 - C)[::-1])
            ang = ang0 - sign * np.linspace(0.0, np.pi / 2, 40)
            arc = list(C + R * np.stack([np.cos(ang), np.sin(ang)], 1))
            new_d = right if turn == "right" else -right
            p5 = arc[-1]
        travelled += float(np.linalg.norm(p5 - pts[-1]))
        pts.extend(arc)
        pts.append(p5)
        taken.append(turn)
        d, lane, pos = new_d, new_lane, p5
    return LaneRoute(np.array(pts), stops, taken)


@dataclass
class Motion:
    """Arc length s (T,), speed v (T,) m/s and longitudinal acceleration a (T,) m/s^2 sampled every STEP_S
    from t = 0."""

    s: np.ndarray
    v: np.ndarray
    a: np.ndarray

    def sample(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s, v, a) at times t (s, any shape), linear between samples, held after the end."""
        grid = np.arange(len(self.s)) * STEP_S
        return np.interp(t, grid, self.s), np.interp(t, grid, self.v), np.interp(t, grid, self.a)


def _feasible_speed(limit: np.ndarray, ds: float, decel: float, stop_index: int | None) -> np.ndarray:
    """Backward pass: the highest speed at each path sample from which the limits ahead (and a stop at
    stop_index) are reachable with deceleration `decel`."""
    v = limit.copy()
    if stop_index is not None:
        v[stop_index:] = 0.0
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2.0 * decel * ds))
    return v


def drive(path: Path, duration: float, cruise: float, stops: list[tuple[float, float]], start_speed: float | None = None,
          lateral_accel: float = 2.0, accel: float = 1.6, decel: float = 2.5, jerk: float = 2.0) -> Motion:
    """Longitudinal motion along `path` for `duration` s: jerk-limited tracking of the feasible speed
    (cruise, curve limit sqrt(lateral_accel / |curvature|), stops at arc length s with dwell seconds)."""
    kappa = np.abs(path.curvature())
    ds = float(path.s[1] - path.s[0])
    limit = np.minimum(cruise, np.sqrt(lateral_accel / np.maximum(kappa, 1e-6)))
    pending = sorted((s, dwell) for s, dwell in stops if 0.0 < s < path.length)
    n = int(round(duration / STEP_S)) + 1
    out_s, out_v, out_a = np.zeros(n), np.zeros(n), np.zeros(n)
    s = 0.0
    v = cruise if start_speed is None else start_speed
    a, hold = 0.0, 0.0
    def plan() -> np.ndarray:
        return _feasible_speed(limit, ds, 0.7 * decel, int((pending[0][0] - 0.3) / ds) if pending else None)

    speed = plan()
    for i in range(n):
        out_s[i], out_v[i], out_a[i] = s, v, a
        if hold > 0.0:
            hold -= STEP_S
            if hold <= 0.0:
                pending.pop(0)
                speed = plan()
            continue
        look = min(int((s + 0.5 * v) / ds), len(speed) - 1)
        target = speed[look]
        a_cmd = np.clip(2.0 * (target - v), -decel, accel)
        a += float(np.clip(a_cmd - a, -jerk * STEP_S * 3, jerk * STEP_S * 3))
        v_new = max(v + a * STEP_S, 0.0)
        if pending and s >= pending[0][0] - 1.0 and v_new < 0.25:
            v_new, a, hold = 0.0, 0.0, pending[0][1]
        s = min(s + 0.5 * (v + v_new) * STEP_S, path.length)
        v = v_new if s < path.length else 0.0
    return Motion(out_s, out_v, out_a)
