"""The standing-platform UWB fix as a tested adjustment: no silent trimming, exclusion by
refit, mirror solutions, anchor names as given.

Synthetic ranges of two tags to the paper's anchors (A1-A3 at 1.0 m, A4 at 3.2 m),
optionally with a fifth anchor above the centre, 5 cm noise, seeded.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.optimize import least_squares

from fabflow.errors import LocalizationError
from fabflow.positioning.integrity import Integrity
from fabflow.positioning.uwb_platform import (
    failing_first,
    finish_mirror_searches,
    locate_platform,
    locate_platforms,
)
from fabflow.positioning.uwb_platform_adjustment import (
    PlatformAdjustment,
    _refits,
    grouped_tests,
    padded_links,
    reflected,
)
from fabflow.positioning.uwb_platform_mirrors import _global_tests
from fabflow.positioning.uwb_platform_model import (
    _jacobian,
    _links,
    _weighted_curvature,
    platform_jacobian,
    platform_newton,
    platform_newton_batch,
    platform_ranges,
    range_curvature,
    rotz,
)
from fabflow.sensors.uwb import PAPER_ANCHORS_3D

ANCHORS_5 = np.vstack([PAPER_ANCHORS_3D, [2.4, 3.0, 3.2]])
TAGS = np.array([[0.8, 0.0, 1.5], [-0.8, 0.0, 1.5]])
BASE = np.array([0.3, 0.0, 0.6])
TRUTH = np.array([1.6, 2.2, 0.0, np.radians(30.0)])
SIGMA = 0.05


def _ranges(anchors: np.ndarray, seed: int, n: int = 60) -> np.ndarray:
    """(n, 2 tags, anchors) ranges at TRUTH with white noise of SIGMA."""
    tags = TRUTH[:3] + TAGS @ rotz(TRUTH[3]).T
    d = np.linalg.norm(tags[:, None] - anchors[None], axis=2)
    return d[None] + SIGMA * np.random.default_rng(seed).standard_normal((n, *d.shape))


def _fix(anchors: np.ndarray, ranges: np.ndarray, **kw):
    return locate_platform(
        anchors, ranges, TAGS, SIGMA, anchor_bias_sigma=np.full(len(anchors), 0.01),
        base_lever=BASE, **kw,
    )  # fmt: skip


def _base_error(fix) -> np.ndarray:
    true = TRUTH[:3] + rotz(TRUTH[3]) @ BASE
    return fix.T[:3, :3] @ BASE + fix.T[:3, 3] - true


def _within(fix, k: float = 3.0) -> bool:
    e = fix.state - TRUTH
    e[3] = np.angle(np.exp(1j * e[3]))
    return bool(np.all(np.abs(e) <= k * np.sqrt(np.diag(fix.covariance))))


def test_every_range_is_used_or_left_out_on_the_record() -> None:
    r = _ranges(PAPER_ANCHORS_3D, 0)
    clean = _fix(PAPER_ANCHORS_3D, r)
    assert clean.integrity.status == "ok" and clean.n_used == clean.n_ranges == r.size
    r[:, 1, 2] += 1.0  # tag 1 to A3 a metre long: used to vanish in a 4-sigma trim
    fix = _fix(PAPER_ANCHORS_3D, r)
    assert fix.integrity.status != "ok"
    left_out = sum(e["ranges"] for e in fix.integrity.excluded)
    assert fix.n_used + left_out == fix.n_ranges == r.size
    assert [e["observation"] for e in fix.integrity.excluded] == ["anchor A3"]
    assert _within(fix)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("anchors", [PAPER_ANCHORS_3D, ANCHORS_5], ids=["4 anchors", "5 anchors"])
def test_a_link_fault_is_found_by_refit_not_by_the_largest_w(seed: int, anchors) -> None:
    r = _ranges(anchors, seed)
    r[:, 1, 2] += 0.4
    fix = _fix(anchors, r)
    # correlated hypotheses: leaving out A3 or its link both explain it; the anchor
    # is the safe side, never another anchor or a mirrored pose
    assert fix.integrity.status == "excluded"
    assert [e["observation"] for e in fix.integrity.excluded] == ["anchor A3"]
    assert fix.integrity.excluded[0]["passed_alone"]
    assert _within(fix)


def test_when_two_anchors_explain_the_misfit_the_fix_fails_naming_them() -> None:
    r = _ranges(ANCHORS_5, 0)
    r[:, :, 3] += 0.5  # A4 long; without A5 the other high anchor could absorb it too
    fix = _fix(ANCHORS_5, r)
    assert fix.integrity.status == "failed"
    assert "any one of anchor A4, anchor A5" in fix.integrity.reason
    assert "cannot be identified" in fix.integrity.reason


def test_anchor_names_with_spaces_are_carried_not_parsed() -> None:
    r = _ranges(ANCHORS_5, 1)
    r[:, 1, 2] += 0.4
    ids = ["A 1", "A 2", "A 3", "A 4", "A 5"]
    fix = _fix(ANCHORS_5, r, anchor_ids=ids)
    assert [e["observation"] for e in fix.integrity.excluded] == ["anchor A 3"]
    assert "anchor A 1 from tag 0" in fix.integrity.mdb


@pytest.mark.parametrize("dz", [0.02, 0.1])
def test_anchors_nearly_in_one_plane_fail_as_mirrored(dz: float) -> None:
    anchors = np.array([[0.0, 0.0, 1.0], [4.8, 0.0, 1.0], [4.8, 6.0, 1.0], [0.0, 6.0, 1.0 + dz]])
    fix = _fix(anchors, _ranges(anchors, 0))
    assert fix.integrity.status == "failed"
    assert "lie nearly in one plane: the mirror solution" in fix.integrity.reason
    mirror = fix.integrity.checks["mirror"]
    assert not mirror["passed"] and mirror["distinct"]
    assert mirror["worse_by"] < mirror["limit"]
    assert abs(abs(mirror["offset_m"][2]) - 1.0) < 0.1  # tags 0.5 m above the plane


def test_a_clearly_worse_mirror_is_resolved() -> None:
    fix = _fix(ANCHORS_5, _ranges(ANCHORS_5, 0))
    assert fix.integrity.status == "ok"
    assert fix.integrity.checks["mirror"]["passed"]
    assert "mirror_by_one_fault" not in fix.integrity.checks


def test_one_anchor_that_alone_tells_the_side_bounds_the_protection_level() -> None:
    r = _ranges(PAPER_ANCHORS_3D, 2)
    clean = _fix(PAPER_ANCHORS_3D, r)
    hidden = clean.integrity.checks["mirror_by_one_fault"]
    assert [m["anchor"] for m in hidden] == ["A4"]
    assert clean.integrity.protection_level["vertical"] > 0.9  # the mirror, 1 m down
    # A4 half a metre long: the fix jumps to the mirror, every test passes, and the
    # protection level says how far that can be
    r[:, :, 3] += 0.5
    fix = _fix(PAPER_ANCHORS_3D, r)
    assert fix.integrity.status == "ok" and not _within(fix)
    err = _base_error(fix)
    assert abs(err[2]) > 0.9
    assert fix.integrity.protection_level["vertical"] > 0.9 * abs(err[2])


def test_no_nan_for_an_anchor_left_out() -> None:
    r = _ranges(ANCHORS_5, 0)
    r[:, :, 2] += 0.5
    fix = _fix(ANCHORS_5, r)
    assert fix.integrity.status == "excluded"
    assert np.isnan(fix.per_anchor_rms[2]) and np.all(np.isfinite(np.delete(fix.per_anchor_rms, 2)))
    assert np.all(np.isfinite(fix.residuals)) and fix.residuals.size == fix.n_used


@settings(deadline=None, max_examples=25)
@given(seed=st.integers(0, 2**31), n=st.integers(5, 40), tags=st.integers(2, 3))
def test_the_link_means_test_every_range(seed: int, n: int, tags: int) -> None:
    # the adjustment holds one mean per link; its fix must be that of every range (a
    # stationary point of the weighted ranges) and its global test that of the link
    # means: v^T Q^-1 v over them, one degree of freedom per link beyond the pose's
    # (the ranges' scatter about their means is no chi-square after the rejection)
    rng = np.random.default_rng(seed)
    lever = np.vstack([TAGS, [0.0, 0.6, 1.4]])[:tags]
    tag_xyz = TRUTH[:3] + lever @ rotz(TRUTH[3]).T
    d = np.linalg.norm(tag_xyz[:, None] - ANCHORS_5[None], axis=2)
    r = d[None] + 0.04 * rng.standard_normal((n, *d.shape))
    r[rng.random(r.shape) < 0.1] = np.nan

    def sigma(x):
        return 0.03 + 0.004 * np.asarray(x)

    bias = np.full(len(ANCHORS_5), 0.01)
    fix = locate_platform(ANCHORS_5, r, lever, sigma, anchor_bias_sigma=bias, base_lever=BASE)
    assume(fix.integrity.status == "ok")
    finite = np.isfinite(r)
    tag_idx = np.broadcast_to(np.arange(tags)[None, :, None], r.shape)[finite]
    anc_idx = np.broadcast_to(np.arange(len(ANCHORS_5))[None, None, :], r.shape)[finite]
    tag_at = fix.state[:3] + lever @ rotz(fix.state[3]).T
    diff = tag_at[tag_idx] - ANCHORS_5[anc_idx]
    v = r[finite] - np.linalg.norm(diff, axis=1)
    np.testing.assert_allclose(fix.residuals, v, atol=1e-12)
    s2 = sigma(r[finite]) ** 2
    u = diff / np.linalg.norm(diff, axis=1)[:, None]
    Rl = lever @ rotz(fix.state[3]).T
    J = np.column_stack([u, u[:, 0] * -Rl[tag_idx, 1] + u[:, 1] * Rl[tag_idx, 0]])
    gradient = J.T @ (v / s2)
    # the step left to take is negligible against its own uncertainty
    assert gradient @ np.linalg.solve(J.T @ (J / s2[:, None]), gradient) < 1e-4
    link = tag_idx * len(ANCHORS_5) + anc_idx
    links, inverse = np.unique(link, return_inverse=True)
    W = np.bincount(inverse, weights=1.0 / s2)
    v_link = np.bincount(inverse, weights=v / s2) / W  # the link means' residuals
    anchor = links % len(ANCHORS_5)
    U = (anchor[:, None] == np.arange(len(ANCHORS_5))[None]).astype(float)
    Q = np.diag(1.0 / W) + (U * bias**2) @ U.T
    statistic = v_link @ np.linalg.solve(Q, v_link)
    assert fix.integrity.global_test["statistic"] == pytest.approx(statistic, rel=1e-8)
    assert fix.integrity.redundancy == links.size - 4
    assert fix.n_ranges == fix.n_used == v.size


@pytest.mark.parametrize("seed", range(80))
def test_the_fix_converges_where_the_residuals_bend_the_height(seed: int) -> None:
    # anchors mostly at one height 8-15 m around, tags 1.7 m below them, every range
    # longer by an NLOS-like excess: the residuals are not small against the ranges'
    # curvature in height, where Gauss-Newton alone crept past 20 iterations
    # (seeds 18 and 66); the minimum is checked against scipy's least squares

    rng = np.random.default_rng(seed)
    n = 10
    angle = np.sort(rng.uniform(0.0, 2 * np.pi, n))
    radius = rng.uniform(8.0, 15.0, n)
    height = np.where(rng.random(n) < 0.8, 3.2, 1.0)
    A = np.column_stack([radius * np.cos(angle), radius * np.sin(angle), height])
    truth = np.array([0.0, 0.0, 0.0, 0.3])
    tag_idx, anc_idx = np.repeat([0, 1], n), np.tile(np.arange(n), 2)
    d = platform_ranges(A, TAGS, truth, tag_idx, anc_idx) + np.abs(rng.normal(0.0, 0.15, 2 * n))
    s = np.full(d.size, 0.003)
    state, iterations, converged = platform_newton(A, TAGS, d, s, tag_idx, anc_idx, truth, None, 20)
    assert converged and iterations <= 10
    ref = least_squares(
        lambda x: (d - platform_ranges(A, TAGS, x, tag_idx, anc_idx)) / s,
        truth,
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
    )
    cost = np.sum(((d - platform_ranges(A, TAGS, state, tag_idx, anc_idx)) / s) ** 2)
    assert cost <= 2 * ref.cost * (1 + 1e-9)
    assert np.allclose(state, ref.x, atol=1e-6)


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("anchors", [PAPER_ANCHORS_3D, ANCHORS_5], ids=["4 anchors", "5 anchors"])
def test_the_wls_t_fix_is_the_least_squares_minimum_whatever_its_start(seed: int, anchors) -> None:
    # the Newton solve starts from the fix of each tag's per-link median ranges
    # (one solve, not one per epoch); where it ends must not depend on that

    rng = np.random.default_rng(seed)
    R = _ranges(anchors, seed)
    R[rng.random(R.shape) < 0.1] = np.nan  # dropped ranges
    fix = locate_platform(anchors, R, TAGS, SIGMA, base_lever=BASE)
    assert fix.converged and not fix.integrity.excluded
    finite = np.isfinite(R)
    tag_idx = np.broadcast_to(np.arange(2)[None, :, None], R.shape)[finite]
    anc_idx = np.broadcast_to(np.arange(len(anchors))[None, None, :], R.shape)[finite]
    ref = least_squares(
        lambda x: R[finite] - platform_ranges(anchors, TAGS, x, tag_idx, anc_idx),
        TRUTH,
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
    )
    np.testing.assert_allclose(fix.state, ref.x, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_the_newton_solve_sums_the_curvature_of_every_link(seed: int) -> None:
    # the solve's closed-form weighted sum is that of the per-link curvatures, and
    # those are the derivative of the Jacobian (central differences)
    rng = np.random.default_rng(seed)
    A = rng.uniform(-10.0, 10.0, (6, 3))
    tags = rng.uniform(-1.0, 1.0, (2, 3))
    x = np.r_[rng.uniform(-5.0, 5.0, 3), rng.uniform(-np.pi, np.pi)]
    tag_idx, anc_idx = np.repeat([0, 1], 6), np.tile(np.arange(6), 2)
    weight = rng.normal(0.0, 100.0, 12)
    lever, diff, dist = _links(A, tags, x, tag_idx, anc_idx)
    J = _jacobian(lever, diff, dist)
    each = range_curvature(A, tags, x, tag_idx, anc_idx)
    np.testing.assert_allclose(
        _weighted_curvature(lever, dist, weight, J),
        np.einsum("m,mij->ij", weight, each),
        rtol=1e-10,
        atol=1e-8,
    )
    h = 1e-6
    for k in range(4):
        dx = np.zeros(4)
        dx[k] = h
        numeric = (
            platform_jacobian(A, tags, x + dx, tag_idx, anc_idx)
            - platform_jacobian(A, tags, x - dx, tag_idx, anc_idx)
        ) / (2 * h)
        np.testing.assert_allclose(each[:, :, k], numeric, rtol=1e-5, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_tags=st.integers(1, 3), n_anchors=st.integers(3, 8))
def test_the_hypotheses_are_counted_as_they_are_made(seed: int, n_tags: int, n_anchors: int):
    # the mirror check needs only their number (Bonferroni), without making them
    rng = np.random.default_rng(seed)
    pairs = np.flatnonzero(rng.random(n_tags * n_anchors) < 0.7)
    m = len(pairs)
    adj = PlatformAdjustment(
        anchors=rng.uniform(-5.0, 5.0, (n_anchors, 3)),
        lever_arms=rng.uniform(-0.5, 0.5, (n_tags, 3)),
        d=np.ones(m), s=np.ones(m), tag_idx=pairs // n_anchors, anc_idx=pairs % n_anchors,
        bias_sigma=np.zeros(n_anchors), ids=tuple(f"A{j}" for j in range(n_anchors)),
        lever=np.zeros(3), heading_prior=None, heading_observed=n_tags > 1, alpha=1e-3,
        max_iter=20, count=np.ones(m), raw_mean=np.ones(m), raw_sq_dev=np.zeros(m),
    )  # fmt: skip
    for _ in range(5):
        use = rng.random(m) < rng.uniform(0.3, 1.0)
        labels, masks = adj.hypotheses(use)
        assert adj.n_hypotheses(use) == len(labels)
        # spelled out: each anchor reached, then per tag each of its links that is
        # not all its anchor has
        want_labels, want_masks = [], []
        anchors = sorted(set(adj.anc_idx[use].tolist()))
        for j in anchors:
            want_labels.append(f"anchor A{j}")
            want_masks.append(use & (adj.anc_idx == j))
        for k in range(n_tags if n_tags >= 2 else 0):
            for j in anchors:
                whole = use & (adj.anc_idx == j)
                link = whole & (adj.tag_idx == k)
                if link.any() and not np.array_equal(link, whole):
                    want_labels.append(f"anchor A{j} from tag {k}")
                    want_masks.append(link)
        assert labels == want_labels
        assert len(masks) == len(want_masks)
        assert all(np.array_equal(a, b) for a, b in zip(masks, want_masks, strict=True))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 12))
def test_the_batched_newton_solve_is_each_problems_own(seed: int, n: int) -> None:
    # problems with their own anchors, links left out, heading priors and starts,
    # padded to one length: each ends where platform_newton ends alone (the sums'
    # rounding can take one more or one less of the last, negligible steps); a
    # singular one is flagged, not raised

    rng = np.random.default_rng(seed)
    m = 2 * 6
    A_link, L_link = np.zeros((n, m, 3)), np.zeros((n, m, 3))
    d, weight, starts, prior = (
        np.zeros((n, m)),
        np.zeros((n, m)),
        np.zeros((n, 4)),
        np.zeros((n, 2)),
    )
    alone = []
    for b in range(n):
        k = int(rng.integers(3, 7))  # anchors of this problem
        A = rng.uniform([-8, -8, 0.5], [8, 8, 3.5], (k, 3))
        tag_idx, anc_idx = np.repeat([0, 1], k), np.tile(np.arange(k), 2)
        truth = np.r_[rng.uniform(-2, 2, 2), 0.0, rng.uniform(-np.pi, np.pi)]
        dd = platform_ranges(A, TAGS, truth, tag_idx, anc_idx) + rng.normal(0, 0.03, 2 * k)
        s = rng.uniform(0.01, 0.05, 2 * k)
        use = rng.random(2 * k) > 0.2
        use[:k] = use[k : k + 2] = True  # all anchors from tag 0, two from tag 1: determined
        if rng.random() < 0.15:
            use[:] = False  # no ranges: the normal matrix is singular
        start = truth + rng.normal(0.0, [0.3, 0.3, 0.3, 0.2])
        hp = (float(truth[3]), 0.05) if rng.random() < 0.3 else None
        A_link[b, : 2 * k], L_link[b, : 2 * k] = A[anc_idx], TAGS[tag_idx]
        d[b, : 2 * k], weight[b, : 2 * k] = dd, np.where(use, 1.0 / s**2, 0.0)
        starts[b] = start
        if hp is not None:
            prior[b] = hp[0], 1.0 / hp[1] ** 2
        try:
            alone.append(
                platform_newton(A, TAGS, dd[use], s[use], tag_idx[use], anc_idx[use], start, hp, 20)
            )
        except LocalizationError:
            alone.append(None)
    states, iterations, converged, solved = platform_newton_batch(
        A_link, L_link, d, weight, starts, prior, 20
    )
    for b, single in enumerate(alone):
        assert solved[b] == (single is not None)
        if single is None:
            continue
        assert converged[b] == single[2] and abs(iterations[b] - single[1]) <= 1
        np.testing.assert_allclose(states[b], single[0], rtol=0, atol=1e-7)


def test_the_hidden_mirrors_of_many_fixes_are_each_fixs_own() -> None:
    # a simulated run's visits are checked together; the padding of fixes with
    # fewer links (an anchor out of sight) changes nothing, nor does a mirror that
    # fits as well (anchors in one plane) failing one of them

    flat = np.array([[0.0, 0.0, 1.0], [4.8, 0.0, 1.0], [4.8, 6.0, 1.0], [0.0, 6.0, 1.02]])
    cases = []
    for seed, anchors in enumerate(
        [PAPER_ANCHORS_3D, ANCHORS_5, PAPER_ANCHORS_3D, ANCHORS_5, flat]
    ):
        r = _ranges(anchors, seed)
        if seed == 3:
            r[:, 1, 4] = np.nan  # tag 1 does not see the fifth anchor
        cases.append((anchors, r))
    alone = [_fix(a, r) for a, r in cases]
    later = [_fix(a, r, search_later=True) for a, r in cases]
    assert all(f.mirror_search is not None for f in later)
    together = finish_mirror_searches(later)
    assert any("mirror_by_one_fault" in f.integrity.checks for f in alone)
    assert not alone[-1].integrity.checks["mirror"]["passed"]  # anchors in one plane
    for a, t in zip(alone, together, strict=True):
        assert t.mirror_search is None
        assert (a.integrity.status, a.integrity.reason) == (t.integrity.status, t.integrity.reason)
        assert a.integrity.checks.keys() == t.integrity.checks.keys()
        for m, n in zip(
            a.integrity.checks.get("mirror_by_one_fault", []),
            t.integrity.checks.get("mirror_by_one_fault", []),
            strict=True,
        ):
            assert m["anchor"] == n["anchor"]
            np.testing.assert_allclose(m["base_shift_m"], n["base_shift_m"], atol=1e-9)
        assert a.integrity.protection_level == pytest.approx(t.integrity.protection_level)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 6))
def test_the_batched_global_tests_are_the_adjustments_own(seed: int, n: int) -> None:
    # the mirror verdicts test many fits at once with Woodbury's identity in closed
    # form (one anchor per link); each must be the adjustment's own global test

    rng = np.random.default_rng(seed)
    fits, states = [], []
    for _ in range(n):
        anchors = ANCHORS_5 if rng.random() < 0.5 else PAPER_ANCHORS_3D
        r = _ranges(anchors, int(rng.integers(0, 1000)), n=20)
        r[rng.random(r.shape) < 0.05] = np.nan
        bias = np.where(rng.random(len(anchors)) < 0.7, rng.uniform(0.0, 0.03, len(anchors)), 0.0)
        later = locate_platform(
            anchors, r, TAGS, SIGMA, anchor_bias_sigma=bias, base_lever=BASE, search_later=True
        )
        if later.mirror_search is None:
            continue
        adjustment, use, state, *_ = later.mirror_search
        use = use & (rng.random(use.size) < 0.9)
        if adjustment.n_anchors_used(use) < 3:
            continue
        fits.append((adjustment, use, state, state, True, 0.0))
        states.append(state + rng.normal(0.0, 0.05, 4))
    assume(fits)
    links = padded_links([(f[0], f[1]) for f in fits])
    observed = np.array([f[0].heading_observed for f in fits])
    redundancy, statistic = _global_tests(
        links, np.arange(len(fits)), np.array(states), observed, fits
    )
    for k, (f, x) in enumerate(zip(fits, states, strict=True)):
        r_ref, t_ref, _ = f[0].global_test(f[1], x)
        assert redundancy[k] == r_ref
        assert statistic[k] == pytest.approx(t_ref, rel=1e-9, abs=1e-9)


def test_many_platforms_located_together_are_each_located_alone() -> None:
    # a simulated run's visits: the first fits in one batched solve, then each
    # fix's own tests; the same fixes as one call each, defaults filled the same

    problems = [
        {"anchors": PAPER_ANCHORS_3D, "ranges": _ranges(PAPER_ANCHORS_3D, 0)},
        {"anchors": ANCHORS_5, "ranges": _ranges(ANCHORS_5, 1), "heading_prior": (0.5, 0.1)},
        {"anchors": ANCHORS_5, "ranges": _ranges(ANCHORS_5, 2), "method": "ls"},
    ]
    for p in problems:
        p.update(lever_arms=TAGS, sigma=SIGMA, base_lever=BASE)
    together = locate_platforms(problems)
    for p, t in zip(problems, together, strict=True):
        alone = locate_platform(**p)
        assert (alone.integrity.status, alone.iterations) == (t.integrity.status, t.iterations)
        np.testing.assert_allclose(t.state, alone.state, atol=1e-10)
        np.testing.assert_allclose(t.covariance, alone.covariance, rtol=1e-8, atol=1e-14)
    one_tag = {**problems[0], "lever_arms": TAGS[:1], "ranges": problems[0]["ranges"][:, :1]}
    with pytest.raises(LocalizationError, match="one UWB tag cannot observe the heading"):
        locate_platforms([*problems, one_tag])


def test_fixes_without_records_search_only_those_that_left_ranges_out() -> None:
    # a hidden mirror raises the protection level, which decides the status only of
    # a fix that left ranges out: without records the others are not searched, and
    # everything but that record is the same

    faulty = _ranges(ANCHORS_5, 7)
    faulty[:, 0, 3] += 0.5  # one link long: the tests leave it out
    problems = [
        {"anchors": a, "ranges": r, "lever_arms": TAGS, "sigma": SIGMA,
         "anchor_bias_sigma": np.full(len(a), 0.01), "base_lever": BASE}
        for a, r in ((PAPER_ANCHORS_3D, _ranges(PAPER_ANCHORS_3D, 6)), (ANCHORS_5, faulty))
    ]  # fmt: skip
    full = locate_platforms(problems)
    lean = locate_platforms(problems, records=False)
    assert [f.integrity.status for f in full] == ["ok", "excluded"]
    for f, g in zip(full, lean, strict=True):
        assert "mirror_by_one_fault" in f.integrity.checks
        np.testing.assert_array_equal(f.state, g.state)
        np.testing.assert_array_equal(f.covariance, g.covariance)
        assert (f.integrity.status, f.integrity.reason) == (g.integrity.status, g.integrity.reason)
    assert "mirror_by_one_fault" not in lean[0].integrity.checks
    assert lean[1].integrity.to_dict() == full[1].integrity.to_dict()


def test_a_mirror_found_last_reads_as_found_right_after_the_record() -> None:
    # the mirror checks are made after the fix's other checks, whose reasons stand
    # first; the mirror's goes where it went when it was checked first

    recorded = Integrity(status="excluded", reason="left out anchor A4")
    then = recorded.failing("MIRROR").failing("not converged")
    now = failing_first(recorded.failing("not converged"), "MIRROR", recorded.reason)
    assert (now.status, now.reason) == (then.status, then.reason)
    assert failing_first(recorded, "MIRROR", recorded.reason).reason == "MIRROR; left out anchor A4"
    clean = Integrity(status="ok")
    assert (
        failing_first(clean.failing("X"), "MIRROR", "").reason
        == clean.failing("MIRROR").failing("X").reason
    )
    assert failing_first(clean, "MIRROR", "").reason == "MIRROR"


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 8))
def test_many_fixes_are_tested_as_each_alone(seed: int, n: int) -> None:
    # fixes of two shapes (links used, heading prior, anchor biases) mixed in one
    # call: each is grouped with its own shape and tested as it is alone
    rng = np.random.default_rng(seed)

    def adjustment(shape: int) -> tuple[PlatformAdjustment, np.ndarray, np.ndarray]:
        pairs = np.arange(8) if shape == 0 else np.array([0, 1, 2, 4, 5, 6, 7])
        m = len(pairs)
        adj = PlatformAdjustment(
            anchors=rng.uniform(-5.0, 5.0, (4, 3)), lever_arms=TAGS,
            d=rng.uniform(2.0, 6.0, m), s=rng.uniform(0.01, 0.05, m),
            tag_idx=pairs // 4, anc_idx=pairs % 4,
            bias_sigma=np.full(4, 0.01 * shape), ids=("A1", "A2", "A3", "A4"),
            lever=BASE, heading_prior=None if shape == 0 else (0.3, 0.1),
            heading_observed=True, alpha=1e-3, max_iter=20,
            count=np.full(m, 30), raw_mean=np.ones(m), raw_sq_dev=np.zeros(m),
        )  # fmt: skip
        use = rng.random(m) < 0.9 if shape == 1 else np.ones(m, dtype=bool)
        return adj, use, np.r_[rng.uniform(-1.0, 1.0, 3), rng.uniform(-np.pi, np.pi)]

    problems = [adjustment(int(rng.integers(0, 2))) for _ in range(n)]
    for (adj, use, state), (got, masks) in zip(problems, grouped_tests(problems), strict=True):
        want, want_masks = adj.tests(use, state)
        assert got.labels == want.labels and got.redundancy == want.redundancy
        assert all(np.array_equal(a, b) for a, b in zip(masks, want_masks, strict=True))
        assert got.statistic == pytest.approx(want.statistic, rel=1e-10)
        for name in ("w", "thresholds", "mdb", "shift"):
            np.testing.assert_allclose(getattr(got, name), getattr(want, name), rtol=1e-9)


def test_fixes_of_one_shape_finished_together_are_each_finished_alone() -> None:
    # a run's visits share anchors and links: their covariances, residuals, records and
    # geometry checks come from one stacked solve per shape, with a fix that left a
    # link out among them

    problems = []
    for seed in range(4):
        r = _ranges(PAPER_ANCHORS_3D, 20 + seed)
        if seed == 2:
            r[:, 1, 2] += 0.5
        problems.append({"anchors": PAPER_ANCHORS_3D, "ranges": r})
    problems += [{"anchors": ANCHORS_5, "ranges": _ranges(ANCHORS_5, 30 + k)} for k in range(2)]
    for p in problems:
        p.update(lever_arms=TAGS, sigma=SIGMA, base_lever=BASE)
        p["anchor_bias_sigma"] = np.full(len(p["anchors"]), 0.01)
    together = locate_platforms(problems)
    assert "excluded" in [t.integrity.status for t in together]
    for p, t in zip(problems, together, strict=True):
        alone = locate_platform(**p)
        assert (t.integrity.status, t.integrity.reason) == (
            alone.integrity.status,
            alone.integrity.reason,
        )
        np.testing.assert_allclose(t.covariance, alone.covariance, rtol=1e-10, atol=1e-16)
        np.testing.assert_allclose(t.residuals, alone.residuals, rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(t.per_anchor_rms, alone.per_anchor_rms, rtol=1e-10)
        for name in ("pdop", "outside_coverage_m"):
            assert t.integrity.checks[name] == pytest.approx(alone.integrity.checks[name])


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    anchor=st.integers(0, 4),
    tag=st.sampled_from([0, 1, None]),
    offset=st.floats(0.1, 0.8),
)
def test_the_refits_of_every_hypothesis_at_once_are_each_hypothesis_own(
    seed: int, anchor: int, tag: int | None, offset: float
) -> None:
    # identify_by_refit fits every hypothesis' ranges from the fix and from that
    # fit's mirror image in two batched solves and tests them in one call: each
    # trial is the better of the hypothesis' own two fits, made one at a time
    r = _ranges(ANCHORS_5, seed % 1000)
    r[:, slice(None) if tag is None else tag, anchor] += offset
    later = _fix(ANCHORS_5, r, search_later=True)
    assume(later.mirror_search is not None)
    adj, use, state, *_ = later.mirror_search
    tests, masks = adj.tests(np.ones(adj.d.size, dtype=bool), state)
    left = [
        (k, use & ~masks[k])
        for k in range(len(tests.labels))
        if adj.n_anchors_used(use & ~masks[k]) >= 3
    ]
    got = {t.index: t for t in _refits(adj, left, state, tests.labels)}
    for k, rest in left:
        fits = []
        try:
            fits.append(adj.fit(rest, state))
            fits.append(adj.fit(rest, reflected(adj, rest, fits[0][0])[0]))
        except LocalizationError:
            if not fits:
                assert k not in got
                continue
        tested = [(st, conv, adj.tests(rest, st)[0]) for st, _, conv in fits]
        st, conv, want = min(tested, key=lambda f: (not f[1], f[2].statistic))
        trial = got[k]
        assert trial.label == tests.labels[k] and np.array_equal(trial.use, rest)
        assert trial.converged == conv and trial.passed == (conv and want.passed)
        np.testing.assert_allclose(trial.state, st, rtol=0, atol=1e-7)
        assert trial.tests.statistic == pytest.approx(want.statistic, rel=1e-6, abs=1e-9)
