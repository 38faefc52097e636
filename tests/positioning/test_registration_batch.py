"""register_points_batch: every problem of a batch gets what register_points gives it alone.

Random rigid transforms, needle-shaped (total station) or isotropic noise, gross
errors on some readings, 3 to 8 points: the same pose and covariance within
1e-9, the same test values within 1e-9 and the same decisions. Batches large
enough for the closed-form routes of the small linear algebra are included,
and the closed forms are checked against LAPACK.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning import small_linalg as sl
from fabflow.positioning.polar import INSTRUMENTS, cartesian_to_polar, polar_covariance
from fabflow.positioning.registration import Registration, register_points
from fabflow.positioning.registration_batch import register_points_batch
from fabflow.positioning.rigid_fit import kabsch, kabsch_leave_one_out
from fabflow.transforms.se3 import apply_T, make_T
from fabflow.transforms.so3 import exp_so3

RTOL = 1e-9
"""Pose, covariance, residuals, global test."""
TEST_RTOL = 1e-8
"""Per-point test values, MDBs, protection levels, bias estimates: one 3x3 system per point,
solved as ``S^-1 W v`` alone and as ``(C - G)^-1 v`` in the batch (rounding times its condition)."""


def problems(
    rng: np.random.Generator, B: int, n: int, shared: bool, faults: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Base points, measured points and their covariances of ``B`` random problems.

    The base anywhere on a 30 x 30 m site with any heading; prism points in a
    robot's workspace; a Leica MS50 8 to 40 m away; a fraction ``faults`` of the
    problems with one reading off by up to 3 cm.
    """
    P = rng.uniform([0.3, -2.0, 0.1], [2.2, 2.0, 2.0], (1 if shared else B, n, 3))
    P = np.broadcast_to(P, (B, n, 3))
    T = make_T(exp_so3(rng.normal(0.0, [0.01, 0.01, 2.0], (B, 3))), rng.uniform(-15, 15, (B, 3)))
    T[:, 2, 3] = 0.6
    M_true = apply_T(T[:, None], P)
    instrument = np.array([rng.uniform(-40, -8), rng.uniform(-40, -8), 1.6])
    C = polar_covariance(*cartesian_to_polar(M_true - instrument), INSTRUMENTS["leica_ms50"])
    M = M_true + np.einsum("bnij,bnj->bni", np.linalg.cholesky(C), rng.normal(size=(B, n, 3)))
    bad = rng.random(B) < faults
    k = rng.integers(0, n, B)
    M[bad, k[bad]] += rng.normal(0.0, 0.015, (int(bad.sum()), 3))
    return (P[0] if shared else P), M, C


def assert_close(a: np.ndarray, b: np.ndarray, what: str, rtol: float = RTOL) -> None:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    assert a.shape == b.shape, what
    assert np.array_equal(np.isfinite(a), np.isfinite(b)), f"{what}: {a} vs {b}"
    fin = np.isfinite(b)
    scale = max(float(np.max(np.abs(b[fin]), initial=0.0)), 1e-300)
    err = float(np.max(np.abs(a[fin] - b[fin]), initial=0.0))
    assert err <= rtol * scale, f"{what}: max |diff| {err:.3g} (scale {scale:.3g})"


def assert_same(batch: Registration, one: Registration, k: int) -> None:
    assert_close(batch.T_world_base, one.T_world_base, f"problem {k} pose")
    assert_close(batch.covariance, one.covariance, f"problem {k} covariance")
    assert_close(batch.residuals, one.residuals, f"problem {k} residuals")
    assert batch.iterations == one.iterations, f"problem {k} iterations"
    assert batch.variance_factor == pytest.approx(one.variance_factor, rel=RTOL)
    bi, oi = batch.integrity, one.integrity
    assert bi is not None and oi is not None
    assert bi.status == oi.status, f"problem {k}: {bi.reason} vs {oi.reason}"
    for key in ("statistic", "threshold", "variance_factor"):
        if key in oi.global_test:
            assert bi.global_test[key] == pytest.approx(oi.global_test[key], rel=RTOL)
    assert bi.global_test.get("passed") == oi.global_test.get("passed")
    assert bi.w_test.get("suspect") == oi.w_test.get("suspect")
    assert bi.w_test.get("passed") == oi.w_test.get("passed")
    if oi.w_test.get("max") is not None:
        assert bi.w_test["max"] == pytest.approx(oi.w_test["max"], rel=TEST_RTOL)
    assert set(bi.mdb) == set(oi.mdb)
    for label, value in oi.mdb.items():
        assert bi.mdb[label] == pytest.approx(value, rel=TEST_RTOL), f"problem {k} MDB {label}"
    for key, value in oi.protection_level.items():
        assert bi.protection_level[key] == pytest.approx(value, rel=TEST_RTOL)
    bt, ot = batch.outlier_test, one.outlier_test
    assert (bt is None) == (ot is None)
    if bt is not None and ot is not None:
        assert (bt.index, bt.flagged, bt.known_sigma) == (ot.index, ot.flagged, ot.known_sigma)
        assert_close(bt.statistics, ot.statistics, f"problem {k} statistics", TEST_RTOL)
        assert_close(bt.loo_residuals, ot.loo_residuals, f"problem {k} loo residuals", TEST_RTOL)
        assert bt.threshold == pytest.approx(ot.threshold, rel=RTOL)


