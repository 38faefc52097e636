"""An arm from a URDF file: the serial chain from a base link to a tip link.

The file is read through yourdfpy (the ``interop`` extra) after a bounded,
well-formedness check of its XML: at most :data:`MAX_URDF_BYTES`, no DOCTYPE
(so no entities), a ``<robot>`` root. Only the joints between ``base_link``
and ``tip_link`` are used: revolute and prismatic joints become the arm's
joints (at most :data:`MAX_URDF_JOINTS`), fixed joints fold into the links
between them; their ``<limit>`` gives the joint limits (radians, metres) and
speeds (rad/s, m/s). Geometry and meshes are not read. Every problem is an
:class:`UrdfError` naming the file, the line and the joint.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fabflow.errors import InputError
from fabflow.files import read_text
from fabflow.robots.joint_chain import JointChain, chain_from_joints

FloatArray = NDArray[np.float64]

MAX_URDF_BYTES = 4 * 2**20
"""Largest URDF file read (bytes): a robot description without meshes is far smaller."""
MAX_URDF_JOINTS = 12
"""Most revolute and prismatic joints between the base and the tip link."""
MAX_OFFSET = 1000.0
"""Largest translation of a joint origin (metres)."""
MAX_TURN = 4.0 * math.pi
"""Largest magnitude of a revolute joint limit (radians: two turns)."""
MAX_SPEED = 1000.0
"""Largest joint speed (rad/s or m/s)."""
JOINT_TYPES = ("revolute", "prismatic", "fixed")


class UrdfError(InputError):
    """A URDF file fabflow cannot take.

    ``field`` names the project field the problem belongs to: ``"urdf"`` (the
    file), ``"base_link"`` or ``"tip_link"``.
    """

    def __init__(
        self, message: str, source: str | Path, location: str | None = None, field: str = "urdf"
    ) -> None:
        super().__init__(message, source, location)
        self.field = field


@dataclass(frozen=True, eq=False)
class UrdfArm:
    """The serial chain of a URDF file between two links.

    Attributes
    ----------
    joint_names
        The revolute and prismatic joints from the base to the tip link.
    chain
        Their kinematics; the chain's tip frame is ``tip_link``'s frame.
    joint_limits
        ``(dof, 2)`` lower and upper limits (radians; metres for a prismatic joint).
    velocity_limits
        ``(dof,)`` joint speeds (rad/s; m/s).
    """

    joint_names: tuple[str, ...]
    chain: JointChain
    joint_limits: FloatArray
    velocity_limits: FloatArray


def read_urdf_text(path: str | Path) -> str:
    """The text of a URDF file of at most :data:`MAX_URDF_BYTES` (UTF-8)."""
    return read_text(path, "URDF file", MAX_URDF_BYTES)


def _parse(text: str, source: str | Path) -> tuple[Any, dict[str, int]]:
    """yourdfpy's robot of a checked XML text, and the line of every joint by name."""
    try:
        from lxml import etree
        from yourdfpy import URDF
    except ImportError:
        raise UrdfError(
            "reading a URDF file needs the yourdfpy package: pip install 'fabflow[interop]'",
            source,
        ) from None
    data = text.encode("utf-8")
    parser = etree.XMLParser(
        resolve_entities=False, no_network=True, load_dtd=False, huge_tree=False
    )
    try:
        root = etree.fromstring(data, parser=parser)
    except etree.XMLSyntaxError as exc:
        line = getattr(exc, "lineno", None)
        raise UrdfError(
            f"not well-formed XML: {exc.msg}", source, f"line {line}" if line else None
        ) from None
    if root.getroottree().docinfo.doctype:
        raise UrdfError("a URDF file with a DOCTYPE is not read (no entities)", source)
    if root.tag != "robot":
        raise UrdfError(f"the root element is <{root.tag}>, not <robot>", source)
    lines = {str(j.get("name")): int(j.sourceline or 0) for j in root.iter("joint")}
    try:
        with np.errstate(all="ignore"):  # non-finite values are refused below, not warned of
            urdf = URDF.load(
                io.BytesIO(data),
                build_scene_graph=False,
                build_collision_scene_graph=False,
                load_meshes=False,
                load_collision_meshes=False,
            )
    except Exception as exc:  # a third-party parser on untrusted input: any failure is the file's
        raise UrdfError(f"not a URDF robot: {type(exc).__name__}: {exc}", source) from None
    return urdf.robot, lines


