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

from fabflow.errors import LocalizationError
from fabflow.positioning.integrity import (
    POWER,
    Integrity,
    TestResult,
    chi2_quantile,
    global_passes,
    noncentrality,
)
from fabflow.positioning.uwb_platform_adjustment import PlatformAdjustment, fit_many, reflected
from fabflow.positioning.uwb_platform_model import platform_ranges, rotz

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
    Baarda's ``lambda_0`` (:func:`~fabflow.positioning.integrity.noncentrality`
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
    start, h = reflected(adj, use, state)
    try:
        mirror, _, converged = adj.fit(use, start)
    except LocalizationError:
        return {"passed": True, "plane_distance_m": h}
    return _judged(adj, use, state, mirror, converged, h, tests)


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
    starts = [reflected(cases[searches[i][0]][0], searches[i][1], near[i]) for i in fixed]
    mirrors, _, mirror_converged, mirror_solved = fit_many(
        [
            (cases[searches[i][0]][0], searches[i][1], start)
            for i, (start, _) in zip(fixed, starts, strict=True)
        ]
    )
    for k, i in enumerate(fixed):
        c, rest = searches[i]
        adj, use, state = cases[c]
        if not mirror_solved[k]:
            continue
        check = _judged(
            adj, rest, near[i], mirrors[k], bool(mirror_converged[k]), starts[k][1],
            decision_only=True,
        )  # fmt: skip
        if check["passed"]:
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


def _judged(
    adj: PlatformAdjustment,
    use: np.ndarray,
    state: np.ndarray,
    mirror: np.ndarray,
    converged: bool,
    plane_distance: float,
    tests: TestResult | None = None,
    decision_only: bool = False,
) -> dict[str, Any]:
    """:func:`mirror_check`'s verdict on the fit ``mirror`` (converged or not) made from
    the reflection of the fix ``state``, ``plane_distance`` metres from the anchors' plane.

    With ``decision_only``, a mirror fit that did not converge or came back to
    the fix is reported as ``passed`` without its tests (they cannot change that).
    """
    out: dict[str, Any] = {"passed": True, "plane_distance_m": plane_distance}
    info = adj.information(use, state)
    if not adj.heading_observed:
        info = info[:3, :3]
    cov = np.linalg.pinv(info)[:3, :3]
    dp = mirror[:3] - state[:3]
    distinct = float(dp @ np.linalg.pinv(cov) @ dp) > chi2_quantile(3, adj.alpha)
    if decision_only and not (converged and distinct):
        return out
    # the global tests decide; the w-tests are not needed
    redundancy, statistic, threshold = adj.global_test(use, mirror)
    if tests is not None:
        main_statistic, n_hypotheses = tests.statistic, len(tests.labels)
    else:
        main_statistic = adj.global_test(use, state)[1]
        n_hypotheses = adj.n_hypotheses(use)
    worse_by = statistic - main_statistic
    limit = noncentrality(adj.alpha / max(n_hypotheses, 1), POWER, 1)
    global_passed = global_passes(redundancy, statistic, threshold)
    out.update(
        statistic=statistic,
        threshold=threshold,
        worse_by=worse_by,
        limit=limit,
        offset_m=[float(x) for x in dp],
        distinct=distinct,
        passed=not (converged and distinct and global_passed and worse_by < limit),
    )
    return out
