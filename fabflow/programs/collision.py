"""Collision check of a robot program: the arm, tool and held block along every motion.

The arm's links are capsules (:mod:`fabflow.robots.geometry`), the tool a capsule
from the flange to the TCP, a block the gripper holds its design box (from the
grip to the release), and the obstacles are the boxes of
:mod:`fabflow.programs.collision_model`: the structure as built at that moment,
the platform, the magazine and the site obstacles.

Every motion is sampled so that no point of the arm, tool or held block moves
more than :data:`SAMPLE_TRAVEL` between two samples: a PTP is interpolated in
joint space from the previous target (the number of samples from a bound of the
lever arm of every joint), a LIN uses its inverse kinematics samples
(``Move.via_q``, one controller step apart). A sample is a contact when a body
comes closer than the clearance to an obstacle that is present at that moment.

By design some bodies touch; these pairs are not contacts:

* the base link and the platform it stands on;
* the tool and the element its move belongs to (the gripper sits on the block it
  grips and releases, the place retract lifts off the block just placed);
* the held block on its *seat moves*, the linear move right after the grip (out
  of the magazine) and the one right before the release (down into its place
  between its neighbours): there it may touch but not penetrate deeper than
  :data:`SEAT_TOLERANCE`.

Broad phase in numpy (axis-aligned boxes of each link swept over a move, then of
each sample, then the capsule against the obstacle's own axes), narrow phase with
python-fcl's signed distance between the capsule (or the held box) and the box.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import fcl
import numpy as np

from fabflow.design.elements import Element
from fabflow.programs.collision_model import Obstacles, environment, held_box
from fabflow.programs.ir import Move, Program, SetOutput
from fabflow.project import Project
from fabflow.robots.catalog import get_robot
from fabflow.robots.chain import RobotModel
from fabflow.robots.geometry import link_segments

SAMPLE_TRAVEL = 0.02
"""Largest travel of any point of the arm, tool or held block between two checked
samples of a PTP move (metres), as between the samples of a linear move."""
SEAT_TOLERANCE = 0.001
"""Penetration allowed for the held block on its seat moves (metres)."""
FIRST_SAMPLES = 4
"""Samples per move, body and obstacle whose distance fcl computes first (those with
the smallest lower bound); a contact's reported distance is the smallest of them."""

_CORNERS = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])


@dataclass(frozen=True)
class Contact:
    """A body closer to an obstacle than the clearance during one move.

    Attributes
    ----------
    move
        Index of the move in ``Program.moves``.
    element
        The move's element.
    label
        The move's label (``"travel"``, ``"place approach"``, ...).
    link
        The body: a link name, ``"tool"`` or ``"held <element>"``.
    obstacle
        What it comes close to (an element id, ``"platform"``, ``"magazine"``, a
        site obstacle's name).
    distance
        Smallest signed distance over the move's samples (metres; negative:
        penetration).
    """

    move: int
    element: str | None
    label: str
    link: str
    obstacle: str
    distance: float

    def describe(self) -> str:
        """One line for an error message or a report."""
        what = "penetrates" if self.distance < 0 else "comes within"
        return (
            f"element {self.element}, move '{self.label}': the {self.link} {what} "
            f"{abs(self.distance) * 1000:.1f} mm of {self.obstacle}"
        )


def _fcl_box(T: np.ndarray, extents: np.ndarray) -> fcl.CollisionObject:
    return fcl.CollisionObject(fcl.Box(*map(float, extents)), fcl.Transform(T[:3, :3], T[:3, 3]))


