"""Tests of the low-level rotation and rigid-transform functions."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from fabflow.errors import InputError
from fabflow.transforms import (
    QuaternionError,
    RotationError,
    abc_from_matrix,
    adjoint,
    apply_T,
    check_rotation,
    compose_covariance,
    compose_jacobians,
    error_from_body_twist,
    exp_so3,
    exp_T,
    inv_T,
    inverse_covariance,
    inverse_jacobian,
    log_so3,
    make_T,
    matrix_from_abc,
    matrix_from_quat,
    perturb,
    pose_error,
    quat_from_matrix,
    quat_from_rotvec,
    rotvec_from_quat,
    skew,
    twist_from_error,
)
from fabflow.transforms.so3 import exp_so3_one, log_so3_one

unit = st.floats(-1.0, 1.0, allow_nan=False)
quats = st.tuples(unit, unit, unit, unit).filter(lambda q: np.linalg.norm(q) > 0.1)
angle = st.floats(-np.pi, np.pi, allow_nan=False)


def _R(q: tuple[float, float, float, float]) -> np.ndarray:
    q = np.asarray(q) / np.linalg.norm(q)
    return Rotation.from_quat(q, scalar_first=True).as_matrix()


def test_skew_is_cross_product() -> None:
    rng = np.random.default_rng(0)
    v, w = rng.normal(size=(2, 10, 3))
    np.testing.assert_allclose(skew(v) @ w[..., None], np.cross(v, w)[..., None], atol=1e-15)


@settings(deadline=None, max_examples=100)
@given(quats)
def test_matrix_quat_rotvec_agree_with_scipy(q: tuple[float, float, float, float]) -> None:
    R = _R(q)
    ref = Rotation.from_matrix(R)
    q_ours = quat_from_matrix(R)
    assert q_ours[0] >= 0.0
    q_ref = ref.as_quat(scalar_first=True)
    q_ref = q_ref if q_ref[0] >= 0 else -q_ref
    np.testing.assert_allclose(q_ours, q_ref, atol=1e-12)
    np.testing.assert_allclose(matrix_from_quat(q_ours), R, atol=1e-12)
    np.testing.assert_allclose(exp_so3(log_so3(R)), R, atol=1e-12)
    np.testing.assert_allclose(exp_so3(ref.as_rotvec()), R, atol=1e-12)
    np.testing.assert_allclose(matrix_from_quat(quat_from_rotvec(log_so3(R))), R, atol=1e-12)


@settings(deadline=None, max_examples=100)
@given(angle, st.floats(-np.pi / 2, np.pi / 2), angle)
def test_abc_matches_scipy_and_round_trips(a: float, b: float, c: float) -> None:
    R = matrix_from_abc(a, b, c)
    np.testing.assert_allclose(R, Rotation.from_euler("ZYX", [a, b, c]).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(matrix_from_abc(*abc_from_matrix(R)), R, atol=1e-12)


@pytest.mark.parametrize(
    "b", [np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-10, -np.pi / 2 + 3e-13, np.pi / 2 - 1e-6]
)
def test_abc_gimbal_lock(b: float) -> None:
    rng = np.random.default_rng(1)
    a, c = rng.uniform(-np.pi, np.pi, size=(2, 50))
    R = matrix_from_abc(a, b, c)
    abc = abc_from_matrix(R)
    np.testing.assert_allclose(matrix_from_abc(abc[:, 0], abc[:, 1], abc[:, 2]), R, atol=1e-12)
    assert np.all(np.isfinite(abc))


def test_abc_gimbal_lock_sets_c_zero() -> None:
    R = matrix_from_abc(0.3, np.pi / 2, -0.2)
    a, b, c = abc_from_matrix(R)
    assert c == pytest.approx(0.0, abs=1e-12)
    assert b == pytest.approx(np.pi / 2)
    assert a == pytest.approx(0.5)


def test_log_near_zero_and_at_pi() -> None:
    rng = np.random.default_rng(2)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    for ang in [0.0, 1e-12, 1e-7, 1e-4, 1.0, np.pi - 1e-7, np.pi]:
        rv = axes * ang
        R = exp_so3(rv)
        rv2 = log_so3(R)
        np.testing.assert_allclose(exp_so3(rv2), R, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(rv2, axis=1), ang, atol=1e-12)
        if ang < 3.0:
            np.testing.assert_allclose(rv2, rv, atol=1e-12, rtol=1e-9)
        else:
            # at 180 deg the axis sign is free; it must be one of +-axis
            same = np.minimum(np.abs(rv2 - rv).max(axis=1), np.abs(rv2 + rv).max(axis=1))
            assert same.max() < 1e-6


def test_quat_to_rotvec_sign_invariant() -> None:
    q = np.array([0.8, 0.2, -0.4, 0.4])
    q /= np.linalg.norm(q)
    np.testing.assert_allclose(rotvec_from_quat(q), rotvec_from_quat(-q), atol=1e-15)


def test_batch_shapes() -> None:
    rng = np.random.default_rng(3)
    rv = rng.normal(size=(4, 5, 3))
    R = exp_so3(rv)
    assert R.shape == (4, 5, 3, 3)
    assert quat_from_matrix(R).shape == (4, 5, 4)
    assert abc_from_matrix(R).shape == (4, 5, 3)
    T = make_T(R, rng.normal(size=(4, 5, 3)))
    assert T.shape == (4, 5, 4, 4)
    np.testing.assert_allclose(T @ inv_T(T), np.broadcast_to(np.eye(4), T.shape), atol=1e-12)


def test_check_rotation_rejects() -> None:
    check_rotation(np.eye(3))
    with pytest.raises(RotationError, match="det"):
        check_rotation(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(RotationError, match="tolerance"):
        check_rotation(np.eye(3) * 1.001)
    stack = np.stack([np.eye(3), np.eye(3), np.eye(3) * 2])
    with pytest.raises(RotationError, match=r"index \(2,\)"):
        check_rotation(stack)
    assert issubclass(RotationError, InputError)


def test_quaternion_normalized_or_rejected() -> None:
    q = np.array([1.0 + 5e-7, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(matrix_from_quat(q), np.eye(3), atol=1e-15)
    with pytest.raises(QuaternionError, match="norm"):
        matrix_from_quat([1.0, 0.1, 0.0, 0.0])
    with pytest.raises(QuaternionError):
        matrix_from_quat([0.0, 0.0, 0.0, 0.0])


def test_apply_T_single_and_batch() -> None:
    rng = np.random.default_rng(4)
    T = make_T(exp_so3(rng.normal(size=(6, 3))), rng.normal(size=(6, 3)))
    p = rng.normal(size=(6, 3))
    out = apply_T(T, p)
    ref = np.einsum("nij,nj->ni", T, np.c_[p, np.ones(6)])[:, :3]
    np.testing.assert_allclose(out, ref, atol=1e-14)
    np.testing.assert_allclose(apply_T(T[0], p), (T[0] @ np.c_[p, np.ones(6)].T).T[:, :3])


def test_adjoint_identities() -> None:
    rng = np.random.default_rng(5)
    T = make_T(exp_so3(rng.normal(size=3)), rng.normal(size=3))
    np.testing.assert_allclose(adjoint(T), twist_from_error(T) @ error_from_body_twist(T))
    np.testing.assert_allclose(adjoint(inv_T(T)), np.linalg.inv(adjoint(T)), atol=1e-12)
    # body twist -> spatial twist: T Exp(xi_b) == Exp(Ad xi_b) T to first order
    xi = 1e-6 * rng.normal(size=6)
    left = T @ exp_T(xi)
    right = exp_T(adjoint(T) @ xi) @ T
    # exp_T is fabflow's decoupled map, equal to the twist Exp to first order
    np.testing.assert_allclose(left, right, atol=1e-11)


def test_perturb_and_error_inverse() -> None:
    rng = np.random.default_rng(6)
    T = make_T(exp_so3(rng.normal(size=3)), rng.normal(size=3))
    d = rng.normal(size=6) * 0.1
    np.testing.assert_allclose(pose_error(T, perturb(T, d)), d, atol=1e-12)


def test_covariance_propagation_first_order() -> None:
    rng = np.random.default_rng(7)
    T_ab = make_T(exp_so3(rng.normal(size=3)), rng.normal(size=3) * 3)
    T_bc = make_T(exp_so3(rng.normal(size=3)), rng.normal(size=3) * 3)
    A = rng.normal(size=(6, 6)) * 1e-3
    B = rng.normal(size=(6, 6)) * 1e-3
    C_ab, C_bc = A @ A.T, B @ B.T
    n = 20000
    e_ab = rng.multivariate_normal(np.zeros(6), C_ab, size=n)
    e_bc = rng.multivariate_normal(np.zeros(6), C_bc, size=n)
    T_ac = perturb(T_ab, e_ab) @ perturb(T_bc, e_bc)
    err = pose_error(T_ab @ T_bc, T_ac)
    C_mc = np.cov(err.T)
    C = compose_covariance(T_ab, C_ab, T_bc, C_bc)
    assert np.abs(C_mc - C).max() < 0.05 * np.abs(C).max()
    err_inv = pose_error(inv_T(T_ab), inv_T(perturb(T_ab, e_ab)))
    C_inv = inverse_covariance(T_ab, C_ab)
    assert np.abs(np.cov(err_inv.T) - C_inv).max() < 0.05 * np.abs(C_inv).max()


@settings(deadline=None, max_examples=25)
@given(st.integers(0, 2**32 - 1))
def test_error_jacobians_match_finite_differences(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T_ab = make_T(exp_so3(rng.normal(size=3)), rng.normal(size=3) * 3)
    T_bc = make_T(exp_so3(rng.normal(size=3)), rng.normal(size=3) * 3)
    J_ab, J_bc = compose_jacobians(T_ab, T_bc)
    J_inv = inverse_jacobian(T_ab)
    h = 1e-6
    T_ac = T_ab @ T_bc
    for k in range(6):
        e = np.zeros(6)
        e[k] = h
        d_ab = (
            pose_error(T_ac, perturb(T_ab, e) @ T_bc) - pose_error(T_ac, perturb(T_ab, -e) @ T_bc)
        ) / (2 * h)
        d_bc = (
            pose_error(T_ac, T_ab @ perturb(T_bc, e)) - pose_error(T_ac, T_ab @ perturb(T_bc, -e))
        ) / (2 * h)
        d_inv = (
            pose_error(inv_T(T_ab), inv_T(perturb(T_ab, e)))
            - pose_error(inv_T(T_ab), inv_T(perturb(T_ab, -e)))
        ) / (2 * h)
        np.testing.assert_allclose(d_ab, J_ab[:, k], atol=1e-6)
        np.testing.assert_allclose(d_bc, J_bc[:, k], atol=1e-6)
        np.testing.assert_allclose(d_inv, J_inv[:, k], atol=1e-6)


@given(v=st.tuples(angle, angle, angle), scale=st.sampled_from([1.0, 1e-3, 1e-6, 0.0]))
@settings(max_examples=150, deadline=None)
def test_the_control_loop_exp_and_log_agree_with_the_general_ones(
    v: tuple[float, float, float], scale: float
) -> None:
    r = scale * np.asarray(v) / np.sqrt(3.0)
    R = exp_so3_one(*r)
    assert np.allclose(R, exp_so3(r), atol=1e-12)
    assert np.allclose(log_so3_one(R), log_so3(R), atol=1e-9)
