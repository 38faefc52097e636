"""Linear algebra on stacks of tiny matrices (2x2, 3x3, 6x6), fast for one problem and for many.

NumPy's ``np.linalg`` routines loop over a stack in C, but make one LAPACK call
per matrix: about a microsecond for a 3x3 eigen-decomposition and four for a
3x3 SVD, which dominates a batch of 10^4 tiny problems; its stacked ``matmul``
likewise pays per product. On a handful of matrices they are the fastest
route, since one call costs less than the tens of elementwise operations of a
closed form. The matrix functions here take a stack ``(..., k, k)`` and pick
the route by the number of matrices in it (:data:`CLOSED_FORM_FROM`): LAPACK
below, closed forms above (adjugate inverses, Schur complements, cyclic Jacobi
sweeps, Horn's quaternion for the best rotation). Both agree to rounding.

The closed forms work on *components*: a 3-vector is a tuple of 3 arrays, a
symmetric 3x3 matrix a tuple of its 6 entries ``(xx, xy, xz, yy, yz, zz)``, a
general 3x3 matrix a tuple of 9 (row-major), every array holding one entry of
every matrix of the stack, contiguous. Elementwise arithmetic on those runs
at memory speed, where the strided views ``A[..., i, j]`` or stacked products
of 3x3 matrices do not; batch kernels (:mod:`fabflow.positioning.registration_soa`)
keep their data in this form throughout.
"""

from __future__ import annotations

import numpy as np

from fabflow.transforms.so3 import exp_so3_one

CLOSED_FORM_FROM = 48
"""Stacks of at least this many matrices take the closed forms, smaller ones LAPACK."""

_JACOBI_SWEEPS = 8
"""Most cyclic Jacobi sweeps (3x3 converges to rounding in 3-4)."""

Vec3 = tuple[np.ndarray, np.ndarray, np.ndarray]
Sym3 = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
Mat3 = tuple[np.ndarray, ...]
"""Nine entries, row-major."""

_SYM = (0, 1, 2, 4, 5, 8)
"""Row-major positions of the entries of a :data:`Sym3` in a 3x3 matrix."""
_SYM_FULL = (0, 1, 2, 1, 3, 4, 2, 4, 5)
"""The :data:`Sym3` entry at each row-major position of a 3x3 matrix."""


# ---------------------------------------------------------------- components


def _count(A: np.ndarray, k: int) -> int:
    """Number of ``k x k`` matrices in the stack ``A``."""
    return A.size // (k * k)


def _rows(A: np.ndarray, k: int) -> np.ndarray:
    """The entries of a stack of ``k x k`` matrices as ``(k * k, m)``, each row contiguous."""
    return np.ascontiguousarray(A.reshape(-1, k * k).T)


def _matrices(
    entries: tuple[np.ndarray, ...] | list[np.ndarray], shape: tuple[int, ...]
) -> np.ndarray:
    """A stack of the given ``shape`` from its entries (row-major), inverse of :func:`_rows`."""
    return np.stack(entries, axis=-1).reshape(shape)


def sym3_of(A: np.ndarray) -> Sym3:
    """The :data:`Sym3` components of symmetric ``(..., 3, 3)`` matrices (upper triangle), each
    ``(m,)`` over the flattened stack."""
    r = _rows(A, 3)
    return (r[0], r[1], r[2], r[4], r[5], r[8])


def sym3_matrices(S: Sym3, shape: tuple[int, ...]) -> np.ndarray:
    """The ``(..., 3, 3)`` stack of :data:`Sym3` components."""
    return _matrices([S[k] for k in _SYM_FULL], shape)


def sym3_inv(S: Sym3) -> Sym3:
    """Inverses of symmetric 3x3 matrices (adjugate over determinant)."""
    a, b, c, d, e, f = S
    i00, i01, i02 = d * f - e * e, c * e - b * f, b * e - c * d
    r = 1.0 / (a * i00 + b * i01 + c * i02)
    return (
        i00 * r,
        i01 * r,
        i02 * r,
        (a * f - c * c) * r,
        (b * c - a * e) * r,
        (a * d - b * b) * r,
    )


