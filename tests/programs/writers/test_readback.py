"""Every KRL and RAPID program of the cabin parsed back and checked against its Program.

The readers (``tests/program_readers.py``) know the statements the writers may
emit and nothing else. Read back, a program must hold the planned motions in
order (kinds, Cartesian targets re-projected through ``$BASE`` / the work object
to 0.01 mm and 0.001 deg, status and turn or confdata), start and end at HOME
with exact stops, carry the tool load, stop every module exactly, never start a
module with a linear move, keep every element in one module, and carry the
lift: as external axis E1 in every target, or as an operator stop naming the
height before the first motion.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from program_cases import sample_program
from program_readers import ReadProgram, program_files, read_krl, read_rapid

from fabflow.build.context import BuildContext
from fabflow.programs.ir import Lift, Move, Program, SetPayload
from fabflow.programs.writers.base import flange_load, split_modules
from fabflow.programs.writers.krl import write_krl
from fabflow.programs.writers.rapid import confdata, write_rapid
from fabflow.robots import get_robot, kuka_status_turn


def _pose_error(T: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    """Position (m) and rotation (deg) difference."""
    cos = np.clip((np.trace(T[:3, :3].T @ T_ref[:3, :3]) - 1) / 2, -1.0, 1.0)
    return float(np.linalg.norm(T[:3, 3] - T_ref[:3, 3])), float(np.degrees(np.arccos(cos)))


def check_read_back(read: ReadProgram, program: Program, vendor: str) -> None:
    """Assert that a program read back is ``program``."""
    planned = program.moves
    # a module that would start with a linear move re-enters with a PTP where the robot stands
    reentry = [m.comment.endswith("(module start)") for m in read.motions]
    motions = [m for m, r in zip(read.motions, reentry, strict=True) if not r]
    # planned motions before each read motion index
    planned_before = np.cumsum([0, *(not r for r in reentry)])
    assert [m.kind for m in motions] == [m.kind for m in planned]
    assert [m.wrist for m in motions] == [m.wrist_interpolated for m in planned]
    # HOME first and last, as joint targets, stopping exactly
    home = np.degrees(planned[0].q)
    for motion in (motions[0], motions[-1]):
        assert motion.T is None and motion.exact
        np.testing.assert_allclose(motion.axes_deg, home, atol=1e-4)
    assert planned[0].joint and planned[-1].joint
    # between them, HOME again only where the configuration changes
    for motion, move in zip(motions[1:-1], planned[1:-1], strict=True):
        assert (motion.T is None) == move.joint
        if move.joint:
            assert move.label == "home (configuration change)"
            np.testing.assert_allclose(motion.axes_deg, home, atol=1e-4)
    # the Cartesian targets through the base frame
    np.testing.assert_allclose(read.base, program.T_base_world, atol=1e-5)
    np.testing.assert_allclose(read.tool, program.T_flange_tool, atol=1e-5)
    robot = get_robot(program.robot)
    pairs = [(mo, mv) for mo, mv in zip(motions[1:-1], planned[1:-1], strict=True) if not mv.joint]
    flanges = robot.fk(np.stack([mv.q for _, mv in pairs]))
    for (motion, move), flange in zip(pairs, flanges, strict=True):
        dist, angle = _pose_error(read.base @ motion.T, program.T_base_world @ move.T_world_tool)
        assert dist < 1e-5 and angle < 1e-3, (move.element, move.label, dist, angle)
        if vendor == "kuka" and move.kind == "ptp":
            assert motion.status_turn == kuka_status_turn(move.q)
        if vendor == "abb":
            assert robot.opw is not None
            assert motion.status_turn == confdata(move.q, flange, robot.opw)
    # the tool load
    assert read.load_mass == pytest.approx(program.load.mass, abs=1e-3)
    np.testing.assert_allclose(read.load_cog, program.load.cog, atol=1e-6)
    # a held element's load switched in after the grip and out after the release
    changes = []
    for ins in program.instructions:
        if isinstance(ins, SetPayload):
            before = sum(
                isinstance(i, Move) for i in program.instructions[: program.instructions.index(ins)]
            )
            load = flange_load(program, ins.payload) if vendor == "kuka" else ins.payload
            mass, cog = (0.0, np.zeros(3)) if load is None else (load.mass, load.cog)
            changes.append((before, mass, cog))
    assert len(read.load_changes) == len(changes)
    for (n, mass, cog), (n_ref, mass_ref, cog_ref) in zip(read.load_changes, changes, strict=True):
        assert planned_before[n] == n_ref and mass == pytest.approx(mass_ref, abs=1e-3)
        np.testing.assert_allclose(cog, cog_ref, atol=1e-6)
    # the lift: an external axis in every target, or an operator stop before any motion
    lift = program.lift
    stops = read.operator_steps
    # the stops for moves that still collide come after the lift's, before any motion
    confirmed = stops[len(stops) - len(program.confirm) :]
    assert all(c in m for (_, m), c in zip(confirmed, program.confirm, strict=True))
    assert all(n == 0 for n, _ in stops)
    stops = stops[: len(stops) - len(program.confirm)]
    if lift is not None and lift.axis is not None:
        assert stops == []
        for motion in motions:
            assert motion.external == {lift.axis: pytest.approx(lift.height * 1000.0, abs=1e-3)}
    else:
        assert all(m.external == {} for m in motions)
    if lift is not None and lift.axis is None:
        ((before, message),) = stops
        assert before == 0
        assert f"{lift.height * 1000.0:.0f} mm" in message
    # module structure: limits, exact ends, no LIN first, elements whole
    if program.module_motions is not None:
        assert max(read.modules.values()) <= program.module_motions
    for motion in read.motions:
        if motion.first:
            assert motion.kind == "ptp", motion.module
        if motion.last:
            assert motion.exact, motion.module
    module_of: dict[str, str] = {}
    for motion, move in zip(motions, planned, strict=True):
        if move.element is not None:
            assert module_of.setdefault(move.element, motion.module) == motion.module, move.element


def _programs(build: tuple[Path, BuildContext]) -> list[tuple[Program, dict[str, str]]]:
    out, ctx = build
    assert ctx.programs
    return [(p, program_files(out / "programs", p.name)) for p in ctx.programs]


def test_every_cabin_krl_program_reads_back(cabin_build: tuple[Path, BuildContext]) -> None:
    programs = _programs(cabin_build)
    for program, files in programs:
        check_read_back(read_krl(files), program, "kuka")
    assert all(p.lift is not None and p.lift.axis is None for p, _ in programs)


def test_every_cabin_rapid_program_reads_back(cabin_abb_build: tuple[Path, BuildContext]) -> None:
    programs = _programs(cabin_abb_build)
    split = 0
    for program, files in programs:
        read = read_rapid(files)
        check_read_back(read, program, "abb")
        split += len(read.modules) > 1
    assert split > 0  # 200 motions a module: the long programs were split
    assert all(p.lift is not None and p.lift.axis == "E1" for p, _ in programs)


@pytest.mark.parametrize("axis", [None, "E1"])
@pytest.mark.parametrize("limit", [None, 20, 8])
def test_sample_programs_read_back_split_and_lifted(axis: str | None, limit: int | None) -> None:
    for robot, write, read, vendor in (
        ("kuka_kr60_3", write_krl, read_krl, "kuka"),
        ("abb_irb4600_60_205", write_rapid, read_rapid, "abb"),
    ):
        program = dataclasses.replace(
            sample_program(robot), lift=Lift(0.4125, axis), module_motions=limit
        )
        files = write(program)
        result = read(files)
        if limit == 8:
            # B1 alone holds 7 motions, P1 5: cut between elements only
            assert len(result.modules) > 2
        check_read_back(result, program, vendor)


def test_an_element_longer_than_a_module_is_cut_with_a_ptp() -> None:
    program = dataclasses.replace(sample_program(), module_motions=3)
    read = read_krl(write_krl(program))
    # each cut inside an element repeats the last point as a PTP: no module starts with LIN
    assert len(read.motions) > len(program.moves)
    assert all(m.kind == "ptp" for m in read.motions if m.first)
    assert all(m.exact for m in read.motions if m.last)
    assert max(read.modules.values()) <= 3
    planned = [m for m in read.motions if not m.comment.endswith("(module start)")]
    assert [m.kind for m in planned] == [m.kind for m in program.moves]


@pytest.mark.parametrize("limit", range(3, 13))
def test_no_module_starts_with_a_linear_move_wherever_the_cut_falls(limit: int) -> None:
    """A cut between elements may fall before an element whose first motion is linear
    (a tucked route's "tuck in"): that module starts with a PTP to the point where
    the robot stands, as a cut inside an element does."""
    program = sample_program()
    firsts, seen = set(), set()
    for k, ins in enumerate(program.instructions):
        if isinstance(ins, Move) and ins.element is not None and ins.element not in seen:
            seen.add(ins.element)
            firsts.add(k)
    body = [
        dataclasses.replace(ins, kind="lin") if k in firsts else ins
        for k, ins in enumerate(program.instructions)
    ]
    modules = split_modules(body, limit)
    assert all(sum(isinstance(i, Move) for i in m) <= limit for m in modules)
    for m in modules:
        assert next(i for i in m if isinstance(i, Move)).kind == "ptp"
    # the re-entries aside, the instructions are the program's, in order
    kept = [
        i
        for m in modules
        for i in m
        if not (isinstance(i, Move) and i.label.endswith("(module start)"))
    ]
    assert kept == body
    lin_program = dataclasses.replace(program, instructions=tuple(body), module_motions=limit)
    read = read_krl(write_krl(lin_program))
    assert all(m.kind == "ptp" for m in read.motions if m.first)
