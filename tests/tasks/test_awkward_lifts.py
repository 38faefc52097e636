"""The chosen stations' reach without the awkward lift levels (fabflow.tasks.awkward_lifts)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import sparse

from fabflow.tasks.awkward_lifts import prefer_regular

LEVELS = 6


@st.composite
def reach_cases(draw: st.DrawFn) -> tuple[sparse.csr_matrix, np.ndarray, np.ndarray]:
    """A small reach matrix (stations x elements, lift bit masks) and two awkward masks."""
    k = draw(st.integers(1, 4))
    n = draw(st.integers(1, 6))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    dense = rng.integers(0, 2**LEVELS, size=(k, n)) * (rng.random((k, n)) < 0.6)
    dense[rng.integers(0, k, size=n), np.arange(n)] |= 1 + rng.integers(0, 2**LEVELS - 1, size=n)
    A = sparse.csr_matrix(dense.astype(np.int64))
    nnz = A.nnz
    singular = rng.integers(0, 2**LEVELS, size=nnz)
    swinging = rng.integers(0, 2**LEVELS, size=nnz)
    return A, singular, swinging


@settings(max_examples=200, deadline=None)
@given(reach_cases())
def test_prefer_regular_keeps_every_element_reachable_and_drops_only_awkward_levels(
    case: tuple[sparse.csr_matrix, np.ndarray, np.ndarray],
) -> None:
    A, singular, swinging = case
    out = prefer_regular(A, singular, swinging).toarray()
    before = A.toarray()
    coo = A.tocoo()
    sing = np.zeros_like(before)
    sing[coo.row, coo.col] = singular
    swing = np.zeros_like(before)
    swing[coo.row, coo.col] = swinging
    assert (out & ~before == 0).all()  # no level is added
    assert (out != 0).any(axis=0).all()  # every element is still reached
    regular_somewhere = ((before & ~sing) != 0).any(axis=0)
    for e in range(before.shape[1]):
        dropped = before[:, e] & ~out[:, e]
        if regular_somewhere[e]:
            # no singular level is left, and only singular or swinging levels went
            assert (out[:, e] & sing[:, e] == 0).all()
            assert (dropped & ~(sing[:, e] | swing[:, e]) == 0).all()
            # a station keeps its calm regular levels where it has any
            calm = before[:, e] & ~sing[:, e] & ~swing[:, e]
            assert ((out[:, e] == calm) | (calm == 0)).all()
        else:
            # singular everywhere: only swinging levels of a station may go, within it
            assert (dropped & ~swing[:, e] == 0).all()
            assert ((out[:, e] != 0) == (before[:, e] != 0)).all()


def test_a_block_singular_everywhere_at_one_station_moves_to_another() -> None:
    A = sparse.csr_matrix(np.array([[0b011], [0b100]], dtype=np.int64))
    coo = A.tocoo()
    singular = np.where(coo.row == 0, 0b011, 0)  # station 0: both levels singular
    out = prefer_regular(A, singular, np.zeros(A.nnz, dtype=np.int64)).toarray()
    np.testing.assert_array_equal(out, [[0], [0b100]])


def test_a_swinging_level_is_left_only_within_its_station() -> None:
    # station 0 reaches the block only at a swinging level, station 1 at a calm one:
    # the swing is avoided within a station, so station 0 keeps its level
    A = sparse.csr_matrix(np.array([[0b001], [0b010]], dtype=np.int64))
    coo = A.tocoo()
    swinging = np.where(coo.row == 0, 0b001, 0)
    out = prefer_regular(A, np.zeros(A.nnz, dtype=np.int64), swinging).toarray()
    np.testing.assert_array_equal(out, [[0b001], [0b010]])
    # a station with a swinging and a calm level keeps the calm one
    A = sparse.csr_matrix(np.array([[0b011]], dtype=np.int64))
    out = prefer_regular(A, np.zeros(1, dtype=np.int64), np.array([0b001])).toarray()
    np.testing.assert_array_equal(out, [[0b010]])


def test_prefer_regular_refuses_masks_that_do_not_match_the_entries() -> None:
    A = sparse.csr_matrix(np.array([[0b011, 0b001]], dtype=np.int64))
    with pytest.raises(ValueError, match="one singular and one swinging mask"):
        prefer_regular(A, np.zeros(1, dtype=np.int64), np.zeros(2, dtype=np.int64))