def sym3_pd(S: Sym3) -> np.ndarray:
    """Whether each symmetric 3x3 matrix is positive definite (leading minors positive)."""
    a, b, c, d, e, f = S
    m2 = a * d - b * b
    m3 = a * (d * f - e * e) - b * (b * f - c * e) + c * (b * e - c * d)
    return (a > 0) & (m2 > 0) & (m3 > 0)


def sym3_vec(S: Sym3, v: Vec3) -> Vec3:
    """``S v`` for symmetric 3x3 ``S``."""
    a, b, c, d, e, f = S
    x, y, z = v
    return (a * x + b * y + c * z, b * x + d * y + e * z, c * x + e * y + f * z)


def sym3_eigvals(S: Sym3) -> Vec3:
    """Ascending eigenvalues of symmetric 3x3 matrices: cyclic Jacobi rotations.

    Sweeps until the off-diagonal part is below rounding (3-4 for 3x3); as
    accurate as LAPACK, repeated eigenvalues included.
    """
    d = [S[0], S[3], S[5]]
    off = {(0, 1): S[1], (0, 2): S[2], (1, 2): S[4]}
    tol = (2.2e-16 * (np.abs(d[0]) + np.abs(d[1]) + np.abs(d[2]))) ** 2
    for _ in range(_JACOBI_SWEEPS):
        for p, q, r in ((0, 1, 2), (0, 2, 1), (1, 2, 0)):
            apq = off[p, q]
            with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
                theta = (d[q] - d[p]) / (2.0 * apq)
                # the smaller rotation angle; |theta| -> inf gives t = 0
                t = np.copysign(1.0, theta) / (np.abs(theta) + np.sqrt(theta * theta + 1.0))
            t = np.where(apq != 0.0, t, 0.0)
            c = 1.0 / np.sqrt(t * t + 1.0)
            s = t * c
            ta = t * apq
            d[p] = d[p] - ta
            d[q] = d[q] + ta
            off[p, q] = np.zeros_like(apq)
            rp, rq = (min(r, p), max(r, p)), (min(r, q), max(r, q))
            arp, arq = off[rp], off[rq]
            off[rp] = c * arp - s * arq
            off[rq] = s * arp + c * arq
        if np.all(off[0, 1] ** 2 + off[0, 2] ** 2 + off[1, 2] ** 2 <= tol):
            break
    lo = np.minimum(np.minimum(d[0], d[1]), d[2])
    hi = np.maximum(np.maximum(d[0], d[1]), d[2])
    return lo, d[0] + d[1] + d[2] - lo - hi, hi


def sym3_min_eigval(S: Sym3) -> np.ndarray:
    """Smallest eigenvalue of symmetric 3x3 matrices: the trigonometric closed form.

    ``lambda = q + 2 p cos(phi + 2 pi / 3)`` with ``q`` the mean eigenvalue, ``p``
    the spread and ``cos(3 phi) = det((S - q I) / p) / 2``. Accurate (rounding
    of ``|S|``) except when the two smallest eigenvalues nearly coincide
    (``cos(3 phi)`` near 1, where ``arccos`` amplifies rounding): those
    matrices take :func:`sym3_eigvals`.
    """
    a, b, c, d, e, f = S
    q = (a + d + f) / 3.0
    a0, d0, f0 = a - q, d - q, f - q
    p2 = (a0 * a0 + d0 * d0 + f0 * f0 + 2.0 * (b * b + c * c + e * e)) / 6.0
    p = np.sqrt(p2)
    det = a0 * (d0 * f0 - e * e) - b * (b * f0 - c * e) + c * (b * e - c * d0)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = det / (2.0 * p2 * p)
    r = np.where(p2 > 0.0, np.clip(r, -1.0, 1.0), -1.0)
    lo = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * np.pi / 3.0)
    near_double = r > 0.5
    if near_double.any():
        sub = tuple(x[near_double] for x in S)
        lo[near_double] = sym3_eigvals(sub)[0]  # type: ignore[arg-type]
    return lo


