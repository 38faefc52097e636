"""Robot program writers: golden files, parse-back of every target, IK checks.

Golden files live in tests/golden/programs/; regenerate them after an intended
change with ``FABFLOW_UPDATE_GOLDEN=1 pytest tests/test_programs.py`` and review
the diff.
"""

from __future__ import annotations

import itertools
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import ROOT

from fabflow.design.elements import Element
from fabflow.errors import InfeasibleError, UnsupportedError
from fabflow.programs.compile import compile_program
from fabflow.programs.ir import Move, Program, sanitize_identifier
from fabflow.programs.motions import work_package_motion
from fabflow.programs.writers import WRITERS, writer_for
from fabflow.programs.writers.krl import write_krl
from fabflow.programs.writers.rapid import write_rapid
from fabflow.programs.writers.urscript import write_urscript
from fabflow.project import load_project
from fabflow.robots import get_robot
from fabflow.transforms.so3 import exp_so3, matrix_from_abc, matrix_from_quat

GOLDEN = ROOT / "tests" / "golden" / "programs"
PROJECT = ROOT / "tests" / "data" / "programs" / "project.yaml"


def _T(xyz, yaw=0.0, flip=False) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = exp_so3(np.array([0.0, 0.0, yaw]))
    if flip:
        T[:3, :3] = T[:3, :3] @ np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = xyz
    return T


def _elements() -> list[Element]:
    size = np.array([0.6, 0.105, 0.105])
    return [
        Element("B1", "block", _T([3.2, 1.0, 0.0525]), extents=size),
        Element("B2", "block", _T([3.0, 1.8, 0.1575], yaw=np.pi / 2), extents=size),
        Element(
            "P1",
            "print_path",
            _T([3.4, 0.6, 0.3]),
            polyline=np.array([[0.0, 0.0, 0.0], [0.1, 0.05, 0.0], [0.2, 0.0, 0.0]]),
            attributes={"speed": 0.1},
        ),
        Element("T1", "task_point", _T([3.0, 0.5, 0.3], flip=True), attributes={"action": "drill"}),
    ]


T_WORLD_BASE = _T([2.0, 1.0, 0.6], yaw=0.1)
BASE_OF_ROBOT = {"ur10e": _T([2.7, 1.0, 0.5], yaw=0.1)}
"""The UR10e reaches 1.3 m only: its base stands closer to the elements."""


def _program(robot: str = "kuka_kr60_3") -> Program:
    project = load_project(PROJECT)
    project = project.model_copy(
        update={"robot": project.robot.model_copy(update={"model": robot})}
    )
    T_world_base = BASE_OF_ROBOT.get(robot, T_WORLD_BASE)
    steps = work_package_motion(_elements(), project, T_world_base)
    header = {"project": project.name, "station": "S1", "generator": "fabflow test"}
    return compile_program("writer test S1", steps, project, T_world_base, header)


@pytest.fixture(scope="module")
def kuka_program() -> Program:
    return _program()


CASES = [
    ("krl", "kuka_kr60_3"),
    ("rapid", "abb_irb4600_60_205"),
    ("urscript", "ur10e"),
    ("json", "kuka_kr60_3"),
]


@pytest.mark.parametrize(("fmt", "robot"), CASES)
def test_golden(fmt: str, robot: str) -> None:
    files = WRITERS[fmt].write(_program(robot))
    folder = GOLDEN / fmt
    if os.environ.get("FABFLOW_UPDATE_GOLDEN"):
        folder.mkdir(parents=True, exist_ok=True)
        for name, text in files.items():
            (folder / name).write_text(text, encoding="utf-8")
    expected = {p.name: p.read_text(encoding="utf-8") for p in folder.iterdir()}
    assert files == expected


@pytest.mark.parametrize(("fmt", "robot"), CASES)
def test_writers_are_deterministic(fmt: str, robot: str) -> None:
    assert WRITERS[fmt].write(_program(robot)) == WRITERS[fmt].write(_program(robot))


# ----------------------------------------------------------------------- readers


def _kuka_T(values: list[float]) -> np.ndarray:
    x, y, z, a, b, c = values
    T = np.eye(4)
    T[:3, :3] = matrix_from_abc(*np.radians([a, b, c]))
    T[:3, 3] = np.array([x, y, z]) / 1000.0
    return T


