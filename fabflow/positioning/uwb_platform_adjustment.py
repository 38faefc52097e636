"""The least-squares adjustment of a standing platform's UWB ranges, its tests and its choices.

A level platform stands at ``x, y, z, yaw`` (anchors' frame, metres and
radians); tag ``k`` sits at the lever arm ``l_k`` (platform frame), so range
``i`` of tag ``k`` to anchor ``j`` observes ``|p + R(yaw) l_k - a_j|``.
:class:`PlatformAdjustment` holds the ranges with their weights and solves,
tests and compares fits of any subset of them:

- :meth:`PlatformAdjustment.fit`: damped Newton over the ranges used;
- :meth:`PlatformAdjustment.tests`: the global test and the w-tests of one
  anchor's ranges and of one tag-anchor link
  (:func:`fabflow.positioning.adjustment_tests.adjustment_test`), each hypothesis with
  the ranges it names (a boolean mask), so nothing is parsed back from labels;
- :func:`identify_by_refit`: which anchor or link to leave out, found by
  leaving out each in turn, fitting again and testing (as
  :mod:`fabflow.positioning.registration` does for prism points); an
  exclusion is accepted only when it is the one that explains the misfit;
- :func:`reflected`: the pose mirrored through the plane of the anchors used
  (anchors nearly in one plane cannot tell above from below; the mirror checks
  are :mod:`fabflow.positioning.uwb_platform_mirrors`').
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import special

from fabflow.positioning.adjustment_tests import TestResult, global_test, one_column_tests_many
from fabflow.positioning.observation_covariance import Covariance
from fabflow.positioning.uwb import COND_LIMIT
from fabflow.positioning.uwb_platform_model import (
    jacobians_many,
    platform_information,
    platform_newton,
    platform_newton_batch,
    rotz,
    rotz_many,
)


@dataclass(frozen=True)
class PlatformAdjustment:
    """The finite ranges of a standing platform with their weights: fit and test any subset.

    A standing platform's ranges of one tag-anchor link all observe the same
    distance, so the adjustment holds one observation per link: the weighted mean
    of its ranges, with the weights' sum
    (:func:`~fabflow.positioning.uwb_platform_start.link_means`). Fits, w-tests,
    MDBs and covariances are those of all the ranges exactly (every hypothesis
    is a whole link or anchor, constant over a link's ranges). The global test
    is that of the link means. The ranges' scatter about their link means is
    not in it: after the rejection around each link's centre it is no
    chi-square. The rejection cuts the noise's tails, so the scatter reads low
    (a variance factor of 0.97 at 3 sigma). The NLOS ranges with a small
    excess that fall within the window add a few large terms on the long side,
    which the error model expects: on a link the structure blocks they made
    the test refuse a good pose several times as often as ``alpha``. The work
    is set by the links, not by the epochs.

    Attributes
    ----------
    anchors
        (n_anchors, 3) anchor positions (metres, anchors' frame).
    lever_arms
        (n_tags, 3) tag positions in the platform frame (metres).
    d, s
        (m,) per link, the weighted mean of its ranges and that mean's standard
        deviation (metres).
    tag_idx, anc_idx
        (m,) tag and anchor of each link.
    count
        (m,) ranges per link.
    raw_mean, raw_sq_dev
        (m,) plain mean of each link's ranges and their sum of squared deviations
        from it (metres, m^2): the residual RMS over the ranges.
    bias_sigma
        (n_anchors,) standard deviation (metres) of the error every range to one
        anchor shares (what the calibration leaves).
    ids
        Anchor names, for the hypotheses' labels.
    lever
        (3,) the arm base in the platform frame (metres): the protection level is
        given for the base.
    heading_prior
        ``(yaw, sigma_yaw)`` (radians) or ``None``.
    heading_observed
        Whether the heading is a parameter (two tags apart, or a prior).
    alpha
        Level of the tests.
    max_iter
        Gauss-Newton iteration cap.
    """

    anchors: np.ndarray
    lever_arms: np.ndarray
    d: np.ndarray
    s: np.ndarray
    tag_idx: np.ndarray
    anc_idx: np.ndarray
    bias_sigma: np.ndarray
    ids: tuple[str, ...]
    lever: np.ndarray
    heading_prior: tuple[float, float] | None
    heading_observed: bool
    alpha: float
    max_iter: int
    count: np.ndarray
    raw_mean: np.ndarray
    raw_sq_dev: np.ndarray

    def n_ranges(self, use: np.ndarray) -> int:
        """How many ranges the links ``use`` hold."""
        return int(self.count[use].sum())

    def fit(self, use: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, int, bool]:
        """Damped Newton over the ranges ``use`` from ``start``: state, iterations, converged."""
        return platform_newton(
            self.anchors, self.lever_arms, self.d[use], self.s[use], self.tag_idx[use],
            self.anc_idx[use], start, self.heading_prior, self.max_iter,
        )  # fmt: skip

    def information(self, use: np.ndarray, state: np.ndarray) -> np.ndarray:
        """4x4 information of ``x, y, z, yaw`` from the ranges ``use`` (white noise only)."""
        return platform_information(
            self.anchors, self.lever_arms, self.s[use], self.tag_idx[use], self.anc_idx[use],
            state, self.heading_prior,
        )  # fmt: skip

    def determined(self, use: np.ndarray, state: np.ndarray) -> bool:
        """Whether the ranges ``use`` determine the pose (well-conditioned information)."""
        info = self.information(use, state)
        if not self.heading_observed:
            info = info[:3, :3]
        ev = np.linalg.eigvalsh(info)
        return bool(ev[0] > ev[-1] / COND_LIMIT)

    def n_anchors_used(self, use: np.ndarray) -> int:
        """How many anchors the ranges ``use`` reach."""
        return int(self.anchors_used(use).size)

    def anchors_used(self, use: np.ndarray) -> np.ndarray:
        """The anchors (indices, ascending) the ranges ``use`` reach; ``np.unique`` of
        their anchor indices without its sort."""
        return np.flatnonzero(np.bincount(self.anc_idx[use], minlength=len(self.anchors)))

    def hypotheses(self, use: np.ndarray) -> tuple[list[str], list[np.ndarray]]:
        """Labels and links (masks over all links) of the hypotheses on the links ``use``.

        One anchor (``anchor A3``: all its ranges used) and, with two or more tags,
        one tag-anchor link (``anchor A3 from tag 1``; tags numbered from 0 as in
        the ranges file), unless the link is all that is left of its anchor.
        """
        anchors = self.anchors_used(use)
        whole = use[None] & (self.anc_idx[None] == anchors[:, None])  # (anchors, links)
        labels = [f"anchor {self.ids[j]}" for j in anchors]
        blocks = [whole]
        if len(self.lever_arms) >= 2:
            n_whole = whole.sum(axis=1)
            for k in range(len(self.lever_arms)):
                link = whole & (self.tag_idx == k)[None]
                n_link = link.sum(axis=1)
                # a link is a hypothesis of its own unless it is all its anchor has
                shown = (n_link > 0) & (n_link < n_whole)
                labels += [f"anchor {self.ids[j]} from tag {k}" for j in anchors[shown]]
                blocks.append(link[shown])
        return labels, list(np.concatenate(blocks))

    def n_hypotheses(self, use: np.ndarray) -> int:
        """How many hypotheses :meth:`hypotheses` makes on the links ``use``, without
        making them: every anchor reached, and with two or more tags each link to an
        anchor more than one tag reaches."""
        reach = np.zeros((len(self.lever_arms), len(self.anchors)), dtype=bool)
        reach[self.tag_idx[use], self.anc_idx[use]] = True
        tags = reach.sum(axis=0)
        shared = int(tags[tags >= 2].sum()) if len(self.lever_arms) >= 2 else 0
        return int(np.count_nonzero(tags)) + shared

    def tests(self, use: np.ndarray, state: np.ndarray) -> tuple[TestResult, list[np.ndarray]]:
        """The adjustment tests over the ranges ``use`` at ``state``, and each hypothesis' ranges.

        Observations are the ranges with their white noise plus the bias every
        range to one anchor shares, ``Q = diag(s^2) + U diag(bias_sigma^2) U^T``
        (``U``: one indicator column per anchor). :func:`grouped_tests` of one.
        """
        return grouped_tests([(self, use, state)])[0]

    def global_test(self, use: np.ndarray, state: np.ndarray) -> tuple[int, float, float]:
        """The global test of :meth:`tests` alone: redundancy, statistic, critical value."""
        J, Q, v = self._test_inputs(use, state)
        return global_test(J, Q, v, self.alpha)

    def _test_inputs(
        self, use: np.ndarray, state: np.ndarray
    ) -> tuple[np.ndarray, Covariance, np.ndarray]:
        """Design matrix, observation covariance and residuals of the ranges ``use``."""
        J, v = self._linearized(use, state)
        U, var = self._shared(use)
        return J, Covariance(diag=self.s[use] ** 2, low_rank=U, low_rank_var=var), v

    def _linearized(self, use: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Design matrix and residuals of the ranges ``use`` at ``state``."""
        J, v = _linearized_many([self], use, np.asarray(state, dtype=float)[None])
        return J[0], v[0]

    def _shared(self, use: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
        """The low-rank part of the ranges ``use``' covariance: one indicator column per
        anchor (None when no anchor has a bias sigma) and the anchors' bias variances."""
        anchors = self.anchors_used(use)
        U = (self.anc_idx[use][:, None] == anchors[None, :]).astype(float)
        var = np.maximum(self.bias_sigma[anchors], 1e-9) ** 2
        return (U if np.any(self.bias_sigma[anchors] > 0) else None), var


def grouped_tests(
    problems: Sequence[tuple[PlatformAdjustment, np.ndarray, np.ndarray]],
) -> list[tuple[TestResult, list[np.ndarray]]]:
    """:meth:`PlatformAdjustment.tests` of many fixes ``(adjustment, use, state)``.

    Fixes of one shape (the same links used, so the same hypotheses and shared
    errors, the same heading prior and level) are tested in one call of
    :func:`~fabflow.positioning.adjustment_tests.one_column_tests_many`: a
    simulated run's visits, where one call per visit was most of the tests' time.
    """
    groups: dict[tuple[Any, ...], list[int]] = {}
    for i, (adj, use, _) in enumerate(problems):
        key = (
            adj.ids, len(adj.lever_arms), adj.tag_idx.tobytes(), adj.anc_idx.tobytes(),
            use.tobytes(), bool(np.any(adj.bias_sigma[adj.anchors_used(use)] > 0)),
            adj.heading_observed, adj.heading_prior, adj.alpha,
        )  # fmt: skip
        groups.setdefault(key, []).append(i)
    out: list[tuple[TestResult, list[np.ndarray]]] = [None] * len(problems)  # type: ignore[list-item]
    for members in groups.values():
        adj, use, _ = problems[members[0]]
        labels, masks = adj.hypotheses(use)
        C = np.ascontiguousarray(
            np.array(masks, dtype=float).reshape(len(masks), use.size)[:, use].T
        )
        U, _ = adj._shared(use)
        adjs = [problems[i][0] for i in members]
        states = np.stack([problems[i][2] for i in members])
        J, v = _linearized_many(adjs, use, states)
        bias = np.stack([a.bias_sigma for a in adjs])[:, adj.anchors_used(use)]
        Q = Covariance(
            diag=np.stack([a.s[use] for a in adjs]) ** 2,
            low_rank=U,
            low_rank_var=np.maximum(bias, 1e-9) ** 2,
        )
        prior = None
        if adj.heading_prior is not None and adj.heading_observed:
            prior = np.zeros((4, 4))
            prior[3, 3] = 1.0 / adj.heading_prior[1] ** 2
        tests = one_column_tests_many(
            J, Q, v, labels, C, adj.alpha,
            position_map=_position_maps(adjs, states), prior_information=prior,
        )  # fmt: skip
        for i, test in zip(members, tests, strict=True):
            out[i] = (test, masks)
    return out


def _linearized_many(
    adjs: Sequence[PlatformAdjustment], use: np.ndarray, states: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`PlatformAdjustment._linearized` of adjustments with the same links and
    heading observability at ``states`` ``(V, 4)``: ``(V, m, u)`` and ``(V, m)``."""
    adj = adjs[0]
    tg, an = adj.tag_idx[use], adj.anc_idx[use]
    A_link = np.stack([a.anchors for a in adjs])[:, an]
    L = np.stack([a.lever_arms for a in adjs])
    J, dist = jacobians_many(A_link, L, states, tg)
    if not adj.heading_observed:
        J = J[..., :3]
    return J, np.stack([a.d[use] for a in adjs]) - dist


def _position_maps(adjs: Sequence[PlatformAdjustment], states: np.ndarray) -> np.ndarray:
    """The derivative ``(V, 3, u)`` of the base position by the state of adjustments of
    one heading observability at ``states`` ``(V, 4)``: the base lever turns with the
    heading."""
    observed = adjs[0].heading_observed
    G = np.zeros((len(adjs), 3, 4 if observed else 3))
    G[:, [0, 1, 2], [0, 1, 2]] = 1.0
    if observed:
        lever = np.stack([a.lever for a in adjs])
        Rl = (rotz_many(states[:, 3]) @ lever[..., None])[..., 0]
        G[:, 0, 3], G[:, 1, 3] = -Rl[:, 1], Rl[:, 0]
    return G


@dataclass(frozen=True)
class Trial:
    """The solution without one hypothesis' ranges, and its tests.

    Attributes
    ----------
    index
        The hypothesis left out (index into the tests it was chosen from).
    label
        Its label.
    use
        (m,) the ranges left.
    state, iterations, converged
        The refit (``x, y, z, yaw``; metres, radians).
    tests, masks
        Its tests and the ranges of each of their hypotheses.
    """

    index: int
    label: str
    use: np.ndarray
    state: np.ndarray
    iterations: int
    converged: bool
    tests: TestResult
    masks: list[np.ndarray]

    @property
    def passed(self) -> bool:
        """Whether the refit converged and passes every test."""
        return self.converged and self.tests.passed

    @property
    def excess(self) -> float:
        """The global test statistic as a standard score, ``(T - r) / sqrt(2 r)``."""
        r = max(self.tests.redundancy, 1)
        return (self.tests.statistic - r) / math.sqrt(2.0 * r)


def padded_links(cases: Sequence[tuple[PlatformAdjustment, np.ndarray]]) -> dict[str, np.ndarray]:
    """The links of many ``(adjustment, use)`` as arrays padded to the longest.

    Returns
    -------
    dict
        ``A_link``, ``L_link`` ``(B, m, 3)``: each link's anchor and lever arm
        (metres); ``d``, ``s`` ``(B, m)``: its mean range and that mean's standard
        deviation (metres; padding 0 and 1); ``use`` ``(B, m)``: used (padding
        ``False``); ``weight``: ``1 / s^2`` where used, else 0; ``anchor``: its
        anchor (index; padding 0).
    """
    B = len(cases)
    m = max((adj.d.size for adj, _ in cases), default=0)
    out = {
        "A_link": np.zeros((B, m, 3)), "L_link": np.zeros((B, m, 3)), "d": np.zeros((B, m)),
        "s": np.ones((B, m)), "use": np.zeros((B, m), dtype=bool),
        "anchor": np.zeros((B, m), dtype=int),
    }  # fmt: skip
    for b, (adj, use) in enumerate(cases):
        k = adj.d.size
        out["A_link"][b, :k] = adj.anchors[adj.anc_idx]
        out["L_link"][b, :k] = adj.lever_arms[adj.tag_idx]
        out["d"][b, :k], out["s"][b, :k], out["use"][b, :k] = adj.d, adj.s, use
        out["anchor"][b, :k] = adj.anc_idx
    out["weight"] = np.where(out["use"], 1.0 / out["s"] ** 2, 0.0)
    return out


def fit_many(
    cases: Sequence[tuple[PlatformAdjustment, np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:meth:`PlatformAdjustment.fit` of many ``(adjustment, use, start)`` at once.

    Each case keeps its own links, weights and heading prior (its links padded
    with weight 0 to the longest);
    :func:`~fabflow.positioning.uwb_platform_model.platform_newton_batch` solves
    them together, as many as share an iteration cap.

    Returns
    -------
    tuple
        ``(B, 4)`` states, ``(B,)`` iterations, converged, and solved (``False``
        where :meth:`PlatformAdjustment.fit` raises :class:`LocalizationError`).
    """
    B = len(cases)
    links = padded_links([(adj, use) for adj, use, _ in cases])
    A_link, L_link, d, weight = links["A_link"], links["L_link"], links["d"], links["weight"]
    prior = np.zeros((B, 2))
    for b, (adj, _, _) in enumerate(cases):
        if adj.heading_prior is not None:
            prior[b] = adj.heading_prior[0], 1.0 / adj.heading_prior[1] ** 2
    starts = np.array([start for _, _, start in cases], dtype=float).reshape(B, 4)
    out = np.zeros((B, 4)), np.zeros(B, dtype=int), np.zeros(B, dtype=bool), np.zeros(B, bool)
    caps = np.array([adj.max_iter for adj, _, _ in cases])
    for cap in np.unique(caps):
        b = np.flatnonzero(caps == cap)
        solved = platform_newton_batch(
            A_link[b], L_link[b], d[b], weight[b], starts[b], prior[b], int(cap)
        )
        for into, part in zip(out, solved, strict=True):
            into[b] = part
    return out


def identify_by_refit(
    adj: PlatformAdjustment,
    use: np.ndarray,
    state: np.ndarray,
    tests: TestResult,
    masks: Sequence[np.ndarray],
) -> tuple[Trial | None, str]:
    """Which anchor or link to leave out: each in turn, fitted again and tested.

    Every excludable hypothesis with a test value is tried (a handful: the
    anchors and the tag-anchor links) as long as three anchors and the pose's
    determination remain. Of the refits that pass every test, those that leave
    out part of what another passing one leaves out (the link A3 from tag 1
    when anchor A3 passes too) are set aside: a fault found on one link may be
    the anchor's (a mis-surveyed anchor biases its links by different amounts),
    and a bias left on its other links below their detection limit would still
    move the pose. Leaving out the whole anchor is the safe side; a link alone
    is left out when its anchor cannot be. Then:

    - exactly one left: it is the exclusion;
    - more than one: several single faults explain the misfit equally, the
      faulty one is not identified (returns ``None`` and the reason);
    - none passes: the refit with the smallest global test statistic is taken
      (a further exclusion follows) only when it is clearly best, its standard
      score ``(T - r) / sqrt(2 r)`` below every other's by more than the
      one-sided normal quantile at ``alpha``; otherwise ``None`` and the reason.

    Returns
    -------
    tuple
        The chosen trial (or ``None``) and, when none is chosen for a reason the
        record should carry, that reason (else ``""``).
    """
    left: list[tuple[int, np.ndarray]] = []
    for k in range(len(tests.labels)):
        if not tests.excludable[k] or not np.isfinite(tests.w[k]):
            continue
        rest = use & ~masks[k]
        if adj.n_anchors_used(rest) < 3 or not adj.determined(rest, state):
            continue
        left.append((k, rest))
    trials = _refits(adj, left, state, tests.labels)
    if not trials:
        return None, ""
    passing = [t for t in trials if t.passed]
    # a passing trial that leaves out part of what another passing one leaves out is set aside
    widest = [
        t
        for t in passing
        if not any(q is not t and _strict_subset(~t.use & use, ~q.use & use) for q in passing)
    ]
    if len(widest) == 1:
        return widest[0], ""
    if widest:
        names = ", ".join(t.label for t in widest)
        return None, (
            f"the misfit is explained by leaving out any one of {names}: "
            "the faulty anchor or link cannot be identified"
        )
    ranked = sorted(trials, key=lambda t: t.excess)
    z = float(special.ndtri(1.0 - adj.alpha))
    if len(ranked) == 1 or ranked[1].excess - ranked[0].excess > z:
        return ranked[0], ""
    best = ", ".join(
        f"{t.label} (variance factor {t.tests.variance_factor:.2f})" for t in ranked[:3]
    )
    return None, f"no single anchor or link explains the misfit (best refits without {best})"


def _refits(
    adj: PlatformAdjustment,
    left: Sequence[tuple[int, np.ndarray]],
    state: np.ndarray,
    labels: Sequence[str],
) -> list[Trial]:
    """Per hypothesis ``(index, ranges left)``, the better of two fits of the ranges left:
    from ``state`` and from the mirror image of that first fit.

    The fix with a fault in it can stand nearer the mirror image of the pose
    the other ranges give (the side of the anchors' plane is the weakly
    determined part); started from there alone, the refit would settle on the
    wrong side. Of the converged fits the one with the smaller global test
    statistic is kept (the first on a tie); a hypothesis whose first fit cannot be
    solved has no trial, one whose mirrored fit cannot keeps its first. Every
    hypothesis' first fits are one :func:`fit_many`, their mirrored ones another,
    and the tests of both one :func:`grouped_tests`.
    """
    if not left:
        return []
    first, f_iters, f_conv, f_solved = fit_many([(adj, rest, state) for _, rest in left])
    kept = np.flatnonzero(f_solved)
    if not kept.size:
        return []
    mirrored = [reflected(adj, left[i][1], first[i])[0] for i in kept]
    second = fit_many([(adj, left[i][1], m) for i, m in zip(kept, mirrored, strict=True)])
    fits = [(i, first[i], f_iters[i], f_conv[i]) for i in kept]
    fits += [(i, st, it, conv) for i, st, it, conv, ok in zip(kept, *second, strict=True) if ok]
    tested = grouped_tests([(adj, left[i][1], st) for i, st, _, _ in fits])
    by_case: dict[int, list[Trial]] = {}
    for (i, st, it, conv), (result, masks) in zip(fits, tested, strict=True):
        k, rest = left[i]
        trial = Trial(k, labels[k], rest, st, int(it), bool(conv), result, masks)
        by_case.setdefault(int(i), []).append(trial)
    return [min(by_case[int(i)], key=lambda t: (not t.converged, t.tests.statistic)) for i in kept]


def reflected(
    adj: PlatformAdjustment, use: np.ndarray, state: np.ndarray
) -> tuple[np.ndarray, float]:
    """The pose mirrored through the plane of the anchors ``use`` reaches, and its distance.

    The tags' centroid is reflected through the best-fit plane of those anchors
    (anchors' frame), the heading kept; the second value is the centroid's
    distance from the plane (metres).
    """
    A = adj.anchors[adj.anchors_used(use)]
    c, normal = _best_fit_plane(A.tobytes(), len(A))
    L_mean = adj.lever_arms.mean(axis=0)
    R = rotz(float(state[3]))
    centroid = state[:3] + R @ L_mean
    h = float((centroid - c) @ normal)
    start = state.copy()
    start[:3] = centroid - 2.0 * h * normal - R @ L_mean
    return start, abs(h)


@functools.lru_cache(maxsize=256)
def _best_fit_plane(points_bytes: bytes, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Centroid and unit normal of the best-fit plane of ``n`` points (their ``(n, 3)``
    float64 bytes), made once per point set: a run's mirror searches reflect through
    the planes of a few anchor sets hundreds of times."""
    A = np.frombuffer(points_bytes, dtype=float).reshape(n, 3)
    c = A.mean(axis=0)
    normal = np.linalg.svd(A - c)[2][-1].copy()
    c.flags.writeable = normal.flags.writeable = False
    return c, normal


def _strict_subset(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the ranges ``a`` are a proper subset of the ranges ``b`` (masks)."""
    return bool(np.all(b[a]) and b.sum() > a.sum())