def mat3_mul(A: Mat3, B: Mat3) -> Mat3:
    """``A B`` for general 3x3 matrices."""
    return tuple(
        A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j]
        for i in range(3)
        for j in range(3)
    )


def mat3_vec(A: Mat3, v: Vec3) -> Vec3:
    """``A v`` for a general 3x3 ``A``."""
    x, y, z = v
    return (
        A[0] * x + A[1] * y + A[2] * z,
        A[3] * x + A[4] * y + A[5] * z,
        A[6] * x + A[7] * y + A[8] * z,
    )


def mat3_tvec(A: Mat3, v: Vec3) -> Vec3:
    """``A^T v`` for a general 3x3 ``A``."""
    x, y, z = v
    return (
        A[0] * x + A[3] * y + A[6] * z,
        A[1] * x + A[4] * y + A[7] * z,
        A[2] * x + A[5] * y + A[8] * z,
    )


def sym3_mat(S: Sym3, B: Mat3) -> Mat3:
    """``S B`` for symmetric ``S`` and general ``B``."""
    return mat3_mul(tuple(S[k] for k in _SYM_FULL), B)


def exp3(v: Vec3) -> Mat3:
    """Rotation matrices of rotation vectors (radians): the formulas of
    :func:`fabflow.transforms.so3.exp_so3` (Rodrigues, series below 1e-4 rad)."""
    x, y, z = v
    th2 = x * x + y * y + z * z
    small = th2 < 1e-8
    th = np.sqrt(np.where(small, 1.0, th2))
    a = np.where(small, 1.0 - th2 / 6.0 + th2 * th2 / 120.0, np.sin(th) / th)
    b = np.where(small, 0.5 - th2 / 24.0 + th2 * th2 / 720.0, (1.0 - np.cos(th)) / (th * th))
    c = np.where(small, 1.0 - th2 / 2.0 + th2 * th2 / 24.0, np.cos(th))
    bx, by = b * x, b * y
    return (
        c + bx * x,
        bx * y - a * z,
        bx * z + a * y,
        bx * y + a * z,
        c + by * y,
        by * z - a * x,
        bx * z - a * y,
        by * z + a * x,
        c + b * z * z,
    )


def spd6_factors(N11: Sym3, N12: Mat3, N22: Sym3) -> tuple[Sym3, Mat3, Sym3]:
    """Schur factors of symmetric positive definite 6x6 matrices ``[[N11, N12], [N12^T, N22]]``.

    Returns ``N11^-1``, ``X = N11^-1 N12`` and ``Sc^-1``, ``Sc = N22 - N12^T X``.
    """
    Ai = sym3_inv(N11)
    X = sym3_mat(Ai, N12)
    Sc = tuple(
        N22[k] - (N12[i] * X[j] + N12[3 + i] * X[3 + j] + N12[6 + i] * X[6 + j])
        for k, (i, j) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))
    )
    return Ai, X, sym3_inv(Sc)  # type: ignore[arg-type]


def spd6_solve(factors: tuple[Sym3, Mat3, Sym3], g1: Vec3, g2: Vec3) -> tuple[Vec3, Vec3]:
    """``N^-1 [g1; g2]`` from :func:`spd6_factors`."""
    Ai, X, Sci = factors
    Xg = mat3_tvec(X, g1)
    x2 = sym3_vec(Sci, (g2[0] - Xg[0], g2[1] - Xg[1], g2[2] - Xg[2]))
    a, Xx = sym3_vec(Ai, g1), mat3_vec(X, x2)
    return (a[0] - Xx[0], a[1] - Xx[1], a[2] - Xx[2]), x2


def spd6_inverse(factors: tuple[Sym3, Mat3, Sym3]) -> tuple[Sym3, Mat3, Sym3]:
    """Blocks ``(I11, I12, I22)`` of ``N^-1`` from :func:`spd6_factors`."""
    Ai, X, Sci = factors
    XS = mat3_mul(X, tuple(Sci[k] for k in _SYM_FULL))
    I11 = tuple(
        Ai[k] + XS[3 * i] * X[3 * j] + XS[3 * i + 1] * X[3 * j + 1] + XS[3 * i + 2] * X[3 * j + 2]
        for k, (i, j) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))
    )
    return I11, tuple(-x for x in XS), Sci  # type: ignore[return-value]