def _read_krl_module(src: str, dat: str) -> tuple[np.ndarray, list[tuple], list[str]]:
    num = r"(-?\d+\.\d+)"
    frame = rf"X {num},Y {num},Z {num},A {num},B {num},C {num}"
    base = re.search(rf"DECL FRAME BASE_WORLD={{{frame}}}", dat)
    points = {}
    for m in re.finditer(rf"DECL E6POS (\w+)={{{frame}(?:,S (\d+),T (\d+))?}}", dat):
        st = (int(m.group(8)), int(m.group(9))) if m.group(8) else ()
        points[m.group(1)] = (_kuka_T([float(g) for g in m.groups()[1:7]]), st)
    moves = [
        (kind.lower(), *points[name], comment.strip())
        for kind, name, comment in re.findall(r"^(PTP|LIN) (\w+)[^;\n]*;?(.*)$", src, flags=re.M)
    ]
    calls = re.findall(r"^(\w+)\( \)$", src, flags=re.M)
    return _kuka_T([float(g) for g in base.groups()]), moves, calls


def read_krl(files: dict[str, str]) -> tuple[np.ndarray, list[tuple[str, np.ndarray, tuple, str]]]:
    """$BASE and the motions (kind, T in $BASE, (S, T) or (), comment) of a KRL program.

    ``files`` holds the main module and its sub-program modules; the motions are
    returned in execution order (sub-programs expanded where they are called).
    """
    modules = {
        name[:-4]: _read_krl_module(text, files[name[:-4] + ".dat"])
        for name, text in files.items()
        if name.endswith(".src")
    }
    called = {c for _, _, calls in modules.values() for c in calls}
    (root,) = [m for m in modules if m not in called]

    def expand(name: str) -> list[tuple]:
        _, moves, calls = modules[name]
        return moves + [m for c in calls for m in expand(c)]

    return modules[root][0], expand(root)


