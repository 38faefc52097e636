"""The platform pose from UWB ranges of several tags: ``x, y, z, yaw`` and its covariance.

Tags sit at known lever arms on the platform (platform frame); every range of
every tag constrains the platform pose. :func:`locate_platform` estimates
``x, y, z, yaw`` (a level platform) jointly over all ranges by Gauss-Newton
(``wls-t``), or as the median of per-epoch fixes (``ls``, ``wls``), and tests it
as a least-squares adjustment (:mod:`fabflow.positioning.uwb_platform_adjustment`);
:func:`platform_to_base_covariance` moves the covariance to the arm base.
Metres and radians; anchors in the world frame.
"""

from __future__ import annotations

import functools
import inspect
import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from fabflow.errors import InputError, LocalizationError
from fabflow.positioning.adjustment_tests import ALPHA, TestResult
from fabflow.positioning.integrity import Integrity, identify
from fabflow.positioning.medians import nanmedian
from fabflow.positioning.uwb import (
    MIN_RANGE_FOR_WEIGHT,
    UNOBSERVED_VARIANCE,
    Method,
    Sigma,
    sigma_of,
)
from fabflow.positioning.uwb_calibration import running_median
from fabflow.positioning.uwb_platform_adjustment import (
    PlatformAdjustment,
    fit_many,
    grouped_tests,
    identify_by_refit,
)
from fabflow.positioning.uwb_platform_finish import Final, PlatformFix, finish_fixes
from fabflow.positioning.uwb_platform_mirrors import (
    hidden_mirrors_batch,
    mirror_checks,
    with_hidden_mirrors,
)
from fabflow.positioning.uwb_platform_model import UNDETERMINED
from fabflow.positioning.uwb_platform_start import (
    initial_states,
    link_means_many,
    tag_starts,
)


