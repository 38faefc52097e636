"""Linear moves past the wrist singularity: every writer switches the vendor's wrist
interpolation on for exactly that move, and the readers find it there."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from program_cases import CASES, PROJECT, T_WORLD_BASE, make_pose, sample_program
from program_readers import read_krl, read_rapid

from fabflow.design.elements import Element
from fabflow.programs.assemble import compile_program
from fabflow.programs.ir import Move, Program
from fabflow.programs.motions import Waypoint, work_package_motion
from fabflow.programs.writers import WRITERS
from fabflow.project import load_project


def _flag_one_linear_move(program: Program) -> tuple[Program, int]:
    """``program`` with its first linear move marked wrist-interpolated, and its index."""
    instructions = list(program.instructions)
    k = next(i for i, ins in enumerate(instructions) if isinstance(ins, Move) and ins.kind == "lin")
    instructions[k] = dataclasses.replace(instructions[k], wrist_interpolated=True)
    index = sum(isinstance(i, Move) for i in instructions[:k])
    return dataclasses.replace(program, instructions=tuple(instructions)), index


@pytest.mark.parametrize(("fmt", "robot"), CASES)
def test_each_writer_marks_the_move_and_nothing_else(fmt: str, robot: str) -> None:
    program, index = _flag_one_linear_move(sample_program(robot))
    files = WRITERS[fmt].write(program)
    text = "\n".join(files.values())
    if fmt == "krl":
        read = read_krl(files)
        assert [m.wrist for m in read.motions] == [m.wrist_interpolated for m in program.moves]
        assert text.count("$ORI_TYPE = #JOINT") == 1 == text.count("$ORI_TYPE = #VAR")
    elif fmt == "rapid":
        read = read_rapid(files)
        assert [m.wrist for m in read.motions] == [m.wrist_interpolated for m in program.moves]
        assert text.count("SingArea \\Wrist") == 1 == text.count("SingArea \\Off")
    elif fmt == "json":
        (doc,) = (json.loads(t) for t in files.values())
        flagged = [c for c in doc["commands"] if c.get("wrist_interpolated")]
        move = program.moves[index]
        assert len(flagged) == (0 if move.via_q is None else len(move.via_q)) + 1
    else:
        move = program.moves[index]
        assert (
            text.count("movej(")
            == sum(m.kind == "ptp" for m in program.moves)
            + (0 if move.via_q is None else len(move.via_q))
            + 1
        )


def test_a_real_wrist_move_reads_back_from_krl() -> None:
    """Blocks low in front of a KR 60-3: the place descents pass the wrist singularity.
    Compiled as if the tool held nothing there (a held block goes by a joint move
    instead, see tests/programs/test_motion_checks.py), they keep their status with
    the wrist axes interpolated."""
    project = load_project(PROJECT)
    low = [
        Element(f"L{i}", "block", make_pose([2.9 + 0.1 * i, 0.5 + 0.2 * i, 0.3], yaw=0.3 * i))
        for i in range(6)
    ]
    steps = [
        dataclasses.replace(s, seated=False) if isinstance(s, Waypoint) else s
        for s in work_package_motion(low, project, T_WORLD_BASE)
    ]
    program = compile_program("low", steps, project, T_WORLD_BASE, {})
    flags = [m.wrist_interpolated for m in program.moves]
    assert sum(flags) >= 1
    read = read_krl(WRITERS["krl"].write(program))
    assert [m.wrist for m in read.motions] == flags
    moves = [m for m in program.moves if m.wrist_interpolated]
    assert all(m.kind == "lin" and m.via_q is not None and len(m.via_q) >= 35 for m in moves)
    assert np.isfinite(np.concatenate([m.via_q for m in moves])).all()
