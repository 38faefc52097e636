"""Medians of many small samples that skip NaN, without numpy's slow path for them.

``np.nanmedian`` computes the medians of small arrays through masked arrays, about
0.6 ms a call whatever the size: more than the UWB solves it seeds. Sorting
(NaN sorts last) and taking the middle of the finite values gives the same
numbers, bit for bit: the mean of the two middle values, ``(low + high) / 2``,
which is the value itself for an odd count.
"""

from __future__ import annotations

import numpy as np


def nanmedian(a: np.ndarray, axis: int | tuple[int, ...] = 0) -> np.ndarray:
    """Median along ``axis`` ignoring NaN, equal to ``np.nanmedian(a, axis)``.

    Parameters
    ----------
    a
        Values (any units; float).
    axis
        Axis or axes reduced.

    Returns
    -------
    numpy.ndarray
        The medians, NaN where a slice holds no number (``np.nanmedian`` also
        warns there; this does not).
    """
    a = np.asarray(a, dtype=float)
    axes = (axis,) if isinstance(axis, int) else tuple(axis)
    axes = tuple(ax % a.ndim for ax in axes)
    kept = [ax for ax in range(a.ndim) if ax not in axes]
    flat = np.transpose(a, kept + list(axes)).reshape(*(a.shape[ax] for ax in kept), -1)
    s = np.sort(flat, axis=-1)
    n = np.count_nonzero(~np.isnan(s), axis=-1)
    high = n // 2
    low = np.where(n % 2 == 1, high, high - 1)
    # an all-NaN slice takes its first (NaN) value
    low_v = np.take_along_axis(s, np.maximum(low, 0)[..., None], axis=-1)[..., 0]
    high_v = np.take_along_axis(s, high[..., None], axis=-1)[..., 0]
    return np.where(n > 0, (low_v + high_v) / 2.0, np.nan)
