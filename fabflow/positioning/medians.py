"""Medians of many small samples that skip NaN, without numpy's slow path for them.

``np.nanmedian`` computes the medians of small arrays through masked arrays, about
a quarter of a millisecond a call whatever the size: more than the UWB solves it
seeds. Sorting (NaN sorts last) and taking the middle of the finite values gives
the same numbers, bit for bit: the mean of the two middle values,
``(low + high) / 2``, which is the value itself for an odd count.
"""

from __future__ import annotations

import operator
from collections.abc import Sequence

import numpy as np


def nanmedian(a: np.ndarray, axis: int | Sequence[int] = 0) -> np.ndarray:
    """Median along ``axis`` ignoring NaN, equal to ``np.nanmedian(a, axis)`` for real input.

    Parameters
    ----------
    a
        Values (any units; taken as float).
    axis
        Axis or axes reduced.

    Returns
    -------
    numpy.ndarray
        The medians, NaN where a slice holds no number, empty slices included
        (``np.nanmedian`` also warns there; this does not).
    """
    a = np.asarray(a, dtype=float)
    axes = (axis,) if not isinstance(axis, Sequence) else tuple(axis)
    axes = tuple(operator.index(ax) % a.ndim for ax in axes)
    kept = [ax for ax in range(a.ndim) if ax not in axes]
    kept_shape = tuple(a.shape[ax] for ax in kept)
    size = int(np.prod([a.shape[ax] for ax in axes]))
    if size == 0:
        return np.full(kept_shape, np.nan)
    flat = np.transpose(a, kept + list(axes)).reshape(*kept_shape, size)
    s = np.sort(flat, axis=-1)
    n = np.count_nonzero(~np.isnan(s), axis=-1)
    high = n // 2
    low = np.where(n % 2 == 1, high, high - 1)
    # an all-NaN slice takes its first (NaN) value
    low_v = np.take_along_axis(s, np.maximum(low, 0)[..., None], axis=-1)[..., 0]
    high_v = np.take_along_axis(s, high[..., None], axis=-1)[..., 0]
    return np.where(n > 0, (low_v + high_v) / 2.0, np.nan)
