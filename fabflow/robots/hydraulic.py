"""Simulated hydraulic joints following a CLIK joint reference, and the contact search.

Paper 004 drives each joint of the BROKK 170 through its valve (PWM) under a PI
controller on the measured joint angle; the pressure build-up in the cylinders
adds a dead time of about 1.3 s. :class:`HydraulicJoints` models each joint as

    u = sat(Kp e + Ki int e)                (PI on e = q_ref - q, PWM in [-1, 1])
    tau dv/dt = -v + v_max db(u(t - T_d))   (valve/flow: first-order lag, dead time)
    dq/dt = v

integrated with a fixed step, all joints at once; ``db`` is the valve's
deadband (spool overlap: no flow below a fraction of the opening, the rest of
the range rescaled). :class:`ValveJoints` steps the valve, lag and dead time
alone, for a controller of one's own (the tracking loop of paper 000);
:class:`HydraulicServo` steps them under the PI, for a live reference (the
machine link's simulated gateway).
:func:`reference_times` gives a CLIK reference its timing (no joint faster
than its speed limit), and :func:`tracking_rmse` compares where the tool went
with where it was meant to go.

:func:`contact_search` is the paper's pressure-threshold primitive: move the tool
along a direction until the main-pump pressure, sampled at 2 Hz, exceeds a
threshold.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.robots.chain import RobotModel
from fabflow.robots.clik import Clik

FloatArray = NDArray[np.float64]


def reference_times(robot: RobotModel, q_ref: ArrayLike, rate: float = 30.0) -> FloatArray:
    """Time stamps of a joint reference: one row per control period, longer if a joint is too fast.

    Parameters
    ----------
    robot
        Supplies the joint speed limits.
    q_ref
        ``(K, dof)`` joint reference (radians).
    rate
        Control rate (Hz); each row takes at least ``1 / rate`` seconds.

    Returns
    -------
    numpy.ndarray
        ``(K,)`` times (seconds) starting at 0.
    """
    q = np.asarray(q_ref, dtype=float)
    dq = np.abs(np.diff(q, axis=0))
    dt = np.maximum(1.0 / rate, np.max(dq / robot.velocity_limits, axis=1))
    return np.concatenate([[0.0], np.cumsum(dt)])


@dataclass(frozen=True)
class HydraulicJoints:
    """Parameters of the simulated valve-controlled hydraulic joints.

    Attributes
    ----------
    v_max
        ``(dof,)`` joint speed at full valve opening (rad/s).
    dead_time
        Delay between a valve command and the joint's response (s); ~1.3 s in paper 004.
    tau
        Time constant of the flow build-up (s).
    kp, ki
        PI gains (valve fraction per radian, per radian-second). The default
        tuning (:meth:`for_robot`) puts the loop crossover ``kp * v_max`` at
        ``0.5 / (dead_time + tau)`` rad/s (0.31 rad/s for 1.3 s), where the
        delay and lag cost less than 30 degrees of phase.
    dt
        Integration step (s).
    deadband
        Valve fraction below which no oil flows (0 to 1; 0: an ideal valve).
    """

    v_max: FloatArray
    dead_time: float = 1.3
    tau: float = 0.3
    kp: FloatArray | None = None
    ki: FloatArray | None = None
    dt: float = 0.01
    deadband: float = 0.0

    def __post_init__(self) -> None:
        ok = (
            self.dead_time >= 0
            and self.tau >= 0
            and self.dt > 0
            and 0.0 <= self.deadband < 1.0
            and np.all(np.asarray(self.v_max, dtype=float) > 0)
        )
        if not ok:
            raise InputError(
                "hydraulic joints need v_max > 0, dead_time >= 0, tau >= 0, dt > 0 and "
                "0 <= deadband < 1"
            )

    @classmethod
    def for_robot(
        cls, robot: RobotModel, dead_time: float = 1.3, tau: float = 0.3
    ) -> HydraulicJoints:
        """Joints with the robot's speed limits and the default PI tuning."""
        v = np.asarray(robot.velocity_limits, dtype=float)
        kp = 0.5 / (dead_time + tau) / v
        return cls(v_max=v, dead_time=dead_time, tau=tau, kp=kp, ki=0.05 * kp)

    def simulate(
        self, t_ref: ArrayLike, q_ref: ArrayLike, t_extra: float = 10.0
    ) -> tuple[FloatArray, FloatArray]:
        """Joint angles of the machine following a time-stamped reference.

        Parameters
        ----------
        t_ref
            ``(K,)`` increasing reference times (s).
        q_ref
            ``(K, dof)`` joint reference (radians); the machine starts at rest at ``q_ref[0]``.
        t_extra
            Time simulated after the last reference sample (s).

        Returns
        -------
        t : numpy.ndarray
            ``(S,)`` simulation times (s).
        q : numpy.ndarray
            ``(S, dof)`` joint angles (radians).
        """
        tr = np.asarray(t_ref, dtype=float)
        qr = np.asarray(q_ref, dtype=float)
        if qr.ndim != 2 or tr.shape != (qr.shape[0],):
            raise InputError(f"reference shapes do not match: t {tr.shape}, q {qr.shape}")
        dof = qr.shape[1]
        t = np.arange(0.0, tr[-1] + t_extra, self.dt)
        ref = np.column_stack([np.interp(t, tr, qr[:, j]) for j in range(dof)])
        servo = HydraulicServo(self, qr[0])
        out = np.empty((t.size, dof))
        for k in range(t.size):
            out[k] = servo.q
            servo.step(ref[k])
        return t, out


