"""The joint setpoints of a JSON command stream, read at the link's cycle.

A program written by :mod:`fabflow.programs.writers.json_stream` is a list of
timed commands; its ``setpoint`` commands carry the joint configuration
(radians) at their time ``t`` (seconds from the start). The streamer sends the
configuration linearly interpolated between them at every cycle; ``io``,
``wait`` and ``confirm`` commands move nothing and are passed over (the
machine simulator has no outputs; a real gateway would take them as their own
messages, which version 1 of the link does not carry).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from fabflow.errors import InputError
from fabflow.files import read_text, strict_json
from fabflow.link.protocol import MAX_JOINTS
from fabflow.robots.catalog import CUSTOM_PREFIX, ROBOT_NAMES, get_robot, is_registered

FloatArray = NDArray[np.float64]

MAX_SETPOINTS = 1_000_000
"""The most setpoints a program may hold."""


@dataclass(frozen=True, eq=False)
class Setpoints:
    """A program's joint path.

    Attributes
    ----------
    robot
        The catalogue robot the program was written for.
    t
        ``(K,)`` non-decreasing times (s from the program's start).
    q
        ``(K, dof)`` joint configurations (radians).
    """

    robot: str
    t: FloatArray
    q: FloatArray

    @property
    def duration(self) -> float:
        """Time of the last setpoint (s)."""
        return float(self.t[-1])

    def at(self, t: float) -> FloatArray:
        """The configuration at time ``t`` (s), held before the first and after the last."""
        k = int(np.searchsorted(self.t, t, side="right"))
        if k <= 0:
            return self.q[0].copy()
        if k >= len(self.t):
            return self.q[-1].copy()
        t0, t1 = self.t[k - 1], self.t[k]
        w = 0.0 if t1 <= t0 else (t - t0) / (t1 - t0)
        return self.q[k - 1] + w * (self.q[k] - self.q[k - 1])


def read_setpoints(path: str | Path) -> Setpoints:
    """The setpoints of a JSON command stream file.

    Raises
    ------
    InputError
        When the file is not a command stream of version 1, names an unknown
        robot, holds no setpoint, or a setpoint with a wrong number of joints, a
        non-finite value, a joint outside the robot's limits or a time earlier
        than the one before.
    """
    text = read_text(path, "program")
    try:
        doc = strict_json(text)
    except (ValueError, RecursionError) as e:
        raise InputError(f"not a JSON file: {e}", path) from None
    if not isinstance(doc, dict) or doc.get("format") != "fabflow-command-stream":
        raise InputError("not a fabflow command stream (format 'fabflow-command-stream')", path)
    if doc.get("version") != 1:
        raise InputError(f"command stream version {doc.get('version')!r}; this reads 1", path)
    robot = doc.get("robot")
    if isinstance(robot, str) and robot.startswith(CUSTOM_PREFIX) and not is_registered(robot):
        raise InputError(
            f"the program is for {robot!r}, a robot defined in a project file, which a JSON "
            "program does not carry; streaming takes the catalogue robots: "
            + ", ".join(ROBOT_NAMES),
            path,
            "robot",
        )
    if robot not in ROBOT_NAMES and not (isinstance(robot, str) and is_registered(robot)):
        raise InputError(f"unknown robot {robot!r}; known: {', '.join(ROBOT_NAMES)}", path, "robot")
    model = get_robot(str(robot))
    commands = doc.get("commands")
    if not isinstance(commands, list):
        raise InputError("'commands' must be a list", path, "commands")
    rows = [(i, c) for i, c in enumerate(commands) if isinstance(c, dict)]
    points = [(i, c) for i, c in rows if c.get("type") == "setpoint"]
    if not points or len(points) > MAX_SETPOINTS:
        raise InputError(f"a program needs 1 to {MAX_SETPOINTS} setpoints", path, "commands")
    t = np.empty(len(points))
    q = np.empty((len(points), model.dof))
    for k, (i, c) in enumerate(points):
        where = f"commands[{i}]"
        tk, qk = c.get("t"), c.get("q")
        if isinstance(tk, bool) or not isinstance(tk, int | float) or not math.isfinite(tk):
            raise InputError("a setpoint's 't' must be a finite number (s)", path, where)
        if (
            not isinstance(qk, list)
            or len(qk) != model.dof
            or len(qk) > MAX_JOINTS
            or not all(
                isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                for v in qk
            )
        ):
            raise InputError(
                f"a setpoint's 'q' must be {model.dof} finite joint values (radians)", path, where
            )
        t[k], q[k] = tk, qk
    if np.any(np.diff(t) < 0) or t[0] < 0:
        raise InputError("setpoint times must start at 0 or later and never decrease", path)
    bad = ~model.within_limits(q, tol=1e-6)
    if bad.any():
        i = points[int(np.argmax(bad))][0]
        raise InputError(f"a setpoint lies outside {robot}'s joint limits", path, f"commands[{i}]")
    return Setpoints(robot=str(robot), t=t, q=q)
