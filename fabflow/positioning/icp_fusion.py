"""EKF fusion of 10 Hz ICP poses with 100 Hz kinematics (paper 000, section III-D).

The state is the end-effector pose ``T_world_ee`` and its twist ``u = [v, w]``
(linear and angular velocity in the world frame). The filter is an error-state
EKF in fabflow's pose convention (errors ``[d, r]`` in the world frame,
``T_true = [Exp(r) R, t + d]``) plus the twist error:

* prediction (constant velocity): ``T <- [Exp(w dt) R, t + v dt]``, error
  transition ``[[I, I dt], [0, I]]``, white acceleration noise;
* kinematics update (every kinematics sample, 100 Hz): the increment between two
  consecutive kinematic poses, divided by ``dt``, measures the twist. Kinematics
  are locally accurate but globally biased (base localization, arm deflection),
  so only their increments are used;
* ICP update (10 Hz): the scan-to-map pose measures the pose directly, with the
  ICP covariance.

The output is a pose at every kinematics sample (100 Hz) that stays consistent
with the map like ICP, but moves smoothly between scans like the kinematics.

:class:`IcpKinematicsFilter` runs the filter online, one call per sample, for a
closed control loop. ICP poses arrive late (the scan is matched after it was
taken), so the filter keeps a short history of its steps and handles an
out-of-sequence ICP pose by re-filtering: it goes back to the scan's time,
applies the ICP update there and re-runs the stored kinematics steps up to the
latest sample, which gives exactly the estimate of a filter that had the scan in
time. Each ICP update passes an integrity gate on its normalized innovation
squared (NIS). :func:`fuse_icp_kinematics` runs the same filter over recorded
streams.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError
from fabflow.positioning.adjustment_tests import chi2_quantile
from fabflow.transforms.so3 import exp_so3_one, log_so3_one

FloatArray = NDArray[np.float64]

_P0_DIAG = (0.05**2,) * 3 + (np.radians(2.0) ** 2,) * 3 + (0.1**2,) * 6
_CACHE_SIZE = 64  # transition matrices kept, one per distinct time step
_EYE12 = np.eye(12)


@dataclass
class FusionParams:
    """Noise model and integrity gate of the ICP/kinematics EKF.

    Attributes
    ----------
    accel_sigma, angular_accel_sigma
        White linear (m/s^2) and angular (rad/s^2) acceleration of the process model.
    kin_velocity_sigma, kin_rate_sigma
        Noise of the twist measured from kinematic increments (m/s, rad/s).
    icp_covariance
        Diagonal of the default 6x6 ICP pose covariance when none is given per scan
        (m^2, rad^2; fabflow's world-frame pose error convention).
    gate_alpha
        Integrity level of the ICP gate: an ICP pose whose NIS exceeds the
        ``1 - gate_alpha`` quantile of the chi-square distribution with 6 degrees of
        freedom is rejected. ``None`` or ``0`` disables the gate.
    """

    accel_sigma: float = 0.5
    angular_accel_sigma: float = 0.5
    kin_velocity_sigma: float = 0.02
    kin_rate_sigma: float = 0.01
    icp_covariance: tuple[float, ...] = (0.005**2,) * 3 + (np.radians(0.3) ** 2,) * 3
    gate_alpha: float | None = 0.001


@dataclass(frozen=True, eq=False)
class FusionResult:
    """Fused poses at the kinematics rate.

    Attributes
    ----------
    t
        ``(n,)`` times (seconds).
    T_world_ee
        ``(n, 4, 4)`` fused poses.
    covariance
        ``(n, 6, 6)`` pose covariances (fabflow convention).
    twist
        ``(n, 6)`` estimated ``[v, w]`` (world frame).
    """

    t: FloatArray
    T_world_ee: FloatArray
    covariance: FloatArray
    twist: FloatArray


@dataclass(frozen=True)
class IcpUpdate:
    """What the filter did with one ICP pose.

    Attributes
    ----------
    applied
        Whether the pose updated the estimate.
    nis
        Normalized innovation squared ``e^T S^-1 e`` of the pose against the
        estimate at the scan's time (dimensionless; NaN when it was too old).
    reason
        ``"ok"`` (applied), ``"gated"`` (NIS above the gate) or ``"too old"`` (the
        scan's time is older than the filter's history).
    """

    applied: bool
    nis: float
    reason: str


@dataclass(slots=True, eq=False)
class _Node:
    """One step of the filter history: its inputs and the state after it.

    ``dt`` is the time since the previous node (s), ``z`` the twist measured by the
    kinematics at this node (``None`` for the first sample and for nodes inserted
    at an ICP scan's time), ``icps`` the ICP poses applied here as ``(R, t, C)``.
    The state is the rotation ``R`` and translation ``p`` of ``T_world_ee``, the
    twist ``u`` and the 12x12 error covariance ``P``.
    """

    t: float
    dt: float
    z: FloatArray | None
    R: FloatArray
    p: FloatArray
    u: FloatArray
    P: FloatArray
    icps: list[tuple[FloatArray, FloatArray, FloatArray]] = field(default_factory=list)


class IcpKinematicsFilter:
    """Online ICP/kinematics EKF with out-of-sequence ICP updates.

    Call :meth:`kinematics` for every kinematics sample (100 Hz) and :meth:`icp`
    whenever an ICP pose is ready, with the time its scan was taken. Between the
    calls, :attr:`pose`, :attr:`covariance` and :attr:`twist` give the estimate at
    the latest kinematics sample. All poses are ``T_world_ee`` (end-effector to
    world, metres); covariances use fabflow's world-frame error convention.

    Parameters
    ----------
    T0
        ``(4, 4)`` initial pose at ``t0``; its standard deviation is 5 cm and 2 deg
        per axis, that of the initial twist (zero) 0.1 m/s and 0.1 rad/s.
    params
        Noise model and gate (defaults of :class:`FusionParams` when ``None``).
    t0
        Time of ``T0`` (s); the first kinematics sample may not be earlier.
    history_s
        How far back (s) an ICP pose may be stamped relative to the latest
        kinematics sample and still be applied.

    Notes
    -----
    A delayed ICP pose is applied to the stored state at its scan time: at the
    stored step with that time, or, between two steps, at a step inserted there
    (predicted from the earlier one). The later steps are then re-run with their
    stored kinematics measurements and ICP poses. The gate decision of a pose is
    taken once, when it arrives; re-runs re-apply the poses that passed. An ICP
    pose stamped after the latest kinematics sample is applied at that sample
    (the filter does not extrapolate).
    """

    def __init__(
        self,
        T0: ArrayLike,
        params: FusionParams | None = None,
        t0: float = 0.0,
        history_s: float = 2.0,
    ) -> None:
        p = params or FusionParams()
        T = _pose(T0, "T0")
        t0, history_s = float(t0), float(history_s)
        if not (math.isfinite(t0) and math.isfinite(history_s) and history_s >= 0):
            raise InputError(f"t0 must be finite and history_s >= 0, got {t0}, {history_s}")
        alpha = p.gate_alpha
        if alpha is not None and not 0.0 <= alpha < 1.0:
            raise InputError(f"gate_alpha must be in [0, 1) or None, got {alpha}")
        if len(p.icp_covariance) != 6:
            raise InputError("icp_covariance must hold the 6 variances of a pose")
        self._gate = math.inf if not alpha else chi2_quantile(6, alpha)
        self._history_s = history_s
        self._R_kin = np.diag([p.kin_velocity_sigma**2] * 3 + [p.kin_rate_sigma**2] * 3)
        self._R_icp = np.diag(np.asarray(p.icp_covariance, dtype=float))
        self._q = np.array([p.accel_sigma**2] * 3 + [p.angular_accel_sigma**2] * 3)
        self._transitions: dict[float, tuple[FloatArray, FloatArray, FloatArray]] = {}
        self._nodes = [
            _Node(t0, 0.0, None, T[:3, :3].copy(), T[:3, 3].copy(), np.zeros(6), np.diag(_P0_DIAG))
        ]
        self._kin_prev: tuple[float, FloatArray, FloatArray] | None = None
        self._counts = {"icp_applied": 0, "icp_gated": 0, "icp_too_old": 0}
        self._nis: list[float] = []

    @property
    def t(self) -> float:
        """Time of the estimate (s): the latest kinematics sample, or ``t0`` before it."""
        return self._nodes[-1].t

    @property
    def pose(self) -> FloatArray:
        """``(4, 4)`` fused pose ``T_world_ee`` at :attr:`t` (metres)."""
        node = self._nodes[-1]
        T = np.eye(4)
        T[:3, :3] = node.R
        T[:3, 3] = node.p
        return T

    @property
    def covariance(self) -> FloatArray:
        """``(6, 6)`` covariance of :attr:`pose` (m^2, rad^2; fabflow convention)."""
        return self._nodes[-1].P[:6, :6].copy()

    @property
    def twist(self) -> FloatArray:
        """``(6,)`` estimated ``[v, w]`` (m/s, rad/s; world frame) at :attr:`t`."""
        return self._nodes[-1].u.copy()

    @property
    def counts(self) -> dict[str, int]:
        """Number of ICP poses applied, gated and rejected as too old."""
        return dict(self._counts)

    @property
    def nis_values(self) -> list[float]:
        """NIS of every applied ICP pose, in arrival order (6 on average if consistent)."""
        return list(self._nis)

    def kinematics(self, t: float, T_kin: ArrayLike) -> None:
        """Add one kinematics sample: predict to ``t`` and update the twist.

        Parameters
        ----------
        t
            Sample time (s), later than the previous sample and not before ``t0``.
        T_kin
            ``(4, 4)`` kinematic pose ``T_world_ee`` (metres). Only its increment from
            the previous sample is used (as a twist measurement); the first sample
            only stores it.

        Raises
        ------
        InputError
            If the time does not increase or the pose is not a finite 4x4 matrix.
        """
        t = float(t)
        T = _pose(T_kin, "T_kin")
        last, prev = self._nodes[-1], self._kin_prev
        if not math.isfinite(t) or (t <= prev[0] if prev is not None else t < last.t):
            raise InputError(f"kinematics times must increase, got {t} after {last.t}")
        R, p = T[:3, :3].copy(), T[:3, 3].copy()
        self._kin_prev = (t, R, p)
        if prev is None:
            if t == last.t:
                return
            z = None
        else:
            dt_kin = t - prev[0]
            z = np.concatenate(((p - prev[2]) / dt_kin, log_so3_one(R @ prev[1].T) / dt_kin))
        node = _Node(t, t - last.t, z, last.R, last.p, last.u, last.P)
        self._propagate(last, node)
        nodes = self._nodes
        nodes.append(node)
        oldest = t - self._history_s
        while len(nodes) > 1 and nodes[1].t <= oldest:
            del nodes[0]

    def icp(
        self, t_stamp: float, T_icp: ArrayLike, covariance: ArrayLike | None = None
    ) -> IcpUpdate:
        """Apply an ICP pose measured at ``t_stamp``, re-filtering if it is late.

        Parameters
        ----------
        t_stamp
            Time the scan was taken (s); at most ``history_s`` before :attr:`t`.
        T_icp
            ``(4, 4)`` scan-to-map pose ``T_world_ee`` (metres).
        covariance
            ``(6, 6)`` ICP covariance (m^2, rad^2; fabflow convention);
            ``params.icp_covariance`` when ``None``.

        Returns
        -------
        IcpUpdate
            Whether the pose was applied, its NIS and why not.

        Raises
        ------
        InputError
            If the time is not finite or the pose or covariance has the wrong shape
            or non-finite values.
        """
        t_stamp = float(t_stamp)
        T = _pose(T_icp, "T_icp")
        C = self._R_icp if covariance is None else np.array(covariance, dtype=float)
        if C.shape != (6, 6) or not np.isfinite(C).all() or not math.isfinite(t_stamp):
            raise InputError("expected a finite time and a finite (6, 6) ICP covariance")
        nodes = self._nodes
        if t_stamp < nodes[-1].t - self._history_s or t_stamp < nodes[0].t:
            self._counts["icp_too_old"] += 1
            return IcpUpdate(applied=False, nis=math.nan, reason="too old")
        i = bisect_right(nodes, t_stamp, key=_node_time) - 1
        target = nodes[i]
        inserted = t_stamp > target.t and i + 1 < len(nodes)
        if inserted:
            base = target
            target = _Node(t_stamp, t_stamp - base.t, None, base.R, base.p, base.u, base.P)
            self._propagate(base, target)
        R_i, p_i = T[:3, :3].copy(), T[:3, 3].copy()
        e = _pose_error(target.R, target.p, R_i, p_i)
        nis = float(e @ np.linalg.solve(target.P[:6, :6] + C, e))
        if not nis <= self._gate:
            self._counts["icp_gated"] += 1
            return IcpUpdate(applied=False, nis=nis, reason="gated")
        target.R, target.p, target.u, target.P = _update(
            target.R, target.p, target.u, target.P, e, 0, C
        )
        target.icps.append((R_i, p_i, C))
        if inserted:
            nodes.insert(i + 1, target)
            nodes[i + 2].dt = nodes[i + 2].t - t_stamp
        for k in range(i + 1 + inserted, len(nodes)):
            self._propagate(nodes[k - 1], nodes[k])
        self._counts["icp_applied"] += 1
        self._nis.append(nis)
        return IcpUpdate(applied=True, nis=nis, reason="ok")

    def _propagate(self, prev: _Node, node: _Node) -> None:
        """Set ``node``'s state from ``prev``'s and ``node``'s stored measurements."""
        dt = node.dt
        F, FT, Q = self._transition(dt)
        u = prev.u
        R = exp_so3_one(*(u[3:] * dt).tolist()) @ prev.R
        p = prev.p + u[:3] * dt
        P = F @ prev.P @ FT + Q
        if node.z is not None:
            R, p, u, P = _update(R, p, u, P, node.z - u, 6, self._R_kin)
        for R_i, p_i, C in node.icps:
            R, p, u, P = _update(R, p, u, P, _pose_error(R, p, R_i, p_i), 0, C)
        node.R, node.p, node.u, node.P = R, p, u, P

    def _transition(self, dt: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``(F, F^T, Q)`` of the constant-velocity model over ``dt`` seconds, cached."""
        cached = self._transitions.get(dt)
        if cached is None:
            if len(self._transitions) >= _CACHE_SIZE:
                self._transitions.clear()
            F = np.eye(12)
            F[:6, 6:] = np.eye(6) * dt
            q = self._q
            Q = np.zeros((12, 12))
            Q[:6, :6] = np.diag(q * dt**4 / 4)
            Q[:6, 6:] = Q[6:, :6] = np.diag(q * dt**3 / 2)
            Q[6:, 6:] = np.diag(q * dt**2)
            cached = self._transitions[dt] = (F, F.T, Q)
        return cached


def fuse_icp_kinematics(
    t_kin: ArrayLike,
    T_kin: ArrayLike,
    t_icp: ArrayLike,
    T_icp: ArrayLike,
    icp_covariances: ArrayLike | None = None,
    params: FusionParams | None = None,
) -> FusionResult:
    """Run the EKF over a kinematics stream and an ICP stream.

    Parameters
    ----------
    t_kin, T_kin
        ``(n,)`` increasing times (s) and ``(n, 4, 4)`` kinematic end-effector poses
        ``T_world_ee`` (metres).
    t_icp, T_icp
        ``(m,)`` times (s) and ``(m, 4, 4)`` ICP poses ``T_world_ee`` (applied at the
        first kinematics sample at or after their time).
    icp_covariances
        ``(m, 6, 6)`` ICP covariances (m^2, rad^2); ``params.icp_covariance`` when
        ``None``.
    params
        Noise model (defaults of :class:`FusionParams` when ``None``); its
        ``gate_alpha`` is ignored: every ICP pose is applied.

    Returns
    -------
    FusionResult
        One fused pose per kinematics sample.
    """
    params = params or FusionParams()
    tk = np.asarray(t_kin, dtype=float)
    Tk = np.asarray(T_kin, dtype=float)
    ti = np.asarray(t_icp, dtype=float)
    Ti = np.asarray(T_icp, dtype=float)
    if Tk.shape != (len(tk), 4, 4) or Ti.shape != (len(ti), 4, 4) or len(tk) < 2:
        raise InputError("expected (n,) times with (n, 4, 4) poses for both streams, n >= 2")
    if np.any(np.diff(tk) <= 0) or np.any(np.diff(ti) < 0):
        raise InputError("times must increase")
    Ci = (
        np.broadcast_to(np.diag(params.icp_covariance), (len(ti), 6, 6))
        if icp_covariances is None
        else np.asarray(icp_covariances, dtype=float)
    )
    T0 = Ti[0] if len(ti) and ti[0] <= tk[0] else Tk[0]
    flt = IcpKinematicsFilter(T0, replace(params, gate_alpha=None), t0=tk[0], history_s=0.0)
    n = len(tk)
    out_T = np.empty((n, 4, 4))
    out_C = np.empty((n, 6, 6))
    out_u = np.empty((n, 6))
    j = 0
    for k in range(n):
        flt.kinematics(tk[k], Tk[k])
        while j < len(ti) and ti[j] <= tk[k]:
            flt.icp(tk[k], Ti[j], Ci[j])
            j += 1
        out_T[k] = flt.pose
        out_C[k] = flt.covariance
        out_u[k] = flt.twist
    return FusionResult(t=tk, T_world_ee=out_T, covariance=out_C, twist=out_u)


def _node_time(node: _Node) -> float:
    return node.t


def _pose(T: ArrayLike, name: str) -> FloatArray:
    """``T`` as a finite ``(4, 4)`` float array, or :class:`InputError`."""
    a = np.asarray(T, dtype=float)
    if a.shape != (4, 4) or not np.isfinite(a).all():
        raise InputError(f"{name} must be a finite (4, 4) pose, got shape {a.shape}")
    return a


def _pose_error(R: FloatArray, p: FloatArray, R_true: FloatArray, p_true: FloatArray) -> FloatArray:
    """Error ``[d, r]`` of ``(R, p)`` w.r.t. ``(R_true, p_true)`` (as se3.pose_error)."""
    return np.concatenate((p_true - p, log_so3_one(R_true @ R.T)))


def _update(
    R: FloatArray,
    p: FloatArray,
    u: FloatArray,
    P: FloatArray,
    innovation: FloatArray,
    i: int,
    C: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """EKF update with a measurement of the 6 error states from index ``i`` (Joseph form)."""
    HP = P[i : i + 6]
    K = np.linalg.solve(HP[:, i : i + 6] + C, HP).T
    dx = K @ innovation
    I_KH = _EYE12.copy()
    I_KH[:, i : i + 6] -= K
    P = I_KH @ P @ I_KH.T + K @ C @ K.T
    return exp_so3_one(*dx[3:6].tolist()) @ R, p + dx[:3], u + dx[6:], P
