"""The start of many standing platforms' UWB fixes made at once: each platform's link
means, start pose and design matrix are those it gets alone, to the bit.

Random platforms (1-3 tags, 3-6 anchors, ranges missing at random, some platforms
without any), seeded by hypothesis.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.positioning.uwb_platform_model import (
    jacobians_many,
    platform_jacobian,
    platform_ranges,
    rotz,
)
from fabflow.positioning.uwb_platform_start import (
    initial_state,
    initial_states,
    link_means,
    link_means_many,
    tag_starts,
)

FIELDS = ("d", "s", "tag_idx", "anc_idx", "count", "raw_mean", "raw_sq_dev", "link")


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n_platforms=st.integers(1, 6),
    n_tags=st.integers(1, 3),
    n_anchors=st.integers(3, 6),
    missing=st.floats(0.0, 0.9),
)
def test_the_link_means_of_many_platforms_are_each_platforms_own(
    seed: int, n_platforms: int, n_tags: int, n_anchors: int, missing: float
) -> None:
    rng = np.random.default_rng(seed)
    rounds = int(rng.integers(1, 12))
    R = rng.uniform(1.0, 9.0, (n_platforms, rounds, n_tags, n_anchors))
    R[rng.random(R.shape) < missing] = np.nan
    if n_platforms > 1 and rng.random() < 0.3:
        R[int(rng.integers(0, n_platforms))] = np.nan  # a platform without a range
    flat = np.flatnonzero(np.isfinite(R))
    d = R.ravel()[flat]
    s = rng.uniform(0.01, 0.1, d.size)
    platform = flat // R[0].size
    many = link_means_many(
        d, s, platform, flat // n_anchors % n_tags, flat % n_anchors, n_platforms, n_tags,
        n_anchors,
    )  # fmt: skip
    assert len(many) == n_platforms
    for k, got in enumerate(many):
        own = platform == k
        local = flat[own] - k * R[0].size
        tag, anchor = local // n_anchors % n_tags, local % n_anchors
        alone = link_means(d[own], s[own], tag, anchor, n_anchors)
        for name in FIELDS:
            np.testing.assert_array_equal(got[name], alone[name], err_msg=name)
        # and the links are what they say: every range's link is its tag and anchor
        assert np.array_equal(got["tag_idx"][got["link"]], tag)
        assert np.array_equal(got["anc_idx"][got["link"]], anchor)
        assert got["count"].sum() == own.sum()


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n_platforms=st.integers(1, 6),
    n_tags=st.integers(1, 3),
)
def test_the_start_poses_of_many_platforms_are_each_platforms_own(
    seed: int, n_platforms: int, n_tags: int
) -> None:
    rng = np.random.default_rng(seed)
    A = rng.uniform([-6.0, -6.0, 0.5], [6.0, 6.0, 3.5], (5, 3))
    L = rng.uniform(-0.8, 0.8, (n_tags, 3))
    tags, priors = [], []
    for _ in range(n_platforms):
        tags.append(rng.uniform(-3.0, 3.0, (n_tags, 3)))
        with_prior = n_tags == 1 or rng.random() < 0.3
        priors.append((float(rng.uniform(-np.pi, np.pi)), 0.1) if with_prior else None)
    states, observed = initial_states(L, np.stack(tags), priors)
    for k in range(n_platforms):
        # the same pose through the one-platform entry point, its tags given as seeds
        R = np.full((1, n_tags, len(A)), np.nan)
        np.testing.assert_array_equal(tag_starts(A, R, L, 0.05, "wls-t", tags[k]), tags[k])
        alone, alone_observed = initial_state(A, R, L, 0.05, "wls-t", priors[k], tags[k])
        np.testing.assert_array_equal(states[k], alone)
        assert observed[k] == alone_observed
        if n_tags == 1:
            assert states[k, 3] == priors[k][0] and observed[k]  # type: ignore[index]
        else:
            # the yaw turns the centred lever arms onto the centred tags (2D Procrustes)
            c, s = np.cos(states[k, 3]), np.sin(states[k, 3])
            lc = L[:, :2] - L[:, :2].mean(axis=0)
            mc = tags[k][:, :2] - tags[k][:, :2].mean(axis=0)
            turned = lc @ np.array([[c, s], [-s, c]])
            other = lc @ np.array([[-c, -s], [s, -c]])  # half a turn more
            assert np.sum(turned * mc) >= np.sum(other * mc) - 1e-12


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_platforms=st.integers(1, 6))
def test_the_jacobians_of_many_platforms_are_each_platforms_own(seed: int, n_platforms: int):
    # the tests and covariances of a run's fixes take their design matrices and
    # predicted ranges in one call: each platform's, to the bit, as alone
    rng = np.random.default_rng(seed)
    n_tags, n_anchors = int(rng.integers(1, 4)), int(rng.integers(3, 7))
    tag_idx = np.repeat(np.arange(n_tags), n_anchors)
    anc_idx = np.tile(np.arange(n_anchors), n_tags)
    keep = rng.random(tag_idx.size) < 0.8
    keep[0] = True
    tag_idx, anc_idx = tag_idx[keep], anc_idx[keep]
    A = rng.uniform(-8.0, 8.0, (n_platforms, n_anchors, 3))
    L = rng.uniform(-1.0, 1.0, (n_platforms, n_tags, 3))
    states = np.column_stack(
        [rng.uniform(-3.0, 3.0, (n_platforms, 3)), rng.uniform(-np.pi, np.pi, n_platforms)]
    )
    J, ranges = jacobians_many(A[:, anc_idx], L, states, tag_idx)
    for k in range(n_platforms):
        np.testing.assert_array_equal(
            J[k], platform_jacobian(A[k], L[k], states[k], tag_idx, anc_idx)
        )
        np.testing.assert_array_equal(
            ranges[k], platform_ranges(A[k], L[k], states[k], tag_idx, anc_idx)
        )
        tags = states[k, :3] + L[k] @ rotz(states[k, 3]).T
        np.testing.assert_allclose(
            ranges[k], np.linalg.norm(tags[tag_idx] - A[k, anc_idx], axis=1), rtol=1e-12
        )
