"""The element model: one thing to build, with its pose, geometry and supports.

Frames: ``T_world_element`` places the element frame in the world. For a block
the element frame sits at the centre of the block, x along its length, z up;
for a print path it is the frame the path's points are given in; for a task
point it is the tool frame to reach; for a stone (a found object) it is the
slot the stone is set in, centre, x along the wall, z up.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Literal

import numpy as np

ElementType = Literal["block", "print_path", "task_point", "stone"]


@dataclass(frozen=True, eq=False)
class Element:
    """One element of the design.

    Attributes
    ----------
    id
        Unique id within a project (e.g. ``"B0123"``).
    type
        ``"block"``, ``"print_path"``, ``"task_point"`` or ``"stone"``.
    T_world_element
        4x4 pose of the element frame in the world frame (metres).
    layer
        Layer index (0 = lowest), used for build order.
    supports
        Ids of the elements this one rests on.
    part
        Which part of the design it belongs to (``"A"``, ``"front"``, ...), or ``None``.
    robot_built
        Whether the robot places it (pre-built parts are not).
    extents
        Box size (length, width, height) in metres for blocks and stone slots,
        else ``None``.
    polyline
        (N, 3) points in the element frame for print paths, else ``None``.
    attributes
        Extra plain data: bead width, speed, action name and parameters, ...
    """

    id: str
    type: ElementType
    T_world_element: np.ndarray
    layer: int = 0
    supports: tuple[str, ...] = ()
    part: str | None = None
    robot_built: bool = True
    extents: np.ndarray | None = None
    polyline: np.ndarray | None = None
    attributes: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-compatible data; :meth:`from_dict` restores it exactly."""
        d: dict[str, Any] = {
            "id": self.id,
            "type": self.type,
            "T_world_element": np.asarray(self.T_world_element, dtype=float).tolist(),
            "layer": int(self.layer),
            "supports": list(self.supports),
            "part": self.part,
            "robot_built": bool(self.robot_built),
        }
        if self.extents is not None:
            d["extents"] = np.asarray(self.extents, dtype=float).tolist()
        if self.polyline is not None:
            d["polyline"] = np.asarray(self.polyline, dtype=float).tolist()
        if self.attributes:
            d["attributes"] = self.attributes
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Element:
        """Inverse of :meth:`to_dict`."""
        return cls(
            id=str(d["id"]),
            type=d["type"],
            T_world_element=np.asarray(d["T_world_element"], dtype=float).reshape(4, 4),
            layer=int(d.get("layer", 0)),
            supports=tuple(d.get("supports", ())),
            part=d.get("part"),
            robot_built=bool(d.get("robot_built", True)),
            extents=None if d.get("extents") is None else np.asarray(d["extents"], dtype=float),
            polyline=None
            if d.get("polyline") is None
            else np.asarray(d["polyline"], dtype=float).reshape(-1, 3),
            attributes=dict(d.get("attributes", {})),
        )


def hand_built_stages(elements: Sequence[Element], robot_order: Sequence[str]) -> dict[str, int]:
    """When each element the robot does not build stands, counted in robot-built elements.

    An element with ``robot_built=False`` stands once everything it rests on
    stands: from the start when that is the ground or other such elements, else
    as soon as the robot has built the elements under it. Hand work keeps pace
    with the robot: a log cabin's pre-built wall rests, at the corners, on the
    walls the robot builds, and rises course by course with them; a
    prefabricated gable is set on its wall once the wall is finished.

    Parameters
    ----------
    elements
        Every element of the design (``supports`` filled in).
    robot_order
        The robot-built element ids in the order the robot builds them.

    Returns
    -------
    dict[str, int]
        Id to ``k``: the element stands once the first ``k`` elements of
        ``robot_order`` are built (0: from the start). An element that rests,
        directly or through others, on a robot-built element missing from
        ``robot_order`` (or on a cycle of such elements) counts as standing from
        the start: the cautious choice for the collision check. Supports naming
        no element are ignored.
    """
    position = {eid: k + 1 for k, eid in enumerate(robot_order)}
    robot = {e.id for e in elements if e.robot_built}
    pre = {e.id: e for e in elements if not e.robot_built}
    stage: dict[str, int] = {}
    pending = dict(pre)
    while pending:  # what rests on resolved elements resolves; at most one pass per level
        done = {}
        for eid, e in pending.items():
            after = [stage.get(s, position.get(s)) for s in e.supports if s in pre or s in robot]
            if all(a is not None for a in after):
                done[eid] = max([a for a in after if a is not None], default=0)
        if not done:
            break
        stage.update(done)
        pending = {k: v for k, v in pending.items() if k not in done}
    # resting (through others) on an element that is never built, or on each other:
    # taken as standing from the start, where the collision check sees them all along
    stage.update({eid: 0 for eid in pending})
    return stage


