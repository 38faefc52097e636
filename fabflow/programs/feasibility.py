"""Inverse kinematics along the moves of a program: can the arm follow them?

Every Cartesian target is checked with inverse kinematics before anything is
written. A PTP target takes the configuration from which the linear moves
after it can be followed; a linear move must keep the configuration of its
start and is sampled at most one controller step apart (2 cm / 0.015 rad), so
that a joint limit, a configuration change or a joint speed beyond the
robot's limits inside the line is found. A line that passes the wrist
singularity keeps its status with the wrist axes interpolated
(:mod:`fabflow.programs.wrist_lin`) or, failing that (always, for a held block
going into its seat), becomes a joint move through A5 = 0 where its path stays
near the line. Any failure is an :class:`~fabflow.errors.InfeasibleError`
naming the element and the target.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fabflow.errors import InfeasibleError
from fabflow.programs.branch_follow import (
    MAX_JOINT_STEP,
    MIN_SPEED_FRACTION,
    follow_branch,
    follow_branch_chain,
    nearest_prefix,
)
from fabflow.programs.chain_memo import ChainMemo, ChainMove, chain_key, frozen
from fabflow.programs.motion_checks import configuration_of, wrap_angle, wrist_flips
from fabflow.programs.motions import Waypoint
from fabflow.programs.wrist_lin import (
    MAX_DEVIATION_DEG,
    MAX_JOINT_BOW,
    joint_move_bow,
    same_status_ends,
    wrist_interpolated_path,
)
from fabflow.robots.catalog import get_robot
from fabflow.robots.chain import RobotModel
from fabflow.transforms.so3 import exp_so3, log_so3

STEP_TRANSLATION = 0.02
"""Largest tool translation between two checked samples of a linear move (m)."""
STEP_ROTATION = 0.015
"""Largest tool rotation between two checked samples of a linear move (rad)."""
FAST_WINDOW = 64
"""Linear moves followed at once on one branch at most (:func:`follow_branch_chain`): a
move it refuses is searched alone, and the next window starts after it."""
TOOL_ROTATION_SPEED = 1.0
"""Tool rotation speed assumed for timing linear moves (rad/s)."""
WRIST_SAMPLES = 36
"""Samples of a wrist-interpolated linear move at least: A4 and A6 turn half a
turn on it, so that no sample is more than about 5 deg from the next."""
AXIS_WEIGHTS = np.array([1.0, 1.0, 1.0, 0.25, 0.25, 0.25])
"""Weight of each axis' travel in the cost of a PTP move (per radian): the main
axes move the arm's mass through the work area, the wrist axes only the tool."""
SEATED_TURN = 1e-6
"""Largest tool rotation (rad) off the straight move on a seated joint move: its
orientation is exact up to rounding."""
CONFIGURATION_CHANGE_COST = 2.0 * np.pi
"""Cost added to a PTP option on another configuration than the current one: a
configuration is kept while any option on it can follow the motion."""


