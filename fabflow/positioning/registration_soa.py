"""Componentwise kernels of the batch registration: many problems, no per-matrix calls.

The same fits and tests as :mod:`fabflow.positioning.rigid_fit` and
:mod:`fabflow.positioning.registration_tests`, written on components (see
:mod:`fabflow.positioning.small_linalg`): every coordinate of every point of
every problem is an entry of a contiguous ``(n, B)`` array (points by
problems), every entry of a per-problem 3x3 or 6x6 matrix a ``(B,)`` array.
Sums over the points are sums over the first axis. A batch of ``B``
registrations of ``n`` points is then a few hundred elementwise operations on
arrays of ``n B`` numbers, whatever ``B``.

Frames and units as in :func:`fabflow.positioning.registration.register_points`:
base points ``p`` in the robot base frame, measured points ``m`` and their
information matrices ``W`` (1/m^2) in the world, metres.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy import special

from fabflow.positioning.adjustment_tests import MIN_REDUNDANCY, chi2_quantile
from fabflow.positioning.registration_tests import PointTestArrays, levels, partial_tests
from fabflow.positioning.small_linalg import (
    Mat3,
    Sym3,
    Vec3,
    exp3,
    horn_rotation,
    mat3_mul,
    max_eigval_sym2,
    spd6_factors,
    spd6_inverse,
    spd6_matrices,
    spd6_solve,
    sym3_eigvals,
    sym3_inv,
    sym3_matrices,
    sym3_min_eigval,
    sym3_vec,
)

_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def point_vectors(a: np.ndarray) -> Vec3:
    """Components ``(n, B)`` of points ``(B, n, 3)``, or ``(n, 1)`` of points ``(n, 3)``
    shared by every problem."""
    if a.ndim == 2:
        return tuple(np.ascontiguousarray(a[:, k : k + 1]) for k in range(3))  # type: ignore[return-value]
    c = np.ascontiguousarray(np.transpose(a, (2, 1, 0)))
    return c[0], c[1], c[2]


def point_sym(C: np.ndarray) -> Sym3:
    """Components ``(n, B)`` of symmetric matrices ``(B, n, 3, 3)`` (upper triangle)."""
    B, n = C.shape[:2]
    c = np.ascontiguousarray(np.transpose(C.reshape(B, n, 9), (2, 1, 0)))
    return c[0], c[1], c[2], c[4], c[5], c[8]


def spreads(p: Vec3) -> np.ndarray:
    """``(B, 3)`` RMS spreads of each problem's points along their principal axes, largest
    first (:func:`fabflow.positioning.rigid_fit.principal_spreads`), from components."""
    n = p[0].shape[0]
    c = tuple(x - x.mean(axis=0) for x in p)
    scatter = tuple((c[i] * c[j]).sum(axis=0) for i, j in _UPPER)
    lo, mid, hi = sym3_eigvals(scatter)  # type: ignore[arg-type]
    return np.sqrt(np.maximum(np.stack([hi, mid, lo], axis=-1), 0.0) / n)


def stack_points(v: tuple[np.ndarray, ...]) -> np.ndarray:
    """``(B, n, k)`` from ``k`` point components ``(n, B)``."""
    return np.ascontiguousarray(np.stack(v, axis=-1).transpose(1, 0, 2))


class Normal(NamedTuple):
    """The linearised point fits of a batch at a pose (components; see
    :class:`fabflow.positioning.rigid_fit.NormalEquations`).

    ``q = R p``, residuals ``v = m - q - t``, ``Wv``, ``WA = W J_rot`` (the
    rotation columns of ``W J``, 9 components) per point; the normal matrix in
    blocks ``N11 = sum W``, ``N12 = sum W J_rot``, ``N22 = sum J_rot^T W J_rot``
    and ``g = sum J^T W v`` per problem.
    """

    q: Vec3
    v: Vec3
    Wv: Vec3
    WA: Mat3
    N11: Sym3
    N12: Mat3
    N22: Sym3
    g1: Vec3
    g2: Vec3


def rotate(R: Mat3, p: Vec3) -> Vec3:
    """``R p`` of every point, ``(n, B)`` components (one matrix product for shared points)."""
    if p[0].shape[-1] == 1 and R[0].shape[0] > 1:
        B = R[0].shape[0]
        Rt = np.stack([np.stack([R[c], R[3 + c], R[6 + c]]) for c in range(3)]).reshape(3, 3 * B)
        q = np.hstack(p) @ Rt
        return q[:, :B], q[:, B : 2 * B], q[:, 2 * B :]
    return (
        R[0] * p[0] + R[1] * p[1] + R[2] * p[2],
        R[3] * p[0] + R[4] * p[1] + R[5] * p[2],
        R[6] * p[0] + R[7] * p[1] + R[8] * p[2],
    )


def normal(R: Mat3, t: Vec3, p: Vec3, m: Vec3, W: Sym3, N11: Sym3 | None = None) -> Normal:
    """The :class:`Normal` system of ``m_i ~ R p_i + t`` with information ``W_i``.

    The rotation columns of a point's Jacobian are ``A = -skew(q)``, so
    ``W A`` column ``b`` is ``W (e_b x q)`` and ``A^T u = q x u``. The per-point
    terms are written into one buffer and summed over the points at once.
    ``N11 = sum W`` does not depend on the pose: pass it when known.
    """
    q = rotate(R, p)
    q0, q1, q2 = q
    v = (m[0] - q0 - t[0], m[1] - q1 - t[1], m[2] - q2 - t[2])
    w00, w01, w02, w11, w12, w22 = W
    terms = np.empty((21, *v[0].shape))
    mul, sub = np.multiply, np.subtract
    for k, (wa0, wa1, wa2) in enumerate(((w00, w01, w02), (w01, w11, w12), (w02, w12, w22))):
        sub(wa2 * q1, wa1 * q2, out=terms[3 * k])
        sub(wa0 * q2, wa2 * q0, out=terms[3 * k + 1])
        sub(wa1 * q0, wa0 * q1, out=terms[3 * k + 2])
    WA = tuple(terms[:9])
    # (A^T W A)_bd = sum_a A_ab (WA)_ad, A_ab: column b of A = e_b x q
    sub(q1 * WA[6], q2 * WA[3], out=terms[9])  # (0, 0)
    sub(q1 * WA[7], q2 * WA[4], out=terms[10])  # (0, 1)
    sub(q1 * WA[8], q2 * WA[5], out=terms[11])  # (0, 2)
    sub(q2 * WA[1], q0 * WA[7], out=terms[12])  # (1, 1)
    sub(q2 * WA[2], q0 * WA[8], out=terms[13])  # (1, 2)
    sub(q0 * WA[5], q1 * WA[2], out=terms[14])  # (2, 2)
    v0, v1, v2 = v
    mul(w00, v0, out=terms[15])
    terms[15] += w01 * v1
    terms[15] += w02 * v2
    mul(w01, v0, out=terms[16])
    terms[16] += w11 * v1
    terms[16] += w12 * v2
    mul(w02, v0, out=terms[17])
    terms[17] += w12 * v1
    terms[17] += w22 * v2
    Wv = tuple(terms[15:18])
    sub(q1 * Wv[2], q2 * Wv[1], out=terms[18])
    sub(q2 * Wv[0], q0 * Wv[2], out=terms[19])
    sub(q0 * Wv[1], q1 * Wv[0], out=terms[20])
    sums = terms.sum(axis=1)
    if N11 is None:
        N11 = tuple(x.sum(axis=0) for x in W)  # type: ignore[assignment]
    return Normal(
        q,
        v,
        Wv,  # type: ignore[arg-type]
        WA,
        N11,  # type: ignore[arg-type]
        tuple(sums[:9]),
        tuple(sums[9:15]),  # type: ignore[arg-type]
        tuple(sums[15:18]),  # type: ignore[arg-type]
        tuple(sums[18:21]),  # type: ignore[arg-type]
    )


def kabsch(p: Vec3, m: Vec3, w: np.ndarray) -> tuple[Mat3, Vec3]:
    """Weighted Kabsch fits of a batch (weights ``w`` ``(n, B)``, positive)."""
    wn = w / w.sum(axis=0)
    p0 = tuple((wn * x).sum(axis=0) for x in p)
    m0 = tuple((wn * x).sum(axis=0) for x in m)
    pc = tuple(x - c for x, c in zip(p, p0, strict=True))
    mc = tuple(wn * (x - c) for x, c in zip(m, m0, strict=True))
    H = tuple((pc[i] * mc[j]).sum(axis=0) for i in range(3) for j in range(3))
    # trace(R H) <= (sum w |p - p0|^2 + sum w |m - m0|^2) / 2, within half the residuals
    upper = 0.5 * sum((wn * x * x).sum(axis=0) for x in pc) + 0.5 * sum(
        ((x - c) * y).sum(axis=0) for x, c, y in zip(m, m0, mc, strict=True)
    )
    R = horn_rotation(H, upper)
    Rp = (
        R[0] * p0[0] + R[1] * p0[1] + R[2] * p0[2],
        R[3] * p0[0] + R[4] * p0[1] + R[5] * p0[2],
        R[6] * p0[0] + R[7] * p0[1] + R[8] * p0[2],
    )
    return R, (m0[0] - Rp[0], m0[1] - Rp[1], m0[2] - Rp[2])


def gauss_newton(
    R: Mat3, t: Vec3, p: Vec3, m: Vec3, W: Sym3, max_iter: int = 5, tol: float = 1e-10
) -> tuple[Mat3, Vec3, np.ndarray]:
    """:func:`fabflow.positioning.rigid_fit.gauss_newton` for a batch: each problem stops
    at its own convergence. Returns ``R``, ``t`` and the iterations ``(B,)``.

    Once most problems have converged, the rest go on as a smaller batch.
    """
    B = R[0].shape[0]
    iters = np.zeros(B, dtype=int)
    active = np.ones(B, dtype=bool)
    N11 = tuple(x.sum(axis=0) for x in W)
    for k in range(max_iter):
        eq = normal(R, t, p, m, W, N11)  # type: ignore[arg-type]
        d1, d2 = spd6_solve(spd6_factors(eq.N11, eq.N12, eq.N22), eq.g1, eq.g2)
        R_new = mat3_mul(exp3(d2), R)
        iters += active
        R = tuple(np.where(active, a, b) for a, b in zip(R_new, R, strict=True))
        t = tuple(np.where(active, x + d, x) for x, d in zip(t, d1, strict=True))  # type: ignore[assignment]
        step2 = sum(d * d for d in (*d1, *d2))
        active = active & (step2 >= tol**2)
        count = int(active.sum())
        if count == 0:
            break
        if count <= B // 2 and k + 1 < max_iter:
            idx = np.flatnonzero(active)
            Rs, ts, its = gauss_newton(
                tuple(x[idx] for x in R),
                tuple(x[idx] for x in t),  # type: ignore[arg-type]
                _problems(p, idx, B),  # type: ignore[arg-type]
                _problems(m, idx, B),  # type: ignore[arg-type]
                _problems(W, idx, B),  # type: ignore[arg-type]
                max_iter - k - 1,
                tol,
            )
            for x, y in zip(R, Rs, strict=True):
                x[idx] = y
            for x, y in zip(t, ts, strict=True):
                x[idx] = y
            iters[idx] += its
            break
    return R, t, iters


def _problems(comps: tuple[np.ndarray, ...], idx: np.ndarray, B: int) -> tuple[np.ndarray, ...]:
    """The problems ``idx`` of point components ``(n, B)`` (shared ``(n, 1)`` ones as they are)."""
    return tuple(x[:, idx] if x.shape[-1] == B else x for x in comps)


def point_tests(eq: Normal, W: Sym3, C: Sym3, alpha: float) -> PointTestArrays:
    """:func:`fabflow.positioning.registration_tests.point_test_arrays` of a batch.

    ``W`` and ``C = W^-1`` are the information and covariance of the points.
    With ``G_k = J_k N^-1 J_k^T`` (the covariance of the fitted point) and
    ``D_k = C_k - G_k`` (that of its residual), ``S_k = W_k D_k W_k``, so
    ``w_k^2 = v_k^T D_k^-1 v_k``, the bias is ``C_k D_k^-1 v_k``, the shift
    matrix ``Y S^-1 Y^T = H_k^T D_k^-1 H_k`` with ``H_k = J_k (N^-1)[:, :3]``, and a
    bias direction is invisible when ``D_k - MIN_REDUNDANCY C_k`` is not
    positive definite (:func:`~fabflow.positioning.registration_tests.partial_tests`):
    one 3x3 inverse per point. Returns the arrays in the batch layout ``(B, ...)``.
    """
    n, B = eq.v[0].shape
    h = n + 1
    r = 3 * n - 6
    thr_table, lam_table = levels(alpha / h)
    factors = spd6_factors(eq.N11, eq.N12, eq.N22)
    I11, I12, I22 = spd6_inverse(factors)
    statistic = sum((x * y).sum(axis=0) for x, y in zip(eq.v, eq.Wv, strict=True))
    q0, q1, q2 = eq.q
    full_index = (0, 1, 2, 1, 3, 4, 2, 4, 5)
    I11f = tuple(I11[k] for k in full_index)
    I22f = tuple(I22[k] for k in full_index)
    # H = I11 + A I12^T, K = I12 + A I22 (A x = x cross q), column by column
    H: list[np.ndarray] = [I11f[0]] * 9
    K: list[np.ndarray] = [I11f[0]] * 9
    for j in range(3):
        a0, a1, a2 = I12[3 * j], I12[3 * j + 1], I12[3 * j + 2]
        H[j] = I11f[j] + (a1 * q2 - a2 * q1)
        H[3 + j] = I11f[3 + j] + (a2 * q0 - a0 * q2)
        H[6 + j] = I11f[6 + j] + (a0 * q1 - a1 * q0)
        c0, c1, c2 = I22f[j], I22f[3 + j], I22f[6 + j]
        K[j] = I12[j] + (c1 * q2 - c2 * q1)
        K[3 + j] = I12[3 + j] + (c2 * q0 - c0 * q2)
        K[6 + j] = I12[6 + j] + (c0 * q1 - c1 * q0)
    # D = C - G, G = H + K A^T (upper entries)
    D = (
        C[0] - (H[0] + (K[1] * q2 - K[2] * q1)),
        C[1] - (H[1] + (K[2] * q0 - K[0] * q2)),
        C[2] - (H[2] + (K[0] * q1 - K[1] * q0)),
        C[3] - (H[4] + (K[5] * q0 - K[3] * q2)),
        C[4] - (H[5] + (K[3] * q1 - K[4] * q0)),
        C[5] - (H[8] + (K[6] * q1 - K[7] * q0)),
    )
    # S = W D W
    WD = mat3_mul(tuple(W[k] for k in full_index), tuple(D[k] for k in full_index))
    Wf = tuple(W[k] for k in full_index)
    S = tuple(
        WD[3 * i] * Wf[j] + WD[3 * i + 1] * Wf[3 + j] + WD[3 * i + 2] * Wf[6 + j] for i, j in _UPPER
    )
    lo = sym3_min_eigval(S)  # type: ignore[arg-type]
    trace = W[0] + W[3] + W[5]
    # seen when lambda_min(S) > MIN_REDUNDANCY lambda_max(W); lambda_max(W) in [trace/3, trace]
    full = lo > MIN_REDUNDANCY * trace
    unsure = ~full & (lo > MIN_REDUNDANCY * trace / 3.0)
    scale = trace
    if unsure.any():
        scale = np.maximum(sym3_eigvals(W)[2], 1e-300)
        full = lo > MIN_REDUNDANCY * scale
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        Di = sym3_inv(D)  # type: ignore[arg-type]
        Div = sym3_vec(Di, eq.v)
        bias = sym3_vec(C, Div)
        w = np.sqrt(np.maximum(sum(x * y for x, y in zip(eq.v, Div, strict=True)), 0.0))
        # base shift: T = H^T D^-1 H
        Z = mat3_mul(tuple(Di[k] for k in full_index), tuple(H))

        def T(i: int, j: int) -> np.ndarray:
            return H[i] * Z[j] + H[3 + i] * Z[3 + j] + H[6 + i] * Z[6 + j]

        horizontal = max_eigval_sym2(T(0, 0), T(0, 1), T(1, 1))
        vertical = T(2, 2)
    thr = np.full(w.shape, thr_table[3])
    # every direction seen: S > MIN_REDUNDANCY lambda_max(W) I >= MIN_REDUNDANCY W, so every
    # redundancy number is above MIN_REDUNDANCY (the others go to partial_tests)
    visible = full
    mdb = np.where(visible, lam_table[3] / np.sqrt(np.where(visible, lo, 1.0)), np.inf)
    shift_h = np.where(visible, lam_table[3] * np.sqrt(np.where(visible, horizontal, 0.0)), np.inf)
    shift_v = np.where(visible, lam_table[3] * np.sqrt(np.where(visible, vertical, 0.0)), np.inf)
    bias_pts = stack_points(bias)
    w, thr, mdb = w.T.copy(), thr.T.copy(), mdb.T.copy()
    shift = np.stack([shift_h.T, shift_v.T], axis=-1)
    if not full.all():
        rows = (~full).T
        Sm = sym3_matrices(tuple(x.T[rows] for x in S), (-1, 3, 3))  # type: ignore[arg-type]
        Wm = sym3_matrices(tuple(x.T[rows] for x in W), (-1, 3, 3))  # type: ignore[arg-type]
        Hm = np.stack([x.T[rows] for x in H], -1).reshape(-1, 3, 3)
        b = np.stack([x.T[rows] for x in eq.Wv], -1)
        sc = np.broadcast_to(scale, lo.shape).T[rows]
        # Y = (N^-1 J^T W)[:3] = (W H)^T
        w[rows], thr[rows], mdb[rows], shift[rows], bias_pts[rows] = partial_tests(
            Sm, Wm, sc, b, np.swapaxes(Wm @ Hm, -1, -2), thr_table, lam_table
        )

    # scale: one column c = (R p_i) stacked
    Wq = sym3_vec(W, eq.q)
    b_s = sum((x * y).sum(axis=0) for x, y in zip(Wq, eq.v, strict=True))
    B1 = tuple(x.sum(axis=0) for x in Wq)
    # (W A)^T q = A^T W q = q x W q
    B2 = tuple(
        x.sum(axis=0)
        for x in (q1 * Wq[2] - q2 * Wq[1], q2 * Wq[0] - q0 * Wq[2], q0 * Wq[1] - q1 * Wq[0])
    )
    own_s = sum((x * y).sum(axis=0) for x, y in zip(eq.q, Wq, strict=True))
    NB1 = _add(sym3_vec(I11, B1), _mat_vec(I12, B2))
    NB2 = _add(_mat_tvec(I12, B1), sym3_vec(I22, B2))
    S_s = own_s - sum(x * y for x, y in zip((*B1, *B2), (*NB1, *NB2), strict=True))
    seen_s = S_s > MIN_REDUNDANCY * np.maximum(own_s, 1e-300)
    S_safe = np.where(seen_s, S_s, 1.0)
    w_s = np.where(seen_s, np.sqrt(np.maximum(b_s * (1.0 / S_safe) * b_s, 0.0)), np.nan)
    bias_s = np.where(seen_s, b_s / S_safe, np.nan)
    thr_s = np.where(seen_s, thr_table[1], np.inf)
    visible_s = seen_s & (S_s / own_s >= MIN_REDUNDANCY)
    mdb_s = np.where(visible_s, lam_table[1] / np.sqrt(S_safe), np.inf)
    root = np.sqrt(S_safe)
    shift_s = np.where(
        visible_s[:, None],
        lam_table[1]
        * np.stack([np.hypot(NB1[0] / root, NB1[1] / root), np.abs(NB1[2] / root)], -1),
        np.inf,
    )
    return PointTestArrays(
        redundancy=r,
        statistic=statistic,
        threshold=chi2_quantile(r, alpha),
        p_value=special.chdtrc(r, statistic),
        w=np.concatenate([w, w_s[:, None]], axis=-1),
        thresholds=np.concatenate([thr, thr_s[:, None]], axis=-1),
        mdb=np.concatenate([mdb, mdb_s[:, None]], axis=-1),
        shift=np.concatenate([shift, shift_s[:, None, :]], axis=-2),
        bias=bias_pts,
        scale_bias=bias_s,
        Ninv=spd6_matrices(I11, I12, I22, (B, 6, 6)),
    )


def _add(a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    return tuple(x + y for x, y in zip(a, b, strict=True))


def _mat_vec(A: Mat3, v: Vec3) -> Vec3:
    return (
        A[0] * v[0] + A[1] * v[1] + A[2] * v[2],
        A[3] * v[0] + A[4] * v[1] + A[5] * v[2],
        A[6] * v[0] + A[7] * v[1] + A[8] * v[2],
    )


def _mat_tvec(A: Mat3, v: Vec3) -> Vec3:
    return (
        A[0] * v[0] + A[3] * v[1] + A[6] * v[2],
        A[1] * v[0] + A[4] * v[1] + A[7] * v[2],
        A[2] * v[0] + A[5] * v[1] + A[8] * v[2],
    )


def pose_matrices(R: Mat3, t: Vec3) -> np.ndarray:
    """``(B, 4, 4)`` poses from rotation and translation components."""
    B = R[0].shape[0]
    T = np.zeros((B, 16))
    for i in range(3):
        T[:, 4 * i : 4 * i + 3] = np.stack(R[3 * i : 3 * i + 3], -1)
        T[:, 4 * i + 3] = t[i]
    T[:, 15] = 1.0
    return T.reshape(B, 4, 4)


def residuals(R: Mat3, t: Vec3, p: Vec3, m: Vec3) -> tuple[Vec3, np.ndarray]:
    """Measured minus fitted points (components) and the RMS of their lengths ``(B,)``."""
    q = rotate(R, p)
    res = (m[0] - (q[0] + t[0]), m[1] - (q[1] + t[1]), m[2] - (q[2] + t[2]))
    n = res[0].shape[0]
    sq = sum(x * x for x in res).sum(axis=0)
    return res, np.sqrt(sq / n)