def locate_platform(
    anchors: np.ndarray,
    ranges: np.ndarray,
    lever_arms: np.ndarray,
    sigma: Sigma,
    method: Method = "wls-t",
    heading_prior: tuple[float, float] | None = None,
    max_iter: int = 20,
    anchor_bias_sigma: np.ndarray | None = None,
    alpha: float = ALPHA,
    anchor_ids: Sequence[str] | None = None,
    base_lever: np.ndarray | None = None,
    link_sigma: Sigma | np.ndarray | None = None,
    seeds: np.ndarray | None = None,
    search_later: bool = False,
) -> PlatformFix:
    """Estimate a standing platform's ``x, y, z, yaw`` from the ranges of its tags, and test it.

    Every tag's epochs are first multilaterated with ``method``; the median tag
    positions give the initial pose (2D Procrustes fit of the lever arms). For
    ``wls-t`` the pose is then refined by Newton's method on all ranges of all
    tags and epochs jointly, started from each tag's fix of its per-link median
    ranges (``ls`` and ``wls`` keep the median fix unless an exclusion asks for
    a new fit, which is a Newton fit). Roll and pitch
    are taken as zero (a level platform); they are not observed.

    Every range given enters the tested solution: none is trimmed by its
    residual (clean a standing platform's ranges per link beforehand, e.g. with
    :func:`~fabflow.positioning.uwb_calibration.reject_outliers_static`). The
    fix is tested as a least-squares adjustment
    (:mod:`fabflow.positioning.uwb_platform_adjustment`): the global test and a
    w-test per anchor (a bias shared by all its ranges: a mis-surveyed anchor,
    an antenna delay, a wall in the way) and per tag-anchor link. While they
    fail, each anchor and link is left out in turn and the pose fitted again and
    tested; an exclusion is made only when one of them explains the misfit (an
    anchor rather than one of its links when both do), or, when none does, one
    is clearly best (:func:`~fabflow.positioning.uwb_platform_adjustment.identify_by_refit`),
    as long as three anchors and the heading remain. Ranges left out are in
    ``integrity.excluded`` (with their number); when several anchors or links
    explain the misfit, or none does, the fix fails naming them. A fix that
    passes must also be unique: the tags' mirror image through the plane of the
    anchors used must not fit as well
    (:func:`~fabflow.positioning.uwb_platform_mirrors.mirror_check`); a
    mirror image that one anchor's bias could select unseen
    (:func:`~fabflow.positioning.uwb_platform_mirrors.hidden_mirrors`) is
    recorded as ``checks["mirror_by_one_fault"]`` and raises the protection
    level to the base shift it causes. The guard on exclusions
    (:func:`~fabflow.positioning.integrity.guard_exclusion`) is the caller's.

    Parameters
    ----------
    anchors
        (n_anchors, 3) anchor positions (metres).
    ranges
        (N, n_tags, n_anchors) calibrated ranges (metres), NaN where missing.
    lever_arms
        (n_tags, 3) tag positions in the platform frame (metres).
    sigma
        Range noise standard deviation (constant or function of range).
    method
        Estimator for the per-epoch tag fixes; ``wls-t`` also refines jointly.
    heading_prior
        ``(yaw, sigma_yaw)`` in radians; required with a single tag, optional otherwise.
    max_iter
        Gauss-Newton iteration cap.
    anchor_bias_sigma
        (n_anchors,) standard deviation (metres) of a range error shared by every
        range to an anchor (what the calibration leaves); added to the covariance,
        since averaging over epochs does not reduce it.
    alpha
        Level of the tests (global test; the w-tests share it).
    anchor_ids
        Anchor names for the integrity record (default ``A1``, ``A2``, ...).
    base_lever
        (3,) the arm base in the platform frame (metres): the protection level is
        given for the base, which a heading error moves too.
    link_sigma
        Standard deviation (metres) of a range error every range of one tag-anchor
        link shares (position-dependent multipath, which stays while the platform
        stands: :mod:`fabflow.sensors.uwb_multipath`), constant or a function of
        the range, or an ``(n_tags, n_anchors)`` array of one value per link (e.g.
        the multipath and what remains of a predicted through-material delay);
        added to each link mean's variance, since averaging over epochs does not
        reduce it. Links are taken as independent (tags farther apart than the
        multipath's correlation length).
    seeds
        (n_tags, 3) with ``wls-t``: the tags' start fixes of these ranges
        (:func:`~fabflow.positioning.uwb_platform_start.median_seeds`), when the
        caller solved them for many stations at once; computed here when None.
    search_later
        Leave the mirror checks in ``mirror_search`` for the caller, who makes
        those of many fixes at once (:func:`finish_mirror_searches`).

    Raises
    ------
    LocalizationError
        Too few valid fixes, or a single tag without a heading prior.
    """
    [(adj, state, fit, ranges_links)] = _adjustments(
        [
            {
                "anchors": anchors, "ranges": ranges, "lever_arms": lever_arms, "sigma": sigma,
                "method": method, "heading_prior": heading_prior, "max_iter": max_iter,
                "anchor_bias_sigma": anchor_bias_sigma, "alpha": alpha, "anchor_ids": anchor_ids,
                "base_lever": base_lever, "link_sigma": link_sigma, "seeds": seeds,
            }
        ]
    )  # fmt: skip
    iterations, converged = 0, True
    if fit:
        state, iterations, converged = adj.fit(np.ones(adj.d.size, dtype=bool), state)
    [fix] = finish_fixes([_tested(adj, ranges_links, state, iterations, converged)])
    return fix if search_later else finish_mirror_searches([fix])[0]


