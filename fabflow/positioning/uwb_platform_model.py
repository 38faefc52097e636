"""The range model of a standing platform and its damped Newton solve.

A level platform stands at ``x, y, z, yaw`` (anchors' frame, metres and
radians); tag ``k`` sits at the lever arm ``l_k`` (platform frame), so the range
of tag ``k`` to anchor ``j`` is ``|p + R(yaw) l_k - a_j|``. Here are that
range, its first and second derivatives, the information of white ranges and
the solve, of many problems at once (:func:`platform_newton_batch`: a simulated
run's hidden-mirror searches, some 170 fits, in a dozen iterations of array
operations) or of one; :mod:`fabflow.positioning.uwb_platform_adjustment` tests
and compares fits with them.
"""

from __future__ import annotations

import numpy as np

from fabflow.errors import LocalizationError

UNDETERMINED = "the tag and anchor geometry does not determine the platform pose"
"""Why a platform fix fails whose normal matrix is singular."""


def rotz(yaw: float) -> np.ndarray:
    """3x3 rotation about z by ``yaw`` (radians)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotz_many(yaw: np.ndarray) -> np.ndarray:
    """:func:`rotz` of each of the angles ``yaw`` ``(n,)`` (radians), ``(n, 3, 3)``."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((len(yaw), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def _links(
    A: np.ndarray, L: np.ndarray, state: np.ndarray, tag_idx: np.ndarray, anc_idx: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per link at ``state``: the rotated lever arm of its tag and the vector from its
    anchor to the tag ``(m, 3)``, and that vector's length ``(m,)`` (metres)."""
    lever, diff, dist = _links_many(
        A[anc_idx][None], np.asarray(L)[None], np.asarray(state, dtype=float)[None], tag_idx
    )
    return lever[0], diff[0], dist[0]


