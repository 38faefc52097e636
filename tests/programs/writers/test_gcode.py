"""G-code for print paths: golden files, parse-back with a public parser, refusals.

The files are read back with ``gcodeparser`` (its ``parse_gcode_lines``, the
entry point that replaces the deprecated ``GcodeParser`` class), independent of
the writer. Golden files live in tests/golden/programs/gcode/<flavor>/;
regenerate them after an intended change with
``FABFLOW_UPDATE_GOLDEN=1 pytest tests/programs/writers`` and review the diff.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
import yaml
from gcodeparser import parse_gcode_lines
from helpers import PROJECTS, run_cli
from hypothesis import given, settings
from hypothesis import strategies as st
from program_cases import GOLDEN, PROJECT, T_WORLD_BASE, golden, make_pose, sample_program

from fabflow.build.runner import run_build
from fabflow.design.elements import Element
from fabflow.errors import InputError, UnsupportedError
from fabflow.programs.assemble import compile_program
from fabflow.programs.compile import element_beads
from fabflow.programs.ir import Bead, Comment, GcodeOptions, Move, Program, SetOutput
from fabflow.programs.motions import work_package_motion
from fabflow.programs.writers import WRITERS, writer_for
from fabflow.project import load_project, parse_project
from fabflow.tasks.targets import element_tool_frames
from fabflow.transforms.so3 import exp_so3

FLAVORS = ("marlin", "robot")
E_DIGITS = {"marlin": 5, "robot": 3}
MOTION_COMMANDS = {"G0", "G1"}
SETUP_COMMANDS = {"G21", "G90", "M82", "G92", "M0"}
NON_FINITE = re.compile(r"(?<![\w.])-?(?:nan|inf|infinity)(?![\w])", re.IGNORECASE)
RESOLUTION_MM = 0.0005
"""Half the last decimal of X, Y and Z (3 decimals, mm)."""


# ------------------------------------------------------------------ the reader


@dataclass
class ReadGcode:
    """A G-code file read back: one row per motion line, modal values filled in."""

    command: list[str] = field(default_factory=list)
    xyz: list[tuple[float, float, float]] = field(default_factory=list)
    e: list[float] = field(default_factory=list)
    """Absolute E after the line (modal, 0 before any)."""
    e_given: list[bool] = field(default_factory=list)
    f: list[float] = field(default_factory=list)
    """Feed rate given on the line (NaN where none)."""
    element: list[str | None] = field(default_factory=list)
    """The element of the last ``; element X`` comment; ``None`` for a joint target (HOME)."""
    others: list[str] = field(default_factory=list)
    """Every command that is not a motion, in order."""

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """XYZ (N, 3) mm, E (N,), F (N,)."""
        return np.array(self.xyz).reshape(-1, 3), np.array(self.e), np.array(self.f)


def read_gcode(text: str) -> ReadGcode:
    """Parse ``text`` with gcodeparser and collect the motions (X, Y and Z on every line)."""
    read = ReadGcode()
    element: str | None = None
    joint_next = False
    e = 0.0
    for line in parse_gcode_lines(text, include_comments=True):
        command = line.command_str
        if command == ";":
            if line.comment.startswith("element "):
                element = line.comment.split()[1]
            joint_next = line.comment.startswith("joint target")
            continue
        if command not in MOTION_COMMANDS:
            read.others.append(command)
            continue
        params = line.params
        assert {"X", "Y", "Z"} <= set(params), line.gcode_str
        assert set(params) <= {"X", "Y", "Z", "E", "F"}, line.gcode_str
        if "E" in params:
            assert command == "G1", line.gcode_str
            e = float(params["E"])
        read.command.append(command)
        read.xyz.append((float(params["X"]), float(params["Y"]), float(params["Z"])))
        read.e.append(e)
        read.e_given.append("E" in params)
        read.f.append(float(params.get("F", np.nan)))
        read.element.append(None if joint_next else element)
        joint_next = False
    return read


def base_positions(program: Program) -> np.ndarray:
    """The moves' tool centre points in the robot base frame (mm): what the controller reaches."""
    T = program.T_base_world @ np.stack([m.T_world_tool for m in program.moves])
    return T[:, :3, 3] * 1000.0


def extruding_moves(program: Program) -> np.ndarray:
    """Whether the extruder is on along each move (an independent walk through the program)."""
    on, out = False, []
    for ins in program.instructions:
        if isinstance(ins, SetOutput):
            on = ins.value
        elif isinstance(ins, Move):
            out.append(on)
    return np.array(out, dtype=bool)


