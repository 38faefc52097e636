"""Collision check of a robot program: the arm, tool and held block along every motion.

The arm's links are capsules (:mod:`fabflow.robots.geometry`), the tool a capsule
from the flange to the TCP, a block the gripper holds its design box (from the
grip to the release), and the obstacles are the boxes of
:mod:`fabflow.programs.collision_model`: the structure as built at that moment,
the platform, the magazine and the site obstacles. A sample is a contact when a
body comes closer than the clearance to an obstacle present at that moment.

Sampling: a LIN move is checked at its inverse kinematics samples
(``Move.via_q``, one controller step apart, 2 cm / 0.015 rad). A PTP move is
interpolated in joint space from the previous target, coarse to fine: first
every :data:`COARSE_TRAVEL` of body travel (to first order: the joint steps times
the lever arm of the farthest body point about each joint, at either end of the
move) with every body grown by that travel, which covers the motion between the
samples; where a grown body comes near an obstacle, that stretch is sampled again
every :data:`SAMPLE_TRAVEL` (and at most :data:`MAX_JOINT_STEP` of any joint)
and checked at the clearance.

By design some bodies touch; these pairs are not contacts:

* the base link and the platform it stands on;
* the tool and the element its move belongs to (the gripper sits on the block it
  grips and releases, the place retract lifts off the block just placed; the
  nozzle prints onto its layer, whose other pieces it meets at the seams);
* the held block on its *seat moves*, the linear move right after the grip (out
  of the magazine) and the linear moves right before the release that end at
  the place's height (down into its place between its neighbours, or, for a
  block slid in, down onto its bed beside the place and along the bed into it;
  a descent straight down made a joint move, where the line passes the wrist
  singularity, counts as one): there it may touch but not penetrate deeper
  than :data:`SEAT_TOLERANCE`.

Broad phase in numpy (:mod:`fabflow.programs.collision_phases`: boxes of the
bodies swept over chunks of samples against the obstacles' boxes through a plan
grid, then per sample, then in the obstacle's own axes), narrow phase with
python-fcl's signed distance between the capsule (or the held box) and the box.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import repeat

import numpy as np

from fabflow.design.elements import Element
from fabflow.programs.collision_model import Obstacles, box_aabb, held_box, part_of
from fabflow.programs.collision_motion import (
    CheckMemo,
    CheckMotion,
    move_keys,
    only_moves,
    program_motion,
)
from fabflow.programs.collision_phases import (
    Narrow,
    aabb_pairs,
    capsule_frames,
    ranges,
)
from fabflow.programs.ir import Program
from fabflow.project import Project
from fabflow.robots.catalog import get_robot
from fabflow.robots.chain import RobotModel
from fabflow.robots.geometry import link_capsules, link_names, link_segments

COARSE_TRAVEL = 0.1
"""Body travel between the coarse samples of a PTP move (metres)."""
COARSE_JOINT_STEP = np.radians(10.0)
"""Largest joint step between coarse samples of a PTP move (radians)."""
SAMPLE_TRAVEL = 0.02
"""Body travel between the fine samples of a PTP move near an obstacle (metres)."""
MAX_JOINT_STEP = np.radians(1.0)
"""Largest joint step between fine samples of a PTP move (radians)."""
SEAT_TOLERANCE = 0.001
"""Penetration allowed for the held block on its seat moves (metres)."""
CHUNK = 16
"""Samples swept together in the first broad-phase level."""
GRID_CELL = 0.5
"""Plan grid cell of the broad phase (metres)."""
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


def _counts(travel: np.ndarray, step: np.ndarray, max_travel: float, max_step: float) -> np.ndarray:
    return np.maximum(1, np.ceil(np.maximum(travel / max_travel, step / max_step))).astype(np.intp)


@dataclass(frozen=True)
class _Near:
    """Sample, body and obstacle triples closer than their limit by the lower bound."""

    rows: np.ndarray
    body: np.ndarray
    obstacle: np.ndarray
    bound: np.ndarray


class _Bodies:
    """The bodies of a program at a set of samples: capsules and the held block."""

    def __init__(
        self,
        robot: RobotModel,
        motion: CheckMotion,
        q: np.ndarray,
        move: np.ndarray,
        T_flange_tool: np.ndarray,
        held_boxes: Mapping[str, tuple[np.ndarray, np.ndarray]],
        parts: Mapping[str, str],
    ):
        self.move = move
        self.parts = parts
        frames = robot.frames(q) if len(q) else np.zeros((0, robot.dof + 2, 4, 4))
        self.seg, self.radii, self.names = link_segments(robot, q, T_flange_tool, frames)
        n = len(q)
        self.T_held = np.zeros((n, 4, 4))
        self.ext_held = np.zeros((n, 3))
        held_move = np.array([h is not None and h in held_boxes for h in motion.held], dtype=bool)
        self.held_rows = np.flatnonzero(held_move[move]) if n else np.zeros(0, dtype=np.intp)
        if len(self.held_rows):
            # the boxes of the moves that hold one, then of the samples (few moves, many samples)
            moves = np.flatnonzero(held_move)
            of_move = np.zeros(len(held_move), dtype=np.intp)
            of_move[moves] = np.arange(len(moves))
            boxes = [held_boxes[motion.held[m]] for m in moves]  # type: ignore[index]
            which = of_move[move[self.held_rows]]
            T_tool_box = np.stack([b[0] for b in boxes])[which]
            self.ext_held[self.held_rows] = np.stack([b[1] for b in boxes])[which]
            T = frames[self.held_rows, -1] @ T_flange_tool @ T_tool_box
            self.T_held[self.held_rows] = T

    def near(
        self, motion: CheckMotion, obs: Obstacles, grow: np.ndarray, limit: np.ndarray
    ) -> _Near:
        """Triples whose distance lower bound is below their limit (:func:`_limit`); bodies
        grown by ``grow[row]`` (metres) in the broad phase."""
        seg, radii = self.seg, self.radii
        n_samples, n_links = seg.shape[:2]
        pad = radii[None, :, None] + grow[:, None, None]
        # the held block's box last, empty (inf, -inf) where nothing is held
        lo = np.full((n_samples, n_links + 1, 3), np.inf)
        hi = np.full((n_samples, n_links + 1, 3), -np.inf)
        np.subtract(np.minimum(seg[:, :, 0], seg[:, :, 1]), pad, out=lo[:, :n_links])
        np.add(np.maximum(seg[:, :, 0], seg[:, :, 1]), pad, out=hi[:, :n_links])
        rows = self.held_rows
        if len(rows):
            lo[rows, -1], hi[rows, -1] = box_aabb(self.T_held[rows], self.ext_held[rows])
            lo[rows, -1] -= grow[rows, None]
            hi[rows, -1] += grow[rows, None]
        n_bodies = n_links + 1
        # Level 1: bodies swept over chunks of samples against the obstacles.
        starts = np.arange(0, n_samples, CHUNK)
        c_lo = np.minimum.reduceat(lo, starts, axis=0).reshape(-1, 3)
        c_hi = np.maximum.reduceat(hi, starts, axis=0).reshape(-1, 3)
        o_lo, o_hi = box_aabb(obs.T, obs.extents)
        pair, k = aabb_pairs(c_lo, c_hi, o_lo, o_hi, GRID_CELL)
        chunk, b = np.divmod(pair, n_bodies)
        # Level 2: every sample of those chunks, with the obstacles present at its
        # move, without the pairs that touch by design.
        counts = np.minimum(CHUNK, n_samples - starts[chunk])
        rows = np.repeat(starts[chunk], counts) + ranges(counts)
        b, k = np.repeat(b, counts), np.repeat(k, counts)
        mv = self.move[rows]
        keep = np.ones(len(rows), dtype=bool)
        for axis in range(3):
            keep &= lo[rows, b, axis] <= o_hi[k, axis]
            keep &= hi[rows, b, axis] >= o_lo[k, axis]
        keep &= obs.since[k] < motion.stage[mv]
        if "base" in self.names:
            keep &= ~((b == self.names.index("base")) & (obs.kinds[k] == "platform"))
        if "tool" in self.names:
            # parts as integers (-1: no part; -2: a move's part no obstacle has)
            code = {e: i for i, e in enumerate(set(obs.element.tolist()) - {""})}
            of_obstacle = np.array([code.get(e, -1) for e in obs.element.tolist()], dtype=np.intp)
            of_move = np.array(
                [code.get(self.parts.get(m.element, m.element) or "", -2) for m in motion.moves],
                dtype=np.intp,
            )
            own = of_obstacle[k] == of_move[mv]
            keep &= ~((b == self.names.index("tool")) & own)
        rows, b, k = rows[keep], b[keep], k[keep]
        # Level 3: a lower bound of the distance in the obstacle's own frame.
        R, t, half = obs.T[k, :3, :3], obs.T[k, :3, 3], 0.5 * obs.extents[k]
        capsule = b < n_links
        pts = np.empty((len(rows), 8, 3))
        pts[capsule, :2] = seg[rows[capsule], b[capsule]]
        pts[capsule, 2:] = pts[capsule, 1:2]
        Th = self.T_held[rows[~capsule]]
        corners = _CORNERS * self.ext_held[rows[~capsule], None]
        pts[~capsule] = (Th[:, None, :3, :3] @ corners[..., None])[..., 0] + Th[:, None, :3, 3]
        local = np.einsum("nji,nkj->nki", R, pts - t[:, None])
        gap = np.maximum(np.maximum(local.min(axis=1) - half, -half - local.max(axis=1)), 0.0)
        radius = np.where(capsule, radii[np.minimum(b, n_links - 1)], 0.0)
        bound = np.linalg.norm(gap, axis=1) - radius
        # a held box whose corners' box overlaps the obstacle: the penetration is at
        # most the overlap along the obstacle's shallowest axis
        overlap = np.minimum(local.max(axis=1) + half, half - local.min(axis=1)).min(axis=1)
        bound = np.where(~capsule & (bound <= 0.0), -overlap, bound)
        close = bound < _limit(limit, rows, b, n_links)
        return _Near(rows[close], b[close], k[close], bound[close])

    def distances(
        self, near: _Near, narrow: Narrow, limit: np.ndarray
    ) -> dict[tuple[int, int, int], float]:
        """Smallest signed distance per (move, body, obstacle) below its limit (:func:`_limit`).

        fcl computes first the :data:`FIRST_SAMPLES` samples with the smallest
        lower bound of every triple, then the rest of the triples without a contact.
        """
        if not len(near.rows):
            return {}
        n_links = self.seg.shape[1]
        mv = self.move[near.rows]
        triple = (mv * (n_links + 1) + near.body) * (near.obstacle.max() + 1) + near.obstacle
        order = np.lexsort((near.bound, triple))
        rows, b, k, triple = near.rows[order], near.body[order], near.obstacle[order], triple[order]
        mv = mv[order]
        first = np.r_[True, triple[1:] != triple[:-1]]
        index = np.arange(len(triple))
        rank = index - np.maximum.accumulate(np.where(first, index, 0))
        capsule = b < n_links
        R = np.zeros((len(rows), 3, 3))
        t = np.zeros((len(rows), 3))
        R[capsule], t[capsule] = capsule_frames(
            self.seg[rows[capsule], b[capsule], 0], self.seg[rows[capsule], b[capsule], 1]
        )
        R[~capsule] = self.T_held[rows[~capsule], :3, :3]
        t[~capsule] = self.T_held[rows[~capsule], :3, 3]
        ends = self.seg[rows, np.minimum(b, n_links - 1)]
        length = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1).tolist()
        found: dict[int, float] = {}
        for i in [*np.flatnonzero(rank < FIRST_SAMPLES), *np.flatnonzero(rank >= FIRST_SAMPLES)]:
            key = int(triple[i])
            if rank[i] >= FIRST_SAMPLES and key in found:
                continue
            extents = None if capsule[i] else self.ext_held[rows[i]]
            d = narrow.distance(int(k[i]), int(b[i]), R[i], t[i], extents, length[i])
            if d < _limit(limit, rows[i], b[i], n_links):
                found[key] = min(d, found.get(key, np.inf))
        out = {}
        for i in np.flatnonzero(first):
            if int(triple[i]) in found:
                out[(int(mv[i]), int(b[i]), int(k[i]))] = found[int(triple[i])]
        return out


def check_program(
    program: Program,
    robot: RobotModel,
    obstacles: Obstacles,
    held_boxes: Mapping[str, tuple[np.ndarray, np.ndarray]],
    clearance: float,
    parts: Mapping[str, str] | None = None,
    memo: CheckMemo | None = None,
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
    parts
        Element id to the part it belongs to
        (:func:`fabflow.programs.collision_model.part_of`; default: itself), for
        the tool's by-design contact with its own part.
    memo
        The results of earlier checks against the same obstacles, robot, tool,
        clearance, held boxes and parts (a re-planning's rounds; start with
        ``{}``): moves whose check depends on nothing new
        (:func:`~fabflow.programs.collision_motion.move_keys`) take their
        contacts from it, and the moves checked here are added to it.

    Returns
    -------
    list[Contact]
        One per move, body and obstacle: the smallest distance over the move's
        samples; empty when the program keeps its clearance everywhere.
    """
    if not len(obstacles) or not program.moves:
        return []
    obs = obstacles.moved(np.asarray(program.T_base_world, dtype=float))
    beyond = max(float(c.radius) for c in link_capsules(robot))
    beyond = max([beyond, *(float(np.linalg.norm(e)) for _, e in held_boxes.values())])
    motion = program_motion(program, robot, beyond)
    keys = move_keys(motion, parts or {}) if memo is not None else []
    todo = np.array([k not in memo for k in keys], dtype=bool) if memo is not None else None
    found: dict[tuple[int, int, int], float] = {}
    if todo is None or todo.any():
        checked = motion if todo is None else only_moves(motion, todo)
        found = _contacts(checked, program, robot, obs, held_boxes, clearance, parts or {})
    if memo is not None:
        assert todo is not None
        by_move: dict[int, list[tuple[int, int, float]]] = {}
        for (m, b, k), d in found.items():
            by_move.setdefault(m, []).append((b, k, d))
        checked_moves = np.flatnonzero(todo).tolist()
        # filed in one call: a print path's first check files tens of thousands of moves
        memo.update(
            zip(
                map(keys.__getitem__, checked_moves),
                map(by_move.get, checked_moves, repeat(())),
                strict=True,
            )
        )
        for mv in np.flatnonzero(~todo).tolist():
            found.update({(mv, b, k): d for b, k, d in memo[keys[mv]]})
    names = [*link_names(robot, tool=True), "held"]
    out = []
    for (mv, body, k), d in sorted(found.items()):
        link = f"held {motion.held[mv]}" if body == len(names) - 1 else names[body]
        m = motion.moves[mv]
        out.append(Contact(mv, m.element, m.label, link, str(obs.names[k]), d))
    return out