def structure_timeline(
    elements: Sequence[Element], packages: Sequence[Sequence[str]]
) -> list[tuple[list[Element], list[tuple[Element, int]]]]:
    """What stands during each work package of a build.

    Parameters
    ----------
    elements
        Every element of the design.
    packages
        Per work package in build order, its robot-built element ids in build order.

    Returns
    -------
    list
        Per package: the elements standing when it starts (those of earlier
        packages and the hand-built ones, :func:`hand_built_stages`), and the
        hand-built ones that come during it, each with the index of the
        package's element after whose completion it stands.
    """
    by_id = {e.id: e for e in elements}
    stage = hand_built_stages(elements, [eid for ids in packages for eid in ids])
    hand = [e for e in elements if e.id in stage]
    out = []
    robot: list[Element] = []
    offset = 0
    for ids in packages:
        standing = [e for e in hand if stage[e.id] <= offset] + robot
        coming = [
            (e, stage[e.id] - offset - 1) for e in hand if offset < stage[e.id] <= offset + len(ids)
        ]
        out.append((standing, coming))
        robot = robot + [by_id[i] for i in ids]
        offset += len(ids)
    return out


def element_poses(elements: Sequence[Element]) -> np.ndarray:
    """Stack the element poses into an (N, 4, 4) array (world frame, metres)."""
    if not elements:
        return np.zeros((0, 4, 4))
    return np.stack([e.T_world_element for e in elements])


class Standing(tuple):
    """The elements standing at one moment (a tuple of :class:`Element`), their boxes
    (:func:`element_boxes`) made once however often they are asked for: a simulated
    construction run asks at every visit, and a Monte Carlo study runs thousands."""

    def __reduce__(self) -> tuple[type[Standing], tuple[tuple[Element, ...]]]:
        # the elements alone: a copy (a Dask worker's) makes its own boxes, read only
        return (Standing, (tuple(self),))

    @cached_property
    def boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`element_boxes` of the elements (read only)."""
        T, extents = _boxes(self)
        T.flags.writeable = extents.flags.writeable = False
        return T, extents


def element_boxes(elements: Sequence[Element]) -> tuple[np.ndarray, np.ndarray]:
    """The box-shaped elements (those with ``extents``) as arrays.

    Returns
    -------
    T_world_box, extents
        ``(k, 4, 4)`` box centre frames (world, metres) and ``(k, 3)`` full side
        lengths along the box axes (metres); those of a :class:`Standing` are
        shared by every call (read only).
    """
    if isinstance(elements, Standing):
        return elements.boxes
    return _boxes(elements)


def _boxes(elements: Sequence[Element]) -> tuple[np.ndarray, np.ndarray]:
    boxed = [e for e in elements if e.extents is not None]
    if not boxed:
        return np.zeros((0, 4, 4)), np.zeros((0, 3))
    T = np.stack([np.asarray(e.T_world_element, dtype=float) for e in boxed])
    return T, np.stack([np.asarray(e.extents, dtype=float) for e in boxed])


def elements_to_json(elements: Iterable[Element]) -> list[dict[str, Any]]:
    """Serialize elements to a JSON-compatible list."""
    return [e.to_dict() for e in elements]


def elements_from_json(data: Iterable[dict[str, Any]]) -> list[Element]:
    """Deserialize elements written by :func:`elements_to_json`."""
    return [Element.from_dict(d) for d in data]