def _capsule_frames(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3, 3) rotations with z along ``b - a`` and (n, 3) midpoints of segments."""
    axis = b - a
    z = axis / np.maximum(np.linalg.norm(axis, axis=1), 1e-12)[:, None]
    helper = np.where((np.abs(z[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x, axis=1)[:, None]
    return np.stack([x, np.cross(z, x), z], axis=2), 0.5 * (a + b)


class _Narrow:
    """fcl objects of one check: obstacle boxes, and per body a true-size object and
    one grown by the clearance (a hit of the grown one is a candidate contact)."""

    def __init__(self, obs: Obstacles, lengths: np.ndarray, radii: np.ndarray, clearance: float):
        self.obs = obs
        self.clearance = clearance
        self.boxes: dict[int, fcl.CollisionObject] = {}
        self.capsules = [
            (
                fcl.CollisionObject(fcl.Capsule(float(r), float(n))),
                fcl.CollisionObject(fcl.Capsule(float(r) + clearance, float(n))),
            )
            for r, n in zip(radii, lengths, strict=True)
        ]
        self.held: dict[tuple[float, ...], tuple[fcl.CollisionObject, fcl.CollisionObject]] = {}
        self.request = fcl.CollisionRequest()
        self.distance_request = fcl.DistanceRequest(enable_signed_distance=True)

    def _box(self, k: int) -> fcl.CollisionObject:
        if k not in self.boxes:
            T, extents = self.obs.T[k], self.obs.extents[k]
            self.boxes[k] = fcl.CollisionObject(
                fcl.Box(*map(float, extents)), fcl.Transform(T[:3, :3], T[:3, 3])
            )
        return self.boxes[k]

    def _held(self, extents: np.ndarray) -> tuple[fcl.CollisionObject, fcl.CollisionObject]:
        key = tuple(np.round(extents, 9).tolist())
        if key not in self.held:
            grown = extents + 2.0 * self.clearance
            self.held[key] = (
                fcl.CollisionObject(fcl.Box(*map(float, extents))),
                fcl.CollisionObject(fcl.Box(*map(float, grown))),
            )
        return self.held[key]

    def distance(
        self, k: int, body: int, R: np.ndarray, t: np.ndarray, extents: np.ndarray | None
    ) -> float:
        """Signed distance of a body at (R, t) from obstacle k, or +inf when the body
        grown by the clearance does not touch it."""
        true, grown = self.capsules[body] if extents is None else self._held(extents)
        box = self._box(k)
        transform = fcl.Transform(R, t)
        grown.setTransform(transform)
        if not fcl.collide(grown, box, self.request, fcl.CollisionResult()):
            return np.inf
        true.setTransform(transform)
        return float(fcl.distance(true, box, self.distance_request, fcl.DistanceResult()))


@dataclass(frozen=True)
class _Samples:
    """Joint samples of a program's moves and what holds for each move."""

    q: np.ndarray  # (N, dof)
    move: np.ndarray  # (N,) move index of each sample
    stage: np.ndarray  # (M,) per move
    held: list[str | None]  # (M,) element held during each move
    seat: np.ndarray  # (M,) bool: the held block's seat move


def _lever_arms(robot: RobotModel, reach_beyond: float) -> np.ndarray:
    """Upper bound of the distance of any body point from each joint axis (metres)."""
    lengths = np.abs(robot.dh[:, 0]) + np.abs(robot.dh[:, 2])
    tail = np.cumsum(lengths[::-1])[::-1]
    return tail + float(np.linalg.norm(robot.T_n_flange[:3, 3])) + reach_beyond


def sample_program(program: Program, robot: RobotModel, reach_beyond: float) -> _Samples:
    """Joint samples of every move, with stage, held element and seat flags per move.

    ``reach_beyond`` bounds how far the tool and a held block reach past the
    flange (metres); PTP moves get ``ceil(sum |dq_j| R_j / SAMPLE_TRAVEL)`` samples.
    """
    arms = _lever_arms(robot, reach_beyond)
    moves: list[Move] = []
    grip_at: dict[int, str | None] = {}
    last_move: dict[str, int] = {}
    released: dict[str | None, int] = {}
    for ins in program.instructions:
        if isinstance(ins, Move):
            moves.append(ins)
            if ins.element is not None:
                last_move[ins.element] = len(moves)
        elif isinstance(ins, SetOutput) and ins.name == "gripper":
            if ins.value:
                grip_at[len(moves)] = ins.element
            else:
                released[ins.element] = len(moves)
    # An element is complete from its release on, else after its last move.
    complete = np.sort([released.get(e, last) for e, last in last_move.items()])
    release = set(released.values())
    chunks: list[np.ndarray] = []
    held_of: list[str | None] = []
    seat: list[bool] = []
    held: str | None = None
    q_prev: np.ndarray | None = None
    for i, move in enumerate(moves):
        if i in grip_at:
            held = grip_at[i]
        if i in release:
            held = None
        q = np.asarray(move.q, dtype=float)
        if move.kind == "lin" and move.via_q is not None:
            chunks.append(np.vstack([move.via_q, q[None]]))
        elif q_prev is not None and move.kind == "ptp":
            n = max(1, int(np.ceil(float(np.abs(q - q_prev) @ arms) / SAMPLE_TRAVEL)))
            frac = np.arange(1, n + 1)[:, None] / n
            chunks.append(q_prev + frac * (q - q_prev))
        else:
            chunks.append(q[None])
        held_of.append(held)
        seat.append(held is not None and move.kind == "lin" and (i in grip_at or i + 1 in release))
        q_prev = q
    counts = np.array([len(c) for c in chunks], dtype=np.intp)
    return _Samples(
        q=np.vstack(chunks) if chunks else np.zeros((0, robot.dof)),
        move=np.repeat(np.arange(len(chunks)), counts),
        stage=np.searchsorted(complete, np.arange(len(moves)), side="right"),
        held=held_of,
        seat=np.array(seat, dtype=bool),
    )


