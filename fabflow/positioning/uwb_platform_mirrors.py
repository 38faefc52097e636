"""Mirror solutions of a standing platform's UWB fix: the one the ranges allow, and the ones
one anchor's bias would select unseen.

Anchors nearly in one plane give the same ranges to a point and to its mirror
image through their plane. :func:`mirror_check` asks whether the fix's mirror
image fits as well; :func:`hidden_mirrors` whether leaving out one anchor
leaves such a pair (a bias on that anchor then selects the mirror without any
test failing). :func:`hidden_mirrors_batch` searches many fixes at once (a
simulated run's visits): its two rounds of fits, without each anchor and from
their mirror images, are each one batched Newton solve
(:func:`~fabflow.positioning.uwb_platform_adjustment.fit_many`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from fabflow.positioning.adjustment_tests import (
    POWER,
    TestResult,
    chi2_quantile,
    global_passes,
    noncentrality,
)
from fabflow.positioning.integrity import Integrity
from fabflow.positioning.uwb_platform_adjustment import (
    PlatformAdjustment,
    fit_many,
    padded_links,
    reflected,
)
from fabflow.positioning.uwb_platform_model import platform_jacobians, platform_ranges, rotz

MirrorCase = tuple[PlatformAdjustment, np.ndarray, np.ndarray]
"""A fix to search: its adjustment, the links it uses (mask) and its state ``x, y, z, yaw``."""


def mirror_check(
    adj: PlatformAdjustment, use: np.ndarray, state: np.ndarray, tests: TestResult | None = None
) -> dict[str, Any]:
    """Whether the tags' reflection through the plane of the anchors used fits as well.

    Anchors nearly in one plane (three always are; A1-A3 at one height once A4
    is left out) give the same ranges to a point and to its mirror image
    through their plane: the height above them is then not determined by the
    ranges. The check reflects the tags' centroid through the anchors'
    best-fit plane, fits the pose again from there (:meth:`PlatformAdjustment.fit`,
    the heading free to follow) and tests it. The fix is ambiguous when that fit
    converges to a different pose (the difference in ``x, y, z`` beyond the
    chi-square(3) critical value at ``alpha`` of the fix's own covariance),
    passes its global test, and fits the ranges worse than the fix by less than
    Baarda's ``lambda_0`` (:func:`~fabflow.positioning.adjustment_tests.noncentrality`
    at the w-tests' level and ``POWER``, one degree of freedom: 22.8 for 12
    hypotheses at ``alpha`` = 0.001), the misfit a just-detectable bias leaves.
    A mirror that much worse is told apart by the ranges (the level platform,
    the anchors off their plane); one within it is not.

    ``tests``, the tests of the ranges ``use`` at ``state`` when the caller has
    them (:meth:`PlatformAdjustment.tests`), saves computing them again.

    Returns
    -------
    dict
        ``passed`` (no second solution), ``plane_distance_m`` (the tags'
        centroid from the anchors' plane), and, when a mirror fit was made,
        ``statistic``, ``threshold`` (its global test), ``worse_by`` (its
        statistic minus the fix's) and ``limit`` (``lambda_0``), ``offset_m``
        (``x, y, z`` of the mirror fit minus the fix, metres), ``distinct``.
    """
    return mirror_checks([(adj, use, state, tests)])[0]


def mirror_checks(
    cases: Sequence[tuple[PlatformAdjustment, np.ndarray, np.ndarray, TestResult | None]],
) -> list[dict[str, Any]]:
    """:func:`mirror_check` of every ``(adjustment, use, state, tests)``, the mirror fits
    solved together (:func:`~fabflow.positioning.uwb_platform_adjustment.fit_many`)."""
    return _mirror_fits(cases)[0]


def _mirror_fits(
    cases: Sequence[tuple[PlatformAdjustment, np.ndarray, np.ndarray, TestResult | None]],
    decision_only: bool = False,
) -> tuple[list[dict[str, Any]], np.ndarray]:
    """:func:`mirror_checks` (``decision_only`` as :func:`_verdicts` takes it) and the
    mirror fits' states ``(n, 4)``."""
    starts = [reflected(adj, use, state) for adj, use, state, _ in cases]
    mirrors, _, converged, solved = fit_many(
        [(c[0], c[1], start) for c, (start, _) in zip(cases, starts, strict=True)]
    )
    checks = _verdicts(
        [
            (adj, use, state, mirrors[k], bool(converged[k]), starts[k][1])
            for k, (adj, use, state, _) in enumerate(cases)
        ],
        [c[3] for c in cases],
        decision_only,
    )
    # no mirror fit (a singular normal matrix there): no second solution
    checks = [
        check if solved[k] else {"passed": True, "plane_distance_m": starts[k][1]}
        for k, check in enumerate(checks)
    ]
    return checks, mirrors


def hidden_mirrors(
    adj: PlatformAdjustment, use: np.ndarray, state: np.ndarray
) -> list[dict[str, Any]]:
    """Mirror solutions one anchor's bias would select without failing a test.

    When the anchors but one lie nearly in one plane (A1-A3 at one height, A4
    above), that one alone tells the side: a bias on it as large as the
    difference of its ranges between the two sides (about 0.5 m in the cabin)
    moves the fix to the mirror image, and the tests, which see a consistent
    solution, pass. The linear reliability (MDB, protection level) cannot see
    such a jump. For every anchor used whose removal leaves three or more, the
    fit without it (from the fix) is checked with :func:`mirror_check`; a second
    solution found there is such a hidden mirror.

    Returns
    -------
    list of dict
        Per hidden mirror: ``anchor`` (its name), ``bias_m`` (the
        mean residual of its ranges at the mirror: the bias that selects it),
        ``base_shift_m`` (``x, y, z`` of the arm base at the mirror minus at the
        fix, metres).
    """
    return hidden_mirrors_batch([(adj, use, state)])[0]


def hidden_mirrors_batch(cases: Sequence[MirrorCase]) -> list[list[dict[str, Any]]]:
    """:func:`hidden_mirrors` of every case, the fits of all of them solved together.

    Returns
    -------
    list of list of dict
        Per case, its hidden mirrors as :func:`hidden_mirrors` gives them.
    """
    searches: list[tuple[int, np.ndarray]] = []  # (case, links without one anchor)
    for c, (adj, use, state) in enumerate(cases):
        for j in adj.anchors_used(use):
            rest = use & (adj.anc_idx != j)
            if adj.n_anchors_used(rest) >= 3 and adj.determined(rest, state):
                searches.append((c, rest))
    found: list[list[dict[str, Any]]] = [[] for _ in cases]
    if not searches:
        return found
    near, _, converged, solved = fit_many([(cases[c][0], r, cases[c][2]) for c, r in searches])
    fixed = np.flatnonzero(converged & solved)  # no fix without the anchor: nothing to mirror
    checks, mirrors = _mirror_fits(
        [(cases[searches[i][0]][0], searches[i][1], near[i], None) for i in fixed],
        decision_only=True,
    )
    for k, i in enumerate(fixed):
        c, rest = searches[i]
        adj, use, state = cases[c]
        if checks[k]["passed"]:
            continue
        mask = use & ~rest
        residual = adj.raw_mean[mask] - platform_ranges(
            adj.anchors, adj.lever_arms, mirrors[k], adj.tag_idx[mask], adj.anc_idx[mask]
        )
        shift = _base(adj, mirrors[k]) - _base(adj, state)
        found[c].append(
            {
                "anchor": adj.ids[int(adj.anc_idx[mask][0])],
                "bias_m": float(np.average(residual, weights=adj.count[mask])),
                "base_shift_m": [float(x) for x in shift],
            }
        )
    return found


def with_hidden_mirrors(integrity: Integrity, hidden: list[dict[str, Any]]) -> Integrity:
    """The record with the hidden mirrors, its protection level raised to their base shift.

    A hidden mirror (:func:`hidden_mirrors`) is a fault the tests cannot see at
    any size; the base shift it causes (metres, horizontal and vertical) bounds
    the protection level from below.
    """
    if not hidden:
        return integrity
    pl = dict(integrity.protection_level)
    for m in hidden:
        dx, dy, dz = m["base_shift_m"]
        pl["horizontal"] = max(pl.get("horizontal") or 0.0, math.hypot(dx, dy))
        pl["vertical"] = max(pl.get("vertical") or 0.0, abs(dz))
    return replace(integrity.with_checks(mirror_by_one_fault=hidden), protection_level=pl)


def _base(adj: PlatformAdjustment, state: np.ndarray) -> np.ndarray:
    """The arm base position (metres, anchors' frame) at ``state``."""
    return state[:3] + rotz(float(state[3])) @ adj.lever


MirrorFit = tuple[PlatformAdjustment, np.ndarray, np.ndarray, np.ndarray, bool, float]
"""A mirror fit to judge: adjustment, links used, the fix, the fit from its reflection,
whether that converged, and the tags' distance from the anchors' plane (metres)."""


def _verdicts(
    fits: Sequence[MirrorFit],
    tests: Sequence[TestResult | None],
    decision_only: bool = False,
) -> list[dict[str, Any]]:
    """:func:`mirror_check`'s verdict on each mirror fit, all of them at once.

    ``tests``: per fit, the tests of the fix when the caller has them. With
    ``decision_only``, a mirror fit that did not converge or came back to the
    fix is reported as ``passed`` without its tests (they cannot change that).
    The global tests' statistic ``v^T Q^-1 v`` is Woodbury's with
    ``Q = diag(s^2) + U diag(b^2) U^T``: each link has one anchor, so
    ``U^T diag(s^-2) U`` is diagonal and the statistic is
    ``sum v^2 / s^2 - sum_a z_a^2 / (1 / b_a^2 + c_a)`` with ``z_a``, ``c_a`` the
    sums of ``v / s^2`` and ``1 / s^2`` over anchor ``a``'s links.
    """
    links = padded_links([(f[0], f[1]) for f in fits])
    fix = np.array([f[2] for f in fits], dtype=float).reshape(-1, 4)
    mirror = np.array([f[3] for f in fits], dtype=float).reshape(-1, 4)
    converged = np.array([f[4] for f in fits], dtype=bool)
    observed = np.array([f[0].heading_observed for f in fits], dtype=bool)
    # the fix's covariance in x, y, z from its white ranges (and the heading prior)
    J, _ = platform_jacobians(links["A_link"], links["L_link"], fix)
    info = J.swapaxes(-1, -2) @ (J * links["weight"][..., None])
    info[:, 3, 3] += [
        0.0 if f[0].heading_prior is None else f[0].heading_prior[1] ** -2 for f in fits
    ]
    info[~observed, 3, :] = info[~observed, :, 3] = 0.0  # the heading is not a parameter
    cov = np.linalg.pinv(info)[:, :3, :3]
    dp = mirror[:, :3] - fix[:, :3]
    distance = (dp[:, None, :] @ np.linalg.pinv(cov) @ dp[:, :, None])[:, 0, 0]
    distinct = distance > np.array([chi2_quantile(3, f[0].alpha) for f in fits])
    out: list[dict[str, Any]] = [{"passed": True, "plane_distance_m": f[5]} for f in fits]
    judged = np.flatnonzero(converged & distinct) if decision_only else np.arange(len(fits))
    if judged.size == 0:
        return out
    # the global tests decide; the w-tests are not needed
    redundancy, statistic = _global_tests(links, judged, mirror[judged], observed, fits)
    main = np.array([np.nan if tests[i] is None else tests[i].statistic for i in judged])
    untested = np.flatnonzero(np.isnan(main))
    if untested.size:
        main[untested] = _global_tests(
            links, judged[untested], fix[judged[untested]], observed, fits
        )[1]
    for k, i in enumerate(judged):
        adj, use = fits[i][0], fits[i][1]
        n_hypotheses = adj.n_hypotheses(use) if tests[i] is None else len(tests[i].labels)
        r = int(redundancy[k])
        threshold = chi2_quantile(r, adj.alpha) if r > 0 else math.inf
        worse_by = float(statistic[k] - main[k])
        limit = noncentrality(adj.alpha / max(n_hypotheses, 1), POWER, 1)
        global_passed = global_passes(r, float(statistic[k]), threshold)
        out[i].update(
            statistic=float(statistic[k]),
            threshold=threshold,
            worse_by=worse_by,
            limit=limit,
            offset_m=[float(x) for x in dp[i]],
            distinct=bool(distinct[i]),
            passed=not (converged[i] and distinct[i] and global_passed and worse_by < limit),
        )
    return out


def _global_tests(
    links: dict[str, np.ndarray],
    rows: np.ndarray,
    states: np.ndarray,
    observed: np.ndarray,
    fits: Sequence[MirrorFit],
) -> tuple[np.ndarray, np.ndarray]:
    """Redundancy and statistic of the global test of the fits ``rows`` at ``states``
    (:meth:`PlatformAdjustment.global_test`, see :func:`_verdicts`)."""
    use = links["use"][rows]
    J, dist = platform_jacobians(links["A_link"][rows], links["L_link"][rows], states)
    J *= use[..., None]
    J[~observed[rows], :, 3] = 0.0
    redundancy = use.sum(axis=1) - np.linalg.matrix_rank(J)
    v = np.where(use, links["d"][rows] - dist, 0.0)
    w = links["weight"][rows]
    statistic = np.einsum("bm,bm,bm->b", v, v, w)
    n_anchors = max(len(fits[i][0].anchors) for i in rows)
    bias = np.zeros((len(rows), n_anchors))
    for k, i in enumerate(rows):
        bias[k, : len(fits[i][0].anchors)] = fits[i][0].bias_sigma
    at = (links["anchor"][rows][..., None] == np.arange(n_anchors)) & use[..., None]
    z = np.einsum("bma,bm->ba", at, v * w)
    c = np.einsum("bma,bm->ba", at, w)
    reached = c > 0
    shared = np.any(reached & (bias > 0), axis=1)  # else no shared errors in Q
    core = 1.0 / np.maximum(bias, 1e-9) ** 2 + c
    statistic -= np.where(shared, np.sum(np.where(reached, z * z / core, 0.0), axis=1), 0.0)
    return redundancy, statistic