def horn_rotation(H: Mat3, upper: np.ndarray | None = None) -> Mat3:
    """The rotations maximising ``trace(R H)`` (see :func:`best_rotation`), componentwise.

    Horn's quaternion: the eigenvector of the largest eigenvalue of his 4x4
    matrix ``K``, found by Newton's method on its characteristic polynomial
    from the Frobenius bound and the largest column of the adjugate of
    ``K - lambda I`` (Theobald's QCP); then one Newton step on the rotation
    itself (:func:`_polish`), since the polynomial's root loses digits when
    two singular values of ``H`` are far apart. ``upper``: a bound on the
    largest eigenvalue known to the caller (for point sets, the mean of their
    weighted scatters: it exceeds the root by half the residual sum of squares,
    so that Newton's method needs two or three steps).
    """
    sxx, sxy, sxz, syx, syy, syz, szx, szy, szz = H
    # Horn's symmetric matrix: q^T K q = trace(R(q) H) for unit quaternions (w, x, y, z)
    k = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ]
    # characteristic polynomial l^4 + c2 l^2 + c1 l + c0 (K is traceless)
    c2 = -2.0 * sum(h * h for h in H)
    c1 = -8.0 * (
        sxx * (syy * szz - syz * szy)
        - sxy * (syx * szz - syz * szx)
        + sxz * (syx * szy - syy * szx)
    )
    c0 = _det4(k)
    # Newton from above: sum of singular values <= sqrt(3) |H|_F, and lambda_max <= that
    lam = np.sqrt(-1.5 * c2)
    if upper is not None:
        lam = np.minimum(lam, upper)
    for _ in range(60):
        f = ((lam * lam + c2) * lam + c1) * lam + c0
        df = (4.0 * lam * lam + 2.0 * c2) * lam + c1
        step = f / np.where(df == 0.0, 1.0, df)
        lam = lam - step
        if np.all(np.abs(step) <= 1e-15 * np.maximum(np.abs(lam), 1e-300)):
            break
    for i in range(4):
        k[i][i] = k[i][i] - lam
    columns = _adjugate4(k)
    norms = np.stack([sum(x * x for x in col) for col in columns])
    j = np.argmax(norms, axis=0)
    q = [np.choose(j, [col[i] for col in columns]) for i in range(4)]
    scale = 1.0 / np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    w, x, y, z = (c * scale for c in q)
    R = (
        w * w + x * x - y * y - z * z,
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        w * w - x * x + y * y - z * z,
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        w * w - x * x - y * y + z * z,
    )
    return _polish(R, H)


def _polish(R: Mat3, H: Mat3) -> Mat3:
    """One Newton step of ``max trace(Exp(d) R H)`` over ``d``: rounding-level rotations.

    With ``A = R H``: gradient ``g = (A23 - A32, A31 - A13, A12 - A21)``, Hessian
    ``trace(A) I - sym(A)`` (positive definite near a well-posed optimum).
    """
    A = mat3_mul(R, H)
    g = (A[5] - A[7], A[6] - A[2], A[1] - A[3])
    tr = A[0] + A[4] + A[8]
    hess = (
        tr - A[0],
        -0.5 * (A[1] + A[3]),
        -0.5 * (A[2] + A[6]),
        tr - A[4],
        -0.5 * (A[5] + A[7]),
        tr - A[8],
    )
    return mat3_mul(exp3(sym3_vec(sym3_inv(hess), g)), R)


def _det3(m: list[list[np.ndarray]], rows: tuple[int, ...], cols: tuple[int, ...]) -> np.ndarray:
    (r0, r1, r2), (k0, k1, k2) = rows, cols
    return (
        m[r0][k0] * (m[r1][k1] * m[r2][k2] - m[r1][k2] * m[r2][k1])
        - m[r0][k1] * (m[r1][k0] * m[r2][k2] - m[r1][k2] * m[r2][k0])
        + m[r0][k2] * (m[r1][k0] * m[r2][k1] - m[r1][k1] * m[r2][k0])
    )


