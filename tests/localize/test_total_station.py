"""Total station localization at a station: prism points chosen, reached, observed, registered."""

from __future__ import annotations

import numpy as np
import pytest

from fabflow.design.elements import Element, element_boxes
from fabflow.errors import LocalizationError
from fabflow.localize.prism_points import boxes_near_base
from fabflow.localize.total_station import localize_station
from fabflow.positioning.boxes import Boxes, boxes_overlap
from fabflow.project import parse_project
from fabflow.transforms.se3 import apply_T, make_T, pose_error
from fabflow.transforms.so3 import exp_so3

PROJECT = """
name: ts
elements:
  - task_points:
      - id: a
        pose: {xyz: [1, 0, 0]}
localization:
  method: total_station
  total_station:
    T_world_instrument: {xyz: [-6, -4, 1.6]}
    n_points: 5
"""


def _in_base(elements: list[Element], T_world_base: np.ndarray) -> Boxes:
    return boxes_near_base(Boxes(*element_boxes(elements)), T_world_base, np.inf)


def test_boxes_in_base_frame() -> None:
    T_world_base = make_T(exp_so3([0, 0, np.pi / 2]), [5.0, 0.0, 0.5])
    block = Element(
        "B1", "block", make_T(np.eye(3), [5.0, 2.0, 0.5]), extents=np.array([0.6, 0.1, 0.1])
    )
    far = Element("B2", "block", make_T(np.eye(3), [25.0, 2.0, 0.5]), extents=np.ones(3) * 0.1)
    point = Element("T1", "task_point", np.eye(4))
    boxes = _in_base([block, point], T_world_base)
    assert len(boxes) == 1
    np.testing.assert_allclose(boxes.T_base_box[0, :3, 3], [2.0, 0.0, 0.0], atol=1e-12)
    # only the boxes that can reach within the radius of the base are kept
    near = boxes_near_base(Boxes(*element_boxes([block, far])), T_world_base, 3.0)
    assert len(near) == 1


def test_localize_station_simulates_a_plausible_pose() -> None:
    p = parse_project(PROJECT)
    rng = np.random.default_rng(0)
    T = make_T(exp_so3([0.0, 0.0, 0.7]), [2.0, 1.0, 0.6])
    bp = localize_station(p, T, rng, "S1")
    assert bp.method == "total_station" and bp.station == "S1"
    err = pose_error(bp.T_world_base, T)
    nees = err @ np.linalg.solve(bp.covariance, err)
    assert nees < 30  # chi2(6) 0.9999 quantile is about 27
    assert np.linalg.norm(err[:3]) < 0.005
    assert bp.residuals.shape == (5, 3) and bp.quality["n_points"] == 5
    P = np.asarray(bp.quality["points_base"])
    assert np.all(P[:, 0] > 0) and np.all(P[:, 2] > 0.1)
    again = localize_station(p, T, np.random.default_rng(0), "S1")
    np.testing.assert_array_equal(again.T_world_base, bp.T_world_base)


def test_localize_station_three_point_and_obstacles() -> None:
    p = parse_project(PROJECT.replace("n_points: 5", "procedure: three_point"))
    T = make_T(np.eye(3), [0.0, 0.0, 0.6])
    bp = localize_station(p, T, np.random.default_rng(1), "S1")
    assert bp.quality["solver"] == "three_point" and bp.residuals.shape == (3, 3)
    assert np.linalg.norm(pose_error(bp.T_world_base, T)[:3]) < 0.01
    # a block right where an optimal point wants to be pushes it away
    p5 = parse_project(PROJECT)
    free = localize_station(p5, T, np.random.default_rng(1), "S1")
    first = apply_T(T, np.asarray(free.quality["points_base"])[0])
    block = Element("B", "block", make_T(np.eye(3), first), extents=np.array([0.6, 0.3, 0.3]))
    blocked = localize_station(p5, T, np.random.default_rng(1), "S1", built=[block])
    assert blocked.quality["moved_for_obstacles"][0] > 0
    P = np.asarray(blocked.quality["points_base"])
    boxes = _in_base([block], T)
    assert not boxes_overlap(P, np.array([0.15, 0.15, 0.2]), boxes).any()


def test_instrument_setup_uncertainty_propagates() -> None:
    from fabflow.positioning.registration import register_points
    from fabflow.positioning.total_station import add_instrument_uncertainty

    # a heading error a of an instrument 10 m away moves the base sideways by 10 a
    T_wi = make_T(np.eye(3), [0.0, -10.0, 1.6])
    T_base = make_T(np.eye(3), [0.0, 0.0, 0.6])
    P = np.array([[1.0, 0.5, 0.5], [1.5, -0.5, 1.0], [0.5, 1.0, 1.5], [2.0, 0.0, 0.8]])
    reg = register_points(P, apply_T(T_base, P), sigma=1e-6)
    a = 1e-4
    C_wi = np.diag([0.0, 0.0, 0.0, 0.0, 0.0, a * a])
    out = add_instrument_uncertainty(reg, T_wi, C_wi)
    extra = out.covariance - reg.covariance
    assert np.sqrt(extra[0, 0]) == pytest.approx(10.0 * a, rel=1e-6)
    assert extra[1, 1] == pytest.approx(0.0, abs=1e-15)
    assert np.sqrt(extra[5, 5]) == pytest.approx(a)
    setup = "setup_sigma_mm: 3\n    setup_sigma_arcsec: 10"
    p = parse_project(PROJECT.replace("n_points: 5", setup))
    bp = localize_station(p, T_base, np.random.default_rng(2), "S1")
    assert np.sqrt(bp.covariance[2, 2]) > 3e-3
    err = pose_error(bp.T_world_base, T_base)
    assert err @ np.linalg.solve(bp.covariance, err) < 30


@pytest.mark.parametrize("model", ["ur10e", "brokk_170"])
def test_localize_station_other_robots(model: str) -> None:
    # the UR10e has closed-form IK; the 5-DOF BROKK reaches points by sampled FK
    p = parse_project(PROJECT.replace("elements:", f"robot: {{model: {model}}}\nelements:"))
    T = make_T(np.eye(3), [1.0, 2.0, 0.6])
    bp = localize_station(p, T, np.random.default_rng(3), "S1")
    P = np.asarray(bp.quality["points_base"])
    assert len(P) == 5 and np.all(P[:, 0] > 0)
    assert np.linalg.norm(pose_error(bp.T_world_base, T)[:3]) < 0.005


def test_a_given_instrument_too_imprecise_for_the_tolerance_says_so() -> None:
    """A 3 mm prism centring puts the predicted base sigma above 10 % of the 10 mm
    tolerance: the error names the figure and the remedies, not the line of sight."""
    p = parse_project(
        PROJECT.replace("    n_points: 5\n", "    n_points: 5\n    prism_centring_mm: 3\n")
    )
    T = make_T(exp_so3([0.0, 0.0, 0.7]), [2.0, 1.0, 0.6])
    with pytest.raises(LocalizationError, match=r"predicted \d+\.\d+ mm \(XY\).*n_points"):
        localize_station(p, T, np.random.default_rng(0), "S1")