def locate_platforms(problems: Sequence[dict[str, Any]], records: bool = True) -> list[PlatformFix]:
    """:func:`locate_platform` of many standing platforms (a simulated run's visits).

    ``problems`` holds each one's arguments by name; the first fits of all of
    them are one batched Newton solve, as are their mirror checks
    (:func:`finish_mirror_searches`, which takes ``records``); the tests and
    exclusions stay each fix's own.

    Raises
    ------
    LocalizationError
        As :func:`locate_platform`, for the first platform it fails for.
    """
    prepared = _adjustments(problems)
    states = [state for _, state, _, _ in prepared]
    iterations, converged = [0] * len(prepared), [True] * len(prepared)
    fitted = [k for k, (_, _, fit, _) in enumerate(prepared) if fit]
    every = [np.ones(adj.d.size, dtype=bool) for adj, *_ in prepared]
    fits = fit_many([(prepared[k][0], every[k], states[k]) for k in fitted])
    for k, state, its, conv, solved in zip(fitted, *fits, strict=True):
        if not solved:
            raise LocalizationError(UNDETERMINED)
        states[k], iterations[k], converged[k] = state, int(its), bool(conv)
    # every fix's first tests at once: most fixes of a run pass them and need no others
    first = grouped_tests([(adj, every[k], states[k]) for k, (adj, *_) in enumerate(prepared)])
    finals = [
        _tested(adj, ranges_links, states[k], iterations[k], converged[k], first[k])
        for k, (adj, _, _, ranges_links) in enumerate(prepared)
    ]
    return finish_mirror_searches(finish_fixes(finals), records)


def _arguments(problem: dict[str, Any]) -> dict[str, Any]:
    """:func:`locate_platform`'s arguments for ``problem``, its defaults filled in (but
    ``search_later``): what :func:`_checked` takes.

    Raises
    ------
    TypeError
        For a name :func:`locate_platform` does not take, or one it needs missing.
    """
    names, defaults = _parameters()
    unknown = sorted(problem.keys() - names)
    missing = sorted(names - defaults.keys() - problem.keys())
    if unknown or missing:
        raise TypeError(
            f"locate_platform() arguments: unknown {unknown or 'none'}, missing {missing or 'none'}"
        )
    arguments = {**defaults, **problem}
    del arguments["search_later"]
    return arguments


@functools.cache
def _parameters() -> tuple[frozenset[str], dict[str, Any]]:
    """:func:`locate_platform`'s parameter names and defaults, read once (a run fills
    them in at every visit)."""
    parameters = inspect.signature(locate_platform).parameters
    defaults = {k: p.default for k, p in parameters.items() if p.default is not p.empty}
    return frozenset(parameters), defaults


Prepared = tuple[PlatformAdjustment, np.ndarray, bool, tuple[np.ndarray, np.ndarray]]
"""A problem as an adjustment: it, the start state, whether the pose is fitted before
the tests, and every finite range (metres) with its link."""


def _adjustments(problems: Sequence[dict[str, Any]]) -> list[Prepared]:
    """The problems (:func:`locate_platform`'s arguments by name) as adjustments.

    Each is checked and its tags started in turn (:func:`_checked`: the first
    that fails raises); the link means and start poses of those with the same
    ranges' shape and lever arms are then one call each (a simulated run's
    visits), each problem's what it alone would get, to the bit.
    """
    checked = [_checked(**_arguments(p)) for p in problems]
    groups: dict[tuple[Any, ...], list[int]] = {}
    for i, c in enumerate(checked):
        groups.setdefault((c["R"].shape, c["L"].tobytes()), []).append(i)
    out: list[Prepared | None] = [None] * len(problems)
    for members in groups.values():
        R = np.stack([checked[i]["R"] for i in members])
        L = checked[members[0]]["L"]
        n_tags, n_anchors = R.shape[2], R.shape[3]
        flat = np.flatnonzero(np.isfinite(R))  # each finite range's (problem, round, tag, anchor)
        d = R.ravel()[flat]
        own = flat // R[0].size
        bounds = np.searchsorted(own, np.arange(len(members) + 1))
        s = np.concatenate(
            [
                sigma_of(checked[i]["sigma"], np.maximum(d[a:b], MIN_RANGE_FOR_WEIGHT))
                for i, a, b in zip(members, bounds[:-1], bounds[1:], strict=True)
            ]
        )
        links = link_means_many(
            d, s, own, flat // n_anchors % n_tags, flat % n_anchors, len(members), n_tags,
            n_anchors,
        )  # fmt: skip
        states, observed = initial_states(
            L, np.stack([checked[i]["tags"] for i in members]),
            [checked[i]["heading_prior"] for i in members],
        )  # fmt: skip
        for n, i in enumerate(members):
            c = checked[i]
            ranges_links = (d[bounds[n] : bounds[n + 1]], links[n].pop("link"))
            out[i] = _prepared(c, links[n], states[n], bool(observed[n]), ranges_links)
    return out  # type: ignore[return-value]


