"""KUKA KRL writer (KSS 8.x): one ``.src`` / ``.dat`` module pair per program.

Units at this edge: millimetres and degrees; ``A B C`` with R = Rz(A) Ry(B) Rx(C).
``$BASE`` is the design world in the robot base frame (from the localization),
``$TOOL`` the tool centre point in the flange frame; both are declared as FRAMEs
in the ``.dat``. PTP targets are E6POS with status and turn bits from the joint
configuration inverse kinematics chose, so the controller takes the same
configuration. PTP moves are approximated with ``C_PTP`` (``$APO.CPTP``),
linear moves with ``C_DIS`` (``$APO.CDIS``). Every output switch follows a
motion that stops exactly at its point (grip, release, extruder on and off), and
is written without ``CONTINUE``: the advance run waits, so the output switches
when the robot is there, not up to ``$ADVANCE`` motions early. Programs longer
than ``max_moves`` motions are split into sub-programs, each its own module,
called from the main module.
"""

from __future__ import annotations

import numpy as np

from fabflow.programs.ir import Comment, Instruction, Move, Program, SetOutput, Wait
from fabflow.programs.ir import sanitize_identifier as _sanitize
from fabflow.programs.writers.base import Writer, fixed
from fabflow.robots.kuka_config import kuka_status_turn
from fabflow.transforms.vendors import to_kuka_xyzabc

MAX_NAME = 24
"""KRL identifiers and module names have at most 24 characters."""

PTP_APPROXIMATION_PERCENT = 10
"""``$APO.CPTP``: how early an approximated PTP move leaves its point (percent)."""


def _frame(values: np.ndarray) -> str:
    x, y, z, a, b, c = values
    xyz = f"X {fixed(x, 3)},Y {fixed(y, 3)},Z {fixed(z, 3)}"
    return f"{xyz},A {fixed(a, 4)},B {fixed(b, 4)},C {fixed(c, 4)}"


def _module_text(
    name: str, program: Program, instructions: list[Instruction], is_main: bool, calls: list[str]
) -> tuple[str, str]:
    header = [f"; {k}: {v}" for k, v in program.header.items()]
    src = ["&ACCESS RVP", "&REL 1", f"DEF {name}( )", *header]
    dat = ["&ACCESS RVP", "&REL 1", f"DEFDAT {name}", *header]
    base = _frame(to_kuka_xyzabc(program.T_base_world))
    tool = _frame(to_kuka_xyzabc(program.T_flange_tool))
    dat += [f"DECL FRAME BASE_WORLD={{{base}}}", f"DECL FRAME TOOL_TCP={{{tool}}}"]
    if is_main:
        src.append("BAS (#INITMOV,0)")
    src += ["$BASE = BASE_WORLD", "$TOOL = TOOL_TCP"]
    moves = [i for i in instructions if isinstance(i, Move)]
    if moves:
        values = to_kuka_xyzabc(np.stack([m.T_world_tool for m in moves]))
        status, turn = kuka_status_turn(np.stack([m.q for m in moves]))
    current_speed: float | None = None
    current_axis_speed: float | None = None
    current_blend: float | None = None
    n = 0
    for ins in instructions:
        if isinstance(ins, Comment):
            src.append(f"; {ins.text}")
        elif isinstance(ins, SetOutput):
            number = program.outputs[ins.name]
            src.append(f"$OUT[{number}] = {'TRUE' if ins.value else 'FALSE'}")
        elif isinstance(ins, Wait):
            src.append(f"WAIT SEC {fixed(ins.seconds, 3)}")
        else:
            assert isinstance(ins, Move)
            point = f"XP{n + 1}"
            if ins.kind == "ptp" and ins.speed != current_axis_speed:
                percent = fixed(min(max(ins.speed, 0.01), 1.0) * 100.0, 1)
                src += [f"$VEL_AXIS[{i}] = {percent}" for i in range(1, 7)]
                current_axis_speed = ins.speed
            if ins.kind == "lin" and ins.speed != current_speed:
                src.append(f"$VEL.CP = {fixed(ins.speed, 4)}")
                current_speed = ins.speed
            if ins.blend > 0 and ins.blend != current_blend:
                src += [
                    f"$APO.CDIS = {fixed(ins.blend * 1000.0, 3)}",
                    f"$APO.CPTP = {PTP_APPROXIMATION_PERCENT}",
                ]
                current_blend = ins.blend
            approx = ""
            if ins.blend > 0:
                approx = " C_PTP" if ins.kind == "ptp" else " C_DIS"
            if ins.kind == "ptp":
                st = f",S {status[n]},T {turn[n]}"
                dat.append(f"DECL E6POS {point}={{{_frame(values[n])}{st}}}")
                src.append(f"PTP {point}{approx}")
            else:
                dat.append(f"DECL E6POS {point}={{{_frame(values[n])}}}")
                src.append(f"LIN {point}{approx}")
            n += 1
            if ins.element:
                src[-1] += f" ; {ins.element} {ins.label}".rstrip()
    src += [f"{c}( )" for c in calls]
    src.append("END")
    dat.append("ENDDAT")
    return "\n".join(src) + "\n", "\n".join(dat) + "\n"


def write_krl(program: Program, max_moves: int = 400) -> dict[str, str]:
    """KRL files for a program.

    Parameters
    ----------
    program
        The program (frames in metres and radians).
    max_moves
        Most motion instructions in one module; longer programs are split into
        sub-program modules ``<name>_P01``, ``<name>_P02``, ... called in order.

    Returns
    -------
    dict[str, str]
        File name (``NAME.src``, ``NAME.dat``, ...) to file text.
    """
    name = _sanitize(program.name, MAX_NAME)
    chunks: list[list[Instruction]] = [[]]
    count = 0
    for ins in program.instructions:
        if isinstance(ins, Move):
            if count == max_moves:
                chunks.append([])
                count = 0
            count += 1
        chunks[-1].append(ins)
    files: dict[str, str] = {}
    if len(chunks) == 1:
        src, dat = _module_text(name, program, chunks[0], True, [])
        return {f"{name}.src": src, f"{name}.dat": dat}
    sub_names = [
        _sanitize(f"{name[: MAX_NAME - 4]}_P{i + 1:02d}", MAX_NAME) for i in range(len(chunks))
    ]
    for sub, chunk in zip(sub_names, chunks, strict=True):
        src, dat = _module_text(sub, program, chunk, False, [])
        files[f"{sub}.src"] = src
        files[f"{sub}.dat"] = dat
    src, dat = _module_text(name, program, [], True, sub_names)
    return {f"{name}.src": src, f"{name}.dat": dat, **files}


WRITER = Writer("krl", write_krl, "KUKA KRL (KSS 8.x): .src/.dat module pairs")
"""The KRL writer behind the common interface."""
