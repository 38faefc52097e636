"""Errors that ICP's residuals share and cannot show, and the covariance rows they add.

Three such errors move many correspondences by one unknown amount, which no
residual scatter reveals:

* a laser channel's range bias moves every scan point it measured along that
  point's ray from the sensor (``rays``);
* a rigid part of the target, such as a block of the as-built structure added to
  a map at its design pose, moves all its points together (``parts``, per axis);
* a mapping run's channel bias moves every map point that channel measured along
  the ray it was measured on (``map_rays``).

For a group ``k`` of correspondences sharing an error of standard deviation
``s``, :func:`shared_rows` gives ``g_k = s sum_{i in k} w_i J_i^T dr_i/db``, the
change of the weighted normal equations' right-hand side per unit of that error;
:func:`fabflow.positioning.icp.icp` adds ``N^-1 (sum_k g_k g_k^T) N^-1`` to the
pose covariance. Point-to-plane residuals ``r_i = n_i . (p_i - q_i)`` only: a
point-to-point residual slides along a surface and shows a shared error only
across it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from fabflow.errors import InputError, UnsupportedError

FloatArray = NDArray[np.float64]
Groups = NDArray[np.integer]

MAX_SHARED_SIGMA = 1.0
"""Largest standard deviation (metres) of an error shared by a group of points (a
channel's range bias, a map part's shift)."""


@dataclass(frozen=True)
class SharedErrors:
    """The validated shared errors of one registration (each ``None`` when absent).

    Attributes
    ----------
    rays
        ``(groups (N,), sigma)``: the source points' channel and its range bias
        (metres, along the ray from the source frame's origin).
    parts
        ``(groups (M,), sigma)``: the target points' rigid part (``-1``: none) and
        its shift per axis (metres).
    map_rays
        ``(groups (M,), directions (M, 3), sigma)``: the channel each target point
        was measured by (``-1``: none), the unit direction it was measured along
        (target frame) and the channel's range bias (metres).
    """

    rays: tuple[Groups, float] | None = None
    parts: tuple[Groups, float] | None = None
    map_rays: tuple[Groups, FloatArray, float] | None = None


def group_sums(rows: FloatArray, groups: ArrayLike) -> FloatArray:
    """The rows ``(n, c)`` summed over the distinct values of ``groups`` ``(n,)``: ``(G, c)``."""
    _, inverse = np.unique(np.ravel(groups), return_inverse=True)
    inverse = inverse.ravel()
    n = int(inverse.max()) + 1
    return np.stack(
        [np.bincount(inverse, weights=rows[:, k], minlength=n) for k in range(rows.shape[1])],
        axis=1,
    )


def _groups(
    groups: ArrayLike | None, sigma: float, size: int, plane: bool, name: str
) -> Groups | None:
    """Validated groups of an error shared by groups of ``size`` points, or ``None``
    when there is none (``name``: the parameters' prefix, for the messages; for
    ``map_rays`` its first and last items)."""
    if not (isinstance(sigma, (int, float)) and 0.0 <= sigma <= MAX_SHARED_SIGMA):
        raise InputError(f"{name}_sigma must be a number from 0 to {MAX_SHARED_SIGMA:g} m")
    if groups is None or sigma == 0:
        return None
    if not plane:
        raise UnsupportedError(
            f"{name}_groups needs point_to_plane: a point-to-point residual slides along "
            "a surface and shows a shared error only across it"
        )
    g = np.asarray(groups)
    if g.shape != (size,) or not np.issubdtype(g.dtype, np.integer):
        raise InputError(f"{name}_groups needs one integer group per point ({size})")
    return g


def shared_errors(
    plane: bool,
    n_source: int,
    n_target: int,
    rays: tuple[ArrayLike | None, float] = (None, 0.0),
    parts: tuple[ArrayLike | None, float] = (None, 0.0),
    map_rays: tuple[ArrayLike, ArrayLike, float] | None = None,
) -> SharedErrors:
    """Validate the shared errors of a registration of ``n_source`` to ``n_target``
    points (``plane``: point-to-plane residuals); see :class:`SharedErrors`.

    Raises
    ------
    InputError
        A sigma outside ``[0, MAX_SHARED_SIGMA]``, groups that are not one integer
        per point, or map directions that are not finite unit vectors, one per point.
    UnsupportedError
        A shared error with point-to-point residuals.
    """
    ray_groups = _groups(*rays, n_source, plane, "ray")
    part_groups = _groups(*parts, n_target, plane, "target")
    mapped = None
    if map_rays is not None:
        if not (isinstance(map_rays, tuple) and len(map_rays) == 3):
            raise InputError("map_rays must be (groups, directions, sigma)")
        groups, directions, sigma = map_rays
        g = _groups(groups, sigma, n_target, plane, "map_rays")
        if g is not None:
            try:
                u = np.asarray(directions, dtype=float)
            except (TypeError, ValueError):
                u = np.zeros((0, 3))
            if u.shape != (n_target, 3) or not np.all(
                np.abs(np.linalg.norm(u[g >= 0], axis=1) - 1.0) < 1e-6
            ):
                raise InputError(
                    f"map_rays directions need one unit vector per grouped point ({n_target})"
                )
            mapped = (g, u, float(sigma))
    return SharedErrors(
        rays=None if ray_groups is None else (ray_groups, float(rays[1])),
        parts=None if part_groups is None else (part_groups, float(parts[1])),
        map_rays=mapped,
    )


def shared_rows(
    errors: SharedErrors,
    Jw: FloatArray,
    normals: FloatArray,
    rays: FloatArray,
    ok: NDArray[np.bool_],
    matched: NDArray[np.intp],
) -> FloatArray | None:
    """The rows ``g_k`` (one per group, and per axis for the parts) of the shared errors.

    Parameters
    ----------
    errors
        The registration's shared errors.
    Jw
        ``(n, 6)`` the correspondences' Jacobian rows times their weights.
    normals
        ``(n, 3)`` the matched target normals.
    rays
        ``(n, 3)`` each source point's offset from the source frame's origin, in
        the target frame (metres).
    ok
        ``(N,)`` which source points found a correspondence (``n`` of them).
    matched
        ``(n,)`` the target point each one matched.
    """
    out: list[FloatArray] = []
    if errors.rays is not None:
        # the source point moves along its ray: r changes by n . u per metre
        groups, sigma = errors.rays
        u = rays / np.maximum(np.linalg.norm(rays, axis=1), 1e-12)[:, None]
        out.append(sigma * group_sums(Jw * np.einsum("ij,ij->i", u, normals)[:, None], groups[ok]))
    if errors.parts is not None:
        # a part's shift along axis a changes each residual by -n_a per metre
        groups, sigma = errors.parts
        g = groups[matched]
        on = g >= 0
        if on.any():
            out += [sigma * group_sums(Jw[on] * normals[on, a : a + 1], g[on]) for a in range(3)]
    if errors.map_rays is not None:
        # the map point moves along the ray it was measured on: r changes by -n . u
        groups, directions, sigma = errors.map_rays
        g = groups[matched]
        on = g >= 0
        if on.any():
            along = np.einsum("ij,ij->i", directions[matched[on]], normals[on])
            out.append(sigma * group_sums(Jw[on] * along[:, None], g[on]))
    return np.concatenate(out) if out else None
