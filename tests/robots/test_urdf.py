"""Robots from URDF files: the chain against yourdfpy's own, numerical IK, bounds."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest
import yaml
from custom_robots import TRACK_URDF, dh_urdf
from helpers import DATA
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError
from fabflow.project import load_project
from fabflow.robots.catalog import get_robot
from fabflow.robots.chain import RobotModel
from fabflow.robots.urdf import urdf_arm

yourdfpy = pytest.importorskip("yourdfpy")

UR_STYLE = DATA / "robots" / "ur10e_style.urdf"


def urdf_project(folder: Path, urdf: str, base: str, tip: str, **custom) -> Path:
    """A project in ``folder`` whose robot is ``urdf`` (a file name in ``folder``)."""
    spec = {
        "name": "urdf_arm",
        "vendor": "ur",
        "urdf": urdf,
        "base_link": base,
        "tip_link": tip,
        "home_deg": [0.0] * 6,
        "payload": 10.0,
        **custom,
    }
    doc = {
        "name": "urdf",
        "robot": {"model": "custom", "custom": spec, "tool": {"mass": 5.0}},
        "elements": [{"cabin": {"origin": [0, 0, 0]}}],
    }
    path = folder / "project.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


def model_of(folder: Path, text: str, base: str, tip: str, **custom) -> RobotModel:
    (folder / "arm.urdf").write_text(text, encoding="utf-8")
    project = load_project(urdf_project(folder, "arm.urdf", base, tip, **custom))
    return get_robot(project.robot.name)


@pytest.fixture(scope="module")
def ur_style(tmp_path_factory) -> tuple[RobotModel, object]:
    folder = tmp_path_factory.mktemp("ur_style")
    robot = model_of(folder, UR_STYLE.read_text(encoding="utf-8"), "base_link", "tool0")
    urdf = yourdfpy.URDF.load(str(UR_STYLE), build_scene_graph=True, load_meshes=False)
    return robot, urdf


@pytest.fixture(scope="module")
def track(tmp_path_factory) -> tuple[RobotModel, object]:
    folder = tmp_path_factory.mktemp("track")
    robot = model_of(folder, TRACK_URDF, "floor", "tcp", home_deg=[100, 0, 200, 0, 0])
    urdf = yourdfpy.URDF.load(str(folder / "arm.urdf"), build_scene_graph=True, load_meshes=False)
    return robot, urdf


def uniform(robot: RobotModel, u: list[float]) -> np.ndarray:
    lo, hi = robot.joint_limits.T
    return lo + np.asarray(u) * (hi - lo)


unit = st.floats(0.0, 1.0)


def urdf_transform(urdf, q: np.ndarray, tip: str, base: str) -> np.ndarray:
    """yourdfpy's ``base`` to ``tip`` transform at ``q``.

    The scene graph caches its transforms under a hash that does not see a change
    of a joint by 1e-9 rad; moving elsewhere first clears that cache.
    """
    urdf.update_cfg(q + 0.5)
    urdf.get_transform(tip, base)
    urdf.update_cfg(q)
    return urdf.get_transform(tip, base)


@settings(max_examples=60, deadline=None)
@given(u=st.lists(unit, min_size=6, max_size=6))
def test_fk_matches_yourdfpy(ur_style, u: list[float]) -> None:
    robot, urdf = ur_style
    q = uniform(robot, u)
    assert np.max(np.abs(robot.fk(q) - urdf_transform(urdf, q, "tool0", "base_link"))) <= 1e-9


@settings(max_examples=40, deadline=None)
@given(u=st.lists(unit, min_size=5, max_size=5))
def test_prismatic_joints_and_skew_axes_match_yourdfpy(track, u: list[float]) -> None:
    robot, urdf = track
    q = uniform(robot, u)
    assert np.max(np.abs(robot.fk(q) - urdf_transform(urdf, q, "tcp", "floor"))) <= 1e-9


def test_urdf_joints_limits_and_speeds(ur_style, track) -> None:
    robot, _ = ur_style
    assert robot.dof == 6 and robot.chain is not None and robot.dh is None
    assert robot.analytic_ik is None and robot.opw is None
    np.testing.assert_allclose(robot.joint_limits[2], [-np.pi, np.pi])
    np.testing.assert_allclose(robot.velocity_limits[:3], [2.0943951023931953, 2.0943951, np.pi])
    arm, _ = track
    assert arm.prismatic.tolist() == [True, False, True, False, False]
    np.testing.assert_allclose(arm.q_home, [0.1, 0, 0.2, 0, 0])  # home_deg: mm for sliders


@pytest.mark.parametrize("which", ["ur_style", "track"])
def test_jacobian_is_the_derivative_of_fk(which: str, request) -> None:
    robot, _ = request.getfixturevalue(which)
    q = uniform(robot, list(np.random.default_rng(1).uniform(0, 1, robot.dof)))
    J = robot.jacobian(q)
    h = 1e-6
    for j in range(robot.dof):
        dq = np.zeros(robot.dof)
        dq[j] = h
        Tp, Tm = robot.fk(q + dq), robot.fk(q - dq)
        np.testing.assert_allclose(J[:3, j], (Tp[:3, 3] - Tm[:3, 3]) / (2 * h), atol=1e-7)
        W = (Tp[:3, :3] - Tm[:3, :3]) / (2 * h) @ robot.fk(q)[:3, :3].T
        np.testing.assert_allclose(J[3:, j], [W[2, 1], W[0, 2], W[1, 0]], atol=1e-7)


def test_kr60_as_urdf_is_the_catalogues(tmp_path: Path) -> None:
    kr60 = get_robot("kuka_kr60_3")
    robot = model_of(tmp_path, dh_urdf(), "base", "flange", vendor="kuka")
    q = np.random.default_rng(2).uniform(*kr60.joint_limits.T, (200, 6))
    assert np.max(np.abs(robot.fk(q) - kr60.fk(q))) <= 1e-12
    np.testing.assert_allclose(robot.joint_limits, kr60.joint_limits, rtol=1e-15)
    np.testing.assert_allclose(robot.velocity_limits, kr60.velocity_limits, rtol=1e-15)


@settings(max_examples=12, deadline=None)
@given(u=st.lists(st.floats(0.05, 0.95), min_size=6, max_size=6))
def test_numerical_ik_reaches_random_reachable_poses(ur_style, u: list[float]) -> None:
    robot, _ = ur_style
    q = uniform(robot, u)
    T = robot.fk(q)
    solutions = robot.ik(T)
    assert solutions
    for s in solutions:
        assert robot.within_limits(s)
        np.testing.assert_allclose(robot.fk(s), T, atol=1e-9)


# (file text, base, tip, field, words) of URDF files that must be refused
_LIMIT = '<limit lower="-1" upper="1" effort="1" velocity="1"/>'


def _robot(*joints: str, links: Sequence[str] = "abc") -> str:
    body = "".join(f"<link name='{x}'/>" for x in links) + "".join(joints)
    return f"<robot name='r'>{body}</robot>"


def _joint(name: str = "j1", kind: str = "revolute", parent: str = "a", child: str = "b",
           body: str = _LIMIT) -> str:  # fmt: skip
    return (
        f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
        f"{body}</joint>"
    )


BAD_URDF = [
    ("<robot name='r'><link name='a'/>", "a", "b", "urdf", "not well-formed XML"),
    ("<?xml version='1.0'?><!DOCTYPE r [<!ENTITY x 'y'>]><robot name='r'/>", "a", "b", "urdf",
     "DOCTYPE"),
    ("<model/>", "a", "b", "urdf", "not <robot>"),
    (_robot(_joint()), "a", "zz", "tip_link", "no link 'zz'"),
    (_robot(_joint()), "b", "a", "tip_link", "no chain of joints"),
    (_robot(_joint(kind="continuous")), "a", "b", "urdf", "a continuous joint"),
    (_robot(_joint(body="")), "a", "b", "urdf", "needs <limit"),
    (_robot(_joint(body='<limit lower="-1" upper="nan" velocity="1"/>')), "a", "b", "urdf",
     "limits must be finite"),
    (_robot(_joint(body='<origin xyz="0 0 inf"/>' + _LIMIT)), "a", "b", "urdf",
     "origin must be finite"),
    (_robot(_joint(body='<axis xyz="0 0 0"/>' + _LIMIT)), "a", "b", "urdf", "not all 0"),
    (_robot(_joint(body='<limit lower="-1" upper="1" velocity="0"/>')), "a", "b", "urdf",
     "velocity must be positive"),
    (_robot(_joint(kind="fixed", body="")), "a", "b", "tip_link", "no revolute or prismatic"),
    (_robot(*[_joint(f"j{i}", parent=f"l{i}", child=f"l{i + 1}") for i in range(13)],
            links=[f"l{i}" for i in range(14)]), "l0", "l13", "urdf", "more than 12 joints"),
    (_robot(_joint(), _joint("j2", parent="c", child="b")), "a", "b", "urdf", "two joints"),
    (_robot('<joint name="j1" type="revolute"><child link="b"/></joint>'), "a", "b", "urdf",
     "not a URDF robot"),
]  # fmt: skip


@pytest.mark.parametrize(("text", "base", "tip", "field", "words"), BAD_URDF)
def test_bad_urdf_is_refused_naming_the_file_and_field(
    tmp_path: Path, text: str, base: str, tip: str, field: str, words: str
) -> None:
    (tmp_path / "arm.urdf").write_text(text, encoding="utf-8")
    with pytest.raises(InputError) as info:
        load_project(urdf_project(tmp_path, "arm.urdf", base, tip))
    message = str(info.value)
    assert f"robot.custom.{field}" in message and words in message, message
    if field == "urdf":
        assert "arm.urdf" in message


def test_urdf_errors_name_the_line_of_the_joint() -> None:
    text = "<robot name='r'>\n<link name='a'/>\n<link name='b'/>\n" + _joint(kind="planar")
    with pytest.raises(InputError, match="line 4: joint 'j1'"):
        urdf_arm(text + "\n</robot>", "a", "b", "arm.urdf")


def test_missing_and_oversized_urdf_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"robot\.custom\.urdf.*does not exist"):
        load_project(urdf_project(tmp_path, "nope.urdf", "a", "b"))
    (tmp_path / "big.urdf").write_text("<robot name='r'>" + " " * (5 * 2**20) + "</robot>")
    with pytest.raises(InputError, match=r"robot\.custom\.urdf.*MiB"):
        load_project(urdf_project(tmp_path, "big.urdf", "a", "b"))
    with pytest.raises(InputError, match=r"robot\.custom\.joint_limits_deg.*URDF"):
        model_of(tmp_path, dh_urdf(), "base", "flange", joint_limits_deg=[[-1, 1]] * 6)
