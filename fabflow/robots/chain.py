"""Serial robot models as data: a Denavit-Hartenberg chain, limits, batch kinematics.

A model maps controller joint values ``q`` (radians, the values the robot's own
controller shows, e.g. KUKA A1..A6) to DH joint angles with a per-joint sign and
offset, ``theta_i = sign_i * q_i + offset_i``, and chains standard DH link
transforms ``Rz(theta) Tz(d) Tx(a) Rx(alpha)``. A fixed ``T_n_flange`` makes the
last frame the vendor's flange frame. The base frame sits at the foot of axis 1
(z up along axis 1, x forward).

A model read from a URDF file carries a general :class:`~fabflow.robots.joint_chain.JointChain`
instead of the DH table (joints about their z axes between fixed links, joint 1
at a fixed pose in the base; prismatic joints allowed, in metres), with
``theta_i = sign_i * q_i``. Everything below works on either.

Everything is batch-capable: ``q`` of shape ``(dof,)`` or ``(N, dof)``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError, UnsupportedError
from fabflow.robots.joint_chain import JointChain
from fabflow.robots.numeric_ik import solve_seeds
from fabflow.robots.opw import OPWParameters, solved_branches

if TYPE_CHECKING:
    from fabflow.robots.geometry import LinkCapsule

FloatArray = NDArray[np.float64]

AnalyticIK = Callable[..., tuple[FloatArray, NDArray[np.bool_]]]
"""``(T_base_flange (N,4,4), q_ref=None) -> (q (N,K,dof), exists (N,K))``: all closed-form
branches; ``q_ref`` ((dof,) or (N, dof)) only settles joints a singularity leaves free."""

TWO_PI = 2.0 * np.pi
_TURNS = np.array([0.0, -1.0, 1.0, -2.0, 2.0])[:, None]
"""Turns tried from the nearest one, in order of preference (:meth:`RobotModel.nearest_turn`)."""


@dataclass(frozen=True, eq=False)
class RobotModel:
    """A serial manipulator described by a DH table (or a general joint chain).

    Attributes
    ----------
    name
        Catalogue name (``"kuka_kr60_3"``, ...), or the registered name of a
        robot defined in a project file (``"custom:NAME@HASH"``).
    dh
        ``(dof, 4)`` rows ``[a, alpha, d, theta_offset]`` (metres, radians), standard DH;
        ``None`` for a model given by ``chain``.
    joint_sign
        ``(dof,)`` +1 or -1: sign between the controller joint value and the DH angle.
    joint_limits
        ``(dof, 2)`` lower/upper controller joint limits (radians).
    velocity_limits
        ``(dof,)`` maximum joint speeds (rad/s).
    T_n_flange
        4x4 fixed pose of the vendor flange frame in the last DH frame.
    reach
        Approximate maximum distance of the flange from axis 1 (metres).
    approximate
        True when the geometry is an estimate, not the manufacturer's data.
    description
        Where the numbers come from.
    motion_groups
        Sets of joint indices that may move at the same time; a motion that needs
        joints from two groups is split into phases. One group with all joints
        means no restriction.
    analytic_ik
        Closed-form solver returning all branches, or None (numerical IK only).
    q_nominal
        A well-conditioned working configuration (radians): start of examples,
        reference for the CLIK manipulability threshold.
    q_home
        The HOME (rest) configuration every program starts and ends at (radians),
        within the joint limits; a project may set its own (``robot.home_deg``).
    payload
        Rated payload at the flange (kg): the heaviest tool plus held element
        the arm is made for.
    chain
        The general joint chain of a model without a DH table (a URDF arm), else ``None``.
    opw
        The arm's ortho-parallel geometry when it has one (:mod:`fabflow.robots.opw`):
        KUKA status bits and ABB ``confdata`` are computed from it.
    capsules
        The links as capsules for collision checks, when the model brings its own
        (robots defined in a project file); ``None`` takes
        :data:`fabflow.robots.geometry.LINK_CAPSULES`.
    """

    name: str
    dh: FloatArray | None
    joint_sign: FloatArray
    joint_limits: FloatArray
    velocity_limits: FloatArray
    T_n_flange: FloatArray
    reach: float
    approximate: bool = False
    description: str = ""
    motion_groups: tuple[tuple[int, ...], ...] = ()
    analytic_ik: AnalyticIK | None = field(default=None, repr=False)
    q_nominal: FloatArray | None = None
    q_home: FloatArray | None = None
    payload: float = 0.0
    chain: JointChain | None = None
    opw: OPWParameters | None = None
    capsules: tuple[LinkCapsule, ...] | None = None

    def __post_init__(self) -> None:
        if (self.dh is None) == (self.chain is None):
            raise ValueError("a RobotModel needs exactly one of 'dh' and 'chain'")

    # ------------------------------------------------------------------ basics
    @property
    def dof(self) -> int:
        """Number of joints."""
        if self.dh is None:
            return self.chain.dof  # type: ignore[union-attr]
        return int(self.dh.shape[0])

    @cached_property
    def prismatic(self) -> NDArray[np.bool_]:
        """``(dof,)`` True for a joint that slides (its values in metres, not radians)."""
        if self.chain is None:
            return np.zeros(self.dof, dtype=bool)
        return self.chain.prismatic

    def from_deg(self, values: ArrayLike) -> FloatArray:
        """Joint values of a ``*_deg`` field (degrees; millimetres for a sliding joint)
        in radians (metres)."""
        v = np.asarray(values, dtype=float)
        return np.where(self.prismatic, v * 1e-3, np.radians(v))

    def to_deg(self, q: ArrayLike) -> FloatArray:
        """Joint values (radians; metres) as a ``*_deg`` field writes them (degrees; mm)."""
        v = np.asarray(q, dtype=float)
        return np.where(self.prismatic, v * 1e3, np.degrees(v))

    def _as_batch(self, q: ArrayLike) -> tuple[FloatArray, bool]:
        qa = np.asarray(q, dtype=float)
        single = qa.ndim == 1
        qb = qa[None, :] if single else qa
        if qb.ndim != 2 or qb.shape[1] != self.dof:
            raise InputError(
                f"joint values for {self.name} must have shape ({self.dof},) or "
                f"(N, {self.dof}), got {qa.shape}"
            )
        return qb, single

    def within_limits(self, q: ArrayLike, tol: float = 1e-9) -> NDArray[np.bool_]:
        """Whether joint values lie within the joint limits (``tol`` radians slack).

        Parameters
        ----------
        q
            Joint values, shape ``(..., dof)`` (radians).
        """
        qa = np.asarray(q, dtype=float)
        lo, hi = self.joint_limits[:, 0], self.joint_limits[:, 1]
        return np.all((qa >= lo - tol) & (qa <= hi + tol), axis=-1)

    # ------------------------------------------------------------- kinematics
    def _link_transforms(self, qb: FloatArray) -> FloatArray:
        """DH link transforms, shape ``(N, dof, 4, 4)``."""
        if self.dh is None:
            return self.chain.link_transforms(qb * self.joint_sign)  # type: ignore[union-attr]
        a, alpha, d, offset = self.dh.T
        theta = qb * self.joint_sign + offset
        ct, st = np.cos(theta), np.sin(theta)
        ca, sa = np.cos(alpha), np.sin(alpha)
        n = qb.shape[0]
        A = np.zeros((n, self.dof, 4, 4))
        A[..., 0, 0] = ct
        A[..., 0, 1] = -st * ca
        A[..., 0, 2] = st * sa
        A[..., 0, 3] = a * ct
        A[..., 1, 0] = st
        A[..., 1, 1] = ct * ca
        A[..., 1, 2] = -ct * sa
        A[..., 1, 3] = a * st
        A[..., 2, 1] = sa
        A[..., 2, 2] = ca
        A[..., 2, 3] = d
        A[..., 3, 3] = 1.0
        return A

    def frames(self, q: ArrayLike) -> FloatArray:
        """Poses of all DH frames and the flange in the base frame.

        Parameters
        ----------
        q
            Joint values (radians), shape ``(dof,)`` or ``(N, dof)``.

        Returns
        -------
        numpy.ndarray
            ``(N, dof + 2, 4, 4)`` (or without the leading N): frame 0 (the base),
            DH frames 1..dof, then the flange. Frame ``i`` (``i < dof``) has its z
            axis on joint ``i + 1`` and its origin on that axis. For a model with
            a general ``chain`` frame 0 is the frame of joint 1 (its pose in the
            base frame fixed), frames 1..dof-1 those of the next joints and frame
            ``dof`` the tip link.
        """
        qb, single = self._as_batch(q)
        A = self._link_transforms(qb)
        n = qb.shape[0]
        out = np.empty((n, self.dof + 2, 4, 4))
        out[:, 0] = np.eye(4) if self.chain is None else self.chain.T_base_0
        for i in range(self.dof):
            out[:, i + 1] = out[:, i] @ A[:, i]
        out[:, -1] = out[:, self.dof] @ self.T_n_flange
        return out[0] if single else out

    def frames_single(self, q: FloatArray) -> FloatArray:
        """:meth:`frames` of one ``(dof,)`` configuration without input checks (control loops)."""
        if self.dh is None:
            return self.frames(q)
        a, offset = self.dh[:, 0], self.dh[:, 3]
        theta = q * self.joint_sign + offset
        ct, st = np.cos(theta), np.sin(theta)
        A = self._A_template.copy()
        A[:, 0, 0] = ct
        A[:, 0, 1] = -st * self._ca
        A[:, 0, 2] = st * self._sa
        A[:, 0, 3] = a * ct
        A[:, 1, 0] = st
        A[:, 1, 1] = ct * self._ca
        A[:, 1, 2] = -ct * self._sa
        A[:, 1, 3] = a * st
        out = np.empty((self.dof + 2, 4, 4))
        out[0] = np.eye(4)
        T = A[0]
        out[1] = T
        for i in range(1, self.dof):
            T = T @ A[i]
            out[i + 1] = T
        out[-1] = T @ self.T_n_flange
        return out

    @cached_property
    def _ca(self) -> FloatArray:
        return np.cos(self.dh[:, 1])

    @cached_property
    def _sa(self) -> FloatArray:
        return np.sin(self.dh[:, 1])

    @cached_property
    def _A_template(self) -> FloatArray:
        A = np.zeros((self.dof, 4, 4))
        A[:, 2, 1] = self._sa
        A[:, 2, 2] = self._ca
        A[:, 2, 3] = self.dh[:, 2]
        A[:, 3, 3] = 1.0
        return A

    def fk(self, q: ArrayLike) -> FloatArray:
        """Flange pose in the base frame.

        Parameters
        ----------
        q
            Joint values (radians), shape ``(dof,)`` or ``(N, dof)``.

        Returns
        -------
        numpy.ndarray
            ``T_base_flange``, shape ``(4, 4)`` or ``(N, 4, 4)`` (metres).
        """
        qb, single = self._as_batch(q)
        A = self._link_transforms(qb)
        T = A[:, 0] if self.chain is None else self.chain.T_base_0 @ A[:, 0]
        for i in range(1, self.dof):
            T = T @ A[:, i]
        T = T @ self.T_n_flange
        return T[0] if single else T

    def jacobian(self, q: ArrayLike) -> FloatArray:
        """Geometric Jacobian of the flange in the base frame.

        Rows are ``[v; omega]`` (linear velocity of the flange origin, angular
        velocity), columns the controller joints (sign conventions included).

        Parameters
        ----------
        q
            Joint values (radians), shape ``(dof,)`` or ``(N, dof)``.

        Returns
        -------
        numpy.ndarray
            Shape ``(6, dof)`` or ``(N, 6, dof)``.
        """
        qb, single = self._as_batch(q)
        F = self.frames(qb)
        z = F[:, :-2, :3, 2]
        p = F[:, :-2, :3, 3]
        pe = F[:, -1, None, :3, 3]
        s = self.joint_sign[None, :, None]
        Jv = np.cross(z, pe - p) * s
        Jw = z * s
        if self.chain is not None and self.prismatic.any():
            Jv = np.where(self.prismatic[None, :, None], z * s, Jv)
            Jw = np.where(self.prismatic[None, :, None], 0.0, Jw)
        J = np.concatenate([Jv, Jw], axis=2).transpose(0, 2, 1)
        return J[0] if single else J

    # --------------------------------------------------------------------- IK
    def ik(
        self,
        T_base_flange: ArrayLike,
        q_ref: ArrayLike | None = None,
        all_turns: bool = False,
    ) -> list[FloatArray]:
        """All joint solutions for a flange pose, within the joint limits.

        Closed form where the model has one (every branch: shoulder, elbow,
        wrist). A redundant pitch chain (the BROKK) returns a sample of its
        one-parameter solution family (closed form every 7.5 deg of the arm-3
        angle) plus the damped-least-squares solution from ``q_ref``; any other
        chain runs damped least squares from ``q_ref`` and 16 fixed seeds.
        Each branch is returned once, with every joint whose range exceeds
        one turn put at the turn nearest ``q_ref`` (or nearest 0) that lies
        within limits; ``all_turns=True`` returns every turn variant instead.

        Parameters
        ----------
        T_base_flange
            4x4 flange pose in the base frame (metres).
        q_ref
            Reference configuration (radians); solutions are sorted by Euclidean
            joint distance to it.
        all_turns
            Include the +-2 pi variants of joints with more than one turn of range.

        Returns
        -------
        list of numpy.ndarray
            ``(dof,)`` solutions (radians); empty when the pose is unreachable.
        """
        T = np.asarray(T_base_flange, dtype=float)
        if T.shape != (4, 4):
            raise InputError(f"ik expects a 4x4 flange pose, got shape {T.shape}")
        ref = None if q_ref is None else self._as_batch(q_ref)[0][0]
        if self.analytic_ik is not None:
            q, valid = self.ik_batch(T[None], q_ref=ref)
            sols = q[0][valid[0]]
        else:
            sols = solve_seeds(self, T, ref)
        if all_turns and len(sols):
            sols = self._turn_variants(sols)
        if len(sols) == 0:
            return []
        sols = _unique_rows(sols, 1e-9)
        if ref is not None:
            order = np.argsort(np.linalg.norm(sols - ref, axis=1), kind="stable")
            sols = sols[order]
        return [s.copy() for s in sols]

    def ik_batch(
        self,
        T_base_flange: ArrayLike,
        q_ref: ArrayLike | None = None,
        arms: Sequence[int] | None = None,
    ) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Closed-form IK for many poses at once (all branches).

        Parameters
        ----------
        T_base_flange
            Flange poses, shape ``(N, 4, 4)`` (metres).
        q_ref
            ``(dof,)`` or ``(N, dof)`` reference (radians): each joint is moved by
            whole turns to the value nearest the reference that is within limits.
        arms
            For an arm with an ortho-parallel geometry (:attr:`opw`), solve only
            these arm branches (0-3) and their wrist flips (4-7); the others come
            back NaN and invalid. Ignored for other arms (every branch is solved).

        Returns
        -------
        q : numpy.ndarray
            ``(N, K, dof)`` joint values (radians); K is the number of branches.
        valid : numpy.ndarray
            ``(N, K)`` bool: the branch exists (pose within the arm's workspace)
            and lies within the joint limits.
        """
        if self.analytic_ik is None:
            raise UnsupportedError(f"{self.name} has no closed-form IK; use ik()")
        T = np.asarray(T_base_flange, dtype=float)
        ref = np.zeros(self.dof) if q_ref is None else np.asarray(q_ref, dtype=float)
        if ref.ndim == 2:
            ref = ref[:, None, :]
        if arms is None or self.opw is None:
            q, exists = self.analytic_ik(T, q_ref)
            q = self.nearest_turn(q, ref)
            return q, exists & self.within_limits(q)
        # the branches not asked for are NaN and do not exist: only the others are turned
        q, exists = self.analytic_ik(T, q_ref, arms=arms)
        solved = solved_branches(arms)
        q[:, solved] = turned = self.nearest_turn(q[:, solved], ref)
        valid = np.zeros_like(exists)
        valid[:, solved] = exists[:, solved] & self.within_limits(turned)
        return q, valid

    def nearest_turn(self, q: ArrayLike, q_ref: ArrayLike) -> FloatArray:
        """Move each joint by whole turns towards ``q_ref`` while staying within limits.

        Joints whose value cannot be brought within limits by any number of turns
        keep the value nearest the reference.

        Parameters
        ----------
        q, q_ref
            Broadcastable arrays ``(..., dof)`` (radians).
        """
        # one value is one per joint, as the limits broadcast it: an array, so that the
        # arithmetic below can work in place on this call's own arrays
        qa = np.asarray(q, dtype=float).reshape(np.shape(q) or (1,))
        ref = np.asarray(q_ref, dtype=float)
        lo, hi = self._limits_with_slack
        k0 = ref - qa
        k0 /= TWO_PI
        np.round(k0, out=k0)
        best = k0 * TWO_PI
        best += qa
        # The nearest turn is within limits and less than half a turn from the
        # reference: no other turn can be closer. Not a number stays one. Only the
        # rest (outside limits, or near a tie) try the neighbouring turns.
        settled = best >= lo
        settled &= best <= hi
        off = best - ref
        np.abs(off, out=off)
        settled &= off < np.pi - 1e-6
        settled |= np.isnan(best)
        # A joint whose whole range lies within half a turn of the reference has no
        # other turn within limits: the nearest turn stays, within limits or not.
        settled |= (lo > ref - np.pi + 1e-6) & (hi < ref + np.pi - 1e-6)
        shape = settled.shape
        if best.shape != shape:
            best = np.array(np.broadcast_to(best, shape))
        if settled.all():
            return best
        # the rest: of the turns k0, k0 - 1, k0 + 1, k0 - 2, k0 + 2 within limits the
        # first nearest the reference, k0 where none is (one pass over all five)
        rest = np.flatnonzero(~settled)
        qa_r, ref_r, lo_r, hi_r, k_r = (_flat_at(a, shape, rest) for a in (qa, ref, lo, hi, k0))
        cand = qa_r + (k_r + _TURNS) * TWO_PI
        within = (cand >= lo_r) & (cand <= hi_r)
        first = np.argmin(np.where(within, np.abs(cand - ref_r), np.inf), axis=0)
        np.put(best, rest, cand[first, np.arange(cand.shape[1])])
        return best

    @cached_property
    def multi_turn(self) -> NDArray[np.bool_]:
        """(dof,) joints with more than a whole turn of range (their values are
        compared by the shortest angle, and turned whole turns within the limits)."""
        return self.joint_limits[:, 1] - self.joint_limits[:, 0] > TWO_PI

    @cached_property
    def _limits_with_slack(self) -> tuple[FloatArray, FloatArray]:
        """The lower and upper joint limits widened by 1e-9 rad, as the turn rules test them."""
        return self.joint_limits[:, 0] - 1e-9, self.joint_limits[:, 1] + 1e-9

    def _turn_variants(self, sols: FloatArray) -> FloatArray:
        lo, hi = self.joint_limits[:, 0], self.joint_limits[:, 1]
        out = sols
        for j in range(self.dof):
            if hi[j] - lo[j] <= TWO_PI:
                continue
            extra = []
            for k in (-2, -1, 1, 2):
                v = out.copy()
                v[:, j] += k * TWO_PI
                extra.append(v[(v[:, j] >= lo[j] - 1e-9) & (v[:, j] <= hi[j] + 1e-9)])
            out = np.concatenate([out, *extra], axis=0)
        return out