def expected_e(program: Program, positions: np.ndarray) -> np.ndarray:
    """Cumulative E after every move: bead volume (mm^3), per filament area for Marlin."""
    bead = {k: b.width * b.height * 1e6 for k, b in program.beads.items()}  # mm^2
    area = np.array([bead.get(m.element, 0.0) for m in program.moves])  # type: ignore[arg-type]
    segment = np.r_[0.0, np.linalg.norm(np.diff(positions, axis=0), axis=1)]
    volume = np.cumsum(segment * area * extruding_moves(program))
    if program.gcode.flavor == "marlin":
        return volume / (np.pi / 4 * (program.gcode.filament_diameter * 1000.0) ** 2)
    return volume


def check_read_back(text: str, program: Program) -> ReadGcode:
    """Assert that ``text`` holds ``program``'s motions and the format's promises."""
    assert not NON_FINITE.search(text), NON_FINITE.search(text)
    read = read_gcode(text)
    flavor = program.gcode.flavor
    assert read.others[:2] == ["G21", "G90"]
    assert (read.others[2:4] == ["M82", "G92"]) == (flavor == "marlin")
    assert set(read.others) <= SETUP_COMMANDS, read.others
    xyz, e, f = read.arrays()
    moves = program.moves
    assert len(read.command) == len(moves)
    expected = base_positions(program)
    np.testing.assert_allclose(xyz, expected, atol=RESOLUTION_MM + 1e-9, rtol=1e-12)
    extruding = extruding_moves(program)
    linear = np.array([m.kind == "lin" for m in moves])
    assert read.command == ["G1" if g1 else "G0" for g1 in linear | extruding]
    assert read.e_given == extruding.tolist()
    # E: absolute, never decreasing, the bead volume to the format's resolution
    assert np.all(np.diff(e) >= 0.0)
    tol = 0.5 * 10.0 ** -E_DIGITS[flavor]
    np.testing.assert_allclose(e, expected_e(program, expected), atol=tol + 1e-9, rtol=1e-12)
    # F: positive and finite where given, on G1 only; the move's speed on a linear move
    command = np.array(read.command)
    g1 = command == "G1"
    given_f = ~np.isnan(f)
    assert np.all(np.isfinite(f[given_f]) & (f[given_f] > 0.0))
    assert not np.any(given_f & ~g1)
    if g1.any():
        f_g1 = f[g1]
        assert not np.isnan(f_g1[0])
        last = np.where(np.isnan(f_g1), 0, np.arange(len(f_g1)))
        modal = f_g1[np.maximum.accumulate(last)]
        speed = np.array([m.speed * 60000.0 for m in moves])[g1]
        np.testing.assert_allclose(modal[linear[g1]], speed[linear[g1]], atol=0.05 + 1e-9)
    return read


# ---------------------------------------------------------- the sample program


def print_elements() -> list[Element]:
    """Two layers of a small print path; the second has a travel segment."""
    attrs = {"speed": 0.1, "bead_width": 0.04, "layer_height": 0.02}
    polyline = np.array([[0.0, 0.0, 0.0], [0.1, 0.05, 0.0], [0.2, 0.0, 0.0], [0.2, 0.1, 0.0]])
    return [
        Element("P1", "print_path", make_pose([3.4, 0.6, 0.30]), polyline=polyline[:3],
                attributes=attrs),
        Element("P2", "print_path", make_pose([3.4, 0.6, 0.32]), polyline=polyline,
                attributes={**attrs, "speed": 0.05, "extrude": [True, False, True]}),
    ]  # fmt: skip


def print_program(flavor: str = "marlin") -> Program:
    """The print test program for the KUKA KR 60-3, written in ``flavor``."""
    project = load_project(PROJECT)
    tool = project.robot.tool.model_copy(update={"name": "extruder"})
    project = project.model_copy(update={"robot": project.robot.model_copy(update={"tool": tool})})
    elements = print_elements()
    steps = work_package_motion(elements, project, T_WORLD_BASE)
    header = {"project": project.name, "station": "S1", "generator": "fabflow test"}
    program = compile_program(
        "print test S1", steps, project, T_WORLD_BASE, header, lift=0.35,
        beads=element_beads(elements),
    )  # fmt: skip
    return dataclasses.replace(program, gcode=GcodeOptions(flavor))


@pytest.mark.parametrize("flavor", FLAVORS)
def test_golden(flavor: str) -> None:
    files = WRITERS["gcode"].write(print_program(flavor))
    assert files == golden(files, GOLDEN / "gcode" / flavor)
    assert WRITERS["gcode"].write(print_program(flavor)) == files  # deterministic