def check(
    P: np.ndarray, M: np.ndarray, mode: str, C: np.ndarray, w: np.ndarray, alpha: float = 1e-3
) -> None:
    B = M.shape[0]
    kwargs: dict = {"alpha": alpha}
    if mode == "cov":
        batch = register_points_batch(P, M, point_cov=C, base_sigma=1e-4, **kwargs)
    elif mode == "sigma":
        batch = register_points_batch(P, M, w, sigma=2e-3, **kwargs)
    else:
        batch = register_points_batch(P, M, w, **kwargs)
    assert len(batch) == B and batch.T_world_base.shape == (B, 4, 4)
    for k in range(B):
        Pk = P if P.ndim == 2 else P[k]
        if mode == "cov":
            one = register_points(
                Pk, M[k], point_cov=C[k], base_sigma=1e-4, identify_prisms=False, **kwargs
            )
        elif mode == "sigma":
            one = register_points(Pk, M[k], w[k], sigma=2e-3, **kwargs)
        else:
            one = register_points(Pk, M[k], w[k], **kwargs)
        assert_same(batch.registration(k), one, k)
        assert batch.status[k] == one.integrity.status  # type: ignore[union-attr]


@settings(deadline=None, max_examples=60)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(3, 8),
    B=st.integers(1, 12),
    mode=st.sampled_from(["cov", "sigma", "relative"]),
    shared=st.booleans(),
)
def test_batch_agrees_with_the_single_solve(
    seed: int, n: int, B: int, mode: str, shared: bool
) -> None:
    rng = np.random.default_rng(seed)
    P, M, C = problems(rng, B, n, shared, faults=0.4)
    check(P, M, mode, C, rng.uniform(0.5, 2.0, (B, n)))


@pytest.mark.parametrize("mode", ["cov", "sigma", "relative"])
@pytest.mark.parametrize("n", [3, 4, 6])
def test_a_large_batch_agrees_with_the_single_solve(mode: str, n: int) -> None:
    """Enough problems for the closed-form routes; every fifth checked one by one."""
    rng = np.random.default_rng(n)
    P, M, C = problems(rng, 240, n, shared=n != 4, faults=0.3)
    w = rng.uniform(0.5, 2.0, (240, n))
    batch = register_points_batch(
        P,
        M,
        w if mode != "cov" else None,
        point_cov=C if mode == "cov" else None,
        sigma=2e-3 if mode == "sigma" else None,
    )
    assert {"ok", "failed"} <= set(batch.status) or n == 3
    for k in range(0, 240, 5):
        Pk = P if P.ndim == 2 else P[k]
        if mode == "cov":
            one = register_points(Pk, M[k], point_cov=C[k], identify_prisms=False)
        elif mode == "sigma":
            one = register_points(Pk, M[k], w[k], sigma=2e-3)
        else:
            one = register_points(Pk, M[k], w[k])
        assert_same(batch.registration(k), one, k)


def test_a_point_off_a_line_is_tested_like_the_single_solve() -> None:
    """Four points on a line and one off it: that point alone fixes the rotation about
    the line, its bias is partly invisible (fewer degrees of freedom, MDB infinite)."""
    rng = np.random.default_rng(100)
    P = np.array([[0, 0, 0.5], [0.5, 0, 0.5], [1.0, 0, 0.5], [1.5, 0, 0.5], [0.7, 0.8, 0.9]])
    C = np.broadcast_to(np.eye(3) * (5e-4) ** 2, (64, 5, 3, 3))
    M = P + rng.normal(0, 5e-4, (64, 5, 3))
    M[::3, 4] += 0.01
    batch = register_points_batch(P, M, point_cov=C)
    assert np.isinf(batch.mdb[:, 4]).all()
    for k in range(0, 64, 7):
        one = register_points(P, M[k], point_cov=C[k], identify_prisms=False)
        assert_same(batch.registration(k), one, k)


