"""The range model of a standing platform and its damped Newton solve.

A level platform stands at ``x, y, z, yaw`` (anchors' frame, metres and
radians); tag ``k`` sits at the lever arm ``l_k`` (platform frame), so the range
of tag ``k`` to anchor ``j`` is ``|p + R(yaw) l_k - a_j|``. Here are that
range, its first and second derivatives, the information of white ranges and
the solve; :mod:`fabflow.positioning.uwb_platform_adjustment` tests and
compares fits with them.
"""

from __future__ import annotations

import numpy as np

from fabflow.errors import LocalizationError


def rotz(yaw: float) -> np.ndarray:
    """3x3 rotation about z by ``yaw`` (radians)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _links(
    A: np.ndarray, L: np.ndarray, state: np.ndarray, tag_idx: np.ndarray, anc_idx: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per link at ``state``: the rotated lever arm of its tag and the vector from its
    anchor to the tag ``(m, 3)``, and that vector's length ``(m,)`` (metres)."""
    return _links_at(A[anc_idx], L, state, tag_idx)


def _links_at(
    A_link: np.ndarray, L: np.ndarray, state: np.ndarray, tag_idx: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_links` with each link's anchor ``A_link`` (m, 3) given."""
    lever = (L @ rotz(state[3]).T)[tag_idx]
    diff = state[:3] + lever - A_link
    # np.linalg.norm's sum, without its wrapper (a solve makes thousands of these)
    return lever, diff, np.sqrt(np.add.reduce(diff * diff, axis=1))


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
    """(m, 4) the ranges' derivative from :func:`_links`: the unit vectors ``u`` from
    the anchors, and in yaw ``u . dp/dyaw`` with ``dp/dyaw = (-lever_y, lever_x, 0)``."""
    J = np.empty((len(diff), 4))
    u = J[:, :3]
    np.divide(diff, np.maximum(dist, 1e-9)[:, None], out=u)
    J[:, 3] = u[:, 1] * lever[:, 0] - u[:, 0] * lever[:, 1]
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


def _weighted_curvature(
    lever: np.ndarray, dist: np.ndarray, weight: np.ndarray, J: np.ndarray
) -> np.ndarray:
    """``sum_m weight_m`` times :func:`range_curvature` of link ``m`` (4, 4), in closed form.

    With ``G = [I | g]`` (``g = dp/dyaw = (-lever_y, lever_x, 0)``, :func:`_links`)
    and ``J = G^T u`` the Jacobian's rows (:func:`_jacobian`; its first three
    columns are the unit vectors ``u``):
    ``sum a G^T G = [[sum a I, sum a g], [sum a g^T, sum a |g|^2]]`` and
    ``sum a (G^T u)(G^T u)^T = J^T diag(a) J`` with ``a = weight / range``; no
    (m, 4, 4) stack (a platform's Newton solve makes thousands of these a run).
    """
    a = weight / np.maximum(dist, 1e-9)
    x, y = lever[:, 0], lever[:, 1]
    out = np.zeros((4, 4))
    out[0, 0] = out[1, 1] = out[2, 2] = a.sum()
    out[0, 3] = out[3, 0] = -(a @ y)
    out[1, 3] = out[3, 1] = a @ x
    out[3, 3] = a @ (y * y + x * x)
    out -= J.T @ (J * a[:, None])
    out[3, 3] -= weight @ (J[:, 0] * x + J[:, 1] * y)
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
    info = J.T @ (J / s[:, None] ** 2)
    if heading_prior is not None:
        info[3, 3] += 1.0 / heading_prior[1] ** 2
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
    solve has converged when a step is negligible against its own uncertainty.

    Raises
    ------
    LocalizationError
        The normal matrix is singular (the geometry does not determine the pose).
    """
    state = np.array(state, dtype=float)
    weight = 1.0 / s**2

    A_link = A[anc_idx]

    def evaluate(x: np.ndarray) -> tuple[float, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The cost at ``x`` and the links there (the next iteration starts from them)."""
        links = _links_at(A_link, L, x, tag_idx)
        r = (d - links[2]) / s
        c = float(r @ r)
        if heading_prior is not None:
            c += (
                float(np.angle(np.exp(1j * (heading_prior[0] - x[3])))) ** 2 / heading_prior[1] ** 2
            )
        return c, links

    cost, links = evaluate(state)
    for iteration in range(1, max_iter + 1):
        lever, diff, dist = links
        J = _jacobian(lever, diff, dist)
        r = d - dist
        Wj = J * weight[:, None]
        M = J.T @ Wj
        g = Wj.T @ r
        if heading_prior is not None:
            w = 1.0 / heading_prior[1] ** 2
            M[3, 3] += w
            g[3] += w * (np.angle(np.exp(1j * (heading_prior[0] - state[3]))))
        # Newton's Hessian adds the ranges' curvature, which Gauss-Newton drops: with
        # residuals not small against it (height over anchors near one plane) Gauss-
        # Newton only creeps, as the per-tag fixes of positioning.uwb also find.
        H = M - _weighted_curvature(lever, dist, r * weight, J)
        if np.linalg.eigvalsh(H)[0] <= 1e-9 * np.trace(M):
            H = M
        try:
            step = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            raise LocalizationError(
                "the tag and anchor geometry does not determine the platform pose"
            ) from None
        if float(step @ M @ step) < 1e-10 or np.linalg.norm(step) < 1e-8:
            return state, iteration, True
        for scale in 0.5 ** np.arange(8):
            trial = state + scale * step
            new, trial_links = evaluate(trial)
            if new <= cost:
                state, cost, links = trial, new, trial_links
                break
        else:
            return state, iteration, False
    return state, max_iter, False