def _det4(m: list[list[np.ndarray]]) -> np.ndarray:
    """Determinant of a 4x4 matrix of component arrays (expansion in 2x2 minors)."""
    s0 = m[0][0] * m[1][1] - m[1][0] * m[0][1]
    s1 = m[0][0] * m[1][2] - m[1][0] * m[0][2]
    s2 = m[0][0] * m[1][3] - m[1][0] * m[0][3]
    s3 = m[0][1] * m[1][2] - m[1][1] * m[0][2]
    s4 = m[0][1] * m[1][3] - m[1][1] * m[0][3]
    s5 = m[0][2] * m[1][3] - m[1][2] * m[0][3]
    c5 = m[2][2] * m[3][3] - m[3][2] * m[2][3]
    c4 = m[2][1] * m[3][3] - m[3][1] * m[2][3]
    c3 = m[2][1] * m[3][2] - m[3][1] * m[2][2]
    c2 = m[2][0] * m[3][3] - m[3][0] * m[2][3]
    c1 = m[2][0] * m[3][2] - m[3][0] * m[2][2]
    c0 = m[2][0] * m[3][1] - m[3][0] * m[2][1]
    return s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0


def _adjugate4(m: list[list[np.ndarray]]) -> list[list[np.ndarray]]:
    """Columns of the adjugate of a symmetric 4x4 matrix of component arrays."""
    adj: list[list[np.ndarray]] = [[m[0][0]] * 4 for _ in range(4)]
    for i in range(4):
        rows = tuple(r for r in range(4) if r != i)
        for j in range(i, 4):
            cols = tuple(c for c in range(4) if c != j)
            minor = _det3(m, rows, cols)
            adj[i][j] = adj[j][i] = minor if (i + j) % 2 == 0 else -minor
    return adj


# ---------------------------------------------------------------- matrix stacks


def det3(A: np.ndarray) -> np.ndarray:
    """Determinants of ``(..., 3, 3)`` matrices (cofactor expansion, elementwise)."""
    return (
        A[..., 0, 0] * (A[..., 1, 1] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 1])
        - A[..., 0, 1] * (A[..., 1, 0] * A[..., 2, 2] - A[..., 1, 2] * A[..., 2, 0])
        + A[..., 0, 2] * (A[..., 1, 0] * A[..., 2, 1] - A[..., 1, 1] * A[..., 2, 0])
    )


def inv3(A: np.ndarray) -> np.ndarray:
    """Inverses of ``(..., 3, 3)`` non-singular matrices (adjugate over determinant)."""
    if _count(A, 3) < CLOSED_FORM_FROM:
        return np.linalg.inv(A)
    a, b, c, d, e, f, g, h, i = _rows(A, 3)
    c00, c01, c02 = e * i - f * h, c * h - b * i, b * f - c * e
    c10, c11, c12 = f * g - d * i, a * i - c * g, c * d - a * f
    c20, c21, c22 = d * h - e * g, b * g - a * h, a * e - b * d
    r = 1.0 / (a * c00 + b * c10 + c * c20)
    cof = (c00, c01, c02, c10, c11, c12, c20, c21, c22)
    return _matrices([x * r for x in cof], A.shape)


def positive_definite3(A: np.ndarray) -> np.ndarray:
    """Whether each symmetric ``(..., 3, 3)`` matrix is positive definite (Sylvester)."""
    return sym3_pd(sym3_of(A)).reshape(A.shape[:-2])


def eigvalsh3(A: np.ndarray) -> np.ndarray:
    """Ascending eigenvalues ``(..., 3)`` of symmetric ``(..., 3, 3)`` matrices.

    Large stacks: :func:`sym3_eigvals` (cyclic Jacobi).
    """
    if _count(A, 3) < CLOSED_FORM_FROM:
        return np.linalg.eigvalsh(A)
    return np.stack(sym3_eigvals(sym3_of(A)), axis=-1).reshape(*A.shape[:-2], 3)