def test_batch_input_errors_name_the_problem() -> None:
    rng = np.random.default_rng(1)
    P, M, C = problems(rng, 5, 4, shared=True, faults=0.0)
    with pytest.raises(InputError, match=r"points_world must have shape"):
        register_points_batch(P, M[0])
    with pytest.raises(InputError, match=r"no problems"):
        register_points_batch(P, M[:0])
    with pytest.raises(InputError, match=r"points_base must have shape"):
        register_points_batch(P[:3], M)
    bad = M.copy()
    bad[3, 2, 1] = np.nan
    with pytest.raises(InputError, match=r"points_world\[3\]\[2\] is not finite"):
        register_points_batch(P, bad)
    C_bad = C.copy()
    C_bad[2, 1] = -C_bad[2, 1]
    with pytest.raises(InputError, match=r"point_cov\[2\]\[1\] must be positive definite"):
        register_points_batch(P, M, point_cov=C_bad)
    with pytest.raises(InputError, match="weights"):
        register_points_batch(P, M, np.array([1.0, 0.0, 1.0, 1.0]))
    line = np.outer(np.linspace(0, 2, 4), [1.0, 0.5, 0.2])
    M_line = M.copy()
    M_line[4] = line
    with pytest.raises(LocalizationError, match=r"points_world\[4\].*collinear"):
        register_points_batch(P, M_line)
    with pytest.raises(LocalizationError, match=r"points_base.*collinear"):
        register_points_batch(line, M)


# ------------------------------------------------------------------ the closed forms


@settings(deadline=None, max_examples=30)
@given(seed=st.integers(0, 2**31 - 1), spread=st.sampled_from([1.0, 1e-2, 1e-4]))
def test_closed_forms_agree_with_lapack(seed: int, spread: float) -> None:
    rng = np.random.default_rng(seed)
    m = sl.CLOSED_FORM_FROM + 16
    # eigenvalues 1, spread-ish, repeated ones included
    Q = exp_so3(rng.normal(size=(m, 3)))
    ev = np.stack([np.ones(m), rng.choice([1.0, spread], m), np.full(m, spread)], -1)
    S = Q @ (ev[..., None] * np.swapaxes(Q, -1, -2))
    np.testing.assert_allclose(sl.eigvalsh3(S), np.linalg.eigvalsh(S), atol=1e-14)
    np.testing.assert_allclose(
        sl.sym3_min_eigval(sl.sym3_of(S)), np.linalg.eigvalsh(S)[:, 0], atol=1e-14
    )
    Si = np.linalg.inv(S)
    np.testing.assert_allclose(sl.inv3(S), Si, atol=1e-13 * np.abs(Si).max())
    assert np.array_equal(
        sl.positive_definite3(S - 0.5 * np.eye(3)), np.linalg.eigvalsh(S)[:, 0] > 0.5
    )
    X = rng.normal(size=(m, 6, 9))
    N = X @ np.swapaxes(X, -1, -2)
    Ni = np.linalg.inv(N)
    np.testing.assert_allclose(sl.inv_spd6(N), Ni, atol=1e-11 * np.abs(Ni).max())
    b = rng.normal(size=(m, 6))
    x = np.linalg.solve(N, b[..., None])[..., 0]
    np.testing.assert_allclose(sl.solve_spd6(N, b), x, atol=1e-11 * np.abs(x).max())
    v = rng.normal(size=(m, 3)) * rng.choice([1.0, 1e-6], (m, 1))
    np.testing.assert_allclose(sl.exp_rotvec(v), exp_so3(v), atol=1e-15)
    # the best rotation: Horn's quaternion against the SVD, down to nearly collinear sets
    U, V = exp_so3(rng.normal(size=(m, 3))), exp_so3(rng.normal(size=(m, 3)))
    sv = np.stack([np.ones(m), np.full(m, spread), rng.uniform(-spread, spread, m)], -1)
    H = U @ (sv[..., None] * np.swapaxes(V, -1, -2))
    R_svd = sl.best_rotation(H[:3])
    R_horn = sl.best_rotation(H)
    np.testing.assert_allclose(R_horn[:3], R_svd, atol=1e-12 / spread)
    assert np.allclose(np.linalg.det(R_horn), 1.0)


@settings(deadline=None, max_examples=20)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(4, 9))
def test_leave_one_out_fits_are_the_fits_without_the_point(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    P = rng.uniform(-2, 2, (n, 3))
    M = apply_T(make_T(exp_so3(rng.normal(size=3)), rng.uniform(-20, 20, 3)), P)
    M = M + rng.normal(0, 1e-3, M.shape)
    M[rng.integers(n)] += rng.normal(0, 0.05, 3)
    w = rng.uniform(0.2, 3.0, n)
    R, t = kabsch_leave_one_out(P, M, w)
    R0, t0 = kabsch(P, M, w)
    np.testing.assert_allclose(R[0], R0, atol=1e-12)
    np.testing.assert_allclose(t[0], t0, atol=1e-10)
    for k in range(n):
        keep = np.arange(n) != k
        Rk, tk = kabsch(P[keep], M[keep], w[keep])
        np.testing.assert_allclose(R[1 + k], Rk, atol=1e-12)
        np.testing.assert_allclose(t[1 + k], tk, atol=1e-10)