def _checked(
    anchors: np.ndarray,
    ranges: np.ndarray,
    lever_arms: np.ndarray,
    sigma: Sigma,
    method: Method,
    heading_prior: tuple[float, float] | None,
    max_iter: int,
    anchor_bias_sigma: np.ndarray | None,
    alpha: float,
    anchor_ids: Sequence[str] | None,
    base_lever: np.ndarray | None,
    link_sigma: Sigma | np.ndarray | None,
    seeds: np.ndarray | None,
) -> dict[str, Any]:
    """One problem's checked inputs (``A``, ``R``, ``L`` as arrays) with its tags' start
    positions (``tags``, :func:`~fabflow.positioning.uwb_platform_start.tag_starts`).

    Raises
    ------
    InputError
        Arrays of the wrong shape, a per-link sigma not finite or of the wrong shape.
    LocalizationError
        One tag without a heading prior; a tag without a start.
    """
    A = np.asarray(anchors, dtype=float)
    R = np.asarray(ranges, dtype=float)
    L = np.asarray(lever_arms, dtype=float)
    if A.ndim != 2 or A.shape[1] != 3:
        raise InputError(f"platform localization needs 3D anchors, got {A.shape}")
    if R.ndim != 3 or R.shape[1:] != (L.shape[0], A.shape[0]):
        raise InputError(
            f"ranges must be (N, {L.shape[0]} tags, {A.shape[0]} anchors), got {R.shape}"
        )
    n_tags = L.shape[0]
    if n_tags == 1 and heading_prior is None:
        raise LocalizationError(
            "one UWB tag cannot observe the heading of a standing platform; add a second "
            "tag or give a heading prior (from the motion or the IMU)"
        )
    tags = tag_starts(A, R, L, sigma, method, seeds)
    if isinstance(link_sigma, np.ndarray):
        per_link = np.asarray(link_sigma, dtype=float)
        if per_link.shape != (n_tags, A.shape[0]) or not np.isfinite(per_link).all():
            raise InputError(
                f"link_sigma as an array must be finite, (tags, anchors) = "
                f"{(n_tags, A.shape[0])}, got {per_link.shape}"
            )
        link_sigma = per_link
    return {
        "A": A, "R": R, "L": L, "tags": tags, "sigma": sigma, "method": method,
        "heading_prior": heading_prior, "max_iter": max_iter, "alpha": alpha,
        "anchor_bias_sigma": anchor_bias_sigma, "anchor_ids": anchor_ids,
        "base_lever": base_lever, "link_sigma": link_sigma,
    }  # fmt: skip


def _prepared(
    c: dict[str, Any],
    links: dict[str, np.ndarray],
    state: np.ndarray,
    heading_observed: bool,
    ranges_links: tuple[np.ndarray, np.ndarray],
) -> Prepared:
    """A checked problem (:func:`_checked`) with its link means and start pose as an
    adjustment (:data:`Prepared`)."""
    A, L, link_sigma = c["A"], c["L"], c["link_sigma"]
    if isinstance(link_sigma, np.ndarray):
        links["s"] = np.hypot(links["s"], link_sigma[links["tag_idx"], links["anc_idx"]])
    elif link_sigma is not None:
        links["s"] = np.hypot(links["s"], sigma_of(link_sigma, links["d"]))
    bias_sigma = c["anchor_bias_sigma"]
    adj = PlatformAdjustment(
        anchors=A,
        lever_arms=L,
        **links,
        bias_sigma=np.zeros(A.shape[0])
        if bias_sigma is None
        else np.asarray(bias_sigma, dtype=float),
        ids=tuple(c["anchor_ids"])
        if c["anchor_ids"] is not None
        else tuple(f"A{j + 1}" for j in range(len(A))),
        lever=np.zeros(3) if c["base_lever"] is None else np.asarray(c["base_lever"], dtype=float),
        heading_prior=c["heading_prior"],
        heading_observed=heading_observed,
        alpha=c["alpha"],
        max_iter=c["max_iter"],
    )
    fit = c["method"] == "wls-t" or not heading_observed or L.shape[0] == 1
    return adj, state, fit, ranges_links


