"""The arm's links as capsules, from the robot model's link frames.

A capsule is a segment with a radius: every point within the radius of the
segment belongs to the link. The segments are given per robot as two points,
each fixed in one of the frames of :meth:`fabflow.robots.chain.RobotModel.frames`
(frame 0 the base at the foot of axis 1, DH frames 1..dof, then the flange), so
that :func:`link_segments` places every link of many configurations at once.

The radii are envelopes of the vendors' outline drawings, rounded up by a few
centimetres: they are meant for clearance checks, not for rendering.

KUKA KR 60-3 (DH frame 1 on the A2 axis, 2 on A3, 3 at the A4 offset, 4 the
wrist centre, 7 the flange):

============  ===========================================  ==========
link          segment                                      radius (m)
============  ===========================================  ==========
base          0.25 m up the A1 axis from the foot          0.30
carousel      A1 axis at 0.45 m -> A2 axis                 0.25
A2 housing    along the A2 axis, +-0.12 m                  0.20
upper arm     A2 -> A3 (0.85 m)                            0.15
elbow         A3 -> A4 offset point (0.145 m)              0.15
forearm       A4 offset point -> wrist centre (0.82 m)     0.12
wrist         wrist centre -> flange (0.17 m)              0.09
============  ===========================================  ==========

ABB IRB 4600-60/2.05 has the same layout with its own lengths (radii 0.28,
0.22, 0.18, 0.13, 0.13, 0.10, 0.08 m); the UR10e and the BROKK 170 take
capsules between consecutive frame origins (0.075 m and 0.15 m).

The excavator (with the rotating gripper or the print head; APPROXIMATE, like
its lengths; DH frame 1 on the boom pivot, 2 on the stick pivot, 3 the wrist
centre, 7 the flange) is a chain of four capsules. Its cabin, counterweight and
legs are not links: they belong to the platform's footprint, so the boom foot
starts one radius (plus 5 cm) above the slew axis's foot, on the chassis.

============  ===========================================  ==========
link          segment                                      radius (m)
============  ===========================================  ==========
boom foot     0.45 m above the slew foot -> boom pivot     0.40
boom          boom pivot -> stick pivot (4.0 m)            0.25
stick         stick pivot -> wrist centre (2.5 m)          0.25
tiltrotator   wrist centre -> flange (0.4 m)               0.30
============  ===========================================  ==========
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fabflow.robots.chain import RobotModel


@dataclass(frozen=True)
class LinkCapsule:
    """One link: the segment from ``p_a`` (in frame ``frame_a``) to ``p_b`` (in frame ``frame_b``).

    Frame indices are those of :meth:`RobotModel.frames`; points in metres.
    """

    name: str
    frame_a: int
    p_a: tuple[float, float, float]
    frame_b: int
    p_b: tuple[float, float, float]
    radius: float


def _industrial(radii: tuple[float, ...], dof: int = 6) -> tuple[LinkCapsule, ...]:
    """Capsules of a six-axis arm with a shoulder offset, elbow offset and spherical wrist."""
    base, carousel, housing, upper, elbow, forearm, wrist = radii
    flange = dof + 1
    return (
        LinkCapsule("base", 0, (0.0, 0.0, base), 0, (0.0, 0.0, 0.25), base),
        LinkCapsule("carousel", 0, (0.0, 0.0, 0.45), 1, (0.0, 0.0, 0.0), carousel),
        LinkCapsule("A2 housing", 1, (0.0, 0.0, -0.12), 1, (0.0, 0.0, 0.12), housing),
        LinkCapsule("upper arm", 1, (0.0, 0.0, 0.0), 2, (0.0, 0.0, 0.0), upper),
        LinkCapsule("elbow", 2, (0.0, 0.0, 0.0), 3, (0.0, 0.0, 0.0), elbow),
        LinkCapsule("forearm", 3, (0.0, 0.0, 0.0), 4, (0.0, 0.0, 0.0), forearm),
        LinkCapsule("wrist", 4, (0.0, 0.0, 0.0), flange, (0.0, 0.0, 0.0), wrist),
    )


def _excavator() -> tuple[LinkCapsule, ...]:
    """Capsules of the excavator arm: boom foot, boom, stick, tiltrotator (see above)."""
    o = (0.0, 0.0, 0.0)
    return (
        LinkCapsule("boom foot", 0, (0.0, 0.0, 0.45), 1, o, 0.40),
        LinkCapsule("boom", 1, o, 2, o, 0.25),
        LinkCapsule("stick", 2, o, 3, o, 0.25),
        LinkCapsule("tiltrotator", 3, o, 7, o, 0.30),
    )


def _chain(dof: int, radius: float) -> tuple[LinkCapsule, ...]:
    """Capsules between consecutive frame origins (base to flange)."""
    o = (0.0, 0.0, 0.0)
    return tuple(LinkCapsule(f"link {i}", i, o, i + 1, o, radius) for i in range(dof + 1))


LINK_CAPSULES: dict[str, tuple[LinkCapsule, ...]] = {
    "kuka_kr60_3": _industrial((0.30, 0.25, 0.20, 0.15, 0.15, 0.12, 0.09)),
    "abb_irb4600_60_205": _industrial((0.28, 0.22, 0.18, 0.13, 0.13, 0.10, 0.08)),
    "ur10e": _chain(6, 0.075),
    "brokk_170": _chain(5, 0.15),
    "excavator_gripper": _excavator(),
    "excavator_printer": _excavator(),
}
"""Link capsules per catalogue robot."""

TOOL_RADIUS = 0.05
"""Radius of the tool capsule from the flange to the tool centre point (metres): a
vacuum gripper or an extruder nozzle body; the capsule's end cap reaches the TCP."""


