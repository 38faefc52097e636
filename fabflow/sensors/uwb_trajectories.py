"""Trajectories of a moving UWB tag: planar paths at a fixed height, driven smoothly.

A path runs through waypoints with its corners rounded, at a smooth (cosine ramp)
speed profile, so position, velocity and acceleration are all analytic; the IMU
simulator (:mod:`fabflow.sensors.imu`) differentiates nothing numerically. The
paper's trajectories (seeds/003, section 4.2) are
:func:`fabflow.sensors.uwb.paper_trajectories`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fabflow.errors import InputError


@dataclass(frozen=True)
class TrajectorySample:
    """Kinematic truth at given times (world frame, platform level: roll = pitch = 0).

    Attributes
    ----------
    t
        (N,) times (s).
    p, v, a
        (N, 3) position (m), velocity (m/s), acceleration (m/s^2).
    yaw, yaw_rate
        (N,) heading about the world z axis (rad) and its rate (rad/s).
    """

    t: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    yaw: np.ndarray
    yaw_rate: np.ndarray

    @property
    def R_world_body(self) -> np.ndarray:
        """(N, 3, 3) body attitude (rotation about z by ``yaw``)."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        R = np.zeros((self.yaw.size, 3, 3))
        R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
        return R


@dataclass(frozen=True)
class PlanarTrajectory:
    """A planar path at height ``z`` through waypoints, corners rounded, driven smoothly.

    The platform rests ``rest_s`` seconds, accelerates with a cosine ramp of
    ``ramp_s`` seconds to ``speed``, follows the path (lines and circular arcs of
    ``corner_radius``), decelerates and rests again. The heading follows the
    path tangent.

    Attributes
    ----------
    waypoints
        (k, 2) plan waypoints (metres), k >= 2.
    z
        Height of the path (metres).
    speed, corner_radius, ramp_s, rest_s
        Cruise speed (m/s), corner fillet radius (m), ramp and rest durations (s).
    name
        Label used in reports.
    """

    waypoints: np.ndarray
    z: float
    speed: float = 0.3
    corner_radius: float = 0.3
    ramp_s: float = 1.5
    rest_s: float = 3.0
    name: str = "path"
    _segs: dict[str, np.ndarray] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        w = np.asarray(self.waypoints, dtype=float)
        if w.ndim != 2 or w.shape[1] != 2 or w.shape[0] < 2:
            raise InputError("a trajectory needs at least two (x, y) waypoints")
        object.__setattr__(self, "waypoints", w)
        object.__setattr__(self, "_segs", self._build(w))

    def _build(self, w: np.ndarray) -> dict[str, np.ndarray]:
        u = np.diff(w, axis=0)
        lengths = np.linalg.norm(u, axis=1)
        if np.any(lengths <= 0):
            raise InputError("trajectory waypoints must be distinct")
        u = u / lengths[:, None]
        trim = np.zeros(len(w))
        kinds, starts, lens, origin, direction, center, theta0, turn = (
            [],
            [],
            [],
            [],
            [],
            [],
            [],
            [],
        )
        r = self.corner_radius
        arcs = []
        for i in range(1, len(w) - 1):
            cross = u[i - 1, 0] * u[i, 1] - u[i - 1, 1] * u[i, 0]
            phi = np.arccos(np.clip(u[i - 1] @ u[i], -1.0, 1.0))
            L = r * np.tan(phi / 2)
            trim[i] = L
            arcs.append((phi, L, np.sign(cross)))
        if np.any(trim[1:] + trim[:-1] > lengths + 1e-12):
            raise InputError("trajectory corner radius is too large for the waypoint spacing")
        s = 0.0
        for i in range(len(w) - 1):
            p0 = w[i] + u[i] * trim[i]
            seg_len = lengths[i] - trim[i] - trim[i + 1]
            kinds.append(0)
            starts.append(s)
            lens.append(seg_len)
            origin.append(p0)
            direction.append(u[i])
            center.append((0.0, 0.0))
            theta0.append(0.0)
            turn.append(0.0)
            s += seg_len
            if i < len(w) - 2 and arcs[i][2] != 0:
                phi, L, sign = arcs[i]
                p1 = w[i + 1] - u[i] * L
                normal = np.array([-u[i, 1], u[i, 0]])
                c = p1 + sign * r * normal
                kinds.append(1)
                starts.append(s)
                lens.append(r * phi)
                origin.append(p1)
                direction.append(u[i])
                center.append(c)
                theta0.append(np.arctan2(p1[1] - c[1], p1[0] - c[0]))
                turn.append(sign)
                s += r * phi
        return {
            "kind": np.array(kinds),
            "start": np.array(starts),
            "length": np.array(lens),
            "origin": np.array(origin),
            "dir": np.array(direction),
            "center": np.array(center),
            "theta0": np.array(theta0),
            "turn": np.array(turn),
        }

    @property
    def path_length(self) -> float:
        """Length of the path (metres)."""
        return float(self._segs["start"][-1] + self._segs["length"][-1])

    @property
    def _profile(self) -> tuple[float, float, float]:
        """(cruise speed, ramp time, cruise time) for this path length."""
        L = self.path_length
        v, Tr = self.speed, self.ramp_s
        if v * Tr > L:
            v = L / Tr
        return v, Tr, (L - v * Tr) / v

    @property
    def duration(self) -> float:
        """Total duration including both rests (s)."""
        _, Tr, Tc = self._profile
        return 2 * self.rest_s + 2 * Tr + Tc

    def _arclength(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        v, Tr, Tc = self._profile
        L = self.path_length
        tau = t - self.rest_s
        s = np.zeros_like(t)
        sd = np.zeros_like(t)
        sdd = np.zeros_like(t)
        up = (tau > 0) & (tau <= Tr)
        x = np.pi * tau[up] / Tr
        s[up] = 0.5 * v * (tau[up] - Tr / np.pi * np.sin(x))
        sd[up] = 0.5 * v * (1 - np.cos(x))
        sdd[up] = 0.5 * v * np.pi / Tr * np.sin(x)
        cruise = (tau > Tr) & (tau <= Tr + Tc)
        s[cruise] = 0.5 * v * Tr + v * (tau[cruise] - Tr)
        sd[cruise] = v
        down = (tau > Tr + Tc) & (tau < 2 * Tr + Tc)
        tr = 2 * Tr + Tc - tau[down]
        x = np.pi * tr / Tr
        s[down] = L - 0.5 * v * (tr - Tr / np.pi * np.sin(x))
        sd[down] = 0.5 * v * (1 - np.cos(x))
        sdd[down] = -0.5 * v * np.pi / Tr * np.sin(x)
        s[tau >= 2 * Tr + Tc] = L
        return s, sd, sdd

    def sample(self, t: np.ndarray) -> TrajectorySample:
        """Position, velocity, acceleration and heading at times ``t`` (seconds)."""
        t = np.asarray(t, dtype=float)
        s, sd, sdd = self._arclength(t)
        g = self._segs
        i = np.clip(np.searchsorted(g["start"], s, side="right") - 1, 0, len(g["start"]) - 1)
        ds = np.clip(s - g["start"][i], 0.0, g["length"][i])
        arc = g["kind"][i] == 1
        r = self.corner_radius
        sign = g["turn"][i]
        theta = g["theta0"][i] + sign * ds / r
        cth, sth = np.cos(theta), np.sin(theta)
        pos_arc = g["center"][i] + r * np.stack([cth, sth], axis=1)
        tan_arc = sign[:, None] * np.stack([-sth, cth], axis=1)
        curv_arc = -np.stack([cth, sth], axis=1) / r
        pos_line = g["origin"][i] + ds[:, None] * g["dir"][i]
        pos = np.where(arc[:, None], pos_arc, pos_line)
        tangent = np.where(arc[:, None], tan_arc, g["dir"][i])
        curvature = np.where(arc[:, None], curv_arc, 0.0)
        n = t.size
        p = np.column_stack([pos, np.full(n, self.z)])
        v = np.column_stack([tangent * sd[:, None], np.zeros(n)])
        a = np.column_stack([curvature * (sd**2)[:, None] + tangent * sdd[:, None], np.zeros(n)])
        yaw = np.arctan2(tangent[:, 1], tangent[:, 0])
        yaw_rate = np.where(arc, sign * sd / r, 0.0)
        return TrajectorySample(t=t, p=p, v=v, a=a, yaw=yaw, yaw_rate=yaw_rate)
