"""Robots defined in a project file: OPW and DH definitions against the catalogue."""

from __future__ import annotations

import json
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from custom_robots import KR60_CAPSULES, KR60_DH, kr60, project_text
from helpers import ROOT
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError, UnsupportedError
from fabflow.link.setpoints import read_setpoints
from fabflow.project import parse_project
from fabflow.robots.catalog import (
    CONTROLLERS,
    controller_profile,
    formats_of,
    get_robot,
    vendor_of,
)
from fabflow.robots.custom import (
    CustomRobot,
    DHSpec,
    OPWSpec,
    custom_robot_model,
    opw_dh,
    opw_parameters,
    register_custom_robot,
)
from fabflow.robots.geometry import link_capsules
from fabflow.robots.kuka_config import kuka_status_turn
from fabflow.robots.opw import opw_fk

KR60 = get_robot("kuka_kr60_3")


def custom(spec: dict, **robot) -> str:
    """The registered name of the robot of a small project with this definition."""
    return parse_project(project_text(spec, **robot)).robot.name


@pytest.fixture(scope="module")
def kr60_opw():
    return get_robot(custom(kr60("opw")))


@pytest.fixture(scope="module")
def kr60_dh():
    return get_robot(custom(kr60("dh")))


def joints(robot, n: int, seed: int) -> np.ndarray:
    lo, hi = robot.joint_limits.T
    return np.random.default_rng(seed).uniform(lo, hi, (n, robot.dof))


def test_kr60_from_yaml_is_the_catalogues(kr60_opw, kr60_dh) -> None:
    for r in (kr60_opw, kr60_dh):
        assert r.name.startswith("custom:kr60_from_yaml@")
        for field in ("dh", "joint_sign", "joint_limits", "velocity_limits", "T_n_flange"):
            assert np.array_equal(getattr(r, field), getattr(KR60, field)), field
        assert np.array_equal(r.q_home, KR60.q_home)
        assert np.array_equal(r.q_nominal, KR60.q_nominal)
        assert r.opw == KR60.opw and r.analytic_ik is not None
        assert (r.reach, r.payload, r.dof, r.motion_groups) == (
            KR60.reach,
            KR60.payload,
            6,
            KR60.motion_groups,
        )
    assert kr60_opw.name != kr60_dh.name  # two definitions, two names


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_kr60_fk_and_ik_equal_the_catalogues(kr60_opw, kr60_dh, seed: int) -> None:
    q = joints(KR60, 64, seed)
    T = KR60.fk(q)
    q_ref = joints(KR60, 64, seed + 1)
    sols, valid = KR60.ik_batch(T, q_ref)
    for r in (kr60_opw, kr60_dh):
        assert np.max(np.abs(r.fk(q) - T)) <= 1e-12
        s, v = r.ik_batch(T, q_ref)
        assert np.array_equal(v, valid)
        assert np.max(np.abs(s - sols)) <= 1e-12
        assert np.max(np.abs(r.jacobian(q) - KR60.jacobian(q))) <= 1e-12
        assert np.array_equal(kuka_status_turn(q, r)[0], kuka_status_turn(q)[0])


def test_custom_robot_answers_every_catalogue_question(kr60_opw) -> None:
    name = kr60_opw.name
    assert vendor_of(name) == "kuka"
    assert formats_of(name) == ("krl", "json")
    assert controller_profile(name) == CONTROLLERS["krc4"]
    # without capsules of its own a robot gets 0.1 m ones between consecutive frames
    assert kr60_opw.capsules is None
    assert [(c.frame_a, c.frame_b, c.radius) for c in link_capsules(kr60_opw)] == [
        (i, i + 1, 0.1) for i in range(7)
    ]
    with_capsules = get_robot(custom(kr60("opw", capsules=KR60_CAPSULES)))
    assert link_capsules(with_capsules) == link_capsules(KR60)


def test_program_format_defaults_to_the_vendors_language() -> None:
    assert parse_project(project_text(kr60(vendor="abb"))).program.format == "rapid"
    assert parse_project(project_text(kr60(vendor="brokk"))).program.format == "json"


opw_params = st.fixed_dictionaries(
    {
        "a1": st.floats(-0.5, 0.5),
        "a2": st.floats(-0.3, 0.3),
        "b": st.floats(-0.3, 0.3),
        "c1": st.floats(0.2, 1.0),
        "c2": st.floats(0.3, 1.2),
        "c3": st.floats(0.3, 1.2),
        "c4": st.floats(0.05, 0.3),
        "offsets_deg": st.tuples(*[st.sampled_from([-180, -90, 0, 90, 180])] * 6),
        "signs": st.tuples(*[st.sampled_from([-1, 1])] * 6),
    }
)


@settings(max_examples=40, deadline=None)
@given(p=opw_params, seed=st.integers(0, 2**32 - 1))
def test_opw_definitions_match_the_opw_formulas(p: dict, seed: int) -> None:
    """The DH table derived from any OPW parameter set is the OPW arm, and the DH
    table read back is recognised as OPW (closed-form IK)."""
    spec = OPWSpec(**p)
    params = opw_parameters(spec)
    dh, sign = opw_dh(spec)
    base = kr60("opw", opw=p, joint_limits_deg=[[-180, 180]] * 6, home_deg=[0] * 6)
    base.pop("nominal_deg")
    robot = custom_robot_model(CustomRobot(**base), "custom:t@0")
    q = np.random.default_rng(seed).uniform(-np.pi, np.pi, (32, 6))
    assert np.max(np.abs(robot.fk(q) - opw_fk(params, q))) <= 1e-12
    sols, ok = robot.ik_batch(robot.fk(q), q)
    d = np.abs(np.angle(np.exp(1j * (sols - q[:, None, :])))).max(axis=2)
    assert np.all(np.any(ok & (d < 1e-7), axis=1) | ~robot.within_limits(q))
    table = {
        "a": dh[:, 0].tolist(),
        "alpha_deg": np.degrees(dh[:, 1]).round(9).tolist(),
        "d": dh[:, 2].tolist(),
        "offset_deg": (np.array([0, -90, -90, 0, 0, 180]) - np.array(p["offsets_deg"])).tolist(),
        "joint_sign": sign.astype(int).tolist(),
    }
    base.pop("opw")
    again = custom_robot_model(CustomRobot(**base, dh=DHSpec(**table)), "custom:t@1")
    assert again.analytic_ik is not None and again.opw is not None
    assert np.max(np.abs(again.fk(q) - robot.fk(q))) <= 1e-12