@pytest.mark.parametrize("flavor", FLAVORS)
def test_sample_reads_back(flavor: str) -> None:
    program = print_program(flavor)
    (text,) = WRITERS["gcode"].write(program).values()
    read = check_read_back(text, program)
    # a travel G0 between the layers, the lift as an operator stop, HOME by its joints
    assert read.command.count("G0") == 4  # HOME, two approaches, HOME
    assert read.others.count("M0") == 1 and "set the lift to 350 mm" in text
    assert read.element[0] is None and read.element[-1] is None
    assert "; joint target (home): 0.000 -90.000 90.000 0.000 0.000 0.000 deg" in text
    # the travel segment of P2 extrudes nothing
    e = np.array(read.e)[np.array(read.element) == "P2"]
    assert len(e) == 6 and e[3] == e[2] and e[4] > e[3] > e[1]


def test_bead_and_filament_set_e() -> None:
    program = print_program("marlin")
    wide = dataclasses.replace(
        program,
        beads={k: Bead(2 * b.width, b.height) for k, b in program.beads.items()},
        gcode=GcodeOptions("marlin", 2 * program.gcode.filament_diameter),
    )
    e0 = read_gcode(next(iter(WRITERS["gcode"].write(program).values()))).e[-1]
    e1 = read_gcode(next(iter(WRITERS["gcode"].write(wide).values()))).e[-1]
    assert e1 == pytest.approx(e0 / 2, abs=1e-4)  # twice the bead over four times the area


# ---------------------------------------------------------------- refusals


def test_blocks_and_task_points_are_refused() -> None:
    program = sample_program()  # blocks B1, B2, a print path P1, a task point T1
    refused = r"print paths only.*B1, B2, P1, T1.*'krl' or 'json'"
    with pytest.raises(UnsupportedError, match=refused):
        WRITERS["gcode"].write(program)
    printable = dataclasses.replace(program, beads={"P1": Bead(0.03, 0.02)})
    with pytest.raises(UnsupportedError, match="elements B1, B2, T1"):
        WRITERS["gcode"].write(printable)
    # G-code runs on every robot; only the elements decide
    assert writer_for("gcode", "brokk_170").format == "gcode"


def test_bad_beads_and_speeds_are_refused_before_writing() -> None:
    program = print_program()
    for beads in ({"P1": Bead(np.nan, 0.02), "P2": Bead(0.04, 0.02)},
                  {"P1": Bead(0.04, 0.0), "P2": Bead(0.04, 0.02)}):  # fmt: skip
        with pytest.raises(InputError, match="not a finite positive number"):
            WRITERS["gcode"].write(dataclasses.replace(program, beads=beads))
    slow = tuple(
        dataclasses.replace(i, speed=1e-9) if isinstance(i, Move) and i.kind == "lin" else i
        for i in program.instructions
    )
    with pytest.raises(InputError, match="feed rate's resolution"):
        WRITERS["gcode"].write(dataclasses.replace(program, instructions=slow))
    with pytest.raises(UnsupportedError, match="unknown G-code flavor"):
        WRITERS["gcode"].write(dataclasses.replace(program, gcode=GcodeOptions("sailfish")))


def test_comments_cannot_break_out_of_their_line() -> None:
    program = print_program()
    program = dataclasses.replace(program, header={"project": "x\nG1 X0 Y0 Z0 E9999\r%d"})
    (text,) = WRITERS["gcode"].write(program).values()
    assert "; project: x G1 X0 Y0 Z0 E9999 %d" in text
    check_read_back(text, program)


def test_project_with_other_elements_is_refused_for_gcode(tmp_path: Path) -> None:
    data = yaml.safe_load((PROJECTS / "cabin" / "project.yaml").read_text())
    data["program"] = {**data.get("program", {}), "format": "gcode"}
    with pytest.raises(InputError, match=r"program\.format.*print paths only.*elements\[0\]"):
        parse_project(yaml.safe_dump(data), "cabin.yaml", PROJECTS / "cabin")
    with pytest.raises(UnsupportedError, match="print paths only"):
        load_project(PROJECTS / "cabin").with_program_format("gcode")
    with pytest.raises(UnsupportedError, match="unknown program format 'nc'"):
        load_project(PROJECTS / "cabin").with_program_format("nc")