def _box_aabb(T: np.ndarray, extents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., 3) lower and upper corners of the axis-aligned boxes around oriented boxes."""
    half = 0.5 * np.einsum("...ij,...j->...i", np.abs(T[..., :3, :3]), extents)
    return T[..., :3, 3] - half, T[..., :3, 3] + half


def check_program(
    program: Program,
    robot: RobotModel,
    obstacles: Obstacles,
    held_boxes: Mapping[str, tuple[np.ndarray, np.ndarray]],
    clearance: float,
) -> list[Contact]:
    """Every body that comes closer than ``clearance`` to an obstacle, per move.

    Parameters
    ----------
    program
        The program (joint values of every target and linear-move sample).
    robot
        Its robot model.
    obstacles
        The obstacles in the world frame (:func:`fabflow.programs.collision_model.environment`).
    held_boxes
        Per block id, its box in the tool frame while held: ``(T_tool_box, extents)``.
    clearance
        Smallest allowed distance (metres).

    Returns
    -------
    list[Contact]
        One per move, body and obstacle: the smallest distance over the move's
        samples; empty when the program keeps its clearance everywhere.
    """
    if not len(obstacles) or not program.moves:
        return []
    T_flange_tool = np.asarray(program.T_flange_tool, dtype=float)
    obs = obstacles.moved(np.asarray(program.T_base_world, dtype=float))
    beyond = float(np.linalg.norm(T_flange_tool[:3, 3]))
    beyond += max((float(np.linalg.norm(e)) for _, e in held_boxes.values()), default=0.0)
    s = sample_program(program, robot, beyond)
    moves = program.moves
    seg, radii, names = link_segments(robot, s.q, T_flange_tool)
    n_samples, n_links = seg.shape[:2]
    # Body boxes per sample: the capsules, then the held block (empty when none).
    pad = (radii + clearance)[None, :, None]
    lo = np.concatenate([seg.min(axis=2) - pad, np.full((n_samples, 1, 3), np.inf)], axis=1)
    hi = np.concatenate([seg.max(axis=2) + pad, np.full((n_samples, 1, 3), -np.inf)], axis=1)
    held_move = np.array([h is not None and h in held_boxes for h in s.held])
    held_rows = np.flatnonzero(held_move[s.move])
    T_held = np.zeros((n_samples, 4, 4))
    ext_held = np.zeros((n_samples, 3))
    if len(held_rows):
        boxes = [held_boxes[s.held[m]] for m in s.move[held_rows]]  # type: ignore[index]
        T_tool_box = np.stack([b[0] for b in boxes])
        ext_held[held_rows] = np.stack([b[1] for b in boxes])
        T_held[held_rows] = robot.fk(s.q[held_rows]) @ T_flange_tool @ T_tool_box
        lo[held_rows, -1], hi[held_rows, -1] = _box_aabb(T_held[held_rows], ext_held[held_rows])
        lo[held_rows, -1] -= clearance
        hi[held_rows, -1] += clearance
    body_names = [*names, "held"]
    # Level 1: bodies swept over each move against the obstacles present then.
    starts = np.r_[0, np.flatnonzero(np.diff(s.move)) + 1]
    sweep_lo = np.minimum.reduceat(lo, starts, axis=0)
    sweep_hi = np.maximum.reduceat(hi, starts, axis=0)
    o_lo, o_hi = _box_aabb(obs.T, obs.extents)
    overlap = np.all(
        (sweep_lo[:, :, None] <= o_hi[None, None]) & (sweep_hi[:, :, None] >= o_lo[None, None]),
        axis=-1,
    )
    overlap &= (obs.since[None, :] < s.stage[:, None])[:, None, :]
    if "base" in body_names:
        overlap[:, body_names.index("base"), obs.kinds == "platform"] = False
    if "tool" in names:
        move_element = np.array([m.element or "" for m in moves], dtype=object)
        own = (obs.element[None, :] == move_element[:, None]) & (move_element[:, None] != "")
        overlap[:, names.index("tool")] &= ~own
    m, b, k = np.nonzero(overlap)
    if not len(m):
        return []
    # Level 2: each sample of those moves, by its own box.
    counts = np.diff(np.r_[starts, n_samples])[m]
    rows = np.repeat(starts[m], counts) + (
        np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    )
    b, k = np.repeat(b, counts), np.repeat(k, counts)
    keep = np.all((lo[rows, b] <= o_hi[k]) & (hi[rows, b] >= o_lo[k]), axis=-1)
    rows, b, k = rows[keep], b[keep], k[keep]
    # Level 3: in the obstacle's own frame.
    R = obs.T[k, :3, :3]
    t = obs.T[k, :3, 3]
    half = 0.5 * obs.extents[k]
    capsule = b < n_links
    pts = np.empty((len(rows), 8, 3))
    pts[capsule, :2] = seg[rows[capsule], b[capsule]]
    pts[capsule, 2:] = pts[capsule, 1:2]
    Th = T_held[rows[~capsule]]
    pts[~capsule] = (
        np.einsum("nij,nkj->nki", Th[:, :3, :3], _CORNERS * ext_held[rows[~capsule], None])
        + Th[:, None, :3, 3]
    )
    local = np.einsum("nji,nkj->nki", R, pts - t[:, None])
    # Lower bound of the distance: the gap between the body's box in the obstacle's
    # frame and the obstacle, less the capsule's radius.
    gap = np.maximum(np.maximum(local.min(axis=1) - half, -half - local.max(axis=1)), 0.0)
    bound = np.linalg.norm(gap, axis=1) - np.where(capsule, radii[np.minimum(b, n_links - 1)], 0.0)
    mv = s.move[rows]
    held_seat = (b == n_links) & s.seat[mv]
    limit = np.where(held_seat, -SEAT_TOLERANCE, clearance)
    near = bound < limit
    rows, b, k, mv, bound, limit = rows[near], b[near], k[near], mv[near], bound[near], limit[near]
    # Narrow phase with fcl: first the samples most likely nearest (smallest bound) of
    # every move, body and obstacle; the rest only where none of those is a contact.
    triple = (mv * (n_links + 1) + b) * len(obs) + k
    order = np.lexsort((bound, triple))
    rows, b, k, mv, triple, limit = (x[order] for x in (rows, b, k, mv, triple, limit))
    first = np.r_[True, triple[1:] != triple[:-1]]
    rank = np.arange(len(triple)) - np.maximum.accumulate(
        np.where(first, np.arange(len(triple)), 0)
    )
    contacts: dict[int, float] = {}
    lengths = np.linalg.norm(seg[0, :, 1] - seg[0, :, 0], axis=1)
    narrow = _Narrow(obs, lengths, radii, max(clearance, 0.0) + SEAT_TOLERANCE)
    capsule = b < n_links
    R_body = np.zeros((len(rows), 3, 3))
    t_body = np.zeros((len(rows), 3))
    R_body[capsule], t_body[capsule] = _capsule_frames(
        seg[rows[capsule], b[capsule], 0], seg[rows[capsule], b[capsule], 1]
    )
    R_body[~capsule] = T_held[rows[~capsule], :3, :3]
    t_body[~capsule] = T_held[rows[~capsule], :3, 3]

    def distance(i: int) -> float:
        extents = None if capsule[i] else ext_held[rows[i]]
        return narrow.distance(int(k[i]), int(b[i]), R_body[i], t_body[i], extents)

    for i in np.flatnonzero(rank < FIRST_SAMPLES).tolist():
        d = distance(i)
        if d < limit[i]:
            contacts[int(triple[i])] = min(d, contacts.get(int(triple[i]), np.inf))
    rest = np.flatnonzero((rank >= FIRST_SAMPLES) & ~np.isin(triple, list(contacts)))
    for i in rest.tolist():
        if int(triple[i]) in contacts:
            continue
        d = distance(i)
        if d < limit[i]:
            contacts[int(triple[i])] = d
    found = {}
    for i in np.flatnonzero(first).tolist():
        if int(triple[i]) in contacts:
            found[(int(mv[i]), int(b[i]), int(k[i]))] = contacts[int(triple[i])]
    out = []
    for (mv, body, ko), d in sorted(found.items()):
        link = f"held {s.held[mv]}" if body == n_links else body_names[body]
        out.append(Contact(mv, moves[mv].element, moves[mv].label, link, str(obs.names[ko]), d))
    return out


def check_package(
    program: Program,
    project: Project,
    built: Sequence[Element],
    package: Sequence[Element],
    clearance: float | None = None,
) -> list[Contact]:
    """:func:`check_program` against the obstacles of one work package.

    Parameters
    ----------
    program
        The work package's program.
    project
        Platform, magazine, site obstacles and ``program.clearance`` (the default).
    built
        Elements standing when the program starts (pre-built, earlier packages).
    package
        The program's elements in build order.
    clearance
        Overrides ``project.program.clearance`` (metres).
    """
    T_world_base = np.linalg.inv(np.asarray(program.T_base_world, dtype=float))
    obstacles = environment(project, T_world_base, built, package)
    held = {e.id: box for e in package if (box := held_box(e)) is not None}
    limit = project.program.clearance if clearance is None else clearance
    return check_program(program, get_robot(program.robot), obstacles, held, limit)
