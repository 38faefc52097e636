"""Inside a stay at one station the elements go up layer by layer, supports first."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.tasks.order import _layer_major


def test_two_pieces_printed_one_after_the_other_go_layer_by_layer() -> None:
    # elements 0-2: piece A layers 0-2; 3-5: piece B layers 0-2; each rests on the one below
    layer = np.array([0, 1, 2, 0, 1, 2])
    src, dst = np.array([0, 1, 3, 4]), np.array([1, 2, 4, 5])
    order = _layer_major(np.arange(6), layer, src, dst)
    assert order.tolist() == [0, 3, 1, 4, 2, 5]


def test_a_support_the_sort_would_break_keeps_the_order() -> None:
    layer = np.array([1, 0, 1])
    src, dst = np.array([0]), np.array([2])  # element 2 rests on element 0, same layer
    assert _layer_major(np.array([0, 2, 1]), layer, src, dst).tolist() == [1, 0, 2]
    # element 1 (layer 0) rests on element 0 (layer 1): sorting would put it first
    src, dst = np.array([0]), np.array([1])
    assert _layer_major(np.array([0, 1, 2]), layer, src, dst).tolist() == [0, 1, 2]


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_the_order_is_a_permutation_with_supports_first(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 30))
    layer = rng.integers(0, 5, n)
    src = rng.integers(0, n, 40)
    dst = rng.integers(0, n, 40)
    keep = layer[src] < layer[dst]  # supports from a lower layer
    src, dst = src[keep], dst[keep]
    seq = np.argsort(layer + rng.random(n))  # some valid order: by layer, ties at random
    seq = seq[rng.permutation(n)] if not len(src) else seq
    out = _layer_major(seq, layer, src, dst)
    assert sorted(out.tolist()) == sorted(seq.tolist())
    position = np.empty(n, dtype=int)
    position[out] = np.arange(n)
    assert np.all(position[src] < position[dst])
    assert np.all(np.diff(layer[out]) >= 0)
