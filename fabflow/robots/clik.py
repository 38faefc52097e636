"""Closed-loop inverse kinematics (CLIK) for machines without a Cartesian controller.

Implements the controller of Lee & Brell-Cokcan (2021), "Cartesian coordinate
control for teleoperated construction machines" (shared/seeds/004), eqs. 4-9:

* ``dq = J+ (dx + K e)`` (eq. 6): ``dx`` the commanded task step, ``e`` the
  remaining difference between the desired and the actual task value;
* ``J+ = W^-1 J^T (J W^-1 J^T + lambda^2 I)^-1`` (eq. 7; the paper prints ``J W
  J^T``, the weighted least-norm solution of Chan & Dubey uses ``W^-1`` in both
  places, as here);
* ``W = diag(w_i)``, ``w_i = 1 + |dH/dq_i|`` while ``|dH/dq_i|`` grows (the joint
  approaches a limit), else 1, with the joint-limit criterion gradient of eq. 8;
* ``lambda = k (1 - m / m_t)`` below the manipulability threshold ``m_t``, else
  0, with ``m = sqrt(det(J J^T))`` (eq. 9).

On top of one CLIK iteration (:meth:`Clik.step`) come the paper's motions: PTP
in steps of 2 cm / 0.015 rad with the same thresholds (:meth:`Clik.ptp`), PTP
split into phases for joints that cannot move together (:meth:`Clik.ptp_phased`,
BROKK joint 2 alone), a path divided at 4 cm and tracked (:func:`divide_path`,
:meth:`Clik.track`). CLIK produces the joint reference of the machine; the
hydraulic joints that follow it are simulated in :mod:`fabflow.robots.hydraulic`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError, UnsupportedError
from fabflow.robots.chain import RobotModel
from fabflow.robots.planar_ik import is_pitch_chain
from fabflow.transforms.so3 import exp_so3, log_so3

FloatArray = NDArray[np.float64]

TaskName = Literal["pose", "position", "position_pitch"]


@dataclass(frozen=True)
class ClikGains:
    """Parameters of the CLIK controller (SI units).

    Attributes
    ----------
    k_damping
        ``k`` of eq. 9, the largest damping factor (at m = 0).
    m_threshold
        ``m_t`` of eq. 9; None: 10 % of the manipulability at the model's
        ``q_nominal``.
    gain
        ``K = gain * I`` of eq. 6 (per iteration; 1 closes the error in one step).
    step_position, step_rotation
        Largest task step per iteration (metres, radians): the paper's 2 cm and 0.015 rad.
    tol_position, tol_rotation
        A motion is finished when the goal error is below these (the paper uses
        the step sizes).
    max_joint_step
        Largest joint change per iteration (radians); larger steps are scaled down.
    max_iter
        Iteration limit of a motion.
    """

    k_damping: float = 0.05
    m_threshold: float | None = None
    gain: float = 1.0
    step_position: float = 0.02
    step_rotation: float = 0.015
    tol_position: float = 0.02
    tol_rotation: float = 0.015
    max_joint_step: float = 0.1
    max_iter: int = 5000


@dataclass(frozen=True, eq=False)
class ClikResult:
    """Outcome of a CLIK motion.

    Attributes
    ----------
    q
        ``(K + 1, dof)`` joint reference after each iteration, starting with the start
        configuration (radians).
    phase
        ``(K + 1,)`` phase index of each row (0 when the motion has one phase).
    converged
        The goal was reached within the tolerances.
    error_position, error_rotation
        Final goal errors (metres, radians).
    waypoints
        ``(P, M)`` task-space reference of a tracked path (empty for PTP).
    """

    q: FloatArray
    phase: NDArray[np.int64]
    converged: bool
    error_position: float
    error_rotation: float
    waypoints: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def iterations(self) -> int:
        """Number of CLIK iterations."""
        return int(self.q.shape[0] - 1)


class Clik:
    """The CLIK controller of paper 004 for one machine and one task space.

    Parameters
    ----------
    robot
        The machine model.
    task
        ``"pose"`` (6-D flange pose), ``"position"`` (flange position) or
        ``"position_pitch"`` (position and tool pitch, the BROKK's
        ``x = [x, y, z, Theta]``; pitch chains only).
    gains
        Controller parameters.
    """

    def __init__(
        self, robot: RobotModel, task: TaskName = "pose", gains: ClikGains | None = None
    ) -> None:
        if task not in ("pose", "position", "position_pitch"):
            raise UnsupportedError(
                f"unknown CLIK task {task!r}; use 'pose', 'position' or 'position_pitch'"
            )
        if robot.prismatic.any():
            raise UnsupportedError(
                f"CLIK turns revolute joints only; {robot.name} has a sliding one"
            )
        if task == "position_pitch" and not is_pitch_chain(robot):
            raise UnsupportedError(
                f"task 'position_pitch' needs a pitch-chain machine, not {robot.name}"
            )
        self.robot = robot
        self.task = task
        self.gains = gains or ClikGains()
        self.dim = {"pose": 6, "position": 3, "position_pitch": 4}[task]
        self._pitch_row = np.where(np.arange(robot.dof) >= 1, robot.joint_sign, 0.0)
        lo, hi = robot.joint_limits[:, 0], robot.joint_limits[:, 1]
        self._lo, self._hi = lo, hi
        self._span2 = (hi - lo) ** 2
        self._prev_grad = np.full(robot.dof, np.inf)
        m_t = self.gains.m_threshold
        if m_t is None:
            q_nom = robot.q_nominal if robot.q_nominal is not None else 0.5 * (lo + hi)
            _, J = self.measure(q_nom)
            m_t = 0.1 * self.manipulability(J)
        self.m_threshold = float(m_t)

    # ------------------------------------------------------------ task space
    def measure(self, q: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Task value and task Jacobian at ``q``.

        Returns
        -------
        x : numpy.ndarray
            4x4 flange pose (task ``"pose"``), position ``(3,)`` or ``[x, y, z, Theta]``.
        J : numpy.ndarray
            ``(M, dof)`` task Jacobian.
        """
        F = self.robot.frames_single(q)
        T = F[-1]
        z = F[:-2, :3, 2]
        r = T[:3, 3] - F[:-2, :3, 3]
        s = self.robot.joint_sign
        Jv = np.empty((3, self.robot.dof))
        Jv[0] = (z[:, 1] * r[:, 2] - z[:, 2] * r[:, 1]) * s
        Jv[1] = (z[:, 2] * r[:, 0] - z[:, 0] * r[:, 2]) * s
        Jv[2] = (z[:, 0] * r[:, 1] - z[:, 1] * r[:, 0]) * s
        if self.task == "position":
            return T[:3, 3].copy(), Jv
        if self.task == "position_pitch":
            theta = float(self._pitch_row @ q)
            return np.append(T[:3, 3], theta), np.vstack([Jv, self._pitch_row])
        Jw = z.T * s
        return T, np.vstack([Jv, Jw])

    def error(self, x_a: FloatArray, x_b: FloatArray) -> FloatArray:
        """Task difference ``x_a - x_b`` as an ``(M,)`` vector (rotation as a rotation vector)."""
        if self.task == "pose":
            dp = x_a[:3, 3] - x_b[:3, 3]
            dr = _log_rot(x_a[:3, :3] @ x_b[:3, :3].T)
            return np.concatenate([dp, dr])
        return np.asarray(x_a, dtype=float) - np.asarray(x_b, dtype=float)

    def advance(self, x: FloatArray, dx: FloatArray) -> FloatArray:
        """Task value ``x`` moved by the step ``dx``."""
        if self.task == "pose":
            out = x.copy()
            out[:3, 3] += dx[:3]
            out[:3, :3] = _exp_rot(dx[3:]) @ x[:3, :3]
            return out
        return x + dx

    def _split(self, e: FloatArray) -> tuple[float, float]:
        ep = float(np.linalg.norm(e[:3]))
        er = float(np.linalg.norm(e[3:])) if e.shape[0] > 3 else 0.0
        return ep, er

    def clamp_step(self, e: FloatArray) -> FloatArray:
        """The goal error limited to one PTP step (2 cm position, 0.015 rad orientation)."""
        out = e.copy()
        ep, er = self._split(e)
        if ep > self.gains.step_position:
            out[:3] *= self.gains.step_position / ep
        if er > self.gains.step_rotation:
            out[3:] *= self.gains.step_rotation / er
        return out

    # ----------------------------------------------------------- eqs. 7 - 9
    @staticmethod
    def manipulability(J: FloatArray) -> float:
        """``m = sqrt(det(J J^T))`` (eq. 9)."""
        return float(np.sqrt(max(np.linalg.det(J @ J.T), 0.0)))

    def damping(self, J: FloatArray) -> float:
        """Damping factor ``lambda`` of eq. 9."""
        m = self.manipulability(J)
        if m < self.m_threshold:
            return self.gains.k_damping * (1.0 - m / self.m_threshold)
        return 0.0

    def joint_limit_gradient(self, q: FloatArray) -> FloatArray:
        """``|dH/dq_i|`` of the joint-limit criterion (eq. 8), inf at or beyond a limit."""
        lo, hi = self._lo, self._hi
        num = self._span2 * (2.0 * q - hi - lo)
        den = 4.0 * (hi - q) ** 2 * (q - lo) ** 2
        g = np.full(q.shape, np.inf)
        np.divide(np.abs(num), den, out=g, where=den > 0)
        return g

    def weights(self, q: FloatArray) -> FloatArray:
        """Diagonal of W (eq. 8): ``1 + |dH/dq|`` for joints moving towards a limit, else 1."""
        g = self.joint_limit_gradient(q)
        prev = self._prev_grad
        towards = (g >= prev) & np.isfinite(prev)
        self._prev_grad = g
        w = np.where(towards, 1.0 + g, 1.0)
        return np.where(np.isfinite(w), w, 1e12)

    def reset(self) -> None:
        """Forget the joint-limit gradient history (start of a new motion)."""
        self._prev_grad = np.full(self.robot.dof, np.inf)

    def pinv(self, J: FloatArray, w: FloatArray, lam: float | FloatArray) -> FloatArray:
        """Weighted damped pseudo-inverse ``W^-1 J^T (J W^-1 J^T + lambda^2 I)^-1`` (eq. 7).

        ``J`` is ``(M, dof)`` or a stack ``(K, M, dof)`` with weights ``(K, dof)``
        and damping ``(K,)``.
        """
        WiJt = np.swapaxes(J, -1, -2) / w[..., :, None]
        A = J @ WiJt
        m = A.shape[-1]
        A = A + (np.asarray(lam, dtype=float) ** 2)[..., None, None] * np.eye(m)
        try:
            return np.swapaxes(np.linalg.solve(A, np.swapaxes(WiJt, -1, -2)), -1, -2)
        except np.linalg.LinAlgError:
            if J.ndim != 2:
                raise
            return np.linalg.lstsq(A, WiJt.T, rcond=None)[0].T

    def step(
        self, q: FloatArray, dx: FloatArray, e: FloatArray, active: NDArray[np.bool_] | None = None
    ) -> FloatArray:
        """One CLIK iteration: the joint change ``J+ (dx + K e)`` (eq. 6).

        Parameters
        ----------
        q
            Current configuration (radians).
        dx
            Commanded task step ``(M,)``.
        e
            Remaining task error ``(M,)`` (desired minus actual).
        active
            ``(dof,)`` joints allowed to move; others are locked (their Jacobian
            columns removed).

        Returns
        -------
        numpy.ndarray
            ``(dof,)`` joint change (radians), scaled so no joint moves more than
            ``max_joint_step`` and clipped so the result stays within limits.
        """
        _, J = self.measure(q)
        if active is not None:
            J = J * active[None, :]
        return self.joint_step(q, J, dx, e)

    def joint_step(self, q: FloatArray, J: FloatArray, dx: FloatArray, e: FloatArray) -> FloatArray:
        """Eq. 6 with a given task Jacobian ``J`` (see :meth:`step`); updates the W history."""
        w = self.weights(q)
        lam = self.damping(J)
        dq = self.pinv(J, w, lam) @ (dx + self.gains.gain * e)
        big = np.max(np.abs(dq))
        if big > self.gains.max_joint_step:
            dq *= self.gains.max_joint_step / big
        return np.clip(q + dq, self._lo, self._hi) - q

    def _task_vector(self, q: FloatArray) -> FloatArray:
        """Task value as a flat vector (position first; ``"pose"`` adds the rotation vector)."""
        x, _ = self.measure(q)
        if self.task == "pose":
            return np.concatenate([x[:3, 3], log_so3(x[:3, :3])])
        return x

    # --------------------------------------------------------------- motions
    def goal_from(self, goal: ArrayLike) -> FloatArray:
        """Validate a goal for the task space (4x4 pose, (3,) position or (4,) position+pitch)."""
        g = np.asarray(goal, dtype=float)
        want = (4, 4) if self.task == "pose" else (self.dim,)
        if g.shape != want:
            raise InputError(
                f"CLIK goal for task {self.task!r} must have shape {want}, got {g.shape}"
            )
        return g

    def ptp(
        self,
        q0: ArrayLike,
        goal: ArrayLike,
        *,
        active: NDArray[np.bool_] | None = None,
        tol_position: float | None = None,
        tol_rotation: float | None = None,
    ) -> ClikResult:
        """Point-to-point motion to a task-space goal in bounded steps.

        Each iteration moves the desired task value ``x_d`` towards the goal by at
        most one step (2 cm / 0.015 rad) and applies eq. 6 with ``e = x_d - x``.

        Parameters
        ----------
        q0
            Start configuration (radians).
        goal
            Goal in the task space (see :meth:`goal_from`).
        active
            Joints allowed to move (default all).
        tol_position, tol_rotation
            Goal thresholds (default: the gains' 2 cm / 0.015 rad).

        Returns
        -------
        ClikResult
            The joint reference, one row per iteration.
        """
        g = self.goal_from(goal)
        tp = self.gains.tol_position if tol_position is None else tol_position
        tr = self.gains.tol_rotation if tol_rotation is None else tol_rotation
        q = np.array(q0, dtype=float)
        self.reset()
        x, J = self.measure(q)
        x_d = x
        traj = [q.copy()]
        ep, er = self._split(self.error(g, x))
        for _ in range(self.gains.max_iter):
            if ep <= tp and er <= tr:
                break
            if active is not None:
                J = J * active[None, :]
            dx = self.clamp_step(self.error(g, x_d))
            e = self.error(x_d, x)
            x_d = self.advance(x_d, dx)
            q = q + self.joint_step(q, J, dx, e)
            traj.append(q.copy())
            x, J = self.measure(q)
            ep, er = self._split(self.error(g, x))
        qs = np.asarray(traj)
        return ClikResult(qs, np.zeros(len(qs), dtype=np.int64), ep <= tp and er <= tr, ep, er)

    def ptp_phased(self, q0: ArrayLike, goal: ArrayLike, **tol: float) -> ClikResult:
        """PTP for machines whose joints cannot all move at the same time.

        The goal configuration is first found by a CLIK run on the model with
        all joints (it is not sent to the machine). Then every joint group that
        is a single joint (the BROKK's joint 2) moves alone to its goal value in
        steps of at most ``step_rotation``, and finally the remaining group
        tracks the task goal with CLIK while the others stay locked.

        Parameters
        ----------
        q0
            Start configuration (radians).
        goal
            Task-space goal.
        **tol
            ``tol_position`` / ``tol_rotation`` passed to :meth:`ptp`.
        """
        groups = self.robot.motion_groups
        if len(groups) <= 1:
            return self.ptp(q0, goal, **tol)
        q = np.array(q0, dtype=float)
        virtual = self.ptp(q, goal, tol_position=1e-6, tol_rotation=1e-6)
        q_goal = virtual.q[-1]
        rows = [q[None]]
        phases = [np.zeros(1, dtype=np.int64)]
        ordered = sorted(groups, key=len)
        for k, group in enumerate(ordered[:-1], start=1):
            idx = list(group)
            n = int(np.ceil(np.max(np.abs(q_goal[idx] - q[idx])) / self.gains.step_rotation))
            if n == 0:
                continue
            path = np.repeat(q[None], n, axis=0)
            path[:, idx] = q[idx] + np.outer(np.arange(1, n + 1) / n, q_goal[idx] - q[idx])
            rows.append(path)
            phases.append(np.full(n, k, dtype=np.int64))
            q = path[-1].copy()
        active = np.zeros(self.robot.dof, dtype=bool)
        active[list(ordered[-1])] = True
        # The last group is often square (no redundancy left), so a straight task-space
        # line can run into a limit or another branch; it tracks the task-space image
        # of the joint-space interpolation to the goal configuration instead.
        n = max(2, int(np.ceil(np.max(np.abs(q_goal - q)) / 0.005)) + 1)
        q_line = q + np.outer(np.linspace(0.0, 1.0, n), q_goal - q)
        x_line = np.array([self._task_vector(qq) for qq in q_line])
        path = divide_path(x_line, self.gains.step_position)
        if self.task == "pose":
            path_T = np.tile(np.eye(4), (path.shape[0], 1, 1))
            path_T[:, :3, 3] = path[:, :3]
            path_T[:, :3, :3] = exp_so3(path[:, 3:])
            path = path_T
        tracked = self.track(q, path, settle=0, active=active)
        last = self.ptp(tracked.q[-1], goal, active=active, **tol)
        rows.append(tracked.q[1:])
        rows.append(last.q[1:])
        k_last = len(ordered)
        phases.append(np.full(tracked.q.shape[0] - 1, k_last, dtype=np.int64))
        phases.append(np.full(last.q.shape[0] - 1, k_last, dtype=np.int64))
        return ClikResult(
            np.concatenate(rows),
            np.concatenate(phases),
            last.converged,
            last.error_position,
            last.error_rotation,
        )

    def track(
        self,
        q0: ArrayLike,
        waypoints: ArrayLike,
        settle: int = 20,
        active: NDArray[np.bool_] | None = None,
    ) -> ClikResult:
        """Track a task-space path given as waypoints (e.g. divided at 4 cm).

        Iteration k commands ``dx = w[k+1] - w[k]`` with ``e = w[k] - x``; after
        the last waypoint ``settle`` iterations with ``dx = 0`` remove the rest
        of the error.

        Parameters
        ----------
        q0
            Start configuration (radians); the path should start at its task value.
        waypoints
            ``(P, M)`` task values (for ``"pose"``: ``(P, 4, 4)``).
        settle
            Extra iterations at the end.
        active
            Joints allowed to move (default all).
        """
        W = np.asarray(waypoints, dtype=float)
        if W.ndim < 2 or W.shape[0] < 2:
            raise InputError("a tracked path needs at least two waypoints")
        q = np.array(q0, dtype=float)
        self.reset()
        traj = [q.copy()]
        n = W.shape[0]
        for k in range(n - 1 + settle):
            i = min(k, n - 1)
            x, J = self.measure(q)
            if active is not None:
                J = J * active[None, :]
            dx = self.error(W[i + 1], W[i]) if k < n - 1 else np.zeros(self.dim)
            e = self.error(W[i], x)
            q = q + self.joint_step(q, J, dx, e)
            traj.append(q.copy())
        x, _ = self.measure(q)
        ep, er = self._split(self.error(W[-1], x))
        qs = np.asarray(traj)
        ok = ep <= self.gains.tol_position and er <= self.gains.tol_rotation
        return ClikResult(qs, np.zeros(len(qs), dtype=np.int64), ok, ep, er, W)