def _flat_at(a: FloatArray, shape: tuple[int, ...], flat: NDArray[np.intp]) -> FloatArray:
    """The values of ``a`` broadcast to ``shape`` at the flat (C-order) indices ``flat``."""
    if a.shape == shape:
        return np.take(a, flat)
    if a.ndim == 1 and a.shape[0] == shape[-1]:  # one value per joint
        return a[flat % shape[-1]]
    return np.broadcast_to(a, shape)[np.unravel_index(flat, shape)]


def _unique_rows(a: FloatArray, tol: float) -> FloatArray:
    """Rows of ``a`` with near-duplicates (max abs difference <= tol) removed, order kept."""
    keep: list[int] = []
    for i in range(a.shape[0]):
        if not any(np.max(np.abs(a[i] - a[j])) <= tol for j in keep):
            keep.append(i)
    return a[keep]


def dh_table(a: ArrayLike, alpha_deg: ArrayLike, d: ArrayLike, offset_deg: ArrayLike) -> FloatArray:
    """Build a ``(dof, 4)`` DH table from columns (metres, degrees for angles)."""
    return np.column_stack(
        [
            np.asarray(a, dtype=float),
            np.radians(np.asarray(alpha_deg, dtype=float)),
            np.asarray(d, dtype=float),
            np.radians(np.asarray(offset_deg, dtype=float)),
        ]
    )