def _abb_T(p: list[float], q: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat(np.array(q))
    T[:3, 3] = np.array(p) / 1000.0
    return T


def read_rapid(text: str) -> tuple[np.ndarray, list[tuple[str, np.ndarray]]]:
    """Work object frame and the motions (kind, T in the work object) of a RAPID module."""
    vec = r"\[(-?[\d.]+),(-?[\d.]+),(-?[\d.]+)\]"
    quat = r"\[(-?[\d.]+),(-?[\d.]+),(-?[\d.]+),(-?[\d.]+)\]"
    w = re.search(rf"wobjdata wobj_world := \[FALSE,TRUE,\"\",\[{vec},{quat}\]", text)
    wobj = _abb_T([float(g) for g in w.groups()[:3]], [float(g) for g in w.groups()[3:]])
    targets = {
        m.group(1): _abb_T([float(g) for g in m.groups()[1:4]], [float(g) for g in m.groups()[4:]])
        for m in re.finditer(rf"CONST robtarget (\w+) := \[{vec},{quat}", text)
    }
    moves = [
        ("ptp" if kind == "MoveJ" else "lin", targets[name])
        for kind, name in re.findall(r"(MoveJ|MoveL) (\w+),", text)
    ]
    return wobj, moves


def _ur_T(values: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = exp_so3(np.array(values[3:]))
    T[:3, 3] = values[:3]
    return T


def read_urscript(text: str) -> tuple[np.ndarray, list[tuple[str, np.ndarray]]]:
    """world_in_base and the motions (kind, T world or q) of a URScript program."""
    p = r"p\[([^\]]+)\]"
    base = _ur_T([float(v) for v in re.search(rf"world_in_base = {p}", text).group(1).split(",")])
    moves = []
    for kind, args in re.findall(r"(movej|movel)\((.*?)\)?, a=", text):
        if kind == "movej":
            moves.append(("ptp", np.array([float(v) for v in args.strip("[]").split(",")])))
        else:
            values = re.search(p, args).group(1).split(",")
            moves.append(("lin", _ur_T([float(v) for v in values])))
    return base, moves


def _assert_pose_close(T: np.ndarray, T_ref: np.ndarray) -> None:
    assert np.linalg.norm(T[:3, 3] - T_ref[:3, 3]) < 1e-5  # 0.01 mm
    cos = np.clip((np.trace(T[:3, :3].T @ T_ref[:3, :3]) - 1) / 2, -1.0, 1.0)
    assert np.degrees(np.arccos(cos)) < 1e-3  # 0.001 deg


def _base_targets(program: Program) -> list[np.ndarray]:
    """The planned tool targets in the robot base frame (what the controller reaches)."""
    return [program.T_base_world @ m.T_world_tool for m in program.moves]


def test_krl_targets_parse_back(kuka_program: Program) -> None:
    robot = get_robot("kuka_kr60_3")
    base, moves = read_krl(write_krl(kuka_program))
    planned = kuka_program.moves
    assert [kind for kind, _, _, _ in moves] == [m.kind for m in planned]
    T_flange_tool = kuka_program.T_flange_tool
    for (_, T, st, _), move, T_base_ref in zip(
        moves, planned, _base_targets(kuka_program), strict=True
    ):
        _assert_pose_close(base @ T, T_base_ref)
        # joint target through forward kinematics gives the same tool pose
        _assert_pose_close(robot.fk(move.q) @ T_flange_tool, T_base_ref)
        if move.kind == "ptp":
            from fabflow.robots import kuka_status_turn

            assert st == kuka_status_turn(move.q)


def test_rapid_targets_parse_back() -> None:
    program = _program("abb_irb4600_60_205")
    robot = get_robot("abb_irb4600_60_205")
    (text,) = write_rapid(program).values()
    wobj, moves = read_rapid(text)
    assert [kind for kind, _ in moves] == [m.kind for m in program.moves]
    for (_, T), move, T_base_ref in zip(moves, program.moves, _base_targets(program), strict=True):
        _assert_pose_close(wobj @ T, T_base_ref)
        _assert_pose_close(robot.fk(move.q) @ program.T_flange_tool, T_base_ref)


def test_urscript_targets_parse_back() -> None:
    program = _program("ur10e")
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


def test_krl_long_program_is_split(kuka_program: Program) -> None:
    files = write_krl(kuka_program, max_moves=10)
    main = files["writer_test_S1.src"]
    subs = sorted(k[:-4] for k in files if k.endswith(".src") and k != "writer_test_S1.src")
    assert len(subs) == -(-len(kuka_program.moves) // 10)
    for sub in subs:
        assert f"{sub}( )" in main
        assert len(sub) <= 24
    _, moves = read_krl(files)
    assert [m[0] for m in moves] == [m.kind for m in kuka_program.moves]
    _, unsplit = read_krl(write_krl(kuka_program))
    for a, b in zip(moves, unsplit, strict=True):
        np.testing.assert_array_equal(a[1], b[1])


def test_identifiers_are_sanitized() -> None:
    name = sanitize_identifier("7 visit / station S12 of the long cabin project", 24)
    assert len(name) <= 24
    assert re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", name)
    assert sanitize_identifier("ok_name", 24) == "ok_name"


def test_vendor_format_must_fit_robot() -> None:
    with pytest.raises(UnsupportedError, match="KUKA"):
        writer_for("krl", "ur10e")
    with pytest.raises(UnsupportedError, match="unknown program format"):
        writer_for("gcode", "kuka_kr60_3")
    writer_for("json", "brokk_170")


def test_unreachable_target_names_element() -> None:
    project = load_project(PROJECT)
    far = Element(
        "FAR", "task_point", _T([9.0, 1.0, 0.3], flip=True), attributes={"action": "mark"}
    )
    steps = work_package_motion([far], project, T_WORLD_BASE)
    with pytest.raises(InfeasibleError, match=r"element FAR, target 'approach'"):
        compile_program("far", steps, project, T_WORLD_BASE, {})


def test_linear_move_through_limit_is_refused() -> None:
    """A linear move straight through the base axis must fail inside the line."""
    project = load_project(PROJECT)
    steps = work_package_motion(
        [
            Element(
                "X",
                "print_path",
                _T([2.0, 1.0, 0.0]),
                polyline=np.array([[0.9, -0.9, 0.0], [-0.9, 0.9, 0.0]]),
            )
        ],
        project,
        _T([2.0, 1.0, 0.2]),
    )
    with pytest.raises(InfeasibleError, match=r"element X"):
        compile_program("through", steps, project, _T([2.0, 1.0, 0.2]), {})


def test_program_moves_carry_valid_configurations(kuka_program: Program) -> None:
    robot = get_robot("kuka_kr60_3")
    q = np.stack([m.q for m in kuka_program.moves])
    assert robot.within_limits(q).all()
    times = [m.time for m in kuka_program.moves]
    assert times == sorted(times) and times[-1] > 0
    assert all(isinstance(m, Move) for m in kuka_program.moves)


def test_golden_folder_has_no_stale_files() -> None:
    for fmt, robot in CASES:
        names = set(WRITERS[fmt].write(_program(robot)))
        assert {p.name for p in (GOLDEN / fmt).iterdir()} == names
    assert Path(GOLDEN).is_dir()