def _log_rot(R: FloatArray) -> FloatArray:
    """Rotation vector of one rotation matrix; fast path of ``log_so3`` for the control loop."""
    c = min(1.0, max(-1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    angle = math.acos(c)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < 1e-6:
        return 0.5 * v
    if angle > np.pi - 1e-3:
        return np.asarray(log_so3(R))
    return (angle / (2.0 * math.sin(angle))) * v


def _exp_rot(w: FloatArray) -> FloatArray:
    """Rotation matrix of one rotation vector (Rodrigues); fast path of ``exp_so3``."""
    angle = math.sqrt(float(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]))
    if angle < 1e-9:
        return np.asarray(exp_so3(w))
    k = w / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def divide_path(points: ArrayLike, spacing: float = 0.04) -> FloatArray:
    """Resample a polyline at equal arc-length spacing (Grasshopper's Divide Distance).

    Parameters
    ----------
    points
        ``(P, D)`` polyline vertices (metres; extra columns are interpolated too).
    spacing
        Distance between samples along the first three coordinates (metres).

    Returns
    -------
    numpy.ndarray
        ``(K, D)`` samples from the first vertex, every ``spacing``, plus the last vertex.
    """
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[0] < 2 or P.shape[1] < 3:
        raise InputError(f"a path needs (P >= 2, >= 3) vertices, got shape {P.shape}")
    if spacing <= 0:
        raise InputError(f"path spacing must be positive, got {spacing}")
    seg = np.linalg.norm(np.diff(P[:, :3], axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    stations = np.arange(0.0, s[-1], spacing)
    if s[-1] - stations[-1] > 1e-9:
        stations = np.append(stations, s[-1])
    return np.column_stack([np.interp(stations, s, P[:, j]) for j in range(P.shape[1])])