def _path(robot: Any, base: str, tip: str, source: str | Path) -> list[Any]:
    """The joints from ``base`` to ``tip``, in that order."""
    links = {link.name for link in robot.links}
    for field, name in (("base_link", base), ("tip_link", tip)):
        if name not in links:
            known = ", ".join(sorted(map(str, links))[:12])
            raise UrdfError(f"no link {name!r} in the file (links: {known})", source, field=field)
    parent_joint: dict[str, Any] = {}
    for joint in robot.joints:
        if joint.child in parent_joint:
            raise UrdfError(f"link {joint.child!r} is the child of two joints: not a tree", source)
        parent_joint[joint.child] = joint
    path, link = [], tip
    while link != base:
        joint = parent_joint.get(link)
        if joint is None or len(path) > len(robot.joints):
            raise UrdfError(
                f"no chain of joints leads from base_link {base!r} to tip_link {tip!r}",
                source,
                field="tip_link",
            )
        path.append(joint)
        link = joint.parent
    if not path:
        raise UrdfError("base_link and tip_link are the same link", source, field="tip_link")
    return path[::-1]


def _finite(values: Any, bound: float) -> bool:
    a = np.asarray(values, dtype=float)
    return bool(np.all(np.isfinite(a)) and np.all(np.abs(a) <= bound))


def urdf_arm(text: str, base_link: str, tip_link: str, source: str | Path) -> UrdfArm:
    """The arm between two links of a URDF document.

    Parameters
    ----------
    text
        The URDF (XML) text.
    base_link, tip_link
        Link names: the arm's base frame and the link its flange is fixed to.
    source
        The file, for messages.

    Raises
    ------
    UrdfError
        For text that is not a URDF robot, links that are missing or not joined
        by a chain, a joint of another type than revolute, prismatic or fixed, a
        mimic joint, a joint without finite limits and speed, non-finite or
        out-of-bounds values, or more than :data:`MAX_URDF_JOINTS` joints.
    """
    robot, lines = _parse(text, source)
    origins, axes, prismatic, names, limits, speeds = [], [], [], [], [], []
    pending = np.eye(4)
    for joint in _path(robot, base_link, tip_link, source):
        where = f"line {lines.get(joint.name, 0)}: joint {joint.name!r}"
        if joint.type not in JOINT_TYPES:
            raise UrdfError(
                f"a {joint.type} joint; the arm's chain takes revolute, prismatic and fixed "
                "joints (write a continuous joint as revolute with limits)",
                source,
                where,
            )
        origin = np.eye(4) if joint.origin is None else np.asarray(joint.origin, dtype=float)
        if origin.shape != (4, 4) or not _finite(origin, MAX_OFFSET):
            raise UrdfError(f"the origin must be finite, within {MAX_OFFSET:g} m", source, where)
        pending = pending @ origin
        if joint.type == "fixed":
            continue
        if joint.mimic is not None:
            raise UrdfError("a mimic joint is not taken in the arm's chain", source, where)
        axis = np.array([1.0, 0.0, 0.0]) if joint.axis is None else np.asarray(joint.axis, float)
        if axis.shape != (3,) or not _finite(axis, 1e6) or np.linalg.norm(axis) < 1e-9:
            raise UrdfError("the axis must be three finite numbers, not all 0", source, where)
        lim = joint.limit
        bound = MAX_OFFSET if joint.type == "prismatic" else MAX_TURN
        lo, hi, v = (None, None, None) if lim is None else (lim.lower, lim.upper, lim.velocity)
        if lo is None or hi is None or v is None:
            raise UrdfError(
                "a revolute or prismatic joint needs <limit lower upper velocity>", source, where
            )
        if not (_finite([lo, hi], bound) and lo < hi):
            raise UrdfError(
                f"the limits must be finite, lower < upper, within +-{bound:g}", source, where
            )
        if not (_finite([v], MAX_SPEED) and v > 0):
            raise UrdfError(f"the velocity must be positive, at most {MAX_SPEED:g}", source, where)
        origins.append(pending)
        axes.append(axis / np.linalg.norm(axis))
        prismatic.append(joint.type == "prismatic")
        names.append(str(joint.name))
        limits.append((float(lo), float(hi)))
        speeds.append(float(v))
        pending = np.eye(4)
        if len(names) > MAX_URDF_JOINTS:
            raise UrdfError(
                f"more than {MAX_URDF_JOINTS} joints between {base_link!r} and {tip_link!r}",
                source,
                where,
            )
    if not names:
        raise UrdfError(
            f"no revolute or prismatic joint between {base_link!r} and {tip_link!r}",
            source,
            field="tip_link",
        )
    return UrdfArm(
        joint_names=tuple(names),
        chain=chain_from_joints(np.stack(origins), np.stack(axes), prismatic, pending),
        joint_limits=np.array(limits, dtype=float),
        velocity_limits=np.array(speeds, dtype=float),
    )
