"""What the arm must stay clear of while it runs a work package: boxes with a time.

Every obstacle is a box (centre frame and full side lengths, metres):

* **structure**: every element built before the program starts (pre-built
  elements, the elements of earlier work packages) and, from its completion on,
  every element of the program itself. A block is complete when the gripper
  releases it, a print path or task point after its last move. Blocks are their
  design boxes (:func:`fabflow.design.elements.element_boxes`); a printed layer
  is one box per chord of its extruding segments (at most
  :data:`PRINT_CHORD_POINTS` path points, widened by the chord's deviation from
  the path), ``layer_height`` high below the path (the path runs on the top of
  the bead it lays).
* **platform**: the footprint rectangle, from the ground (world z = 0) up to the
  deck at the arm's foot (the lift height is in the localized base pose).
* **magazine**: the stack under the block waiting at the pick pose
  (``robot.platform.T_platform_pick``), from the deck up to the waiting block's
  bottom, the block's footprint plus :data:`MAGAZINE_MARGIN` on each side. The
  waiting block itself is the block the gripper takes. The footprint is the
  package's shortest block (longer blocks overhang the magazine).
* **site**: ``site.obstacles``; a polygon obstacle is checked as its bounding box.

``since`` orders obstacles in time: an obstacle is present for the motions of
stage ``s`` when ``since < s``. When ``c`` elements are complete, a move of the
last of them (its retract) has stage ``2 c - 1``, and the moves from the next
element's first on (and the HOME moves) have stage ``2 c``. So the program's
``j``-th element has ``since = 2 j`` (present from its completion), an element
built by hand that can come once the ``j``-th element stands has
``since = 2 j + 1`` (it comes when the tool has left, before the next element's
first move), and obstacles present from the start have ``since = -1``.
:func:`present_while` gives the obstacles standing while an element is built.
"""

from __future__ import annotations

import weakref
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fabflow.design.elements import Element, element_boxes
from fabflow.programs.motions import Placement
from fabflow.project import Project
from fabflow.tasks.targets import T_base_pick_tool, block_approach, element_tool_frames

PRINT_CHORD_POINTS = 8
"""Path points per box of a printed layer (the sine wall's points are ~6 mm apart)."""
MAGAZINE_MARGIN = 0.02
"""The magazine's frame around the waiting block, on each side (metres)."""


@dataclass(frozen=True)
class Obstacles:
    """Boxes in one frame, with their names, kinds, elements and times.

    Attributes
    ----------
    T
        (K, 4, 4) box centre frames (metres).
    extents
        (K, 3) full side lengths (metres).
    names
        (K,) what each box is (element id, ``"platform"``, a site obstacle's name).
    kinds
        (K,) ``"structure"``, ``"platform"``, ``"magazine"`` or ``"site"``.
    element
        (K,) the part a structure box belongs to (:func:`part_of`: the element's
        id, or the layer a piece of a split print path was cut from), else ``""``.
    since
        (K,) stage after which the box is present (see the module docstring).
    """

    T: np.ndarray
    extents: np.ndarray
    names: np.ndarray
    kinds: np.ndarray
    element: np.ndarray
    since: np.ndarray

    def __len__(self) -> int:
        return len(self.T)

    def moved(self, T_new_old: np.ndarray) -> Obstacles:
        """The same boxes expressed in another frame (``T_new_old``: old frame in the new)."""
        return Obstacles(
            T_new_old @ self.T, self.extents, self.names, self.kinds, self.element, self.since
        )

    @staticmethod
    def join(parts: Sequence[Obstacles]) -> Obstacles:
        """All boxes of ``parts``, in order."""
        parts = [p for p in parts if len(p)]
        if not parts:
            return _boxes(np.zeros((0, 4, 4)), np.zeros((0, 3)), [], "structure", [], [])
        return Obstacles(
            *(np.concatenate([getattr(p, f) for p in parts]) for f in Obstacles._fields())
        )

    @staticmethod
    def _fields() -> tuple[str, ...]:
        return ("T", "extents", "names", "kinds", "element", "since")


def _boxes(
    T: np.ndarray,
    extents: np.ndarray,
    names: Sequence[str],
    kind: str,
    element: Sequence[str],
    since: Sequence[int],
) -> Obstacles:
    n = len(T)
    return Obstacles(
        np.asarray(T, dtype=float).reshape(n, 4, 4),
        np.asarray(extents, dtype=float).reshape(n, 3),
        np.array(list(names), dtype=object),
        np.full(n, kind, dtype=object),
        np.array(list(element), dtype=object),
        np.asarray(since, dtype=np.int64).reshape(n),
    )