def _tested(
    adj: PlatformAdjustment,
    ranges_links: tuple[np.ndarray, np.ndarray],
    state: np.ndarray,
    iterations: int,
    converged: bool,
    first: tuple[TestResult, list[np.ndarray]] | None = None,
) -> Final:
    """The final solution from the first solution ``state``: tested, with exclusions
    while the tests fail and one explains it (:func:`locate_platform`). ``first``: the
    tests of ``state`` on all links, when made already (:func:`grouped_tests`)."""
    use = np.ones(adj.d.size, dtype=bool)
    tests, masks = adj.tests(use, state) if first is None else first
    excluded: list[dict[str, Any]] = []
    problem = ""
    while identify(tests) is not None:
        trial, problem = identify_by_refit(adj, use, state, tests, masks)
        if trial is None:
            break
        k = trial.index
        excluded.append(
            {
                "observation": tests.labels[k],
                "w": float(tests.w[k]),
                "threshold": float(tests.thresholds[k]),
                "ranges": adj.n_ranges(masks[k]),
                "passed_alone": trial.passed,
            }
        )
        use, state, tests, masks = trial.use, trial.state, trial.tests, trial.masks
        iterations, converged = trial.iterations, trial.converged
    return Final(adj, ranges_links, use, state, tests, excluded, problem, iterations, converged)


def finish_mirror_searches(fixes: Sequence[PlatformFix], records: bool = True) -> list[PlatformFix]:
    """The fixes with their mirror checks made, all of them at once.

    A fix whose mirror image fits as well fails
    (:func:`~fabflow.positioning.uwb_platform_mirrors.mirror_checks`); one that
    passes is searched for hidden mirrors
    (:func:`~fabflow.positioning.uwb_platform_mirrors.hidden_mirrors_batch`).

    With ``records`` False only the fixes that left ranges out are searched: a
    hidden mirror raises the protection level, which decides only such a fix's
    status (:func:`~fabflow.positioning.integrity.guard_exclusion`); the others'
    poses, covariances and statuses are the same, their records without the
    ``mirror_by_one_fault`` check (a simulated run that keeps no records).
    """
    pending = [k for k, f in enumerate(fixes) if f.mirror_search is not None]
    checks = mirror_checks([fixes[k].mirror_search[:4] for k in pending])  # type: ignore[index]
    out = list(fixes)
    searched = []
    for k, mirror in zip(pending, checks, strict=True):
        integrity = fixes[k].integrity.with_checks(mirror=mirror)  # type: ignore[union-attr]
        if mirror["passed"]:
            if records or integrity.status == "excluded":
                searched.append(k)
        else:
            dz = mirror["offset_m"][2]
            left = "" if not integrity.excluded else " left"
            reason = (
                f"the anchors{left} lie nearly in one plane: the mirror solution "
                f"{abs(dz):.2f} m {'below' if dz < 0 else 'above'} fits the ranges as well "
                f"(global test {mirror['statistic']:.1f} <= {mirror['threshold']:.1f}), "
                "so the height is not determined"
            )
            integrity = failing_first(integrity, reason, fixes[k].mirror_search[4])  # type: ignore[index]
        out[k] = replace(fixes[k], integrity=integrity, mirror_search=None)
    found = hidden_mirrors_batch([fixes[k].mirror_search[:3] for k in searched])  # type: ignore[index]
    for k, hidden in zip(searched, found, strict=True):
        out[k] = replace(out[k], integrity=with_hidden_mirrors(out[k].integrity, hidden))  # type: ignore[arg-type]
    return out


