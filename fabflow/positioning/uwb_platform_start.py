"""The start of a standing platform's UWB fix: its ranges as link means, its first pose.

:func:`link_means` holds a platform's ranges as one observation per tag-anchor
link (:class:`~fabflow.positioning.uwb_platform_adjustment.PlatformAdjustment`);
:func:`initial_state` gives the pose the Newton solve of
:func:`~fabflow.positioning.uwb_platform.locate_platform` starts from, from each
tag's fix of its per-link median ranges (:func:`median_seeds`, one call for many
stations) or of its epochs.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fabflow.errors import LocalizationError
from fabflow.positioning.medians import nanmedian
from fabflow.positioning.uwb import Method, Sigma, locate
from fabflow.positioning.uwb_platform_model import rotz_many


def link_means(
    d: np.ndarray, s: np.ndarray, tag_idx: np.ndarray, anc_idx: np.ndarray, n_anchors: int
) -> dict[str, np.ndarray]:
    """A standing platform's ranges as one observation per tag-anchor link.

    Returns the per-link fields of
    :class:`~fabflow.positioning.uwb_platform_adjustment.PlatformAdjustment`
    (``d, s, tag_idx, anc_idx, count, raw_mean, raw_sq_dev``) from ranges
    ``d`` with standard deviations ``s`` (metres) of the tags ``tag_idx`` to the
    anchors ``anc_idx``, and ``link``: the link of each range (index into them).
    """
    tag_idx = np.asarray(tag_idx)
    n_tags = int(tag_idx.max(initial=-1)) + 1
    one = np.zeros(len(tag_idx), dtype=np.intp)
    return link_means_many(d, s, one, tag_idx, anc_idx, 1, n_tags, n_anchors)[0]


def link_means_many(
    d: np.ndarray,
    s: np.ndarray,
    platform: np.ndarray,
    tag_idx: np.ndarray,
    anc_idx: np.ndarray,
    n_platforms: int,
    n_tags: int,
    n_anchors: int,
) -> list[dict[str, np.ndarray]]:
    """:func:`link_means` of many platforms in one pass: the ranges ``d`` (metres) of
    all of them, ``platform`` the platform of each (ascending). Each platform's
    links are those :func:`link_means` gives it alone, to the bit (a link's sums
    add its ranges in their order either way).
    """
    per = n_tags * n_anchors
    key = (np.asarray(platform) * n_tags + np.asarray(tag_idx)) * n_anchors + np.asarray(anc_idx)
    # np.unique's sorted links and inverse, from a count: the keys are a few small integers
    present = np.bincount(key, minlength=n_platforms * per) > 0
    links = np.flatnonzero(present)
    link = (np.cumsum(present) - 1)[key]
    w = 1.0 / s**2
    W = np.bincount(link, weights=w)
    mean = np.bincount(link, weights=w * d) / W
    sd = 1.0 / np.sqrt(W)
    count = np.bincount(link)
    raw_mean = np.bincount(link, weights=d) / count
    sq_dev = np.bincount(link, weights=(d - raw_mean[link]) ** 2)
    bounds = np.arange(n_platforms + 1)
    first_link = np.searchsorted(links, bounds * per)
    first_range = np.searchsorted(platform, bounds)
    out = []
    for k in range(n_platforms):
        own = slice(first_link[k], first_link[k + 1])
        local = links[own] - k * per
        out.append(
            {
                "d": mean[own],
                "s": sd[own],
                "tag_idx": local // n_anchors,
                "anc_idx": local % n_anchors,
                "count": count[own],
                "raw_mean": raw_mean[own],
                "raw_sq_dev": sq_dev[own],
                "link": link[first_range[k] : first_range[k + 1]] - first_link[k],
            }
        )
    return out


def initial_state(
    A: np.ndarray,
    R: np.ndarray,
    L: np.ndarray,
    sigma: Sigma,
    method: Method,
    heading_prior: tuple[float, float] | None,
    seeds: np.ndarray | None = None,
) -> tuple[np.ndarray, bool]:
    """``[x, y, z, yaw]`` from the median per-tag fixes, and whether the heading is observed.

    With ``wls-t`` the median pose only starts the Newton solve on all ranges, so
    each tag's start is the fix of its per-link median ranges (:func:`median_seeds`,
    or ``seeds`` given); a tag's per-epoch fixes are the fallback when its fails.
    :func:`tag_starts`, then :func:`initial_states` of one.
    """
    tags = tag_starts(A, R, L, sigma, method, seeds)
    states, observed = initial_states(L, tags[None], [heading_prior])
    return states[0], bool(observed[0])


def tag_starts(
    A: np.ndarray,
    R: np.ndarray,
    L: np.ndarray,
    sigma: Sigma,
    method: Method,
    seeds: np.ndarray | None = None,
) -> np.ndarray:
    """Each tag's start position ``(n_tags, 3)`` (metres) for :func:`initial_state`.

    Raises
    ------
    LocalizationError
        A tag without a seed whose epochs give no fix.
    """
    n_tags = L.shape[0]
    tag_pos = np.empty((n_tags, 3))
    seeded = np.zeros(n_tags, dtype=bool)
    if method == "wls-t":
        seed = median_seeds(A, R, sigma) if seeds is None else np.asarray(seeds, dtype=float)
        seeded = np.isfinite(seed).all(axis=-1)
        tag_pos[seeded] = seed[seeded]
    for k in np.flatnonzero(~seeded):
        fix = locate(A, R[:, k, :], method=method, sigma=sigma)
        if not fix.valid.any():
            raise LocalizationError(
                f"tag {k}: no epoch has enough usable ranges ({int((~fix.too_few).sum())} of "
                f"{len(fix.valid)} epochs with >= 4 ranges, {int(fix.degenerate.sum())} degenerate)"
            )
        tag_pos[k] = nanmedian(fix.positions[fix.valid], 0)
    return tag_pos


def initial_states(
    L: np.ndarray,
    tag_pos: np.ndarray,
    heading_priors: Sequence[tuple[float, float] | None],
) -> tuple[np.ndarray, np.ndarray]:
    """The start poses ``[x, y, z, yaw]`` ``(P, 4)`` of ``P`` platforms with the lever
    arms ``L`` ``(n_tags, 3)`` from their tags' start positions ``(P, n_tags, 3)``
    (:func:`tag_starts`; metres), and whether each one's heading is observed: the
    2D Procrustes fit of the lever arms to the tags, the prior's yaw with one tag
    (which needs a prior) or where the fit gives none."""
    n_tags = L.shape[0]
    has_prior = np.array([h is not None for h in heading_priors], dtype=bool)
    prior_yaw = np.array([np.nan if h is None else float(h[0]) for h in heading_priors])
    if n_tags >= 2:
        lc = L[:, :2] - L[:, :2].mean(axis=0)
        mc = tag_pos[..., :2] - tag_pos[..., :2].mean(axis=1)[:, None]
        yaw0 = np.arctan2(
            np.sum(lc[:, 0] * mc[..., 1] - lc[:, 1] * mc[..., 0], axis=-1),
            np.sum(lc * mc, axis=(-2, -1)),
        )
        observed = np.full(len(tag_pos), bool(np.linalg.norm(lc, axis=1).max() > 0.05))
        yaw0 = np.where(has_prior & ~np.isfinite(yaw0), prior_yaw, yaw0)
    else:
        yaw0 = prior_yaw
        observed = np.zeros(len(tag_pos), dtype=bool)
    p0 = tag_pos.mean(axis=1) - rotz_many(yaw0) @ L.mean(axis=0)
    return np.column_stack([p0, yaw0]), observed | has_prior


def median_seeds(A: np.ndarray, R: np.ndarray, sigma: Sigma) -> np.ndarray:
    """Each tag's ``wls-t`` fix of its per-link median ranges, ``(..., tags, 3)``
    (metres; NaN where it fails), for ranges ``(rounds, ..., tags, anchors)``: one
    :func:`~fabflow.positioning.uwb.locate` call for every tag of every station
    (one epoch each), where there were as many as tags and stations."""
    medians = nanmedian(R, 0)
    seed = locate(A, medians.reshape(-1, A.shape[0]), method="wls-t", sigma=sigma)
    return seed.positions.reshape(*medians.shape[:-1], 3)
