"""The adjustment tests: exact against dense formulas, calibrated false alarms, MDB power."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.positioning.adjustment_tests import (
    Hypothesis,
    adjustment_test,
    global_passes,
    global_test,
    noncentrality,
    one_column_test,
    one_column_tests_many,
)
from fabflow.positioning.integrity import Integrity, identify, record
from fabflow.positioning.observation_covariance import Covariance
from fabflow.positioning.registration import register_points


def _dense(Q: Covariance) -> np.ndarray:
    m = Q.size
    return np.linalg.inv(Q.solve(np.eye(m)))


def _model(rng: np.random.Generator, m: int, u: int, shared: bool):
    A = rng.normal(size=(m, u))
    d = rng.uniform(0.5, 2.0, m) ** 2 * 1e-4
    groups = rng.integers(0, 3, m)
    U = (groups[:, None] == np.arange(3)[None]).astype(float)
    Q = Covariance(diag=d, low_rank=U, low_rank_var=np.full(3, 4e-5) if shared else None)
    if not shared:
        Q = Covariance(diag=d)
    return A, Q, U


@settings(deadline=None, max_examples=30)
@given(seed=st.integers(0, 2**31), m=st.integers(6, 30), shared=st.booleans())
def test_woodbury_solve_and_w_match_dense_formulas(seed: int, m: int, shared: bool) -> None:
    rng = np.random.default_rng(seed)
    A, Q, _ = _model(rng, m, 3, shared)
    Qd = _dense(Q)
    x = rng.normal(size=(m, 2))
    np.testing.assert_allclose(Q.solve(x), np.linalg.solve(Qd, x), rtol=1e-8, atol=1e-6)
    np.testing.assert_allclose(Q.inverse_diag(), np.diag(np.linalg.inv(Qd)), rtol=1e-8)
    v = rng.normal(size=m) * 0.01
    hyps = [Hypothesis(f"obs {i}", np.eye(m)[:, i]) for i in range(m)]
    res = adjustment_test(A, Q, v, hyps, alpha=0.01)
    Qi = np.linalg.inv(Qd)
    N = A.T @ Qi @ A
    Qvv = Qd - A @ np.linalg.inv(N) @ A.T
    w = np.abs(Qi @ v) / np.sqrt(np.diag(Qi @ Qvv @ Qi))
    np.testing.assert_allclose(res.w, w, rtol=1e-6)
    assert res.redundancy == m - 3
    np.testing.assert_allclose(res.statistic, v @ Qi @ v, rtol=1e-9)


@settings(deadline=None, max_examples=30)
@given(seed=st.integers(0, 2**31), m=st.integers(6, 30), shared=st.booleans())
def test_one_column_hypotheses_at_once_match_one_at_a_time(seed: int, m: int, shared: bool) -> None:
    # a two-column hypothesis sends the same tests through the per-hypothesis loop;
    # alpha scaled so both share the Bonferroni level alpha / h
    rng = np.random.default_rng(seed)
    A, Q, U = _model(rng, m, 3, shared)
    v = rng.normal(size=m) * 0.01
    cols = [np.eye(m)[:, i] for i in range(m)] + list(U.T) + [np.ones(m), A[:, 0]]
    hyps = [Hypothesis(f"h{i}", c) for i, c in enumerate(cols)]
    G = rng.normal(size=(3, 3))
    fast = adjustment_test(A, Q, v, hyps, alpha=0.01, position_map=G)
    pair = Hypothesis("pair", np.stack([np.eye(m)[:, 0], np.eye(m)[:, 1]], axis=1))
    h = len(hyps)
    slow = adjustment_test(A, Q, v, [*hyps, pair], alpha=0.01 * (h + 1) / h, position_map=G)
    for name in ("w", "thresholds", "mdb", "shift"):
        np.testing.assert_allclose(getattr(fast, name), getattr(slow, name)[:h], rtol=1e-7)
    np.testing.assert_allclose(
        np.concatenate(fast.bias), np.concatenate(slow.bias[:h]), rtol=1e-7, atol=1e-12
    )
    assert not np.isfinite(fast.mdb[-1])  # a bias along A's column is invisible


@settings(deadline=None, max_examples=30)
@given(seed=st.integers(0, 2**31), m=st.integers(3, 12), extra=st.integers(0, 3))
def test_the_global_test_alone_is_that_of_the_full_tests(seed: int, m: int, extra: int) -> None:
    """Redundancy, statistic, critical value and verdict of :func:`global_test` are
    those :func:`adjustment_test` reports, with and without redundancy."""
    rng = np.random.default_rng(seed)
    A, Q, _ = _model(rng, m, 3, bool(seed % 2))
    v = rng.normal(size=m) * 0.01 * rng.uniform(0.1, 10.0)
    scatter = float(rng.uniform(0.0, 5.0)) if extra else 0.0
    full = adjustment_test(A, Q, v, [], 0.01, extra_statistic=scatter, extra_redundancy=extra)
    r, statistic, threshold = global_test(A, Q, v, 0.01, scatter, extra)
    assert (r, statistic, threshold) == (full.redundancy, full.statistic, full.threshold)
    assert global_passes(r, statistic, threshold) == full.global_passed


def test_false_alarm_rate_is_alpha_and_mdb_is_found_with_its_power() -> None:
    rng = np.random.default_rng(3)
    m, u, trials, alpha = 12, 3, 4000, 0.05
    A = rng.normal(size=(m, u))
    sigma = rng.uniform(0.005, 0.02, m)
    Q = Covariance(diag=sigma**2)
    hyps = [Hypothesis(f"obs {i}", np.eye(m)[:, i]) for i in range(m)]
    N = A.T @ (A / sigma[:, None] ** 2)
    P = np.eye(m) - A @ np.linalg.solve(N, (A / sigma[:, None] ** 2).T)
    noise = rng.normal(size=(trials, m)) * sigma
    alarms = 0
    for e in noise:
        res = adjustment_test(A, Q, P @ e, hyps, alpha=alpha)
        alarms += any(res.w > res.thresholds)
    rate = alarms / trials
    assert abs(rate - alpha) < 0.015, rate
    # a bias of exactly the MDB of observation 4 is found about POWER of the time
    mdb = adjustment_test(A, Q, np.zeros(m), hyps, alpha=alpha).mdb[4]
    found = 0
    for e in noise[:2000]:
        e = e.copy()
        e[4] += mdb
        res = adjustment_test(A, Q, P @ e, hyps, alpha=alpha)
        found += res.w[4] > res.thresholds[4]
    assert 0.75 < found / 2000 < 0.85


def test_noncentrality_matches_baarda() -> None:
    assert noncentrality(0.001, 0.8, 1) == pytest.approx(17.07, abs=0.01)
    assert noncentrality(0.05, 0.8, 1) == pytest.approx(7.85, abs=0.01)


def test_a_gross_error_is_identified_and_recorded() -> None:
    rng = np.random.default_rng(5)
    m = 10
    A = rng.normal(size=(m, 2))
    Q = Covariance(diag=np.full(m, 1e-4))
    e = rng.normal(size=m) * 0.01
    e[7] += 0.2
    N = A.T @ A
    v = e - A @ np.linalg.solve(N, A.T @ e)
    hyps = [Hypothesis(f"obs {i}", np.eye(m)[:, i]) for i in range(m)]
    res = adjustment_test(A, Q, v, hyps)
    assert not res.passed and identify(res) == 7
    rec = record(res)
    assert rec.status == "failed" and "obs 7" in rec.reason
    back = Integrity.from_dict(rec.to_dict())
    assert back.status == "failed" and back.w_test["suspect"] == "obs 7"
    assert rec.protection_level["horizontal"] > 0


@settings(deadline=None, max_examples=25)
@given(seed=st.integers(0, 2**31), k=st.integers(1, 3))
def test_protection_level_is_the_worst_undetected_shift(seed: int, k: int) -> None:
    # the largest base shift over every bias on the ellipsoid nabla^T S nabla = lambda_0,
    # found by brute force over many directions, equals the closed form
    rng = np.random.default_rng(seed)
    m, u = 12, 4
    A = rng.normal(size=(m, u))
    Q = Covariance(diag=rng.uniform(0.5, 2.0, m) * 1e-4)
    C = np.zeros((m, k))
    C[rng.choice(m, k, replace=False), np.arange(k)] = 1.0
    G = rng.normal(size=(3, u))
    res = adjustment_test(A, Q, np.zeros(m), [Hypothesis("h", C)], alpha=0.01, position_map=G)
    Qi = np.linalg.inv(_dense(Q))
    N = A.T @ Qi @ A
    S = C.T @ Qi @ C - C.T @ Qi @ A @ np.linalg.solve(N, A.T @ Qi @ C)
    lam = noncentrality(0.01, 0.8, k)
    d = rng.normal(size=(20000, k))
    d *= np.sqrt(lam / np.einsum("ni,ij,nj->n", d, S, d))[:, None]
    shifts = d @ (G @ np.linalg.solve(N, A.T @ Qi @ C)).T
    horizontal = np.hypot(shifts[:, 0], shifts[:, 1]).max()
    vertical = np.abs(shifts[:, 2]).max()
    h, v = res.protection_level()
    assert horizontal <= h * (1 + 1e-9) and vertical <= v * (1 + 1e-9)
    assert horizontal > 0.97 * h if k > 1 else horizontal == pytest.approx(h, rel=1e-9)
    assert vertical > 0.97 * v if k > 1 else vertical == pytest.approx(v, rel=1e-9)
    assert res.mdb[0] == pytest.approx(np.sqrt(lam / np.linalg.eigvalsh(S)[0]), rel=1e-9)


def test_an_undetectable_bias_makes_the_protection_level_unbounded() -> None:
    # three prism points: moving P1 normal to their plane is a rotation about P2-P3,
    # which the pose absorbs; the tests cannot see it, so nothing bounds its effect
    P = np.array([[1.0, 0.0, 0.5], [0.0, 1.2, 0.8], [-0.8, -0.5, 1.1]])
    axis = (P[2] - P[1]) / np.linalg.norm(P[2] - P[1])
    normal = np.cross(axis, P[0] - P[1])
    M = P.copy()
    M[0] += 0.03 * normal / np.linalg.norm(normal)
    cov = np.array([np.eye(3) * (5e-4) ** 2] * 3)
    reg = register_points(P, M, point_cov=cov, point_labels=["P1", "P2", "P3"])
    assert reg.integrity is not None and reg.integrity.status == "ok"  # nothing to see
    assert reg.integrity.protection_level == {"horizontal": np.inf, "vertical": np.inf}
    assert "P1" not in reg.integrity.mdb  # infinite MDBs are not listed
    # with a fourth point the same fault is seen
    P4 = np.vstack([P, [0.3, -1.0, 0.2]])
    M4 = np.vstack([M, P4[3]])
    reg4 = register_points(P4, M4, point_cov=np.array([np.eye(3) * (5e-4) ** 2] * 4))
    assert reg4.integrity is not None and reg4.integrity.status == "failed"
    assert np.isfinite(reg4.integrity.protection_level["horizontal"])


@settings(deadline=None, max_examples=30)
@given(
    seed=st.integers(0, 2**31),
    n=st.integers(1, 6),
    m=st.integers(3, 12),
    shared=st.booleans(),
    prior=st.booleans(),
)
def test_many_solutions_are_tested_as_each_alone(
    seed: int, n: int, m: int, shared: bool, prior: bool
) -> None:
    # a stack of solutions of one shape, their own covariances, residuals and
    # position maps, the same hypotheses: each result is that solution's alone
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, m, 4))
    d = rng.uniform(0.5, 2.0, (n, m)) ** 2 * 1e-4
    U = (rng.integers(0, 3, m)[:, None] == np.arange(3)[None]).astype(float)
    var = rng.uniform(1e-5, 1e-4, (n, 3))
    v = rng.normal(size=(n, m)) * 0.01 * rng.uniform(0.1, 10.0, (n, 1))
    C = np.c_[np.eye(m), U].astype(float)
    labels = [f"h{i}" for i in range(C.shape[1])]
    G = rng.normal(size=(n, 3, 4))
    P = np.diag([0.0, 0.0, 0.0, 100.0]) if prior else None
    low_rank = U if shared else None
    many = one_column_tests_many(
        A, Covariance(diag=d, low_rank=low_rank, low_rank_var=var), v, labels, C, 0.01, G, P
    )
    assert len(many) == n
    for i, got in enumerate(many):
        Q = Covariance(diag=d[i], low_rank=low_rank, low_rank_var=var[i])
        want = one_column_test(A[i], Q, v[i], labels, C, 0.01, G[i], P)
        assert (got.redundancy, got.labels, got.units) == (want.redundancy, want.labels, want.units)
        for name in ("statistic", "threshold", "p_value"):
            assert getattr(got, name) == pytest.approx(getattr(want, name), rel=1e-10)
        for name in ("w", "thresholds", "mdb", "shift"):
            np.testing.assert_allclose(getattr(got, name), getattr(want, name), rtol=1e-9)
        np.testing.assert_allclose(np.concatenate(got.bias), np.concatenate(want.bias), rtol=1e-9)
        assert got.passed == want.passed and np.array_equal(got.excludable, want.excludable)