def failing_first(integrity: Integrity, reason: str, recorded: str) -> Integrity:
    """``integrity`` failed for ``reason`` as if that had been found right after the record.

    ``recorded`` is the reason the record had then (its exclusions, or ""); the
    reasons found later stand before it, and :meth:`Integrity.failing` puts a
    new reason first, so ``reason`` goes between them.
    """
    if recorded:
        later = integrity.reason[: len(integrity.reason) - len(recorded)]
        text = f"{later}{reason}; {recorded}"
    else:
        text = f"{integrity.reason}; {reason}" if integrity.reason else reason
    return replace(integrity, status="failed", reason=text)


def rejected_ranges(rejected: np.ndarray, anchor_ids: Sequence[str]) -> dict[str, Any]:
    """The integrity check of the ranges a per-link outlier test removed before the fix.

    Parameters
    ----------
    rejected
        (N, n_tags, n_anchors) ranges removed (e.g.
        :attr:`~fabflow.positioning.uwb_calibration.Rejection.rejected` of
        :func:`~fabflow.positioning.uwb_calibration.reject_outliers_static`).
    anchor_ids
        Anchor names.

    Returns
    -------
    dict
        ``count`` (ranges removed), ``per_link`` (label to count, the links with
        any) and ``test`` (what removed them): a range far from its own link's
        robust centre is a single NLOS reading; a link or an anchor off as a
        whole is not removed here but left to the tests of the fix.
    """
    r = np.asarray(rejected, dtype=bool)
    counts = r.sum(axis=0)
    tags, anchors = np.nonzero(counts)
    return {
        "count": int(counts.sum()),
        "per_link": {
            f"anchor {anchor_ids[j]} from tag {k}": int(counts[k, j])
            for k, j in zip(tags, anchors, strict=True)
        },
        "test": "beyond 3 sigma (at least 0.1 m) of its link's robust centre",
    }


def platform_to_base_covariance(
    T_world_platform: np.ndarray, T_platform_base: np.ndarray, cov_state: np.ndarray
) -> np.ndarray:
    """Map the 4x4 ``[x, y, z, yaw]`` covariance to the 6x6 base pose covariance
    (``(..., 6, 6)`` of platform poses ``(..., 4, 4)`` and covariances ``(..., 4, 4)``).

    Follows the convention of :mod:`fabflow.positioning.result`: the yaw error is a
    rotation about the world z axis and moves the base origin by
    ``e_z x (t_base - t_platform)``. Roll and pitch get ``UNOBSERVED_VARIANCE``.
    """
    lever = T_world_platform[..., :3, :3] @ T_platform_base[:3, 3]
    J = np.zeros((*lever.shape[:-1], 6, 4))
    J[..., :3, :3] = np.eye(3)
    J[..., :3, 3] = np.cross([0.0, 0.0, 1.0], lever)
    J[..., 5, 3] = 1.0
    cov = J @ cov_state @ np.swapaxes(J, -1, -2)
    cov[..., 3, 3] += UNOBSERVED_VARIANCE
    cov[..., 4, 4] += UNOBSERVED_VARIANCE
    return 0.5 * (cov + np.swapaxes(cov, -1, -2))


def heading_from_motion(fix_xy: np.ndarray, min_travel: float = 0.3, window: int = 31) -> float:
    """Heading (rad) of the first displacement longer than ``min_travel`` metres.

    ``fix_xy`` are (N, 2) position fixes in time order (NaN allowed). They are
    smoothed by a running median of ``window`` fixes first, so single noisy
    fixes do not trigger; the displacement is measured from the median of the
    first ``window`` fixes.
    """

    xy = np.asarray(fix_xy, dtype=float)
    if np.sum(np.all(np.isfinite(xy), axis=1)) < window:
        raise LocalizationError("too few position fixes to take the heading from the motion")
    smooth = running_median(xy, window)
    start = nanmedian(xy[:window], 0)
    dist = np.linalg.norm(smooth - start, axis=1)
    moved = np.flatnonzero(dist > min_travel)
    if moved.size == 0:
        raise LocalizationError(
            "one tag and an IMU: the heading comes from the motion, but the tag never moved "
            f"more than {min_travel} m; add a second tag"
        )
    d = smooth[moved[0]] - start
    return float(math.atan2(d[1], d[0]))