def link_capsules(robot: RobotModel) -> tuple[LinkCapsule, ...]:
    """The link capsules of a robot: its own (``RobotModel.capsules``), the catalogue's,
    or capsules of 0.1 m between consecutive frame origins."""
    if robot.capsules is not None:
        return robot.capsules
    return LINK_CAPSULES.get(robot.name, _chain(robot.dof, 0.1))


def link_segments(
    robot: RobotModel,
    q: np.ndarray,
    T_flange_tool: np.ndarray | None = None,
    frames: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Segment end points of every link capsule for many configurations.

    Parameters
    ----------
    robot
        The robot model.
    q
        (N, dof) joint values (radians).
    T_flange_tool
        4x4 tool centre point in the flange frame; when given, a tool capsule
        (radius :data:`TOOL_RADIUS`) from the flange to the TCP is appended,
        its end cap touching the TCP.
    frames
        ``robot.frames(q)`` of the (N, dof) configurations when the caller has it.

    Returns
    -------
    segments
        (N, L, 2, 3) end points in the robot base frame (metres).
    radii
        (L,) capsule radii (metres).
    names
        The L link names (``"tool"`` last when a tool is given).
    """
    if frames is None:
        frames = robot.frames(np.atleast_2d(np.asarray(q, dtype=float)))
    caps = link_capsules(robot)
    ia = np.array([c.frame_a for c in caps])
    ib = np.array([c.frame_b for c in caps])
    pa = np.array([c.p_a for c in caps])
    pb = np.array([c.p_b for c in caps])
    n = len(frames)
    ends = np.empty((n, len(caps), 2, 3))
    for end, index, p in ((0, ia, pa), (1, ib, pb)):
        # R @ p + t as a sum of the columns p uses (capsules run along an axis):
        # numpy's stacked 3x3 products are slow; the sum's order is the product's
        terms = [frames[:, :, :3, j][:, index] * p[:, j, None] for j in range(3) if p[:, j].any()]
        origin = frames[:, :, :3, 3][:, index]
        ends[:, :, end] = sum(terms[1:], terms[0]) + origin if terms else origin
    segments = [ends]
    radii = [c.radius for c in caps]
    names = link_names(robot, tool=T_flange_tool is not None)
    if T_flange_tool is not None:
        T = np.asarray(T_flange_tool, dtype=float)
        flange = frames[:, -1]
        tcp = flange[:, :3, :3] @ T[:3, 3] + flange[:, :3, 3]
        length = float(np.linalg.norm(T[:3, 3]))
        back = min(TOOL_RADIUS, length) / max(length, 1e-12)
        end = tcp + back * (flange[:, :3, 3] - tcp)
        segments.append(np.stack([flange[:, :3, 3], end], axis=1)[:, None])
        radii.append(TOOL_RADIUS)
    return np.concatenate(segments, axis=1), np.array(radii), names


def link_names(robot: RobotModel, tool: bool = False) -> list[str]:
    """The names of :func:`link_segments`' bodies: the link capsules', then ``"tool"``
    when it appends the tool capsule."""
    return [*(c.name for c in link_capsules(robot)), *(["tool"] if tool else [])]


def shoulder_radius(robot: RobotModel) -> float:
    """Plan radius about axis 1 swept by the links that only axis 1 moves (metres).

    The base, the carousel and the axis-2 housing (capsules fixed in frames 0 and 1)
    turn with axis 1 alone: whatever stands within this distance of the axis, at
    their height, is hit when axis 1 turns towards it.
    """
    frames = robot.frames(np.zeros(robot.dof))
    reach = 0.0
    for c in link_capsules(robot):
        if max(c.frame_a, c.frame_b) > 1:
            continue
        for f, p in ((c.frame_a, c.p_a), (c.frame_b, c.p_b)):
            point = frames[f, :3, :3] @ np.asarray(p) + frames[f, :3, 3]
            reach = max(reach, float(np.hypot(point[0], point[1])) + c.radius)
    return reach