def _aabb_box(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    T = np.eye(4)
    T[:3, 3] = 0.5 * (lo + hi)
    return T, hi - lo


_BEAD_BOXES: weakref.WeakKeyDictionary[Element, tuple[np.ndarray, np.ndarray]] = (
    weakref.WeakKeyDictionary()
)
""":func:`print_path_boxes` per element (an element is frozen and hashed by identity;
an entry goes with its element): every later work package stands beside the layer."""


def print_path_boxes(element: Element) -> tuple[np.ndarray, np.ndarray]:
    """The bead of a print path as boxes along chords of its extruding segments.

    Made once per element: each later work package's environment holds the layer
    again (21 packages of 76 layers on the print wall).

    Returns
    -------
    T_world_box, extents
        (k, 4, 4) box centre frames (world) and (k, 3) side lengths: along the
        chord, across it (bead width plus twice the path's deviation from the
        chord), and the layer height (metres); read only.
    """
    boxes = _BEAD_BOXES.get(element)
    if boxes is None:
        T, extents = _bead_boxes(element)
        T.flags.writeable = extents.flags.writeable = False
        boxes = _BEAD_BOXES[element] = (T, extents)
    return boxes


def _bead_boxes(element: Element) -> tuple[np.ndarray, np.ndarray]:
    if element.polyline is None or len(element.polyline) < 2:
        return np.zeros((0, 4, 4)), np.zeros((0, 3))
    pts = np.asarray(element.polyline, dtype=float)
    n = len(pts)
    extrude = np.asarray(element.attributes.get("extrude", np.ones(n - 1)), dtype=bool)
    width = float(element.attributes.get("bead_width", 0.02))
    height = float(element.attributes.get("layer_height", 0.02))
    # Chord k runs from point starts[k] to ends[k] within one extruding run.
    edges = np.flatnonzero(np.diff(np.r_[0, extrude.astype(np.int8), 0]))
    starts, ends = [], []
    for a, b in zip(edges[::2], edges[1::2], strict=True):  # segments a..b-1: points a..b
        s = np.arange(a, b, PRINT_CHORD_POINTS)
        starts.append(s)
        ends.append(np.minimum(s + PRINT_CHORD_POINTS, b))
    if not starts:
        return np.zeros((0, 4, 4)), np.zeros((0, 3))
    i0, i1 = np.concatenate(starts), np.concatenate(ends)
    p0, p1 = pts[i0], pts[i1]
    # Deviation of the intermediate points from their chord (in plan).
    offs = np.arange(PRINT_CHORD_POINTS + 1)
    idx = np.minimum(i0[:, None] + offs, i1[:, None])
    d = p1[:, :2] - p0[:, :2]
    length = np.linalg.norm(d, axis=1)
    u = d / np.maximum(length, 1e-12)[:, None]
    rel = pts[idx, :2] - p0[:, None, :2]
    across = np.abs(rel[..., 0] * u[:, None, 1] - rel[..., 1] * u[:, None, 0]).max(axis=1)
    T_local = np.repeat(np.eye(4)[None], len(i0), axis=0)
    T_local[:, :2, 0] = u
    T_local[:, :2, 1] = np.c_[-u[:, 1], u[:, 0]]
    T_local[:, :3, 3] = 0.5 * (p0 + p1)
    T_local[:, 2, 3] -= 0.5 * height
    extents = np.c_[length + width, width + 2.0 * across, np.full(len(i0), height)]
    return np.asarray(element.T_world_element, dtype=float) @ T_local, extents


def part_of(element: Element) -> str:
    """The part an element belongs to: the print layer a piece was cut from, else itself.

    Pieces of one print layer (:mod:`fabflow.tasks.split`) meet at their seams, where
    the nozzle joins the new bead to the old one: for the tool they are one part.
    """
    return str(element.attributes.get("parent", element.id))


def structure_boxes(elements: Sequence[Element], since: Sequence[int]) -> Obstacles:
    """The boxes of built elements (blocks and printed layers), each with its ``since``."""
    parts: list[Obstacles] = []
    run: list[tuple[Element, int]] = []  # box-shaped elements in a row: one box each, at once

    def flush() -> None:
        if run:
            T, ext = element_boxes([e for e, _ in run])
            ids, owners = [e.id for e, _ in run], [part_of(e) for e, _ in run]
            parts.append(_boxes(T, ext, ids, "structure", owners, [s for _, s in run]))
            run.clear()

    for e, s in zip(elements, since, strict=True):
        if e.extents is not None:
            run.append((e, s))
        elif e.type == "print_path":
            flush()
            T, ext = print_path_boxes(e)
            part = part_of(e)
            parts.append(
                _boxes(T, ext, [e.id] * len(T), "structure", [part] * len(T), [s] * len(T))
            )
    flush()
    return Obstacles.join(parts)


def site_boxes(project: Project) -> Obstacles:
    """``site.obstacles`` as boxes in the world (a polygon by its bounding box)."""
    T, ext, names = [], [], []
    for obstacle in project.site.obstacles:
        if obstacle.box is not None:
            lo, hi = np.array(obstacle.box.min, float), np.array(obstacle.box.max, float)
            names.append(obstacle.box.name)
        else:
            assert obstacle.polygon is not None
            xy = np.asarray(obstacle.polygon.points, dtype=float)
            lo = np.r_[xy.min(axis=0), obstacle.polygon.z_min]
            hi = np.r_[xy.max(axis=0), obstacle.polygon.z_max]
            names.append(obstacle.polygon.name)
        Ti, ei = _aabb_box(lo, hi)
        T.append(Ti)
        ext.append(ei)
    n = len(T)
    return _boxes(np.array(T).reshape(n, 4, 4), np.array(ext), names, "site", [""] * n, [-1] * n)


def platform_boxes(
    project: Project, T_world_base: np.ndarray, block: np.ndarray | None
) -> Obstacles:
    """The platform (ground to deck) and, for blocks, the magazine, in the world.

    Parameters
    ----------
    project
        ``robot.platform`` gives the footprint, the arm mounting and the pick pose.
    T_world_base
        The station's localized base pose (its height includes the lift).
    block
        (3,) extents of the blocks the program picks, or None (no magazine).
    """
    platform = project.robot.platform
    T_platform_base = platform.T_platform_base.matrix()
    deck_height = max(float(T_world_base[2, 3]), 0.05)
    centre = np.linalg.inv(T_platform_base)[:3, 3]
    T_deck = np.eye(4)
    T_deck[:3, 3] = (centre[0], centre[1], -0.5 * deck_height)
    T_base = [T_deck]
    ext = [np.array([*platform.footprint, deck_height])]
    names = ["platform"]
    kinds = ["platform"]
    if block is not None:
        T_pick = T_base_pick_tool(project)
        height = float(T_pick[2, 3]) - float(block[2])
        if height > 1e-3:
            T_mag = T_pick.copy()
            T_mag[:3, :3] = T_pick[:3, :3] @ np.diag([1.0, -1.0, -1.0])
            T_mag[:3, 3] = T_pick[:3, 3] - np.array([0.0, 0.0, block[2] + 0.5 * height])
            T_base.append(T_mag)
            ext.append(
                np.array([block[0] + 2 * MAGAZINE_MARGIN, block[1] + 2 * MAGAZINE_MARGIN, height])
            )
            names.append("magazine")
            kinds.append("magazine")
    T = np.asarray(T_world_base, dtype=float) @ np.stack(T_base)
    return Obstacles(
        T,
        np.stack(ext),
        np.array(names, dtype=object),
        np.array(kinds, dtype=object),
        np.full(len(T), "", dtype=object),
        np.full(len(T), -1, dtype=np.int64),
    )


def held_box(element: Element) -> tuple[np.ndarray, np.ndarray] | None:
    """A block's box in the tool frame while the gripper holds it, or None.

    Returns
    -------
    T_tool_box, extents
        The block's centre frame in the tool frame (the grip of the place pose)
        and its side lengths (metres).
    """
    if element.type != "block" or element.extents is None:
        return None
    T_world_tool = element_tool_frames(element)[0]
    T_tool_box = np.linalg.inv(T_world_tool) @ np.asarray(element.T_world_element, dtype=float)
    return T_tool_box, np.asarray(element.extents, dtype=float)


def environment(
    project: Project,
    T_world_base: np.ndarray,
    built: Sequence[Element],
    package: Sequence[Element],
    coming: Sequence[tuple[Element, int]] = (),
) -> Obstacles:
    """Every obstacle of one work package's program, in the world frame.

    Parameters
    ----------
    project
        Platform, magazine and site obstacles.
    T_world_base
        The station's localized base pose.
    built
        Elements standing before the program starts (pre-built ones and those of
        earlier work packages).
    package
        The program's elements in build order (element ``j`` has ``since = 2 j``).
    coming
        Elements the robot does not build that come during the program, each
        with its ``since`` (:func:`fabflow.design.elements.structure_timeline`).
    """
    blocks = [e.extents for e in package if e.type == "block" and e.extents is not None]
    # the magazine holds the shortest block; longer ones overhang it
    blocks = sorted(blocks, key=lambda x: float(x[0]))
    return Obstacles.join(
        [
            structure_boxes(built, [-1] * len(built)),
            structure_boxes(package, [2 * j for j in range(len(package))]),
            structure_boxes([e for e, _ in coming], [2 * k + 1 for _, k in coming]),
            platform_boxes(project, T_world_base, None if not blocks else np.asarray(blocks[0])),
            site_boxes(project),
        ]
    )


def present_while(obstacles: Obstacles, j: int) -> np.ndarray:
    """Which obstacles stand while the program's ``j``-th element is built (before
    its release): the stage of its moves is ``2 j``."""
    return obstacles.since < 2 * j


SAFE_MARGIN = 0.02
"""Added to the safe travel height above the structure (metres)."""


def safe_heights(
    obstacles: Obstacles,
    package: Sequence[Element],
    T_world_pick: np.ndarray,
    clearance: float,
    width: float,
) -> dict[str, float]:
    """Per block of the package, a tool height (world z) above the structure it crosses.

    The highest structure box standing when the block is built whose plan
    outline comes within ``width`` (metres) of the straight line from the
    magazine to the block's place, plus the block's height (it hangs below the
    tool), twice the clearance and :data:`SAFE_MARGIN`.
    """
    structure = obstacles.kinds == "structure"
    lo, hi = box_aabb(obstacles.T, obstacles.extents)
    centre = 0.5 * (lo[:, :2] + hi[:, :2])
    half = 0.5 * np.linalg.norm(hi[:, :2] - lo[:, :2], axis=1)
    a = np.asarray(T_world_pick, dtype=float)[:2, 3]
    out = {}
    for j, e in enumerate(package):
        if e.type != "block" or e.extents is None:
            continue
        b = np.asarray(e.T_world_element, dtype=float)[:2, 3]
        ab = b - a
        t = np.clip((centre - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        gap = np.linalg.norm(a + t[:, None] * ab - centre, axis=1) - half
        crossed = structure & present_while(obstacles, j) & (gap < width)
        if crossed.any():
            top = float(hi[crossed, 2].max())
            out[e.id] = top + float(e.extents[2]) + 2.0 * clearance + SAFE_MARGIN
    return out


def tuck_heights(
    obstacles: Obstacles,
    package: Sequence[Element],
    T_world_base: np.ndarray,
    radius: float,
    clearance: float,
) -> dict[str, float]:
    """Per block of the package, a tool height (world z) at which the arm, tucked to
    ``radius`` about A1, turns above all the structure it could sweep.

    The highest structure box standing while the block is built whose plan
    outline comes within ``radius`` plus half the block's plan diagonal plus
    twice the clearance of the A1 axis, plus the block's height (it hangs below the tool),
    twice the clearance and :data:`SAFE_MARGIN`. Blocks with no such structure
    are left out.
    """
    structure = obstacles.kinds == "structure"
    lo, hi = box_aabb(obstacles.T, obstacles.extents)
    axis = np.asarray(T_world_base, dtype=float)[:2, 3]
    # plan distance of each box from the A1 axis
    gap = np.linalg.norm(np.maximum(np.maximum(lo[:, :2] - axis, axis - hi[:, :2]), 0.0), axis=1)
    out = {}
    for j, e in enumerate(package):
        if e.type != "block" or e.extents is None:
            continue
        ext = np.asarray(e.extents, dtype=float)
        reach = radius + 0.5 * float(np.hypot(ext[0], ext[1])) + 2.0 * clearance
        swept = structure & present_while(obstacles, j) & (gap < reach)
        if swept.any():
            top = float(hi[swept, 2].max())
            out[e.id] = top + float(ext[2]) + 2.0 * clearance + SAFE_MARGIN
    return out


def box_aabb(T: np.ndarray, extents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) lower and upper corners of the axis-aligned boxes around oriented boxes."""
    half = 0.5 * np.einsum("...ij,...j->...i", np.abs(T[..., :3, :3]), extents)
    return T[..., :3, 3] - half, T[..., :3, 3] + half


SLIDE_MARGIN = 0.005
"""Added to twice the clearance for the length a block slides in over and for the
height its descent starts above its neighbours (metres)."""
_TOUCH = 1e-6
"""Boxes that only touch (a face on a face) do not overlap (metres)."""


def placements(
    obstacles: Obstacles, package: Sequence[Element], project: Project
) -> dict[str, Placement]:
    """How each block of a work package goes into its place, where the structure
    standing around it asks for more than the plain descent.

    * **Slide.** A block is lowered onto its bed from above. Where structure
      standing when it is built covers one end of its place from above (a log
      cabin's corner, where the crossing wall's next layer already stands), it is
      lowered beside its place instead, along its length away from that end, and
      slides in at its final height. The offset is the covered length plus twice
      the clearance plus :data:`SLIDE_MARGIN`; the column above the offset place
      and the path of the slide must be free of standing structure (else the
      block gets no slide, and the collision check reports its descent).
    * **Approach.** The descent starts above whatever stands within the
      clearance around the block's footprint (its place and, sliding, its
      lowering point): neighbours standing higher than the block's own layer
      (the crossing wall's layer above, at a corner) raise it to their top
      plus twice the clearance plus :data:`SLIDE_MARGIN`.

    Parameters
    ----------
    obstacles
        The work package's obstacles (:func:`environment`); only structure counts.
    package
        The program's elements in build order (:func:`present_while` for element ``j``).
    project
        ``program.clearance`` and the plain approach (:func:`block_approach`).

    Returns
    -------
    dict[str, Placement]
        Block id to its placement, for the blocks that need more than the plain one.
    """
    clearance = project.program.clearance
    structure = obstacles.kinds == "structure"
    out: dict[str, Placement] = {}
    for j, e in enumerate(package):
        if e.type != "block" or e.extents is None:
            continue
        standing = structure & present_while(obstacles, j)
        if not standing.any():
            continue
        T_block = np.asarray(e.T_world_element, dtype=float)
        half = 0.5 * np.asarray(e.extents, dtype=float)
        # the standing boxes' bounding boxes in the block's frame
        lo, hi = box_aabb(
            np.linalg.solve(T_block, obstacles.T[standing]), obstacles.extents[standing]
        )
        shift = _slide(lo, hi, half, clearance)
        # what stands around the footprint (at the place and where it is lowered)
        grow = 2.0 * clearance + SLIDE_MARGIN
        around = _overlap(
            lo, hi, [min(shift, 0.0) - half[0] - grow, -half[1] - grow, -half[2]],
            [max(shift, 0.0) + half[0] + grow, half[1] + grow, np.inf],
        )  # fmt: skip
        top = float(hi[around, 2].max()) if around.any() else -np.inf
        need = top + half[2] + 2.0 * clearance + SLIDE_MARGIN
        approach = need if need > block_approach(e, project) + 1e-9 else None
        slide = T_block[:3, 0] * shift if shift else None
        if approach is not None or slide is not None:
            out[e.id] = Placement(approach=approach, slide=slide)
    return out


def _slide(lo: np.ndarray, hi: np.ndarray, half: np.ndarray, clearance: float) -> float:
    """Signed offset along the block's length (metres) where it is lowered to slide
    in, 0.0 for none (see :func:`placements`); boxes in the block's frame."""
    above = _overlap(lo, hi, [-half[0], -half[1], half[2]], [half[0], half[1], np.inf])
    if not above.any():
        return 0.0
    covered_lo = max(float(lo[above, 0].min()), -half[0])
    covered_hi = min(float(hi[above, 0].max()), half[0])
    if covered_lo > 0.0:  # the + end is covered: slide in from -x
        shift = -(half[0] - covered_lo)
    elif covered_hi < 0.0:
        shift = covered_hi + half[0]
    else:
        return 0.0  # covered across the middle: no slide gets it in
    shift = float(np.sign(shift)) * (abs(shift) + 2.0 * clearance + SLIDE_MARGIN)
    # the slide's path in the block's own layer and the column above its start
    path = _overlap(
        lo, hi, [min(shift, 0.0) - half[0], -half[1], -half[2]],
        [max(shift, 0.0) + half[0], half[1], half[2]],
    )  # fmt: skip
    column = _overlap(lo, hi, [shift - half[0], -half[1], -half[2]],
                      [shift + half[0], half[1], np.inf])  # fmt: skip
    return 0.0 if (path | column).any() else shift


def _overlap(lo: np.ndarray, hi: np.ndarray, a: Sequence[float], b: Sequence[float]) -> np.ndarray:
    """Which boxes overlap the box ``[a, b]`` by more than a touch."""
    return np.all((lo < np.asarray(b) - _TOUCH) & (hi > np.asarray(a) + _TOUCH), axis=1)
