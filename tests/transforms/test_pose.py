"""Property and unit tests of Pose and the vendor conventions (KUKA, ABB, UR)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from fabflow.errors import InputError
from fabflow.transforms import (
    DegenerateFrameError,
    Pose,
    QuaternionError,
    RotationError,
    from_abb_pose,
    from_kuka_xyzabc,
    from_ur_pose,
    to_abb_pose,
    to_kuka_xyzabc,
    to_ur_pose,
)

TOL = 1e-9
unit = st.floats(-1.0, 1.0, allow_nan=False)
quats = st.tuples(unit, unit, unit, unit).filter(lambda q: np.linalg.norm(q) > 0.1)
coord = st.floats(-50.0, 50.0, allow_nan=False)
vec3 = st.tuples(coord, coord, coord)
poses = st.builds(lambda q, t: Pose.from_quat(np.asarray(q) / np.linalg.norm(q), t), quats, vec3)
settings_ = settings(deadline=None, max_examples=60)


def _random_poses(n: int, seed: int) -> Pose:
    rng = np.random.default_rng(seed)
    return Pose.from_rotvec(
        Rotation.random(n, rng=rng).as_rotvec(), rng.uniform(-5, 5, size=(n, 3))
    )


# ------------------------------------------------------------------ algebra


@settings_
@given(poses, poses, poses)
def test_compose_inverse_identities(a: Pose, b: Pose, c: Pose) -> None:
    ident = Pose.identity()
    assert (a @ a.inverse()).allclose(ident, TOL)
    assert (a.inverse() @ a).allclose(ident, TOL)
    assert ((a @ b) @ c).allclose(a @ (b @ c), 1e-8)
    assert (a @ b).inverse().allclose(b.inverse() @ a.inverse(), 1e-9)
    assert a.inverse().inverse().allclose(a, TOL)
    np.testing.assert_allclose((a @ b).matrix, a.matrix @ b.matrix, atol=1e-9)
    p = np.array([[1.0, -2.0, 3.0], [0.5, 0.0, 0.25]])
    np.testing.assert_allclose((a @ b).apply(p), a.apply(b.apply(p)), atol=1e-9)


@settings_
@given(poses)
def test_round_trip_every_representation(p: Pose) -> None:
    assert Pose.from_matrix(p.matrix).allclose(p, TOL)
    assert Pose.from_quat(p.quat, p.t).allclose(p, TOL)
    assert Pose.from_rotvec(p.rotvec, p.t).allclose(p, TOL)
    for seq in ("ZYX", "xyz", "ZYZ"):
        # within about 1e-7 rad of gimbal lock scipy declares the lock and sets the third
        # angle to zero: the round trip is then good to that order, not to rounding
        assert Pose.from_euler(seq, p.euler(seq), p.t).allclose(p, 1e-6)
    assert from_kuka_xyzabc(to_kuka_xyzabc(p)).allclose(p, TOL)
    assert from_abb_pose(*to_abb_pose(p)).allclose(p, TOL)
    assert from_ur_pose(to_ur_pose(p)).allclose(p, TOL)


@settings_
@given(quats, vec3)
def test_agrees_with_scipy(q: tuple[float, float, float, float], t: tuple) -> None:
    q = np.asarray(q) / np.linalg.norm(q)
    ref = Rotation.from_quat(q, scalar_first=True)
    p = Pose.from_quat(q, t)
    np.testing.assert_allclose(p.R, ref.as_matrix(), atol=1e-12)
    rv = ref.as_rotvec()
    assert Pose.from_rotvec(rv).allclose(Pose(ref.as_matrix()), 1e-12)
    if np.linalg.norm(rv) < np.pi - 1e-6:
        np.testing.assert_allclose(p.rotvec, rv, atol=1e-9)
    else:  # at 180 degrees +axis*pi and -axis*pi are the same rotation
        assert min(np.abs(p.rotvec - rv).max(), np.abs(p.rotvec + rv).max()) < 1e-6
    abc = to_kuka_xyzabc(p)[3:]
    np.testing.assert_allclose(
        Rotation.from_euler("ZYX", abc, degrees=True).as_matrix(), ref.as_matrix(), atol=1e-12
    )
    pts = np.array([[1.0, 2.0, 3.0], [-4.0, 0.5, 2.0]])
    np.testing.assert_allclose(p.apply(pts), ref.apply(pts) + np.asarray(t), atol=1e-9)


@settings(deadline=None, max_examples=40)
@given(st.floats(-180.0, 180.0), st.sampled_from([90.0, -90.0]), st.floats(-180.0, 180.0))
def test_kuka_gimbal_lock(a: float, b: float, c: float) -> None:
    p = from_kuka_xyzabc([1.0, 2.0, 3.0, a, b, c])
    out = to_kuka_xyzabc(p)
    assert out[4] == pytest.approx(b, abs=1e-6)
    assert out[5] == pytest.approx(0.0, abs=1e-9)
    assert from_kuka_xyzabc(out).allclose(p, TOL)


@settings(deadline=None, max_examples=40)
@given(st.tuples(unit, unit, unit).filter(lambda v: np.linalg.norm(v) > 0.1), vec3)
def test_ur_at_180_degrees(axis: tuple[float, float, float], t: tuple) -> None:
    axis = np.asarray(axis) / np.linalg.norm(axis)
    p = from_ur_pose([*t, *(np.pi * axis)])
    ur = to_ur_pose(p)
    assert np.linalg.norm(ur[3:]) == pytest.approx(np.pi, abs=1e-9)
    assert min(np.abs(ur[3:] - np.pi * axis).max(), np.abs(ur[3:] + np.pi * axis).max()) < 1e-7
    assert from_ur_pose(ur).allclose(p, TOL)


@pytest.mark.parametrize("angle", [0.0, 1e-15, 1e-9, 1e-5, np.pi - 1e-9])
def test_ur_near_zero_and_pi(angle: float) -> None:
    rv = angle * np.array([0.6, -0.8, 0.0])
    p = from_ur_pose([0.1, 0.2, 0.3, *rv])
    out = to_ur_pose(p)
    np.testing.assert_allclose(out[3:], rv, atol=1e-12 if angle < 1 else 1e-7)
    assert from_ur_pose(out).allclose(p, TOL)


# ------------------------------------------------------------------ vendor units


def test_vendor_units_and_known_values() -> None:
    p = Pose.from_euler("ZYX", [90.0, 0.0, 0.0], [0.1, 0.2, 0.3], degrees=True)
    np.testing.assert_allclose(to_kuka_xyzabc(p), [100.0, 200.0, 300.0, 90.0, 0.0, 0.0], atol=1e-9)
    pos, q = to_abb_pose(p)
    np.testing.assert_allclose(pos, [100.0, 200.0, 300.0])
    np.testing.assert_allclose(q, [np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)], atol=1e-12)
    np.testing.assert_allclose(to_ur_pose(p), [0.1, 0.2, 0.3, 0.0, 0.0, np.pi / 2], atol=1e-12)
    # ABB sign convention: q1 >= 0 even when given a negative-w quaternion
    _, q2 = to_abb_pose(from_abb_pose([0, 0, 0], -q))
    assert q2[0] >= 0
    np.testing.assert_allclose(q2, q, atol=1e-12)


def test_vendor_batches_in_and_out() -> None:
    b = _random_poses(7, 0)
    k = to_kuka_xyzabc(b)
    assert k.shape == (7, 6)
    pos, q = to_abb_pose(b)
    assert pos.shape == (7, 3) and q.shape == (7, 4)
    assert np.all(q[:, 0] >= 0)
    u = to_ur_pose(b)
    assert u.shape == (7, 6)
    for back in (from_kuka_xyzabc(k), from_abb_pose(pos, q), from_ur_pose(u)):
        assert back.shape == (7,)
        np.testing.assert_allclose(back.matrix, b.matrix, atol=TOL)
    assert b.matrix.shape == (7, 4, 4)
    # 4x4 matrices are accepted wherever a Pose is
    np.testing.assert_array_equal(to_kuka_xyzabc(b.matrix), k)
    np.testing.assert_array_equal(to_ur_pose(b.matrix[2]), u[2])
    np.testing.assert_array_equal(to_abb_pose(b.matrix)[1], q)
    assert Pose.from_matrix(b.matrix).allclose(b, 0.0)


def test_vendor_bad_input() -> None:
    with pytest.raises(InputError, match="6 values"):
        from_kuka_xyzabc([1, 2, 3])
    with pytest.raises(InputError, match="finite"):
        from_ur_pose([0, 0, 0, np.nan, 0, 0])
    with pytest.raises(QuaternionError, match="norm"):
        from_abb_pose([0, 0, 0], [0.9, 0.0, 0.0, 0.0])
    # within tolerance: normalized, never used un-normalized
    p = from_abb_pose([0, 0, 0], [1.0 + 4e-7, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(p.R, np.eye(3), atol=1e-15)


def test_project_posespec_uses_kuka_abc() -> None:
    from fabflow.schema import PoseSpec

    spec = PoseSpec(xyz=(1.0, 2.0, 3.0), abc_deg=(30.0, -45.0, 120.0))
    ref = from_kuka_xyzabc([1000.0, 2000.0, 3000.0, 30.0, -45.0, 120.0])
    np.testing.assert_allclose(spec.matrix(), ref.matrix, atol=1e-12)
    # made once per value, handed out as a fresh array: a caller's edit stays its own
    first = spec.matrix()
    first[:3, 3] = 0.0
    np.testing.assert_allclose(spec.matrix(), ref.matrix, atol=1e-12)
    moved = spec.model_copy(update={"xyz": (0.0, 0.0, 0.0)})
    np.testing.assert_allclose(moved.matrix()[:3, 3], 0.0)
    # equal values of another sign of zero are another pose, not the cached one's
    negative = spec.model_copy(update={"xyz": (-0.0, 0.0, 0.0)})
    assert not np.signbit(moved.matrix()[0, 3]) and np.signbit(negative.matrix()[0, 3])


# ------------------------------------------------------------------ validation & API


def test_from_matrix_validates() -> None:
    m = np.eye(4)
    m[:3, :3] *= 1.01
    with pytest.raises(RotationError, match="tolerance 1e-06"):
        Pose.from_matrix(m)
    m = np.eye(4)
    m[3, 0] = 1.0
    with pytest.raises(InputError, match="bottom row"):
        Pose.from_matrix(m)
    with pytest.raises(InputError, match="shape"):
        Pose.from_matrix(np.eye(3))
    with pytest.raises(RotationError, match="det"):
        Pose(np.diag([1.0, -1.0, 1.0]))
    # a rounding-level deviation is accepted
    r = Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix() + 1e-9
    Pose(r)


def test_immutable() -> None:
    p = Pose.identity()
    with pytest.raises(AttributeError):
        p.t = np.zeros(3)  # type: ignore[misc]
    with pytest.raises(ValueError):
        p.t[0] = 1.0
    m = p.matrix
    m[0, 3] = 5.0
    assert p.t[0] == 0.0
    # no memory shared with the caller's arrays
    R, t = np.eye(3), np.zeros(3)
    q = Pose(R, t)
    R[0, 0], t[0] = 5.0, 5.0
    assert q.R[0, 0] == 1.0 and q.t[0] == 0.0
    t2 = np.zeros((2, 3))
    for r in (Pose.from_rotvec(np.zeros(3), t2), Pose.from_quat([1.0, 0, 0, 0], t2)):
        t2[0, 0] = 7.0
        assert r.t[0, 0] == 0.0
        t2[0, 0] = 0.0
    big = np.tile(np.eye(4), (3, 1, 1))
    f = Pose.from_matrix(big)
    big[:, 0, 3] = 1.0
    assert np.all(f.t == 0.0)


def test_batch_broadcast_and_indexing() -> None:
    b = _random_poses(5, 1)
    s = _random_poses(1, 2)[0]
    assert (s @ b).shape == (5,)
    assert (b @ s).shape == (5,)
    np.testing.assert_allclose((b @ s)[3].matrix, b[3].matrix @ s.matrix, atol=1e-12)
    assert len(b) == 5 and len(list(b)) == 5
    assert Pose.stack(list(b)).allclose(b, 0.0)
    pts = np.random.default_rng(3).normal(size=(5, 3))
    np.testing.assert_allclose(b.apply(pts)[2], b[2].apply(pts[2]), atol=1e-12)
    assert s.apply(pts).shape == (5, 3)
    with pytest.raises(TypeError):
        len(s)
    with pytest.raises(TypeError):
        _ = np.eye(4) @ s


def test_interpolate_and_distance() -> None:
    a = Pose.from_rotvec([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    b = Pose.from_rotvec([0.0, 0.0, np.pi / 2], [2.0, 0.0, 0.0])
    mid = a.interpolate(b, 0.5)
    np.testing.assert_allclose(mid.rotvec, [0.0, 0.0, np.pi / 4], atol=1e-12)
    np.testing.assert_allclose(mid.t, [1.0, 0.0, 0.0])
    path = a.interpolate(b, np.linspace(0, 1, 5))
    assert path.shape == (5,)
    assert path[0].allclose(a, 1e-12) and path[4].allclose(b, 1e-12)
    d, ang = a.distance(path)
    np.testing.assert_allclose(d, np.linspace(0, 2, 5), atol=1e-12)
    np.testing.assert_allclose(ang, np.linspace(0, np.pi / 2, 5), atol=1e-12)
    # batch x fractions
    bb = _random_poses(3, 4)
    cc = _random_poses(3, 5)
    grid = bb[:, None].interpolate(cc[:, None], np.linspace(0, 1, 4))
    assert grid.shape == (3, 4)
    assert grid[:, 3].allclose(cc, 1e-9)


@settings(deadline=None, max_examples=40)
@given(poses, st.floats(0.0, 1.0))
def test_slerp_constant_speed(a: Pose, s: float) -> None:
    b = a @ Pose.from_rotvec([0.3, -0.2, 1.1], [1.0, 2.0, 3.0])
    m = a.interpolate(b, s)
    d0, a0 = a.distance(m)
    d1, a1 = m.distance(b)
    dtot, total = a.distance(b)
    assert d0 + d1 == pytest.approx(dtot, abs=1e-9)
    assert d0 == pytest.approx(s * dtot, abs=1e-9)
    assert a0 + a1 == pytest.approx(total, abs=1e-9)
    assert a0 == pytest.approx(s * total, abs=1e-9)


def test_from_frame() -> None:
    rng = np.random.default_rng(6)
    T = _random_poses(1, 7)[0]
    local = np.array([[0.0, 0.0, 0.0], [2.5, 0.0, 0.0], [0.7, 1.3, 0.0]])
    pts = T.apply(local)
    F = Pose.from_frame(pts[0], pts[1], pts[2])
    assert F.allclose(T, 1e-12)
    # batch of frames
    Ts = _random_poses(4, 8)
    P = np.stack([Ts.apply(np.broadcast_to(p, (4, 3))) for p in local])
    assert Pose.from_frame(P[0], P[1], P[2]).allclose(Ts, 1e-12)
    with pytest.raises(DegenerateFrameError, match="collinear"):
        Pose.from_frame([0, 0, 0], [1, 0, 0], [2, 0, 0])
    with pytest.raises(DegenerateFrameError):
        Pose.from_frame([1, 1, 1], [1, 1, 1], rng.normal(size=3))


def test_pickle_and_deepcopy() -> None:
    import copy
    import pickle

    b = _random_poses(3, 9)
    for clone in (pickle.loads(pickle.dumps(b)), copy.deepcopy(b)):
        assert isinstance(clone, Pose)
        assert clone.allclose(b, 0.0)
        with pytest.raises(ValueError):
            clone.R[0, 0, 0] = 2.0