class HydraulicServo:
    """Valve-driven hydraulic joints under their PI controller, stepped one period at a time.

    The controller of :meth:`HydraulicJoints.simulate` (which runs on this class)
    for a reference that arrives live, e.g. over the machine link.

    Parameters
    ----------
    joints
        Speeds, dead time, lag, deadband, step and PI gains (without gains: 1
        valve fraction per radian, and ``ki = 0.05 kp``).
    q0
        ``(dof,)`` joint angles at rest at the start (radians).
    """

    def __init__(self, joints: HydraulicJoints, q0: ArrayLike) -> None:
        self.joints = joints
        self.valves = ValveJoints(joints, q0)
        dof = self.valves.q.size
        self._kp = np.full(dof, 1.0) if joints.kp is None else np.asarray(joints.kp, dtype=float)
        self._ki = 0.05 * self._kp if joints.ki is None else np.asarray(joints.ki, dtype=float)
        self._integ = np.zeros(dof)
        self.stopped = False

    @property
    def q(self) -> FloatArray:
        """``(dof,)`` the current joint angles (radians)."""
        return self.valves.q

    def step(self, q_ref: ArrayLike) -> FloatArray:
        """Run the PI for one period ``joints.dt`` towards a reference and advance the joints.

        Parameters
        ----------
        q_ref
            ``(dof,)`` joint reference (radians); ignored once stopped.

        Returns
        -------
        numpy.ndarray
            Joint angles one period later (radians).
        """
        if self.stopped:
            return self.valves.step(np.zeros_like(self._integ))
        e = np.asarray(q_ref, dtype=float) - self.valves.q
        dt = self.joints.dt
        u_raw = self._kp * e + self._ki * (self._integ + e * dt)
        # Anti-windup: integrate only while the valve is not saturated.
        self._integ = np.where(np.abs(u_raw) < 1.0, self._integ + e * dt, self._integ)
        return self.valves.step(u_raw)

    def stop(self) -> None:
        """Close the valves: a zero command from now on, the integrator cleared.

        Commands already sent still act for the dead time, as on the machine.
        """
        self.stopped = True
        self._integ = np.zeros_like(self._integ)