def _links_many(
    A_link: np.ndarray, L: np.ndarray, states: np.ndarray, tag_idx: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_links` of ``V`` platforms with the same links: each with its links'
    anchors ``A_link`` ``(V, m, 3)``, its tags' lever arms ``L`` ``(V, tags, 3)`` and
    its state ``states`` ``(V, 4)``; ``(V, m, 3)``, ``(V, m, 3)`` and ``(V, m)``."""
    lever = (L @ np.swapaxes(rotz_many(states[:, 3]), -1, -2))[:, tag_idx]
    diff = states[:, None, :3] + lever - A_link
    # np.linalg.norm's sum, without its wrapper (a solve makes thousands of these)
    return lever, diff, np.sqrt(np.add.reduce(diff * diff, axis=-1))


def jacobians_many(
    A_link: np.ndarray, L: np.ndarray, states: np.ndarray, tag_idx: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`platform_jacobian` ``(V, m, 4)`` and :func:`platform_ranges` ``(V, m)`` of
    ``V`` platforms with the same links at once (:func:`_links_many`'s arguments;
    metres, radians)."""
    lever, diff, dist = _links_many(A_link, L, states, tag_idx)
    return _jacobian(lever, diff, dist), dist


def platform_ranges(
    A: np.ndarray, L: np.ndarray, state: np.ndarray, tag_idx: np.ndarray, anc_idx: np.ndarray
) -> np.ndarray:
    """Predicted ranges (metres) of the tag-anchor pairs ``(tag_idx, anc_idx)`` at ``state``."""
    return _links(A, L, state, tag_idx, anc_idx)[2]


def platform_jacobian(
    A: np.ndarray, L: np.ndarray, state: np.ndarray, tag_idx: np.ndarray, anc_idx: np.ndarray
) -> np.ndarray:
    """(m, 4) derivative of the ranges by ``x, y, z`` (1) and ``yaw`` (metres per radian)."""
    return _jacobian(*_links(A, L, state, tag_idx, anc_idx))


def _jacobian(lever: np.ndarray, diff: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(..., m, 4) the ranges' derivative from :func:`_links`: the unit vectors ``u``
    from the anchors, and in yaw ``u . dp/dyaw`` with ``dp/dyaw = (-lever_y, lever_x, 0)``."""
    J = np.empty((*diff.shape[:-1], 4))
    u = J[..., :3]
    np.divide(diff, np.maximum(dist, 1e-9)[..., None], out=u)
    J[..., 3] = u[..., 1] * lever[..., 0] - u[..., 0] * lever[..., 1]
    return J


def range_curvature(
    A: np.ndarray, L: np.ndarray, state: np.ndarray, tag_idx: np.ndarray, anc_idx: np.ndarray
) -> np.ndarray:
    """(m, 4, 4) second derivative of the ranges by ``x, y, z, yaw`` (1/metres, metres
    per radian squared, 1 per radian).

    With ``G = [I | dp/dyaw]`` the tag's derivative and ``u`` the unit vector to it:
    ``G^T (I - u u^T) G / range``, plus ``u . d2p/dyaw2`` in yaw-yaw.
    """
    lever, diff, dist = _links(A, L, state, tag_idx, anc_idx)
    dist = np.maximum(dist, 1e-9)
    u = diff / dist[:, None]
    G = np.zeros((len(diff), 3, 4))
    G[:, [0, 1, 2], [0, 1, 2]] = 1.0
    G[:, 0, 3], G[:, 1, 3] = -lever[:, 1], lever[:, 0]
    Gu = np.einsum("mi,mij->mj", u, G)
    out = (np.einsum("mij,mik->mjk", G, G) - Gu[:, :, None] * Gu[:, None, :]) / dist[:, None, None]
    out[:, 3, 3] -= np.sum(u[:, :2] * lever[:, :2], axis=1)
    return out


_SCATTER = np.zeros((4, 16))
"""Where the four sums of :func:`_weighted_curvature` go in the flattened 4x4."""
_SCATTER[0, [0, 5, 10]] = 1.0  # sum a, on the x, y, z diagonal
_SCATTER[1, [3, 12]] = 1.0  # sum a g_x, x-yaw
_SCATTER[2, [7, 13]] = 1.0  # sum a g_y, y-yaw
_SCATTER[3, 15] = 1.0  # yaw-yaw


def _weighted_curvature(
    lever: np.ndarray, dist: np.ndarray, weight: np.ndarray, J: np.ndarray
) -> np.ndarray:
    """``sum_m weight_m`` times :func:`range_curvature` of link ``m`` (..., 4, 4), in closed form.

    With ``G = [I | g]`` (``g = dp/dyaw = (-lever_y, lever_x, 0)``, :func:`_links`)
    and ``J = G^T u`` the Jacobian's rows (:func:`_jacobian`; its first three
    columns are the unit vectors ``u``):
    ``sum a G^T G = [[sum a I, sum a g], [sum a g^T, sum a |g|^2]]`` and
    ``sum a (G^T u)(G^T u)^T = J^T diag(a) J`` with ``a = weight / range``, and
    ``u . d2p/dyaw2 = -(u_x lever_x + u_y lever_y)`` in yaw-yaw; no (m, 4, 4)
    stack (a platform's Newton solve makes thousands of these a run). Leading
    axes (``lever (..., m, 3)``, ``dist`` and ``weight (..., m)``, ``J (..., m, 4)``)
    are problems solved together.
    """
    a = weight / np.maximum(dist, 1e-9)
    x, y = lever[..., 0], lever[..., 1]
    K = np.empty((*x.shape, 4))
    K[..., 0] = 1.0
    np.negative(y, out=K[..., 1])
    K[..., 2] = x
    # a |g|^2 - weight u . (x, y) = a (|g|^2 - range u . (x, y))
    K[..., 3] = x * x + y * y - np.maximum(dist, 1e-9) * (J[..., 0] * x + J[..., 1] * y)
    sums = (a[..., None, :] @ K)[..., 0, :]
    out = (sums @ _SCATTER).reshape(*sums.shape[:-1], 4, 4)
    out -= J.swapaxes(-1, -2) @ (J * a[..., None])
    return out


def platform_information(
    A: np.ndarray,
    L: np.ndarray,
    s: np.ndarray,
    tag_idx: np.ndarray,
    anc_idx: np.ndarray,
    state: np.ndarray,
    heading_prior: tuple[float, float] | None,
) -> np.ndarray:
    """4x4 information of ``x, y, z, yaw`` from white ranges of sd ``s`` (and the heading prior)."""
    J = platform_jacobian(A, L, state, tag_idx, anc_idx)
    return information_of(J, s, heading_prior)


def information_of(
    J: np.ndarray, s: np.ndarray, heading_prior: tuple[float, float] | None
) -> np.ndarray:
    """Information ``(..., 4, 4)`` of ``x, y, z, yaw`` from ranges with Jacobian ``J``
    ``(..., m, 4)`` and white sd ``s`` ``(..., m)`` (metres), and the heading prior:
    of one fix, or of a stack of fixes with the same prior."""
    info = np.swapaxes(J, -1, -2) @ (J / s[..., None] ** 2)
    if heading_prior is not None:
        info[..., 3, 3] += 1.0 / heading_prior[1] ** 2
    return info


def platform_newton(
    A: np.ndarray,
    L: np.ndarray,
    d: np.ndarray,
    s: np.ndarray,
    tag_idx: np.ndarray,
    anc_idx: np.ndarray,
    state: np.ndarray,
    heading_prior: tuple[float, float] | None,
    max_iter: int,
) -> tuple[np.ndarray, int, bool]:
    """Damped Newton on the ranges ``d``: the state, the iterations, whether it converged.

    Newton's step where its Hessian is positive definite, else Gauss-Newton's;
    each step is scaled back (halved, up to 7 times) until it lowers the cost; the
    solve has converged when a step is negligible against its own uncertainty
    (:func:`platform_newton_batch` with one problem).

    Raises
    ------
    LocalizationError
        The normal matrix is singular (the geometry does not determine the pose).
    """
    prior = np.zeros((1, 2))
    if heading_prior is not None:
        prior[0] = heading_prior[0], 1.0 / heading_prior[1] ** 2
    states, iterations, converged, solved = platform_newton_batch(
        A[anc_idx][None], L[tag_idx][None], np.asarray(d, dtype=float)[None],
        1.0 / np.asarray(s, dtype=float)[None] ** 2, np.asarray(state, dtype=float)[None],
        prior, max_iter,
    )  # fmt: skip
    if not solved[0]:
        raise LocalizationError(UNDETERMINED)
    return states[0], int(iterations[0]), bool(converged[0])


def platform_newton_batch(
    A_link: np.ndarray,
    L_link: np.ndarray,
    d: np.ndarray,
    weight: np.ndarray,
    starts: np.ndarray,
    heading_prior: np.ndarray,
    max_iter: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Damped Newton of ``B`` problems at once, each over its own links.

    Problem ``b`` fits ``x, y, z, yaw`` (its anchors' frame, metres and radians)
    to the link ranges ``d[b]`` with the weights ``weight[b]`` (``1 / s^2``; 0
    for a link it leaves out, or padding) from ``starts[b]``; its links' anchors
    and lever arms are ``A_link[b]`` and ``L_link[b]`` (m, 3). ``heading_prior``
    is ``(B, 2)``: the prior's yaw and its weight ``1 / sigma^2`` (0 for none).
    Per problem: Newton's step where its Hessian is positive definite (beyond
    ``1e-9`` of the normal matrix's trace), else Gauss-Newton's; the full step
    if it lowers the cost, else the first of its halvings (up to 7) that does
    (none: the problem stops, not converged); converged when a step is
    negligible against its own uncertainty (``step^T N step < 1e-10`` or
    ``|step| < 1e-8``). The problems share each iteration's array operations,
    so a few hundred solve in about the time of a few. A finished problem
    keeps its state.

    Returns
    -------
    tuple
        ``(B, 4)`` states, ``(B,)`` iterations, ``(B,)`` converged and ``(B,)``
        solved: ``False`` where the normal matrix was singular (the geometry does
        not determine the pose; the state is the last iterate).
    """
    state = np.array(starts, dtype=float)
    B = len(state)
    prior_yaw, prior_w = heading_prior[:, 0], heading_prior[:, 1]
    with_prior = bool(np.any(prior_w > 0))
    L_c, L_s, L_z = _lever_basis(L_link)
    scales = 0.5 ** np.arange(8)
    eye = np.eye(4)

    def links(x: np.ndarray, k: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:func:`_rotated_links` at ``x`` ``(B, ..., 4)``; ``k`` indexes the per-link
        arrays to broadcast with ``x``."""
        return _rotated_links(x, A_link[k], L_c[k], L_s[k], L_z[k])

    def cost_of(x: np.ndarray, dist: np.ndarray, k: tuple) -> np.ndarray:
        """Weighted squared residuals at ``x`` plus the heading prior's term."""
        r = d[k] - dist
        c = np.add.reduce(weight[k] * r * r, axis=-1)
        if with_prior:
            c += prior_w[k] * _wrap(prior_yaw[k] - x[..., 3]) ** 2
        return c

    now = (slice(None),)
    lever, diff, dist = links(state, now)
    cost = cost_of(state, dist, now)
    iterations = np.full(B, max_iter)
    converged = np.zeros(B, dtype=bool)
    solved = np.ones(B, dtype=bool)
    active = np.ones(B, dtype=bool)
    for iteration in range(1, max_iter + 1):
        J = _jacobian(lever, diff, dist)
        r = d - dist
        Wj = J * weight[..., None]
        M = J.swapaxes(-1, -2) @ Wj
        g = (Wj.swapaxes(-1, -2) @ r[..., None])[..., 0]
        if with_prior:
            M[:, 3, 3] += prior_w
            g[:, 3] += prior_w * _wrap(prior_yaw - state[:, 3])
        H = M - _weighted_curvature(lever, dist, r * weight, J)
        shift = 1e-9 * np.trace(M, axis1=1, axis2=2)
        try:  # positive definite beyond the shift: a Cholesky factor exists (all, mostly)
            np.linalg.cholesky(H - shift[:, None, None] * eye)
            newton = np.ones(B, dtype=bool)
        except np.linalg.LinAlgError:
            newton = np.linalg.eigvalsh(H)[:, 0] > shift
        # a finished problem solves with I: a singular one must not hold the others up
        H = np.where(newton[:, None, None], H, M)
        H = np.where(active[:, None, None], H, eye)
        step, ok = _solve_each(H, g)
        failed = active & ~ok
        solved[failed], iterations[failed] = False, iteration
        quad = (step[:, None, :] @ M @ step[:, :, None])[:, 0, 0]
        small = (quad < 1e-10) | (np.sqrt(np.add.reduce(step * step, axis=1)) < 1e-8)
        done = active & ok & small
        converged[done], iterations[done] = True, iteration
        active &= ok & ~small
        if not active.any():
            break
        # the full step first; the halved ones only where it does not lower the cost
        trial = state + step
        t_lever, t_diff, t_dist = links(trial, now)
        new = cost_of(trial, t_dist, now)
        take = active & (new <= cost)
        state[take], cost[take] = trial[take], new[take]
        lever[take], diff[take], dist[take] = t_lever[take], t_diff[take], t_dist[take]
        back = np.flatnonzero(active & ~take)
        if back.size:
            k = (back, None)
            trials = state[k] + scales[1:, None] * step[k]
            b_lever, b_diff, b_dist = links(trials, k)
            b_new = cost_of(trials, b_dist, k)
            lower = b_new <= cost[k]
            first = np.argmax(lower, axis=1)
            found = lower[np.arange(back.size), first]
            iterations[back[~found]] = iteration  # no scale lowers the cost: not converged
            active[back[~found]] = False
            pick, rows_b = (np.flatnonzero(found), first[found]), back[found]
            state[rows_b], cost[rows_b] = trials[pick], b_new[pick]
            lever[rows_b], diff[rows_b], dist[rows_b] = b_lever[pick], b_diff[pick], b_dist[pick]
        if not active.any():
            break
    return state, iterations, converged, solved


def platform_jacobians(
    A_link: np.ndarray, L_link: np.ndarray, states: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`platform_jacobian` and :func:`platform_ranges` of ``B`` problems, each over
    its own links: ``(B, m, 4)`` and ``(B, m)`` at ``states`` ``(B, 4)``, for links
    with anchors ``A_link`` and lever arms ``L_link`` ``(B, m, 3)`` (metres)."""
    lever, diff, dist = _rotated_links(states, A_link, *_lever_basis(L_link))
    return _jacobian(lever, diff, dist), dist


def _lever_basis(L_link: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``L_c, L_s, L_z`` with the lever arm rotated by ``yaw`` ``cos(yaw) L_c + sin(yaw) L_s
    + L_z`` (per link, ``(..., m, 3)``)."""
    L_c = L_link * np.array([1.0, 1.0, 0.0])
    L_s = L_link[..., [1, 0, 2]] * np.array([-1.0, 1.0, 0.0])
    L_z = L_link * np.array([0.0, 0.0, 1.0])
    return L_c, L_s, L_z


def _rotated_links(
    x: np.ndarray, A_link: np.ndarray, L_c: np.ndarray, L_s: np.ndarray, L_z: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotated lever arms and anchor-to-tag vectors ``(..., m, 3)`` and ranges ``(..., m)``
    at the states ``x`` ``(..., 4)`` (:func:`_lever_basis`; metres)."""
    yaw = x[..., 3, None, None]
    lever = np.cos(yaw) * L_c + np.sin(yaw) * L_s + L_z
    diff = (x[..., None, :3] - A_link) + lever
    return lever, diff, np.sqrt(np.add.reduce(diff * diff, axis=-1))


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles (radians) wrapped to ``(-pi, pi]`` as :func:`platform_newton` wraps them."""
    return np.angle(np.exp(1j * angle))


def _solve_each(H: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``H^-1 g`` per problem ``(B, 4)`` and whether it could be solved (``H`` not singular)."""
    try:
        return np.linalg.solve(H, g[..., None])[..., 0], np.ones(len(H), dtype=bool)
    except np.linalg.LinAlgError:
        step, ok = np.zeros_like(g), np.ones(len(H), dtype=bool)
        for b in range(len(H)):  # only when one of them is singular: find which
            try:
                step[b] = np.linalg.solve(H[b], g[b])
            except np.linalg.LinAlgError:
                ok[b] = False
        return step, ok
