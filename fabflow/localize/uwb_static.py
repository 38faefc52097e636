"""The UWB estimate of a standing platform from its ranges, for simulated and measured ones.

One estimator for both: the ranges of every tag-anchor link are cleaned around
the link's robust centre
(:func:`~fabflow.positioning.uwb_calibration.reject_outliers_static`), the bias
the NLOS ranges the cleaning keeps leave in each link's mean is taken off with
its spread (:func:`without_nlos_leak`), and
:func:`~fabflow.positioning.uwb_platform.locate_platform` gives the pose with
its tests. :func:`fabflow.localize.uwb.estimate_station` feeds it simulated
ranges, :mod:`fabflow.localize.uwb_files` measured ones.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fabflow.positioning.adjustment_tests import ALPHA
from fabflow.positioning.medians import nanmedian
from fabflow.positioning.uwb import Method
from fabflow.positioning.uwb_calibration import (
    Rejection,
    kept_centre,
    kept_mean_variance,
    kept_moments,
    reject_outliers_static,
    static_window,
)
from fabflow.positioning.uwb_platform import PlatformFix, locate_platforms
from fabflow.positioning.uwb_platform_start import median_seeds
from fabflow.sensors.uwb import UwbErrorModel


def static_fix(
    model: UwbErrorModel,
    A: np.ndarray,
    ranges: np.ndarray,
    L: np.ndarray,
    link_sigma: Any,
    anchor_bias_sigma: np.ndarray,
    method: Method = "wls-t",
    heading_prior: tuple[float, float] | None = None,
    alpha: float = ALPHA,
    anchor_ids: Sequence[str] | None = None,
    base_lever: np.ndarray | None = None,
) -> tuple[PlatformFix, Rejection]:
    """The platform fix of a standing platform's calibrated ranges, and what was rejected.

    Parameters
    ----------
    model
        The ranging error model: the noise ``sigma(d)`` that weighs the ranges
        and sets the cleaning's window, and the NLOS excess it may keep.
    A
        (n, 3) anchor positions (metres, the frame of the fix).
    ranges
        (rounds, tags, anchors) calibrated ranges (metres; NaN where none).
    L
        (tags, 3) the tags in the platform frame (metres).
    link_sigma
        The error every range of one link shares (multipath, material): a
        function of the range or one value per link (metres).
    anchor_bias_sigma
        (n,) the error every range to one anchor shares (the calibration's).
    method, heading_prior, alpha, anchor_ids, base_lever
        As :func:`~fabflow.positioning.uwb_platform.locate_platform` takes them.
    """
    per_link = link_sigma if callable(link_sigma) else np.asarray(link_sigma, dtype=float)[None]
    return static_fixes(
        model, A, np.asarray(ranges, dtype=float)[:, None], L, per_link,
        np.asarray(anchor_bias_sigma, dtype=float)[None], method, [heading_prior], alpha,
        anchor_ids, base_lever,
    )[0]  # fmt: skip


def static_fixes(
    model: UwbErrorModel,
    A: np.ndarray,
    ranges: np.ndarray,
    L: np.ndarray,
    link_sigma: Any,
    anchor_bias_sigma: np.ndarray,
    method: Method = "wls-t",
    heading_priors: Sequence[tuple[float, float] | None] | None = None,
    alpha: float = ALPHA,
    anchor_ids: Sequence[str] | None = None,
    base_lever: np.ndarray | None = None,
    records: bool = True,
) -> list[tuple[PlatformFix, Rejection]]:
    """:func:`static_fix` of several standing platforms that range with the same anchors.

    The cleaning and the NLOS correction treat every link on its own, so they
    run on all the stations' links at once (a simulated run's visits: one call
    where there were as many calls as visits); then each station's fix. A
    station's numbers are those :func:`static_fix` gives it alone, except that
    the correction's integration grid is the finest any of the stations needs
    (:func:`~fabflow.positioning.uwb_calibration.kept_mean_variance`: the same
    with the error model's default noise).

    Parameters
    ----------
    ranges
        (rounds, stations, tags, anchors) calibrated ranges (metres; NaN where none).
    link_sigma
        A function of the range, or (stations, tags, anchors) values (metres).
    anchor_bias_sigma
        (stations, n) per station.
    heading_priors
        Per station, as ``heading_prior`` (default: none).
    model, A, L, method, alpha, anchor_ids, base_lever
        As :func:`static_fix` takes them.
    records
        False: the fixes' records without what cannot change a status
        (:func:`~fabflow.positioning.uwb_platform.finish_mirror_searches`).
    """
    n_stations = ranges.shape[1]
    priors = [None] * n_stations if heading_priors is None else list(heading_priors)
    rej = reject_outliers_static(ranges, model.sigma(ranges))
    kept, per_link = without_nlos_leak(model, ranges, rej.ranges, link_sigma)
    seeds = median_seeds(A, kept, model.sigma) if method == "wls-t" else [None] * n_stations
    # every station's first fit, mirror checks and hidden-mirror search solved together
    fixes = locate_platforms(
        [
            {
                "anchors": A, "ranges": kept[:, v], "lever_arms": L, "sigma": model.sigma,
                "method": method, "heading_prior": priors[v],
                "anchor_bias_sigma": anchor_bias_sigma[v], "link_sigma": per_link[v],
                "anchor_ids": anchor_ids, "base_lever": base_lever, "alpha": alpha,
                "seeds": seeds[v],
            }
            for v in range(n_stations)
        ],
        records,
    )  # fmt: skip
    return [
        (fix, Rejection(rej.ranges[:, v], rej.rejected[:, v], rej.out_of_bounds[:, v]))
        for v, fix in enumerate(fixes)
    ]


def without_nlos_leak(
    model: UwbErrorModel, ranges: np.ndarray, kept: np.ndarray, link_sigma: Any
) -> tuple[np.ndarray, np.ndarray]:
    """The ranges the rejection kept, less the bias that what it kept leaves in each
    link's mean, and each link's shared sigma with what that adds to the mean's
    spread (metres; :func:`~fabflow.positioning.uwb_calibration.kept_moments`: an
    NLOS range with a small excess falls within the rejection's window now and
    then, and moves the window's centre too).

    Each link's share of NLOS ranges is estimated from the share the rejection
    left out (``ranges`` before it, ``kept`` after) of the ranges the error model
    explains (within the window below, within the NLOS excess above): a line of
    sight the structure blocks shows about half, a clear one the error model's
    ``nlos_prob``. ``link_sigma``: the shared sigma so far, a function of the
    range or one value per link.
    """
    centre = nanmedian(kept, 0)
    d = np.where(np.isfinite(centre), centre, 1.0)
    sigma = model.sigma(d)
    # the window's half-widths: a multiple of the sigma at the range measured
    upper = lower = static_window(sigma)
    for _ in range(3):
        upper = static_window(model.sigma(d + upper))
        lower = static_window(model.sigma(np.maximum(d - lower, 0.0)))
    # Only ranges the error model can explain count: the noise about the link's
    # distance and its NLOS excess. One rejected for what the model does not hold
    # (a dropout's zero, a spike metres long, as measured files have) says nothing
    # of the NLOS share, and counted as NLOS it would pull the link short.
    explained = (ranges >= d - lower - 3.0 * sigma) & (
        ranges <= d + model.nlos_excess[1] + upper + 3.0 * sigma
    )
    n = explained.sum(axis=0)
    n_kept = np.isfinite(kept).sum(axis=0)
    observed = n_kept / np.maximum(n, 1)
    p, shift = np.full(d.shape, model.nlos_prob), np.zeros(d.shape)
    for _ in range(2):  # the NLOS share and the window's centre, each given the other
        share_los, *_, share_nlos = kept_moments(
            0.0, model.nlos_excess, sigma, lower - shift, upper + shift
        )
        p = np.clip((share_los - observed) / np.maximum(share_los - share_nlos, 1e-12), 0.0, 1.0)
        shift = kept_centre(p, model.nlos_excess, sigma, lower, upper)
    window = (sigma, lower - shift, upper + shift)
    share, first, *_ = kept_moments(p, model.nlos_excess, *window)
    bias = first / np.maximum(share, 1e-12)
    # how the bias follows the share kept (through the NLOS share, the window held)
    step = np.where(p + 1e-4 <= 1.0, 1e-4, -1e-4)
    share_by, first_by, *_ = kept_moments(p + step, model.nlos_excess, *window)
    gap = np.maximum(share_los - share_nlos, 1e-12)
    slope = -(first_by / np.maximum(share_by, 1e-12) - bias) / step / gap
    slope = np.where((p > 0.0) & (p < 1.0), slope, 0.0)  # a clipped share does not move
    # the corrected mean's variance over n epochs (the window's wander and the share's
    # in it too), less the noise's that the fit counts
    variance = kept_mean_variance(
        p, model.nlos_excess, sigma, lower, upper, shift, slope
    ) / np.maximum(n, 1)
    spread = np.sqrt(np.maximum(variance - sigma**2 / np.maximum(n_kept, 1), 0.0))
    shared = link_sigma(d) if callable(link_sigma) else np.asarray(link_sigma, dtype=float)
    return kept - bias[None], np.hypot(np.broadcast_to(shared, d.shape), spread)