class ValveJoints:
    """The state of valve-driven hydraulic joints, stepped one period at a time.

    Parameters
    ----------
    joints
        Speeds, dead time, lag, deadband and step (the PI gains are not used:
        the caller commands the valves).
    q0
        ``(dof,)`` joint angles at rest at the start (radians).
    """

    def __init__(self, joints: HydraulicJoints, q0: ArrayLike) -> None:
        self.joints = joints
        self.q = np.array(q0, dtype=float)
        self.v = np.zeros_like(self.q)
        self._delay = round(joints.dead_time / joints.dt)
        self._hist = np.zeros((self._delay + 1, self.q.size))
        self._k = 0
        self._a = joints.dt / (joints.tau + joints.dt)

    def step(self, u: ArrayLike) -> FloatArray:
        """Command the valves for one period and advance the joints.

        Parameters
        ----------
        u
            ``(dof,)`` valve commands (fraction of full opening; clipped to [-1, 1]).

        Returns
        -------
        numpy.ndarray
            Joint angles one period later (radians).
        """
        j = self.joints
        u = np.clip(np.asarray(u, dtype=float), -1.0, 1.0)
        if j.deadband > 0:
            u = np.sign(u) * np.maximum(np.abs(u) - j.deadband, 0.0) / (1.0 - j.deadband)
        n = self._delay + 1
        self._hist[self._k % n] = u
        self._k += 1
        u_del = self._hist[self._k % n] if self._delay > 0 else u
        self.v = self.v + self._a * (j.v_max * u_del - self.v)
        self.q = self.q + self.v * j.dt
        return self.q


@dataclass(frozen=True)
class TrackingError:
    """TCP tracking error of a simulated motion (metres).

    Attributes
    ----------
    rmse_xyz
        ``(3,)`` RMSE per base axis between the actual and the reference TCP at equal times.
    rmse
        3-D RMSE at equal times.
    path_rmse
        RMS distance of the actual TCP to the reference polyline (timing ignored).
    max_path
        Largest distance to the reference polyline.
    """

    rmse_xyz: FloatArray
    rmse: float
    path_rmse: float
    max_path: float


def tracking_rmse(
    robot: RobotModel,
    t: ArrayLike,
    q: ArrayLike,
    t_ref: ArrayLike,
    q_ref: ArrayLike,
    T_flange_tool: ArrayLike | None = None,
) -> TrackingError:
    """Compare the TCP of a simulated joint trajectory with the reference trajectory.

    Parameters
    ----------
    robot
        The machine.
    t, q
        Actual times ``(S,)`` and joint angles ``(S, dof)``.
    t_ref, q_ref
        Reference times ``(K,)`` and joint reference ``(K, dof)``.
    T_flange_tool
        TCP in the flange frame (default: the flange).
    """
    T_ft = np.eye(4) if T_flange_tool is None else np.asarray(T_flange_tool, dtype=float)
    ta, qa = np.asarray(t, dtype=float), np.asarray(q, dtype=float)
    tr, qr = np.asarray(t_ref, dtype=float), np.asarray(q_ref, dtype=float)
    p_act = (robot.fk(qa) @ T_ft)[:, :3, 3]
    p_ref_k = (robot.fk(qr) @ T_ft)[:, :3, 3]
    p_ref = np.column_stack([np.interp(ta, tr, p_ref_k[:, j]) for j in range(3)])
    d = p_act - p_ref
    rmse_xyz = np.sqrt(np.mean(d**2, axis=0))
    dist = _distance_to_polyline(p_act, p_ref_k)
    return TrackingError(
        rmse_xyz,
        float(np.sqrt(np.mean(np.sum(d**2, axis=1)))),
        float(np.sqrt(np.mean(dist**2))),
        float(dist.max()),
    )