def max_eigval_sym2(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Largest eigenvalue of the symmetric 2x2 matrices ``[[a, b], [b, c]]`` (elementwise)."""
    return 0.5 * (a + c) + np.hypot(0.5 * (a - c), b)


def _blocks6(N: np.ndarray) -> tuple[Sym3, Mat3, Sym3]:
    r = _rows(N, 6)
    N11 = tuple(r[6 * i + j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))
    N12 = tuple(r[6 * i + 3 + j] for i in range(3) for j in range(3))
    N22 = tuple(r[6 * (3 + i) + 3 + j] for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))
    return N11, N12, N22  # type: ignore[return-value]


def inv_spd6(N: np.ndarray) -> np.ndarray:
    """Inverses of symmetric positive definite ``(..., 6, 6)`` matrices."""
    if _count(N, 6) < CLOSED_FORM_FROM:
        return np.linalg.inv(N)
    I11, I12, I22 = spd6_inverse(spd6_factors(*_blocks6(N)))
    return spd6_matrices(I11, I12, I22, N.shape)


def spd6_matrices(I11: Sym3, I12: Mat3, I22: Sym3, shape: tuple[int, ...]) -> np.ndarray:
    """The ``(..., 6, 6)`` stack of symmetric matrices with blocks ``I11``, ``I12``, ``I22``."""
    entries = []
    for i in range(6):
        for j in range(6):
            if i < 3 and j < 3:
                entries.append(I11[_SYM_FULL[3 * i + j]])
            elif i < 3:
                entries.append(I12[3 * i + j - 3])
            elif j < 3:
                entries.append(I12[3 * j + i - 3])
            else:
                entries.append(I22[_SYM_FULL[3 * (i - 3) + j - 3]])
    return _matrices(entries, shape)


def solve_spd6(N: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``N^-1 b`` for symmetric positive definite ``N (..., 6, 6)`` and ``b (..., 6)``."""
    if _count(N, 6) < CLOSED_FORM_FROM:
        return np.linalg.solve(N, b[..., None])[..., 0]
    rb = np.ascontiguousarray(b.reshape(-1, 6).T)
    x1, x2 = spd6_solve(spd6_factors(*_blocks6(N)), tuple(rb[:3]), tuple(rb[3:]))  # type: ignore[arg-type]
    return np.stack([*x1, *x2], axis=-1).reshape(b.shape)


def exp_rotvec(v: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of rotation vectors ``(..., 3)`` (radians).

    The formulas of :func:`fabflow.transforms.so3.exp_so3` without its input
    handling: scalar arithmetic for one vector, componentwise over a stack.
    """
    if v.ndim == 1:
        x, y, z = v.tolist()
        return exp_so3_one(x, y, z)
    r = np.ascontiguousarray(v.reshape(-1, 3).T)
    return _matrices(exp3((r[0], r[1], r[2])), (*v.shape, 3))


def best_rotation(H: np.ndarray) -> np.ndarray:
    """The rotations ``R`` maximising ``trace(R H)`` for cross-covariances ``H (..., 3, 3)``.

    With ``H = sum_i w_i (p_i - p0)(m_i - m0)^T`` this is the Kabsch/Umeyama
    rotation taking the ``p_i`` onto the ``m_i`` (reflection-safe:
    ``R = V diag(1, 1, det(V U^T)) U^T`` from ``H = U S V^T``). Large stacks:
    :func:`horn_rotation`.
    """
    if _count(H, 3) < CLOSED_FORM_FROM:
        U, _, Vt = np.linalg.svd(H)
        R = U @ Vt
        # flipping the weakest axis when U V^T is a reflection: R - 2 u3 v3^T
        if H.ndim == 2:
            (a, b, c), (d, e, f), (g, h, i) = R.tolist()
            if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0:
                R = R - 2.0 * np.outer(U[:, 2], Vt[2])
            return R.T
        flip = det3(R) < 0
        if flip.any():
            R = R - (2.0 * flip)[..., None, None] * (U[..., :, 2:] * Vt[..., 2:, :])
        return np.swapaxes(R, -1, -2)
    return _matrices(horn_rotation(tuple(_rows(H, 3))), H.shape)