def _contacts(
    motion: CheckMotion,
    program: Program,
    robot: RobotModel,
    obs: Obstacles,
    held_boxes: Mapping[str, tuple[np.ndarray, np.ndarray]],
    clearance: float,
    parts: Mapping[str, str],
) -> dict[tuple[int, int, int], float]:
    """:func:`check_program`'s smallest distance below the clearance per (move, body,
    obstacle) over the samples of ``motion``, obstacles ``obs`` in the base frame."""
    T_flange_tool = np.asarray(program.T_flange_tool, dtype=float)
    narrow: Narrow | None = None

    def limits(bodies: _Bodies) -> np.ndarray:
        """Per sample, the limit of the links and of the held block (:func:`_limit`)."""
        seat = motion.seat[bodies.move]
        return np.c_[np.full(len(seat), clearance), np.where(seat, -SEAT_TOLERANCE, clearance)]

    # Coarse PTP samples, every body grown by the travel to its neighbours.
    n_coarse = _counts(motion.ptp_travel, motion.ptp_step, COARSE_TRAVEL, COARSE_JOINT_STEP)
    which = np.repeat(np.arange(len(n_coarse)), n_coarse)
    j = ranges(n_coarse) + 1
    frac = j / n_coarse[which]
    q0, q1 = motion.ptp_q0[which], motion.ptp_q1[which]
    travel = (motion.ptp_travel / n_coarse)[which]
    q = np.vstack([motion.fixed_q, q0 + frac[:, None] * (q1 - q0)])
    move = np.r_[motion.fixed_move, motion.ptp_move[which]].astype(np.intp)
    order = np.argsort(move, kind="stable")
    q, move = q[order], move[order]
    grow = np.r_[np.zeros(len(motion.fixed_q)), travel][order]
    coarse = np.r_[np.zeros(len(motion.fixed_q), dtype=bool), np.ones(len(which), dtype=bool)]
    coarse = coarse[order]
    sample_ptp = np.r_[np.full(len(motion.fixed_q), -1), which][order]
    sample_j = np.r_[np.zeros(len(motion.fixed_q), dtype=np.intp), j][order]
    bodies = _Bodies(robot, motion, q, move, T_flange_tool, held_boxes, parts)
    limit = limits(bodies) + grow[:, None]
    near = bodies.near(motion, obs, clearance + grow, limit)
    # Every sample at the clearance itself: linear-move samples are final; a coarse
    # sample whose own distance is already below the clearance settles its move
    # (it collides; its other near samples are not refined); the coarse samples
    # that came near in the other moves are refined.
    found: dict[tuple[int, int, int], float] = {}
    limit = limits(bodies)
    at_sample = near.bound < _limit(limit, near.rows, near.body, len(bodies.names))
    if at_sample.any():
        narrow = Narrow(obs, bodies.radii, clearance + SEAT_TOLERANCE)
        sub = _Near(*(getattr(near, f)[at_sample] for f in ("rows", "body", "obstacle", "bound")))
        found.update(bodies.distances(sub, narrow, limit))
    refine = coarse[near.rows]
    settled = np.isin(move[near.rows[refine]], [m for m, _, _ in found])
    rows = near.rows[refine][~settled]
    flagged = np.unique(np.c_[sample_ptp[rows], sample_j[rows]], axis=0).reshape(-1, 2)
    if len(flagged):
        p, jf = flagged[:, 0], flagged[:, 1]
        nc = n_coarse[p]
        lo, hi = np.maximum(jf - 1, 0) / nc, np.minimum(jf + 1, nc) / nc
        n_fine = _counts(
            motion.ptp_travel[p] * (hi - lo), motion.ptp_step[p] * (hi - lo),
            SAMPLE_TRAVEL, MAX_JOINT_STEP,
        )  # fmt: skip
        owner = np.repeat(np.arange(len(p)), n_fine)
        frac = lo[owner] + (ranges(n_fine) + 1) / n_fine[owner] * (hi - lo)[owner]
        q0, q1 = motion.ptp_q0[p[owner]], motion.ptp_q1[p[owner]]
        move = motion.ptp_move[p[owner]]
        order = np.argsort(move, kind="stable")
        q = (q0 + frac[:, None] * (q1 - q0))[order]
        fine = _Bodies(robot, motion, q, move[order], T_flange_tool, held_boxes, parts)
        limit = limits(fine)
        near = fine.near(motion, obs, np.full(len(q), clearance), limit)
        if len(near.rows):
            narrow = narrow or Narrow(obs, fine.radii, clearance + SEAT_TOLERANCE)
            for key, d in fine.distances(near, narrow, limit).items():
                found[key] = min(d, found.get(key, np.inf))
    return found