def _distance_to_polyline(p: FloatArray, poly: FloatArray) -> FloatArray:
    a, b = poly[:-1], poly[1:]
    ab = b - a
    L2 = np.maximum(np.sum(ab**2, axis=1), 1e-300)
    best = np.full(p.shape[0], np.inf)
    chunk = max(1, 2_000_000 // max(len(a), 1))
    for s in range(0, p.shape[0], chunk):
        pp = p[s : s + chunk, None, :]
        u = np.clip(np.sum((pp - a) * ab, axis=2) / L2, 0.0, 1.0)
        d = np.linalg.norm(pp - (a + u[..., None] * ab), axis=2)
        best[s : s + chunk] = d.min(axis=1)
    if len(a) == 0:
        return np.linalg.norm(p - poly[0], axis=1)
    return best


@dataclass(frozen=True)
class ContactResult:
    """Outcome of a pressure-threshold contact search.

    Attributes
    ----------
    contact
        The pressure exceeded the threshold (the tool is on a surface).
    q
        Configuration at the end of the search (radians).
    p_tcp
        TCP position at the end (base frame, metres).
    travel
        Distance the TCP moved along the search direction (metres).
    pressure
        ``(S,)`` the 2 Hz pressure samples (bar).
    """

    contact: bool
    q: FloatArray
    p_tcp: FloatArray
    travel: float
    pressure: FloatArray


def contact_search(
    clik: Clik,
    q0: ArrayLike,
    surface_height: Callable[[FloatArray], float],
    *,
    direction: ArrayLike = (0.0, 0.0, -1.0),
    speed: float = 0.05,
    max_travel: float = 0.5,
    threshold: float = 40.0,
    base_pressure: float = 20.0,
    stiffness: float = 2000.0,
    sample_rate: float = 2.0,
    rate: float = 30.0,
) -> ContactResult:
    """Move the tool along ``direction`` until the pump pressure passes a threshold.

    The machine is commanded by CLIK at ``rate`` Hz with steps of
    ``speed / rate``. Once the commanded tool tip goes below the surface, the
    tool stays on the surface and the cylinder pressure rises by ``stiffness``
    bar per metre of commanded penetration. The pressure is read at
    ``sample_rate`` (2 Hz in paper 004), so the stop comes up to one sample late.
    Reaching ``max_travel`` without contact means no surface there (e.g. the
    borehole was found).

    Parameters
    ----------
    clik
        Controller with task ``"position"`` or ``"position_pitch"`` (the flange is the tool tip).
    q0
        Start configuration (radians).
    surface_height
        Height of the surface under an ``(x, y)`` position (base frame, metres);
        ``-inf`` where there is none (a hole).
    direction
        Search direction in the base frame (normalized here).
    speed, max_travel
        Commanded tool speed (m/s) and travel limit (m).
    threshold, base_pressure, stiffness
        Pressure threshold and model (bar, bar, bar/m).
    sample_rate, rate
        Pressure sampling rate and control rate (Hz).
    """
    if clik.task == "pose":
        raise InputError("contact_search needs a CLIK with task 'position' or 'position_pitch'")
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    q = np.array(q0, dtype=float)
    clik.reset()
    x0, _ = clik.measure(q)
    x_cmd = x0.copy()
    step = speed / rate
    per_sample = max(1, round(rate / sample_rate))
    samples: list[float] = []
    travel = 0.0
    contact = False
    k = 0
    while travel < max_travel:
        k += 1
        dx = np.zeros(clik.dim)
        dx[:3] = d * step
        x_cmd = x_cmd + dx
        travel += step
        z_surf = surface_height(x_cmd[:2])
        target = x_cmd.copy()
        target[2] = max(target[2], z_surf)
        x, J = clik.measure(q)
        q = q + clik.joint_step(q, J, target - x, np.zeros(clik.dim))
        if k % per_sample == 0:
            pen = max(0.0, z_surf - x_cmd[2])
            samples.append(base_pressure + stiffness * pen)
            if samples[-1] > threshold:
                contact = True
                break
    x, _ = clik.measure(q)
    return ContactResult(
        contact, q, np.asarray(x[:3]), float(np.dot(x[:3] - x0[:3], d)), np.asarray(samples)
    )
