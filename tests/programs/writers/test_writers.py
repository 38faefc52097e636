"""Robot program writers: golden files, parse-back of every target, IK checks.

Golden files live in tests/golden/programs/; regenerate them after an intended
change with ``FABFLOW_UPDATE_GOLDEN=1 pytest tests/programs/writers`` and review
the diff.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from program_cases import CASES, GOLDEN, golden, sample_program
from program_readers import read_krl, read_rapid, read_urscript

from fabflow.errors import InputError, UnsupportedError
from fabflow.programs.ir import Move, Program, sanitize_identifier
from fabflow.programs.writers import WRITERS, rapid, writer_for
from fabflow.programs.writers.base import fixed
from fabflow.programs.writers.krl import write_krl
from fabflow.programs.writers.rapid import write_rapid
from fabflow.programs.writers.urscript import write_urscript
from fabflow.robots import get_robot
from fabflow.transforms.so3 import matrix_from_quat


@pytest.mark.parametrize(("fmt", "robot"), CASES)
def test_golden(fmt: str, robot: str) -> None:
    files = WRITERS[fmt].write(sample_program(robot))
    assert files == golden(files, GOLDEN / fmt)


@pytest.mark.parametrize(("fmt", "robot"), CASES)
def test_writers_are_deterministic(fmt: str, robot: str) -> None:
    assert WRITERS[fmt].write(sample_program(robot)) == WRITERS[fmt].write(sample_program(robot))


def _assert_pose_close(T: np.ndarray, T_ref: np.ndarray) -> None:
    assert np.linalg.norm(T[:3, 3] - T_ref[:3, 3]) < 1e-5  # 0.01 mm
    cos = np.clip((np.trace(T[:3, :3].T @ T_ref[:3, :3]) - 1) / 2, -1.0, 1.0)
    assert np.degrees(np.arccos(cos)) < 1e-3  # 0.001 deg


def _base_targets(program: Program) -> list[np.ndarray]:
    """The planned tool targets in the robot base frame (what the controller reaches)."""
    return [program.T_base_world @ m.T_world_tool for m in program.moves]


def test_krl_targets_parse_back(kuka_program: Program) -> None:
    robot = get_robot("kuka_kr60_3")
    read = read_krl(write_krl(kuka_program))
    planned = kuka_program.moves
    assert [kind for kind, _, _, _ in read.moves] == [m.kind for m in planned]
    T_flange_tool = kuka_program.T_flange_tool
    for (_, T, status_turn, _), move, T_base_ref in zip(
        read.moves[1:-1], planned[1:-1], _base_targets(kuka_program)[1:-1], strict=True
    ):
        _assert_pose_close(read.base @ T, T_base_ref)
        # joint target through forward kinematics gives the same tool pose
        _assert_pose_close(robot.fk(move.q) @ T_flange_tool, T_base_ref)
        if move.kind == "ptp":
            from fabflow.robots import kuka_status_turn

            assert status_turn == kuka_status_turn(move.q)


def test_rapid_targets_parse_back() -> None:
    program = sample_program("abb_irb4600_60_205")
    robot = get_robot("abb_irb4600_60_205")
    read = read_rapid(write_rapid(program))
    assert [kind for kind, _, _, _ in read.moves] == [m.kind for m in program.moves]
    for (_, T, _, _), move, T_base_ref in zip(
        read.moves[1:-1], program.moves[1:-1], _base_targets(program)[1:-1], strict=True
    ):
        _assert_pose_close(read.base @ T, T_base_ref)
        _assert_pose_close(robot.fk(move.q) @ program.T_flange_tool, T_base_ref)


@pytest.mark.parametrize("max_moves", [None, 3, 4])
def test_rapid_one_call_conversion_writes_the_same_bytes(monkeypatch, max_moves) -> None:
    # the writer converts every robtarget (print path included) in one call; the
    # text must be byte for byte what one conversion per pose wrote, split or not
    program = sample_program("abb_irb4600_60_205")
    assert any(m.element == "P1" and not m.joint for m in program.moves)
    batched = write_rapid(program, max_moves)
    one_call = rapid.to_abb_pose

    def per_pose(T):
        T = np.asarray(T)
        if T.ndim == 2:
            return one_call(T)
        pairs = [one_call(t) for t in T]
        return np.stack([p for p, _ in pairs]), np.stack([q for _, q in pairs])

    monkeypatch.setattr(rapid, "to_abb_pose", per_pose)
    assert write_rapid(program, max_moves) == batched


_NEAR_ZERO = st.sampled_from([0.0, -0.0, -1e-4, -4.9999e-4, -5e-4, -5.0001e-4, -5e-10, -6e-10])


@settings(max_examples=300, deadline=None)
@given(
    p=st.lists(st.floats(-1e5, 1e5) | _NEAR_ZERO, min_size=3, max_size=3),
    q=st.lists(st.floats(-1.0, 1.0) | _NEAR_ZERO, min_size=4, max_size=4),
)
def test_rapid_pose_text_writes_each_number_as_fixed_does(p: list[float], q: list[float]) -> None:
    # one format for the seven numbers of a robtarget, never a negative zero
    expected = "[[" + ",".join(fixed(v, 3) for v in p) + "],["
    expected += ",".join(fixed(v, 9) for v in q) + "]]"
    assert rapid._pose_text(np.array(p), np.array(q)) == expected


def test_urscript_targets_parse_back() -> None:
    program = sample_program("ur10e")
    robot = get_robot("ur10e")
    (text,) = write_urscript(program).values()
    base, moves = read_urscript(text)
    assert [kind for kind, _ in moves] == [m.kind for m in program.moves]
    for (kind, value), T_base_ref in zip(moves, _base_targets(program), strict=True):
        if kind == "ptp":
            assert np.abs(value - 0).max() < 10  # joint list, checked through FK below
            _assert_pose_close(robot.fk(value) @ program.T_flange_tool, T_base_ref)
        else:
            _assert_pose_close(base @ value, T_base_ref)


def test_json_stream_setpoints(kuka_program: Program) -> None:
    robot = get_robot("kuka_kr60_3")
    (text,) = WRITERS["json"].write(kuka_program).values()
    doc = json.loads(text)
    setpoints = [c for c in doc["commands"] if c["type"] == "setpoint"]
    times = [c["t"] for c in doc["commands"]]
    assert times == sorted(times)
    q = np.array([c["q"] for c in setpoints])
    T = robot.fk(q) @ kuka_program.T_flange_tool
    pos = np.array([c["position"] for c in setpoints])
    np.testing.assert_allclose(T[:, :3, 3], pos, atol=1e-6)
    quat = np.array([c["quaternion"] for c in setpoints])
    np.testing.assert_allclose(matrix_from_quat(quat), T[:, :3, :3], atol=1e-6)
    # linear moves are broken into controller steps of at most 2 cm
    lin = [c for c in setpoints if c["kind"] == "lin"]
    steps = np.linalg.norm(np.diff([c["position"] for c in lin], axis=0), axis=1)
    same_move = np.array([a["label"] == b["label"] for a, b in itertools.pairwise(lin)])
    assert steps[same_move].max() <= 0.02 + 1e-9
    assert {c["name"] for c in doc["commands"] if c["type"] == "io"} == {
        "gripper",
        "extruder",
        "drill",
    }


def test_krl_header_and_structure(kuka_program: Program) -> None:
    files = write_krl(kuka_program)
    src = files["writer_test_S1.src"]
    assert src.startswith("&ACCESS RVP\n&REL 1\nDEF writer_test_S1( )\n")
    assert "BAS (#INITMOV,0)" in src
    assert "; station: S1" in src
    # every output switch follows an exact stop, and is not advanced with CONTINUE
    lines = src.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("$OUT["):
            motion = next(m for m in reversed(lines[:i]) if m.startswith(("PTP", "LIN")))
            assert "C_DIS" not in motion and "C_PTP" not in motion, motion
    assert "CONTINUE" not in src
    assert all("C_DIS" not in m for m in lines if m.startswith("PTP"))
    assert any(m.startswith("PTP") and "C_PTP" in m for m in lines)
    assert "FOLD" not in src


def test_krl_long_program_is_split_between_elements(kuka_program: Program) -> None:
    files = write_krl(kuka_program, max_moves=10)
    main = files["writer_test_S1.src"]
    subs = sorted(k[:-4] for k in files if k.endswith(".src") and k != "writer_test_S1.src")
    # B1 and B2 hold 7 motions each, P1 5 and T1 3: B1 | B2 | P1 T1
    assert len(subs) == 3
    for sub in subs:
        assert f"{sub}( )" in main
        assert len(sub) <= 24
    read = read_krl(files)
    assert [m[0] for m in read.moves] == [m.kind for m in kuka_program.moves]
    unsplit = read_krl(write_krl(kuka_program))
    for a, b in zip(read.moves[1:-1], unsplit.moves[1:-1], strict=True):
        np.testing.assert_array_equal(a[1], b[1])
    # HOME stays in the main module, around the calls
    lines = [line for line in main.splitlines()[3:] if line.startswith("PTP") or "( )" in line]
    assert lines[0].startswith("PTP XFABHOME") and lines[-1].startswith("PTP XFABHOME")


def test_identifiers_are_sanitized() -> None:
    name = sanitize_identifier("7 visit / station S12 of the long cabin project", 24)
    assert len(name) <= 24
    assert re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", name)
    assert sanitize_identifier("ok_name", 24) == "ok_name"


@pytest.mark.parametrize(("fmt", "robot"), CASES)
def test_non_finite_values_are_refused_before_writing(fmt: str, robot: str) -> None:
    program = sample_program(robot)
    moves = [i for i in program.instructions if isinstance(i, Move)]
    faults = {
        moves[3]: dataclasses.replace(moves[3], speed=float("inf")),
        moves[2]: dataclasses.replace(moves[2], T_world_tool=np.full((4, 4), np.nan)),
    }
    for good, bad in faults.items():
        broken = dataclasses.replace(
            program, instructions=tuple(bad if i is good else i for i in program.instructions)
        )
        with pytest.raises(InputError, match="not finite"):
            WRITERS[fmt].write(broken)
    WRITERS[fmt].write(program)


def test_vendor_format_must_fit_robot() -> None:
    with pytest.raises(UnsupportedError, match="KUKA"):
        writer_for("krl", "ur10e")
    with pytest.raises(UnsupportedError, match="use format 'rapid' or 'json'"):
        writer_for("krl", "abb_irb4600_60_205")
    with pytest.raises(UnsupportedError, match=r"use format 'json'$"):
        writer_for("rapid", "brokk_170")
    with pytest.raises(UnsupportedError, match="unknown program format"):
        writer_for("nc", "kuka_kr60_3")
    writer_for("json", "brokk_170")


def test_golden_folder_has_no_stale_files() -> None:
    for fmt, robot in CASES:
        names = set(WRITERS[fmt].write(sample_program(robot)))
        assert {p.name for p in (GOLDEN / fmt).iterdir()} == names
    assert Path(GOLDEN).is_dir()