def _limit(limit: np.ndarray, rows: np.ndarray, body: np.ndarray, n_links: int) -> np.ndarray:
    """The distance limit of each (sample, body): ``limit`` holds per sample the links'
    (the clearance) and the held block's (less on its seat moves, where it may touch)."""
    return limit[rows, (np.asarray(body) >= n_links).astype(np.intp)]


def check_package(
    program: Program,
    project: Project,
    obstacles: Obstacles,
    package: Sequence[Element],
    clearance: float | None = None,
    memo: CheckMemo | None = None,
) -> list[Contact]:
    """:func:`check_program` of a work package's program.

    Parameters
    ----------
    program
        The work package's program.
    project
        ``program.clearance`` (the default clearance).
    obstacles
        Its obstacles (:func:`fabflow.programs.collision_model.environment`).
    package
        The program's elements in build order (the blocks it holds).
    clearance
        Overrides ``project.program.clearance`` (metres).
    memo
        To :func:`check_program`: earlier checks of the package's programs.
    """
    held = {e.id: box for e in package if (box := held_box(e)) is not None}
    limit = project.program.clearance if clearance is None else clearance
    parts = {e.id: part_of(e) for e in package}
    robot = get_robot(program.robot)
    return check_program(program, robot, obstacles, held, limit, parts, memo)
