"""The object database (paper 002, eq. 3) and the placing of found stones in slots."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError
from fabflow.manipulation.objects import (
    ObjectDatabase,
    add_segments,
    grasp,
    object_frame,
    realign,
    release,
    remove_object_points,
)
from fabflow.stones.placing import (
    assign_slots,
    backed_off,
    choose_release,
    release_poses,
    target_poses,
)
from fabflow.transforms.se3 import apply_T, inv_T
from fabflow.transforms.so3 import exp_so3

finite = st.floats(-3.0, 3.0, allow_nan=False)


def _pose(r: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = exp_so3(np.asarray(r, dtype=float))
    T[:3, 3] = t
    return T


def _box_points(size: tuple[float, float, float], n: int = 3000, seed: int = 0) -> np.ndarray:
    """Points on the surface of a box of ``size`` centred at the origin."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.5, 0.5, (n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.sign(p[np.arange(n), axis]) * 0.5
    return p * np.asarray(size)


def test_object_frame_follows_the_principal_axes_with_z_up() -> None:
    T_true = _pose([0.0, 0.0, 0.7], [4.0, -2.0, 0.3])
    pts = apply_T(T_true, _box_points((1.2, 0.8, 0.4)))
    T = object_frame(pts)
    np.testing.assert_allclose(T[:3, 3], T_true[:3, 3], atol=0.02)
    assert abs(T[:3, 0] @ T_true[:3, 0]) > 0.99  # longest axis
    assert T[:3, 2] @ T_true[:3, 2] > 0.99  # shortest axis, up
    assert T[0, 0] >= 0.0
    np.testing.assert_allclose(np.linalg.det(T[:3, :3]), 1.0, atol=1e-9)


def test_new_objects_hold_their_points_in_their_own_frame() -> None:
    pts = apply_T(_pose([0.1, -0.2, 1.0], [3.0, 1.0, 0.4]), _box_points((1.0, 0.7, 0.5)))
    db = add_segments(ObjectDatabase(), [pts, pts + np.array([5.0, 0.0, 0.0])])
    assert [o.id for o in db.objects] == [0, 1]
    obj = db.get(0)
    np.testing.assert_allclose(obj.points.mean(axis=0), 0.0, atol=1e-9)
    # principal axes from sampled points: a few degrees off the box axes
    np.testing.assert_allclose(sorted(obj.extents, reverse=True), [1.0, 0.7, 0.5], atol=0.06)
    assert [e.event for e in obj.history] == ["detected"]
    more = add_segments(db, [pts - np.array([5.0, 0.0, 0.0])])
    assert [o.id for o in more.objects] == [0, 1, 2]


@settings(max_examples=30, deadline=None)
@given(
    st.tuples(finite, finite, finite),
    st.tuples(finite, finite, finite),
    st.tuples(finite, finite, finite),
    st.tuples(finite, finite, finite),
)
def test_release_moves_the_object_with_the_gripper(r_g, t_g, r_r, t_r) -> None:
    """Eq. 3: the object's pose in the gripper is the same at the grasp and the release."""
    pts = _box_points((1.0, 0.6, 0.4), n=200)
    db = add_segments(ObjectDatabase(), [pts + np.array([2.0, 1.0, 0.3])])
    obj = db.get(0)
    G, R = _pose(np.array(r_g) / 3, t_g), _pose(np.array(r_r) / 3, t_r)
    db = release(grasp(db, 0, G), 0, R)
    moved = db.get(0)
    np.testing.assert_allclose(
        inv_T(R) @ moved.T_world_object, inv_T(G) @ obj.T_world_object, atol=1e-9
    )
    assert [e.event for e in moved.history] == ["detected", "grasp", "release"]
    np.testing.assert_allclose(moved.history[1].T_world_gripper, G)
    np.testing.assert_allclose(moved.history[2].T_world_gripper, R)


def test_release_without_grasp_and_double_grasp_are_refused() -> None:
    db = add_segments(ObjectDatabase(), [_box_points((1.0, 0.6, 0.4), n=100)])
    with pytest.raises(InputError, match="not grasped"):
        release(db, 0, np.eye(4))
    with pytest.raises(InputError, match="already held"):
        grasp(grasp(db, 0, np.eye(4)), 0, np.eye(4))
    with pytest.raises(InputError, match="no object 7"):
        grasp(db, 7, np.eye(4))
    with pytest.raises(InputError, match="finite 4x4"):
        grasp(db, 0, np.full((4, 4), np.nan))


