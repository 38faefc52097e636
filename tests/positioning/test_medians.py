"""The NaN-skipping median equals numpy's, bit for bit."""

from __future__ import annotations

import warnings

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.positioning.medians import nanmedian


@settings(deadline=None, max_examples=200)
@given(
    seed=st.integers(0, 2**31),
    shape=st.lists(st.integers(0, 9), min_size=1, max_size=3),
    nan_fraction=st.sampled_from([0.0, 0.2, 0.7, 1.0]),
    repeats=st.booleans(),
    data=st.data(),
)
def test_nanmedian_equals_numpys(
    seed: int, shape: list[int], nan_fraction: float, repeats: bool, data: st.DataObject
) -> None:
    rng = np.random.default_rng(seed)
    a = rng.normal(0.0, 10.0, shape)
    if repeats:  # ties, as ranges rounded to the sensor's resolution
        a = np.round(a)
    a[rng.random(shape) < nan_fraction] = np.nan
    ndim = len(shape)
    axes = data.draw(
        st.one_of(
            st.integers(-ndim, ndim - 1),
            st.lists(st.integers(0, ndim - 1), min_size=1, max_size=ndim, unique=True).map(tuple),
        )
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        expected = np.nanmedian(a, axis=axes)
    got = nanmedian(a, axes)
    assert got.shape == np.shape(expected)
    np.testing.assert_array_equal(got, expected)


def test_numpy_integers_name_the_axis() -> None:
    a = np.arange(12.0).reshape(3, 4)
    np.testing.assert_array_equal(nanmedian(a, np.int64(1)), np.median(a, axis=1))


def test_a_large_sample_takes_numpys_other_path_and_still_agrees() -> None:
    # np.nanmedian switches from masked arrays to a per-slice median above 600 values
    rng = np.random.default_rng(1)
    a = rng.normal(size=(2001, 3))
    a[rng.random(a.shape) < 0.1] = np.nan
    np.testing.assert_array_equal(nanmedian(a, 0), np.nanmedian(a, axis=0))
