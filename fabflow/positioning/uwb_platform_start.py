"""The start of a standing platform's UWB fix: its ranges as link means, its first pose.

:func:`link_means` holds a platform's ranges as one observation per tag-anchor
link (:class:`~fabflow.positioning.uwb_platform_adjustment.PlatformAdjustment`);
:func:`initial_state` gives the pose the Newton solve of
:func:`~fabflow.positioning.uwb_platform.locate_platform` starts from, from each
tag's fix of its per-link median ranges (:func:`median_seeds`, one call for many
stations) or of its epochs.
"""

from __future__ import annotations

import numpy as np

from fabflow.errors import LocalizationError
from fabflow.positioning.medians import nanmedian
from fabflow.positioning.uwb import Method, Sigma, locate
from fabflow.positioning.uwb_platform_model import rotz


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
    key = np.asarray(tag_idx) * n_anchors + np.asarray(anc_idx)
    # np.unique's sorted links and inverse, from a count: the keys are a few small integers
    present = np.bincount(key) > 0
    links = np.flatnonzero(present)
    link = (np.cumsum(present) - 1)[key]
    w = 1.0 / s**2
    W = np.bincount(link, weights=w)
    mean = np.bincount(link, weights=w * d) / W
    count = np.bincount(link)
    raw_mean = np.bincount(link, weights=d) / count
    return {
        "d": mean,
        "s": 1.0 / np.sqrt(W),
        "tag_idx": links // n_anchors,
        "anc_idx": links % n_anchors,
        "count": count,
        "raw_mean": raw_mean,
        "raw_sq_dev": np.bincount(link, weights=(d - raw_mean[link]) ** 2),
        "link": link,
    }


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
    if n_tags >= 2:
        lc = L[:, :2] - L[:, :2].mean(axis=0)
        mc = tag_pos[:, :2] - tag_pos[:, :2].mean(axis=0)
        yaw0 = np.arctan2(np.sum(lc[:, 0] * mc[:, 1] - lc[:, 1] * mc[:, 0]), np.sum(lc * mc))
        heading_observed = bool(np.linalg.norm(lc, axis=1).max() > 0.05)
    else:
        yaw0 = float(heading_prior[0])  # type: ignore[index]
        heading_observed = False
    if heading_prior is not None:
        heading_observed = True
        if n_tags >= 2 and not np.isfinite(yaw0):
            yaw0 = heading_prior[0]
    p0 = tag_pos.mean(axis=0) - rotz(yaw0) @ L.mean(axis=0)
    return np.array([*p0, yaw0]), heading_observed


def median_seeds(A: np.ndarray, R: np.ndarray, sigma: Sigma) -> np.ndarray:
    """Each tag's ``wls-t`` fix of its per-link median ranges, ``(..., tags, 3)``
    (metres; NaN where it fails), for ranges ``(rounds, ..., tags, anchors)``: one
    :func:`~fabflow.positioning.uwb.locate` call for every tag of every station
    (one epoch each), where there were as many as tags and stations."""
    medians = nanmedian(R, 0)
    seed = locate(A, medians.reshape(-1, A.shape[0]), method="wls-t", sigma=sigma)
    return seed.positions.reshape(*medians.shape[:-1], 3)