def test_flange_offset_keeps_closed_form_ik() -> None:
    flange = {"xyz": [0.01, -0.02, 0.05], "abc_deg": [30, -10, 5]}
    r = get_robot(custom(kr60("opw", flange=flange)))
    q = joints(r, 50, 3)
    T = r.fk(q)
    np.testing.assert_allclose(T, KR60.fk(q) @ r.T_n_flange, atol=1e-12)
    sols, ok = r.ik_batch(T, q)
    assert np.all(np.any(ok & (np.abs(sols - q[:, None]).max(axis=2) < 1e-7), axis=1))


def test_dh_without_opw_geometry_takes_numerical_ik() -> None:
    ur = get_robot("ur10e")
    assert ur.dh is not None
    table = {
        "a": ur.dh[:, 0].tolist(),
        "alpha_deg": [90, 0, 0, 90, -90, 0],
        "d": ur.dh[:, 2].tolist(),
        "offset_deg": [0] * 6,
    }
    spec = kr60(
        "dh",
        dh=table,
        vendor="ur",
        joint_limits_deg=[[-360, 360]] * 6,
        joint_speeds_deg_s=[120, 120, 180, 180, 180, 180],
        home_deg=[0, -90, 0, -90, 0, 0],
        nominal_deg=[0, -90, 90, -90, -90, 0],
        payload=12.5,
    )
    spec.pop("reach")
    r = get_robot(custom(spec))
    assert r.analytic_ik is None and r.opw is None
    q = joints(ur, 20, 4)
    assert np.max(np.abs(r.fk(q) - ur.fk(q))) <= 1e-12
    assert ur.reach < r.reach < 1.6  # the flange, sampled; below the sum of the lengths
    T = r.fk(q[0])
    sols = r.ik(T, q_ref=q[0] + 0.1)
    assert sols and np.allclose(r.fk(sols[0]), T, atol=1e-9)
    with pytest.raises(UnsupportedError, match="OPW"):
        kuka_status_turn(q[0], r)


def test_same_definition_same_name_and_one_model() -> None:
    a = parse_project(project_text(kr60("opw")))
    b = parse_project(project_text(kr60("opw")))
    assert a.robot.name == b.robot.name and get_robot(a.robot.name) is get_robot(b.robot.name)
    c = parse_project(project_text(kr60("opw", payload=50.0)))
    assert c.robot.name != a.robot.name and get_robot(c.robot.name).payload == 50.0


def test_unpickled_project_registers_its_robot_in_a_new_process(tmp_path: Path) -> None:
    """What a Dask worker does with a scattered project: unpickle it, use the robot."""
    project = parse_project(project_text(kr60("dh", payload=55.0)))
    assert register_custom_robot(project.robot.custom) == project.robot.name
    q = np.radians([10, -80, 100, 20, 30, 40])
    (tmp_path / "project.pkl").write_bytes(pickle.dumps(project))
    script = (
        "import json, pickle, sys\n"
        "from fabflow.robots.catalog import get_robot, is_registered\n"
        "name = sys.argv[2]\n"
        "before = is_registered(name)\n"
        "p = pickle.loads(open(sys.argv[1], 'rb').read())\n"
        "T = get_robot(name).fk(json.loads(sys.argv[3]))\n"
        "print(json.dumps([before, is_registered(name), T.tolist()]))\n"
    )
    args = [str(tmp_path / "project.pkl"), project.robot.name, json.dumps(q.tolist())]
    out = subprocess.run(
        [sys.executable, "-c", script, *args], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout
    before, after, T = json.loads(out)
    assert (before, after) == (False, True)
    assert np.array_equal(np.array(T), get_robot(project.robot.name).fk(q))


def test_unknown_custom_name_says_where_it_comes_from(tmp_path: Path) -> None:
    with pytest.raises(UnsupportedError, match="defined in a project file"):
        get_robot("custom:nowhere@0123456789")
    # a JSON program names its robot; one defined in a project file cannot be streamed
    doc = {"format": "fabflow-command-stream", "version": 1, "robot": "custom:arm@0123456789"}
    (tmp_path / "p.json").write_text(json.dumps({**doc, "commands": []}))
    with pytest.raises(InputError, match=r"defined in a project file.*catalogue robots"):
        read_setpoints(tmp_path / "p.json")


def test_dh_table_of_the_catalogue_kr60_is_recognised() -> None:
    assert KR60_DH["alpha_deg"] == [-90, 0, -90, 90, -90, 0]
    assert get_robot(custom(kr60("dh"))).analytic_ik is not None
    skew = {**KR60_DH, "alpha_deg": [-90, 0, -90, 90, -90, 1]}
    assert get_robot(custom(kr60("dh", dh=skew))).analytic_ik is None