def move_lengths(T_world_tool: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tool translation (m) and rotation (rad) from each pose to the next, (n-1,) each."""
    R = T_world_tool[:, :3, :3]
    dist = np.linalg.norm(np.diff(T_world_tool[:, :3, 3], axis=0), axis=1)
    angle = np.linalg.norm(log_so3(R[:-1].transpose(0, 2, 1) @ R[1:]), axis=1)
    return dist, angle


def sample_linear_moves(
    T_world_tool: np.ndarray, linear: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Every target, preceded for linear moves by samples one controller step apart.

    Parameters
    ----------
    T_world_tool
        (n, 4, 4) targets in execution order.
    linear
        (n,) whether each target is reached by a linear move from the previous one.

    Returns
    -------
    samples
        (m, 4, 4) poses: for each target its intermediate samples (positions on the
        line, rotations on the geodesic), then the target itself, exactly.
    stops
        (n,) end index (exclusive) of each target's rows in ``samples``.
    """
    n = len(T_world_tool)
    linear = np.asarray(linear, dtype=bool).copy()
    linear[0] = False
    dist, angle = move_lengths(T_world_tool)
    counts = np.ones(n, dtype=np.intp)
    steps = np.maximum(np.ceil(dist / STEP_TRANSLATION), np.ceil(angle / STEP_ROTATION))
    counts[1:] = np.where(linear[1:], np.maximum(steps, 1), 1).astype(np.intp)
    stops = np.cumsum(counts)
    owner = np.repeat(np.arange(n), counts)
    within = np.arange(stops[-1]) - np.repeat(stops - counts, counts) + 1
    frac = within / counts[owner]
    prev = np.maximum(owner - 1, 0)
    out = _along_line(T_world_tool[prev], T_world_tool[owner], frac)
    out[stops - 1] = T_world_tool  # targets exactly as given, not re-interpolated
    return out, stops


def _along_line(T_from: np.ndarray, T_to: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """(m, 4, 4) poses at fractions ``frac`` (m,) of the way from ``T_from`` to ``T_to``
    ((m, 4, 4) each): positions on the line, rotations on the geodesic."""
    R0 = T_from[:, :3, :3]
    w = log_so3(R0.transpose(0, 2, 1) @ T_to[:, :3, :3])
    out = np.repeat(np.eye(4)[None], len(frac), axis=0)
    out[:, :3, :3] = R0 @ exp_so3(frac[:, None] * w)
    p0, p1 = T_from[:, :3, 3], T_to[:, :3, 3]
    out[:, :3, 3] = p0 + frac[:, None] * (p1 - p0)
    return out


def _fail(wp: Waypoint, why: str, T_base_tool: np.ndarray) -> InfeasibleError:
    x, y, z = T_base_tool[:3, 3]
    error = InfeasibleError(
        f"element {wp.element}, target '{wp.label}': {why} "
        f"(tool at x={x:.3f}, y={y:.3f}, z={z:.3f} m in the robot base frame)"
    )
    error.element = wp.element
    return error


def solve_moves(
    waypoints: Sequence[Waypoint],
    robot_name: str,
    T_base_world: np.ndarray,
    T_flange_tool: np.ndarray,
    q_start: np.ndarray | None = None,
    q_end: np.ndarray | None = None,
    memo: ChainMemo | None = None,
) -> tuple[
    np.ndarray, list[np.ndarray | None], list[np.ndarray | None], np.ndarray, np.ndarray, np.ndarray
]:
    """Joint configurations for every waypoint, with linear moves checked along the line.

    Parameters
    ----------
    waypoints
        Cartesian targets in the world frame, in execution order.
    robot_name
        Robot model name.
    T_base_world
        Pose of the world in the robot base frame (metres).
    T_flange_tool
        Tool centre point in the flange frame.
    q_start
        Configuration before the first move (default: the middle of the joint limits).
    q_end
        Joint target after the last move (HOME), which the last PTP target looks
        ahead to as each looks to the next.
    memo
        Chains solved by earlier calls for the same work package
        (:mod:`fabflow.programs.chain_memo`): a chain found there is not solved
        again, and the chains solved here are added.

    Returns
    -------
    q
        (n, dof) joint configuration at each waypoint (radians).
    via_q, via_T
        Per waypoint, the intermediate samples of a linear move (or None);
        the joint paths are read-only, as a memo's programs share them.
    slowdown
        (n,) factor (>= 1) each linear move's speed must be divided by so that
        its joints stay within their speed limits (near a singularity).
    wrist
        (n,) bool: linear moves that pass the wrist singularity with the wrist
        axes interpolated (:mod:`fabflow.programs.wrist_lin`), their status kept.
    joint
        (n,) bool: linear moves through the wrist singularity made joint moves.
        A short one that neither the straight nor the wrist-interpolated move can
        pass (a ``seated`` one: that the straight move cannot) takes A5 through 0,
        its bow off the line within :data:`~fabflow.programs.wrist_lin.MAX_JOINT_BOW`
        and its orientation within
        :data:`~fabflow.programs.wrist_lin.MAX_DEVIATION_DEG` (a seated one's
        exact, A1, A4 and A6 standing still); a ``free`` one keeps its
        configuration with a half turn of A4 and A6, whatever its path.

    Raises
    ------
    InfeasibleError
        Naming the element and target that is unreachable, or the linear move
        that crosses a joint limit or changes configuration.
    """
    robot = get_robot(robot_name)
    n = len(waypoints)
    if n == 0:
        empty = np.zeros(0, dtype=bool)
        return np.zeros((0, robot.dof)), [], [], np.ones(0), empty, empty.copy()
    T_tool_flange = np.linalg.inv(np.asarray(T_flange_tool, dtype=float))
    T_world_tool = np.stack([w.T_world_tool for w in waypoints])
    flat, stops = sample_linear_moves(T_world_tool, np.array([w.kind == "lin" for w in waypoints]))
    T_base_tool = T_base_world @ flat
    T_base_flange = T_base_tool @ T_tool_flange
    q_all, valid = robot.ik_batch(T_base_flange)

    q_prev = (
        robot.joint_limits.mean(axis=1) if q_start is None else np.asarray(q_start, dtype=float)
    )
    current = int(configuration_of(robot, q_prev[None])[0])
    # Time per sample of each linear move at its programmed speed: the joint
    # speeds the line demands must stay within the robot's limits.
    dist, angle = move_lengths(T_world_tool)
    speed = np.array([w.speed for w in waypoints[1:]])
    counts = np.diff(stops)
    dt = np.r_[np.inf, np.maximum(dist / speed, angle / TOOL_ROTATION_SPEED) / counts]
    q_out = np.zeros((n, robot.dof))
    slowdown = np.ones(n)
    via_q: list[np.ndarray | None] = [None] * n
    via_T: list[np.ndarray | None] = [None] * n
    wrist = np.zeros(n, dtype=bool)
    joint = np.zeros(n, dtype=bool)
    starts = np.r_[0, stops[:-1]]

    def follow(i: int, q_prev: np.ndarray, branch: int) -> tuple[np.ndarray, int, float]:
        """Joint path of linear move ``i`` from ``q_prev`` on IK branch ``branch``."""
        rows = slice(starts[i], stops[i])
        path = follow_branch(robot, q_all[rows, branch], valid[rows, branch], q_prev, dt[i])
        if path is not None:
            return path[0], branch, path[1]
        return _step_through(
            robot,
            waypoints[i],
            q_all[rows],
            valid[rows],
            q_prev,
            T_base_flange[rows],
            T_base_tool[rows],
            dt=dt[i],
        )

    def follow_chain(
        i: int, end: int, q_i: np.ndarray, branch: int, wrist_ok: bool
    ) -> tuple[list[ChainMove], bool]:
        """The linear moves after PTP ``i`` from ``q_i``; whether one takes A5 through 0.

        Each move is ``(joint path, slowdown, samples, joint)``: ``samples`` are the
        tool poses (world) of a wrist-interpolated move's path, None for the
        others; ``joint``: made a joint move (:func:`_as_joint_move`).
        """
        chain: list[ChainMove] = []
        q_chain = q_i
        flips = False
        k = i + 1
        while k < end:
            if end - k > 1:  # several linear moves: as many as go, at once on this branch
                last = min(end, k + FAST_WINDOW)
                rows = slice(starts[k], stops[last - 1])
                fast = follow_branch_chain(
                    robot, q_all[rows, branch], valid[rows, branch], (stops - starts)[k:last],
                    q_chain, dt[k:last],
                )  # fmt: skip
                if fast:
                    chain += [(path, slow, None, False) for path, slow in fast]
                    q_chain = fast[-1][0][-1]
                    k += len(fast)
                    continue
            path, branch, slow = follow(k, q_chain, branch)
            samples = None
            as_joint = False
            if wrist_flips(np.vstack([q_chain, path])):
                seated = waypoints[k].seated
                kept = _keep_status(k, q_chain) if wrist_ok and not seated else None
                if kept is not None:
                    path, branch, slow, samples = kept
                elif wrist_ok and (q_joint := _as_joint_move(k, q_chain)) is not None:
                    path, slow, as_joint = q_joint[None], 1.0, True
                    row = stops[k] - 1
                    same = _same_branch(q_all[row], q_joint) & valid[row]
                    branch = int(np.argmax(same)) if same.any() else branch
                else:
                    flips = True
            chain.append((path, slow, samples, as_joint))
            q_chain = path[-1]
            k += 1
        return chain, flips

    def _as_joint_move(k: int, q_from: np.ndarray) -> np.ndarray | None:
        """The end of linear move ``k`` as a joint move from ``q_from`` through A5 = 0,
        where its bow and turn off the line are within bounds
        (:func:`~fabflow.programs.wrist_lin.joint_move_bow`; a ``seated`` move's
        orientation exact, with A1, A4 and A6 standing still); None otherwise. A
        ``free`` move (the empty tool drawn in) keeps its configuration instead,
        with a half turn of A4 and A6, whatever its path (checked for collisions)."""
        end_row = stops[k] - 1
        ends = robot.nearest_turn(q_all[end_row][valid[end_row]], q_from)
        ends = ends[robot.within_limits(ends)]
        # the wrist only flips: the main axes move as little as the line asks
        ends = ends[np.abs(ends[:, :3] - q_from[:3]).max(axis=1) < MAX_JOINT_STEP]
        ends = ends[np.argsort(np.abs(ends - q_from).max(axis=1), kind="stable")]
        seated = waypoints[k].seated
        if waypoints[k].free and not seated:
            same = configuration_of(robot, ends) == configuration_of(robot, q_from[None])[0]
            return ends[same][0] if same.any() else None
        if seated:  # A2, A3 and A5 alone turn, about parallel axes
            ends = ends[np.abs(ends[:, [0, 3, 5]] - q_from[[0, 3, 5]]).max(axis=1) < 1e-6]
        turn = SEATED_TURN if seated else np.radians(MAX_DEVIATION_DEG)
        for q_end in ends:
            bow, deviation = joint_move_bow(robot, q_from, q_end, T_flange_tool)
            if bow <= MAX_JOINT_BOW and deviation <= turn:
                return q_end
        return None

    def _keep_status(
        k: int, q_from: np.ndarray
    ) -> tuple[np.ndarray, int, float, np.ndarray] | None:
        """Linear move ``k`` with the wrist axes interpolated to an end of the same status,
        sampled finely enough (:data:`WRIST_SAMPLES`) for the wrist's half turn."""
        end_row = stops[k] - 1
        count = max(int(stops[k] - starts[k]), WRIST_SAMPLES)
        samples = _line_samples(flat[starts[k] - 1], flat[end_row], count)
        T_samples = T_base_world @ samples
        found = [
            wrist_interpolated_path(robot, q_from, q_end, T_samples, T_flange_tool)
            for q_end in same_status_ends(robot, q_from, q_all[end_row], valid[end_row])
        ]
        paths = [f for f in found if f is not None and f[1] <= np.radians(MAX_DEVIATION_DEG)]
        if not paths:
            return None
        path = min(paths, key=lambda f: f[1])[0]
        # the poses the joints really take (the orientation off the straight move)
        samples = np.linalg.inv(T_base_world) @ robot.fk(path) @ T_flange_tool
        samples[-1] = flat[end_row]  # the target as given
        q_end = path[-1]
        steps = np.abs(np.diff(np.vstack([q_from, path]), axis=0))
        dt_sample = dt[k] * (stops[k] - starts[k]) / count
        slow = max(1.0, float((steps / (robot.velocity_limits * dt_sample)).max()))
        if steps.max() > MAX_JOINT_STEP or slow > 1.0 / MIN_SPEED_FRACTION:
            return None
        same = _same_branch(q_all[end_row], q_end)
        return path, int(np.argmax(same & valid[end_row])), slow, samples

    # Branches on which an element's whole motion (every target and every sample
    # of its linear moves) has a solution: a configuration change, where one is
    # needed, then happens once, at the element's first target.
    element_of = np.array([w.element for w in waypoints])
    _, owner = np.unique(element_of, return_inverse=True)
    sample_owner = np.repeat(owner.ravel(), np.diff(np.r_[0, stops]))
    whole = np.ones((owner.max() + 1, valid.shape[1]), dtype=bool)
    np.logical_and.at(whole, sample_owner, valid)
    ptp_index = np.flatnonzero([w.kind == "ptp" for w in waypoints])

    # A PTP target and the linear moves after it form a chain: the PTP takes the
    # cheapest configuration from which the whole chain can be followed.
    fixed = np.stack([T_base_world, T_tool_flange])
    home = None if q_end is None else ("home", q_end)
    i = 0
    while i < n:
        end = i + 1
        while end < n and waypoints[end].kind == "lin":
            end += 1
        later = ptp_index[ptp_index > i]
        nxt = stops[later[0]] - 1 if len(later) else None
        key = None
        if memo is not None:
            ahead = ("ptp", flat[nxt]) if nxt is not None else home
            key = chain_key(
                robot.name, fixed, q_prev, current, flat[starts[i] : stops[end - 1]],
                stops[i:end] - starts[i:end], waypoints[i:end], whole[owner.ravel()[i]], ahead,
            )  # fmt: skip
        solved = None if key is None else memo.get(key)
        if solved is None:
            options = _ptp_options(
                robot,
                q_all[stops[i] - 1],
                valid[stops[i] - 1],
                q_prev,
                current,
                whole[owner.ravel()[i]],
                None if nxt is None else (q_all[nxt], valid[nxt]),
                q_end,
            )
            if not options:
                raise _fail(
                    waypoints[i],
                    "no inverse kinematics solution within the joint limits",
                    T_base_tool[stops[i] - 1],
                )
            first_error: InfeasibleError | None = None
            chosen = flipping = None
            # First a chain on which no linear move takes A5 through 0; failing that,
            # one whose flipping moves can keep their status with the wrist axes
            # interpolated (:mod:`fabflow.programs.wrist_lin`) or be made joint moves
            # (:func:`_as_joint_move`); failing that too, the cheapest chain, its
            # flips counted by the program's checks.
            for wrist_ok in (False, True):
                for q_i, branch in options:
                    try:
                        chain, flips = follow_chain(i, end, q_i, branch, wrist_ok)
                    except InfeasibleError as error:
                        first_error = first_error or error
                        continue
                    if not flips:
                        chosen = (q_i, branch, chain)
                        break
                    flipping = flipping or (q_i, branch, chain)
                if chosen is not None or robot.dof != 6:
                    break
            if chosen is None:
                if flipping is None:
                    assert first_error is not None
                    raise first_error
                chosen = flipping
            q_i, current, chain = chosen
            if chain:  # the configuration the chain ends in, which the next one keeps
                end_row = stops[end - 1] - 1
                same = _same_branch(q_all[end_row], chain[-1][0][-1])
                if same.any():
                    current = int(np.argmax(same))
            solved = frozen(q_i, current, chain)
            if key is not None:
                memo[key] = solved
        q_i, current, chain = solved
        q_out[i] = q_prev = q_i
        for k, (path, slow, samples, as_joint) in zip(range(i + 1, end), chain, strict=True):
            q_out[k] = q_prev = path[-1]
            slowdown[k] = slow
            wrist[k] = samples is not None
            joint[k] = as_joint
            if len(path) > 1:
                via_q[k] = path[:-1]
                via_T[k] = flat[starts[k] : stops[k] - 1] if samples is None else samples[:-1]
        i = end
    return q_out, via_q, via_T, slowdown, wrist, joint


def _line_samples(T_from: np.ndarray, T_to: np.ndarray, count: int) -> np.ndarray:
    """``count`` poses from ``T_from`` (excluded) to ``T_to`` (included): positions on the
    line, rotations on the geodesic, uniformly spaced."""
    frac = np.arange(1, count + 1) / count
    out = _along_line(T_from[None].repeat(count, 0), T_to[None].repeat(count, 0), frac)
    out[-1] = T_to
    return out


def _ptp_options(
    robot: RobotModel,
    q_branches: np.ndarray,
    ok: np.ndarray,
    q_prev: np.ndarray,
    current: int,
    whole_element: np.ndarray,
    next_ptp: tuple[np.ndarray, np.ndarray] | None,
    q_end: np.ndarray | None = None,
) -> list[tuple[np.ndarray, int]]:
    """Valid configurations of a PTP target with their IK branch, cheapest first.

    The cost of an option is the joint travel from ``q_prev`` and on to the
    next PTP target on the same branch, weighted per axis
    (:data:`AXIS_WEIGHTS`), plus :data:`CONFIGURATION_CHANGE_COST` for a branch
    other than ``current``, once more for one on which the element's whole
    motion has no solution (``whole_element``, per branch), and once more for
    one the next PTP target does not have. Looking one target ahead settles A1
    at the back of its range (where both turns are within the limits) on the
    side the arm goes next. The last PTP target looks ahead to the joint target
    ``q_end`` (HOME) as it is, no turn of it taken. Other multi-turn joints take
    the turn nearest ``q_prev``.
    """
    candidates = np.flatnonzero(ok)
    if len(candidates) == 0:
        return []
    turned = _nearest_turn(robot, q_branches[candidates], q_prev)
    turned, candidates = _a1_turns(robot, turned, candidates)
    weights = AXIS_WEIGHTS[: robot.dof] if robot.dof <= len(AXIS_WEIGHTS) else 1.0
    cost = (np.abs(turned - q_prev) * weights).sum(axis=1)
    # a branch the element's motion cannot keep forces a change inside the
    # element later: as costly as changing now, at its first target
    penalty = (candidates != current).astype(float) + ~whole_element[candidates]
    if next_ptp is not None:
        q_next, ok_next = next_ptp
        ahead = _nearest_turn(robot, q_next[candidates], turned)
        reachable = ok_next[candidates]
        cost += np.where(reachable, (np.abs(ahead - turned) * weights).sum(axis=1), 0.0)
        penalty += ~reachable
    elif q_end is not None:
        cost += (np.abs(np.asarray(q_end, dtype=float) - turned) * weights).sum(axis=1)
    cost += CONFIGURATION_CHANGE_COST * penalty
    order = np.argsort(cost, kind="stable")
    return [(turned[k], int(candidates[k])) for k in order]


def _a1_turns(
    robot: RobotModel, q: np.ndarray, branch: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The options ``q`` plus, where A1 may also stand one turn away, that turn too."""
    lo, hi = robot.joint_limits[0]
    other = q.copy()
    other[:, 0] -= 2.0 * np.pi * np.sign(q[:, 0])
    inside = (other[:, 0] >= lo - 1e-9) & (other[:, 0] <= hi + 1e-9) & (other[:, 0] != q[:, 0])
    return np.vstack([q, other[inside]]), np.r_[branch, branch[inside]]


def _same_branch(q_branches: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(K,) which branches of one target's solutions ``q_branches`` (K, dof) are ``q``,
    modulo whole turns."""
    return (np.abs(wrap_angle(q_branches - q)) < 1e-6).all(axis=1)


def _nearest_turn(robot: RobotModel, q: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    """Candidates (k, dof) with multi-turn joints put at the turn nearest ``q_ref``.

    ``q_ref`` is one configuration ``(dof,)`` or one per candidate ``(k, dof)``.
    The shortest-angle turn is tried first; candidates it puts outside the
    limits are left to the robot model's general rule.
    """
    lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
    turned = np.where(robot.multi_turn, q_ref + wrap_angle(q - q_ref), q)
    outside = ((turned < lo - 1e-9) | (turned > hi + 1e-9)).any(axis=1)
    if outside.any():
        ref = np.broadcast_to(q_ref, q.shape)
        turned[outside] = robot.nearest_turn(q[outside], ref[outside])
    return turned


def _step_through(
    robot: RobotModel,
    wp: Waypoint,
    q_rows: np.ndarray,
    valid_rows: np.ndarray,
    q_prev: np.ndarray,
    T_base_flange: np.ndarray,
    T_base_tool: np.ndarray,
    dt: float,
) -> tuple[np.ndarray, int, float]:
    """Follow a linear move sample by sample, each time taking the valid
    configuration nearest the previous one (the samples up to the first that
    needs more than that at once, :func:`~fabflow.programs.branch_follow.nearest_prefix`).

    Handles the places where the branch numbering of the closed-form solver
    swaps, and the wrist singularity, where only the sum of the two aligned
    axes is determined: there the sample is solved again with the previous
    configuration as reference, which keeps the split continuous. The joint
    speeds must stay within the robot's limits (``dt``: seconds per sample at the
    programmed speed): the returned slowdown (>= 1) divides the move's speed so
    they do. Raises naming the element and target when no configuration
    continues the motion.
    """
    rate_limit = robot.velocity_limits * dt
    path = np.zeros((len(q_rows), robot.dof))
    settled, branch = nearest_prefix(robot, q_rows, valid_rows, q_prev, dt)
    path[: len(settled)] = settled
    if len(settled):
        q_prev = settled[-1]
    slowdown = 1.0  # the settled samples' steps are within the speed limits
    for j in range(len(settled), len(q_rows)):
        candidates = np.flatnonzero(valid_rows[j])
        if len(candidates) == 0:
            why = (
                "no inverse kinematics solution within the joint limits"
                if j == len(q_rows) - 1
                else "the linear move to it crosses a joint limit or leaves the workspace"
            )
            raise _fail(wp, why, T_base_tool[j])
        turned = _nearest_turn(robot, q_rows[j, candidates], q_prev)
        load = (np.abs(turned - q_prev) / rate_limit).max(axis=1)
        best = int(np.argmin(load))
        if load[best] > 1.0:
            q_again, ok = robot.ik_batch(T_base_flange[j][None], q_ref=q_prev)
            if ok[0].any():
                candidates = np.flatnonzero(ok[0])
                turned = _nearest_turn(robot, q_again[0, candidates], q_prev)
                load = (np.abs(turned - q_prev) / rate_limit).max(axis=1)
                best = int(np.argmin(load))
        step = np.abs(turned[best] - q_prev)
        k = int(np.argmax(step / rate_limit))
        if step[k] > MAX_JOINT_STEP:
            why = (
                f"the linear move to it changes configuration "
                f"(joint {k + 1} jumps {np.degrees(step[k]):.0f} deg)"
            )
            raise _fail(wp, why, T_base_tool[j])
        if load[best] > 1.0 / MIN_SPEED_FRACTION:
            why = (
                f"the linear move to it passes too close to a singularity: joint {k + 1} "
                f"would need {np.degrees(step[k] / dt * MIN_SPEED_FRACTION):.0f} deg/s at "
                f"{MIN_SPEED_FRACTION:.0%} of the speed (limit "
                f"{np.degrees(robot.velocity_limits[k]):.0f} deg/s)"
            )
            raise _fail(wp, why, T_base_tool[j])
        slowdown = max(slowdown, float(load[best]))
        q_prev = turned[best]
        path[j] = q_prev
        branch = int(candidates[best])
    return path, branch, slowdown
