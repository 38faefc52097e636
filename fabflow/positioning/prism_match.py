"""Which prism reading belongs to which robot point, identified by the distances between them."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import special

from fabflow.errors import LocalizationError

MAX_PERMUTED = 7
"""Up to this many points every order of the readings is tried; beyond, pairwise swaps."""
RCOND = 1e-5
"""Directions of the distances' covariance with a variance below this fraction of the
largest are left out of the test. There the distances change only to second order
(the errors squared over the distance, about a micrometre for millimetre errors a
metre apart), which the linear covariance does not hold: prisms nearly in one
plane leave up to three such directions (``2n - 3`` distances are then
independent, not ``3n - 6``), and kept in the test they raised its mean from its
degrees of freedom to over a hundred times them."""


def match_prisms(
    P: np.ndarray, M: np.ndarray, C: np.ndarray, labels: Sequence[str], alpha: float
) -> tuple[np.ndarray, dict[str, Any]]:
    """Which reading belongs to which robot point, from the distances between the points.

    Distances between prisms are the same in the robot base frame and in the
    world, so a reading given under the wrong point id shows as distances that
    do not fit. The readings are kept as given when their distances pass a
    chi-square test at ``alpha``; otherwise the one order of the readings whose
    distances fit (over every permutation up to :data:`MAX_PERMUTED` points,
    pairwise swaps beyond) is taken and reported. Two orders fitting equally
    well cannot be told apart: that is refused.

    Parameters
    ----------
    P
        (n, 3) robot points, base frame (metres).
    M
        (n, 3) measured points, world frame (metres), in the order given.
    C
        (n, 3, 3) their covariances (robot and instrument errors, m^2).
    labels
        Point names, for the report.
    alpha
        Level of the distance test.

    Returns
    -------
    order, report
        ``M[order]`` matches ``P``; the report says what was tested and done.

    Raises
    ------
    LocalizationError
        When the readings do not fit as given and several orders fit them.
    """
    n = len(P)
    if n < 4:
        return np.arange(n), {}
    identity = np.arange(n)[None]
    stat0, dof = order_statistics(P, M, C, identity)
    t0 = float(stat0[0])
    if dof == 0:  # no spread at all (zero covariances): nothing to test
        return np.arange(n), {
            "distance_test": t0,
            "threshold": 0.0,
            "dof": 0,
            "assignment": "as given",
        }
    threshold = float(special.chdtri(dof, alpha))
    report: dict[str, Any] = {"distance_test": t0, "threshold": threshold, "dof": dof}
    if t0 <= threshold:
        return np.arange(n), {**report, "assignment": "as given"}
    if n <= MAX_PERMUTED:
        orders = np.array(list(itertools.permutations(range(n))))
    else:
        swaps = [(a, b) for a in range(n) for b in range(a + 1, n)]
        orders = np.tile(np.arange(n), (len(swaps), 1))
        for k, (a, b) in enumerate(swaps):
            orders[k, [a, b]] = orders[k, [b, a]]
    stats, _ = order_statistics(P, M, C, orders)
    fits = np.flatnonzero(stats <= threshold)
    if len(fits) > 1:
        raise LocalizationError(
            f"the prism readings do not fit the robot points as given (distance test "
            f"{t0:.0f} > {threshold:.1f}) and {len(fits)} orders of the readings fit them: "
            "the prisms cannot be identified; check the point ids"
        )
    if len(fits) == 0:
        return np.arange(n), {**report, "assignment": "as given (no order fits)"}
    order = orders[fits[0]]
    moved = [f"{labels[i]} <- reading of {labels[order[i]]}" for i in range(n) if order[i] != i]
    return order, {
        **report,
        "assignment": "reassigned",
        "reassigned": "readings reassigned by their distances: " + ", ".join(moved),
        "distance_test_after": float(stats[fits[0]]),
    }


def order_statistics(
    P: np.ndarray, M: np.ndarray, C: np.ndarray, orders: np.ndarray
) -> tuple[np.ndarray, int]:
    """The distance test of each order of the readings, and its degrees of freedom.

    For the order ``o`` (``M[o]`` read as the points ``P``) the statistic is
    ``e^T cov^+ e`` of the differences ``e`` between the readings' pairwise
    distances and the points', ``cov`` their covariance (:data:`RCOND`). An
    order only permutes the pairs: its distances and their covariance are the
    readings' own, rows and columns permuted, so one eigendecomposition serves
    every order (a permuted matrix has the same eigenvalues, and its
    eigenvectors' rows permuted), and the degrees of freedom are the same for all.

    Parameters
    ----------
    P, M, C
        As :func:`match_prisms` takes them.
    orders
        (K, n) orders of the readings.

    Returns
    -------
    statistics, dof
        (K,) and one number.
    """
    n = len(P)
    iu, ju = np.triu_indices(n, 1)
    d_P = np.linalg.norm(P[iu] - P[ju], axis=1)
    diff = M[iu] - M[ju]
    d_M = np.linalg.norm(diff, axis=-1)
    u = diff / np.maximum(d_M, 1e-12)[..., None]
    # n points in space have 3n - 6 independent distances: the n(n-1)/2 measured
    # ones share points, so they are tested with their full (singular) covariance,
    # over the directions it determines (RCOND).
    # cov[p, q] = sum_k D_pk^T C_k D_qk over the readings k, D_pk = E[p, k] u_p the
    # derivative of distance p by reading k (E: +1, -1 at the pair's two points)
    D = np.zeros((len(iu), n, 3))
    D[np.arange(len(iu)), iu] = u
    D[np.arange(len(iu)), ju] = -u
    cov = np.einsum("pki,kij->pkj", D, C).reshape(len(iu), -1) @ D.reshape(len(iu), -1).T
    w, V = np.linalg.eigh(cov)
    keep = w > RCOND * w[-1]
    # the pair p of an order reads the readings' pair pair_of[o[i_p], o[j_p]]
    pair_of = np.zeros((n, n), dtype=np.intp)
    pair_of[iu, ju] = pair_of[ju, iu] = np.arange(len(iu))
    read = pair_of[orders[:, iu], orders[:, ju]]
    d_P_at = np.empty(read.shape)
    d_P_at[np.arange(len(orders))[:, None], read] = d_P[None]
    z = (d_M[None] - d_P_at) @ V[:, keep]
    return np.sum(z**2 / w[keep], axis=1), int(keep.sum())