def test_realign_recovers_a_small_offset_and_refuses_a_wrong_place() -> None:
    surface = _box_points((1.0, 0.7, 0.5), n=6000, seed=1)
    T_true = _pose([0.0, 0.0, 0.4], [3.0, 2.0, 0.25])
    map_points = apply_T(T_true, surface)
    db = add_segments(ObjectDatabase(), [map_points])
    good = db.get(0).T_world_object
    # the database believes the object 4 cm and 2 deg off where the map has it
    off = _pose([0.0, 0.0, np.radians(2.0)], [0.04, -0.03, 0.0]) @ good
    db_off = ObjectDatabase((db.get(0).with_event(type(db.get(0).history[0])("detected", off)),))
    fixed, rmse = realign(db_off, 0, map_points)
    assert rmse < 0.01
    np.testing.assert_allclose(fixed.get(0).T_world_object[:3, 3], good[:3, 3], atol=0.005)
    assert fixed.get(0).history[-1].rmse == pytest.approx(rmse)
    # a map with nothing where the object should be: the pose is kept
    empty, rmse = realign(db_off, 0, map_points + np.array([10.0, 0.0, 0.0]))
    assert rmse == np.inf and empty.get(0).T_world_object is off


def test_remove_object_points_cuts_a_sphere() -> None:
    pts = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [1.5, 0.0, 0.0]])
    np.testing.assert_array_equal(remove_object_points(pts, [0.0, 0.0, 0.0], 1.0), pts[2:])


def test_assign_slots_matches_sizes_not_order() -> None:
    extents = np.array([[0.6, 0.5, 0.3], [1.4, 1.0, 0.6], [1.0, 0.8, 0.5]])
    slots = np.array([[1.0, 0.8, 0.5], [0.6, 0.3, 0.5], [1.4, 0.6, 1.0]])  # any axis order
    np.testing.assert_array_equal(assign_slots(extents, slots), [2, 0, 1])
    np.testing.assert_array_equal(assign_slots(extents[:1], slots), [-1, 0, -1])
    np.testing.assert_array_equal(assign_slots(np.zeros((0, 3)), slots[:1]), [-1])


def test_target_poses_set_the_stone_on_the_slot_floor() -> None:
    db = add_segments(
        ObjectDatabase(), [apply_T(_pose([0.3, 0.2, 1.0], [5, 5, 1]), _box_points((1.2, 0.8, 0.5)))]
    )
    obj = db.get(0)
    T_slot = _pose([0.0, 0.0, 0.5], [1.0, 2.0, 0.3])
    targets = target_poses(obj, T_slot, (1.3, 0.9, 0.6))
    assert targets.shape == (4, 4, 4)
    for T in targets:
        in_slot = apply_T(inv_T(T_slot) @ T, obj.points)
        assert in_slot[:, 2].min() == pytest.approx(-0.3, abs=1e-9)  # on the floor
        np.testing.assert_allclose(in_slot.mean(axis=0)[:2], 0.0, atol=1e-9)
        # longest axis along the wall, shortest up
        assert abs((inv_T(T_slot) @ T)[0, 0]) == pytest.approx(1.0)
        assert abs((inv_T(T_slot) @ T)[2, 2]) == pytest.approx(1.0)


def test_release_poses_put_the_object_on_its_target() -> None:
    rng = np.random.default_rng(3)
    T_obj = _pose(rng.normal(size=3), rng.normal(size=3))
    G = np.stack([_pose(rng.normal(size=3), rng.normal(size=3)) for _ in range(3)])
    targets = np.stack([_pose(rng.normal(size=3), rng.normal(size=3)) for _ in range(4)])
    R = release_poses(T_obj, G, targets)
    assert R.shape == (3, 4, 4, 4)
    for m in range(3):
        for v in range(4):
            np.testing.assert_allclose(R[m, v] @ inv_T(G[m]) @ T_obj, targets[v], atol=1e-9)
    np.testing.assert_allclose(release_poses(T_obj, G[0], targets), R[0])


def test_choose_release_needs_every_pose_reachable_and_prefers_vertical() -> None:
    T_obj = np.eye(4)
    down = np.diag([1.0, -1.0, -1.0, 1.0])  # gripper z pointing down
    G = np.stack([down, down])
    G[1, :3, 3] = (50.0, 0.0, 0.0)  # far away
    targets = np.stack([np.eye(4), np.diag([1.0, -1.0, -1.0, 1.0])])  # upright, upside down

    def near(T: np.ndarray) -> np.ndarray:
        return np.linalg.norm(T[:, :3, 3], axis=1) < 10.0

    ok, variant = choose_release(T_obj, G, targets, near, 0.6)
    np.testing.assert_array_equal(ok, [True, False])
    assert variant[0] == 0  # upright: the gripper still points down at the release
    assert variant[1] == -1
    np.testing.assert_allclose(backed_off(down, 0.6)[:3, 3], [0.0, 0.0, 0.6])
    with pytest.raises(InputError, match="one bool per pose"):
        choose_release(T_obj, G, targets, lambda T: np.ones(2, dtype=bool), 0.6)
