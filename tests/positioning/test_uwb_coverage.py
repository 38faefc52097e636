"""The coverage checks of a UWB fix: the distance outside the anchors' plan hull."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.positioning.uwb_coverage import geometry_checks, outside_hull


def _distance_to_square(p: np.ndarray, half: float) -> np.ndarray:
    """Plan distance of points outside the square ``[-half, half]^2`` (0 inside)."""
    return np.linalg.norm(np.maximum(np.abs(p) - half, 0.0), axis=1)


@settings(max_examples=60, deadline=None)
@given(
    st.floats(0.5, 20.0),
    st.lists(st.tuples(st.floats(-40, 40), st.floats(-40, 40)), min_size=1, max_size=20),
)
def test_outside_hull_is_the_distance_to_the_square(half: float, points: list) -> None:
    """Corners, an inner anchor and an edge midpoint: the hull is the square, and the
    same anchors asked again (the hull made once) give the same distances."""
    square = half * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [0, 0], [0, -1]], float)
    p = np.array(points)
    expected = _distance_to_square(p, half)
    np.testing.assert_allclose(outside_hull(square, p), expected, atol=1e-9 * (1 + half))
    np.testing.assert_array_equal(outside_hull(square.copy(), p), outside_hull(square, p))


def test_outside_hull_of_anchors_without_area_is_zero() -> None:
    line = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    np.testing.assert_array_equal(outside_hull(line, np.array([[5.0, 5.0]])), [0.0])
    np.testing.assert_array_equal(outside_hull(line[:2], np.array([[5.0, 5.0]])), [0.0])


def test_geometry_checks() -> None:
    anchors = np.array([[0, 0, 0], [10, 0, 3], [10, 10, 0], [0, 10, 3]], float)
    states = np.array([[5.0, 5.0, 1.0, 0.3], [13.0, 5.0, 1.0, 0.3]])  # inside, 3 m outside
    pdop, outside = geometry_checks(anchors, states)
    assert outside[0] == 0.0
    assert abs(outside[1] - 3.0) < 1e-12
    assert 1.0 < pdop[0] < pdop[1]