def test_cli_refuses_gcode_for_a_cabin(tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = run_cli("program", str(PROJECTS / "cabin"), "--format", "gcode", "-o", str(out))
    assert result.returncode == 2, result.stderr
    assert "print paths only" in result.stderr and "Traceback" not in result.stderr
    assert not out.exists()


# ---------------------------------------------------------------- property


@st.composite
def print_programs(draw: st.DrawFn) -> Program:
    """A program of one random polyline (finite, within 10 m), extruding where drawn."""
    n = draw(st.integers(2, 40))
    coordinate = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)
    points = np.array(draw(st.lists(st.tuples(coordinate, coordinate, coordinate),
                                    min_size=n, max_size=n)))  # fmt: skip
    extrude = draw(st.lists(st.booleans(), min_size=n - 1, max_size=n - 1))
    speeds = draw(st.lists(st.floats(1e-3, 3.0), min_size=n, max_size=n))
    yaw, x, y, z = (draw(st.floats(-5.0, 5.0)) for _ in range(4))
    axis = np.array([draw(st.floats(-1.0, 1.0)) for _ in range(3)])
    T_base_world = np.eye(4)
    T_base_world[:3, :3] = exp_so3(axis) @ exp_so3(np.array([0.0, 0.0, yaw]))
    T_base_world[:3, 3] = (x, y, z)
    flavor = draw(st.sampled_from(FLAVORS))
    bead = Bead(draw(st.floats(1e-3, 0.2)), draw(st.floats(1e-3, 0.1)))
    diameter = draw(st.floats(1e-3, 0.1))
    q = np.zeros(6)
    instructions: list = [Comment("element P1", "P1")]
    on = False
    for k, p in enumerate(points):
        if k and extrude[k - 1] != on:
            on = extrude[k - 1]
            instructions.append(SetOutput("extruder", on, "P1"))
        pose = make_pose(p, flip=True)
        kind = "ptp" if k == 0 else "lin"
        instructions.append(Move(kind, pose, q, speeds[k], element="P1"))
    if on:
        instructions.append(SetOutput("extruder", False, "P1"))
    return Program(
        name="random print",
        robot="kuka_kr60_3",
        T_base_world=T_base_world,
        T_flange_tool=np.eye(4),
        instructions=tuple(instructions),
        beads={"P1": bead},
        gcode=GcodeOptions(flavor, diameter),
    )


@settings(max_examples=60, deadline=None)
@given(print_programs())
def test_random_polylines_round_trip(program: Program) -> None:
    (text,) = WRITERS["gcode"].write(program).values()
    check_read_back(text, program)


# ----------------------------------------------------- the print wall example


@pytest.fixture(scope="module")
def print_wall(tmp_path_factory: pytest.TempPathFactory):
    """The print wall with ``program: {format: gcode, gcode: {flavor: robot}}``, built."""
    folder = PROJECTS / "print_path"
    data = yaml.safe_load((folder / "project.yaml").read_text())
    data["program"] = {**data["program"], "format": "gcode", "gcode": {"flavor": "robot"}}
    project = parse_project(yaml.safe_dump(data), folder / "project.yaml", folder)
    project = project.model_copy(update={"path": (folder / "project.yaml").resolve()})
    out = tmp_path_factory.mktemp("print_wall_gcode") / "out"
    return out, run_build(project, out, until="program")


def test_print_wall_parses_back_to_its_path(print_wall) -> None:
    """Every sample of every print path, through its station's base frame, within 0.01 mm."""
    out, ctx = print_wall
    by_id = {e.id: e for e in ctx.need_elements()}
    read_xyz, design_xyz = [], []
    count = 0
    for program in ctx.programs:
        text = (out / "programs" / f"{program.name.lower()}.gcode").read_text()
        read = check_read_back(text, program)
        xyz, _, _ = read.arrays()
        owner = np.array([x or "" for x in read.element])
        for eid in program.beads:
            lines = xyz[owner == eid]  # approach, start, the samples after it, retract
            samples = element_tool_frames(by_id[eid])[:, :3, 3]
            assert len(lines) == len(samples) + 2, eid
            world = np.c_[samples, np.ones(len(samples))]
            design_xyz.append((world @ program.T_base_world.T)[:, :3] * 1000.0)
            read_xyz.append(lines[1:-1])
            count += len(samples)
    deviation = np.linalg.norm(np.concatenate(read_xyz) - np.concatenate(design_xyz), axis=1)
    assert count == sum(len(e.polyline) for e in by_id.values() if e.type == "print_path")
    assert deviation.max() < 0.01, deviation.max()  # mm
    assert count > 20_000


def test_cli_writes_gcode_for_the_print_wall(tmp_path: Path) -> None:
    out = tmp_path / "out"
    result = run_cli("program", str(PROJECTS / "print_path"), "--format", "gcode", "-o", str(out))
    assert result.returncode == 0, result.stderr
    files = sorted((out / "programs").iterdir())
    assert files and all(p.suffix == ".gcode" for p in files)
    for path in files:
        text = path.read_text()
        assert "(marlin flavor)" in text and not NON_FINITE.search(text)
        read = read_gcode(text)
        assert read.command.count("G1") > 100 and read.others[:4] == ["G21", "G90", "M82", "G92"]
    assert "gcode" in result.stdout
