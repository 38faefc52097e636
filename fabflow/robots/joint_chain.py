"""A serial chain of fixed transforms and joint axes: the kinematics of a URDF arm.

A Denavit-Hartenberg table (:mod:`fabflow.robots.chain`) needs the joint axes
placed in its convention; a chain read from a URDF file has them anywhere: each
joint ``i`` sits at a fixed pose ``O_i`` in its parent link and turns about (or
slides along) a unit axis ``a_i`` of that pose. With a rotation ``R_i`` that
takes z onto ``a_i``, ``Rot(a_i, q) = R_i Rz(q) R_i^T``, so the chain

    T_base_tip = O_1 Rot(a_1, q_1) O_2 Rot(a_2, q_2) ... O_n Rot(a_n, q_n) O_tip

regroups into joints about their own z axis between fixed links:

    T_base_tip = T_base_0 Rz(q_1) L_1 Rz(q_2) L_2 ... Rz(q_n) L_n

with ``T_base_0 = O_1 R_1``, ``L_i = R_i^T O_(i+1) R_(i+1)`` and
``L_n = R_n^T O_tip``: the form of a DH chain (``Rz(theta)`` then a fixed
link), with a general fixed link and a fixed pose of joint 1 in the base. The
frame before joint ``i``'s motion has its z axis on the joint axis and its
origin on it, as a DH frame does, so Jacobians are built the same way. A
prismatic joint slides along its z axis (``Tz(q)``) instead.

Lengths in metres, angles in radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class JointChain:
    """Joints about (or along) their z axes between fixed link transforms.

    Attributes
    ----------
    T_base_0
        4x4 pose of the frame of joint 1 (z on its axis) in the base frame.
    links
        ``(dof, 4, 4)`` fixed transforms: ``links[i]`` takes the frame of joint
        ``i + 1`` after its motion to the frame of joint ``i + 2`` (the last one
        to the tip link's frame).
    prismatic
        ``(dof,)`` True for a joint that slides along its z axis (metres),
        False for one that turns about it (radians).
    """

    T_base_0: FloatArray
    links: FloatArray
    prismatic: NDArray[np.bool_]

    @property
    def dof(self) -> int:
        """Number of joints."""
        return int(self.links.shape[0])

    def link_transforms(self, theta: FloatArray) -> FloatArray:
        """Joint motion then fixed link, per joint: ``(N, dof, 4, 4)``.

        Parameters
        ----------
        theta
            ``(N, dof)`` joint values (radians, metres for a prismatic joint).
        """
        n = theta.shape[0]
        M = np.zeros((n, self.dof, 4, 4))
        turn = ~self.prismatic
        ct = np.where(turn, np.cos(theta), 1.0)
        st = np.where(turn, np.sin(theta), 0.0)
        M[..., 0, 0] = ct
        M[..., 0, 1] = -st
        M[..., 1, 0] = st
        M[..., 1, 1] = ct
        M[..., 2, 2] = 1.0
        M[..., 3, 3] = 1.0
        M[..., 2, 3] = np.where(self.prismatic, theta, 0.0)
        return M @ self.links


def rotation_z_to(axis: ArrayLike) -> FloatArray:
    """A 3x3 rotation taking the z axis onto the unit vector ``axis``.

    The identity for z itself and a half turn about x for -z, so that chains
    whose joints turn about z keep their link transforms exactly.
    """
    a = np.asarray(axis, dtype=float)
    z = np.array([0.0, 0.0, 1.0])
    c = float(a @ z)
    if c > 1.0 - 1e-15:
        return np.eye(3)
    if c < -1.0 + 1e-15:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(z, a)
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def chain_from_joints(
    origins: ArrayLike, axes: ArrayLike, prismatic: ArrayLike, T_last_tip: ArrayLike
) -> JointChain:
    """The chain of joints given as URDF gives them.

    Parameters
    ----------
    origins
        ``(dof, 4, 4)``: ``origins[0]`` the pose of joint 1 in the base frame,
        ``origins[i]`` that of joint ``i + 1`` in the frame of joint ``i`` after
        its motion (fixed joints in between folded in).
    axes
        ``(dof, 3)`` unit joint axes, each in its joint's frame.
    prismatic
        ``(dof,)`` True for a sliding joint.
    T_last_tip
        4x4 pose of the tip link in the frame of the last joint after its motion.
    """
    origin = np.asarray(origins, dtype=float)
    R = np.stack([np.eye(4) for _ in range(origin.shape[0])])
    for i, a in enumerate(np.asarray(axes, dtype=float)):
        R[i, :3, :3] = rotation_z_to(a)
    Rt = np.swapaxes(R, 1, 2)
    after = np.concatenate([origin[1:], np.asarray(T_last_tip, dtype=float)[None]])
    links = Rt @ after
    links[:-1] = links[:-1] @ R[1:]
    return JointChain(
        T_base_0=origin[0] @ R[0], links=links, prismatic=np.asarray(prismatic, dtype=bool)
    )
