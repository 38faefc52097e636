"""KUKA KRL writer (KSS 8.x): one ``.src`` / ``.dat`` module pair per program.

Units at this edge: millimetres and degrees; ``A B C`` with R = Rz(A) Ry(B) Rx(C).
``$BASE`` is the design world in the robot base frame (from the localization),
``$TOOL`` the tool centre point in the flange frame; both are declared as FRAMEs
in the ``.dat``. ``$LOAD`` is the tool's mass and centre of gravity in the flange
frame (a point mass: inertia 0; ``$LOAD_A3``, a load on axis 3, is left as the
controller has it); while the gripper holds an element with a mass, ``$LOAD`` is
the tool and the element together. Every program starts and ends with an exact ``PTP`` to the
HOME joint target ``XFABHOME`` (E6AXIS). PTP targets are E6POS with status and
turn bits from the joint configuration inverse kinematics chose, so the
controller takes the same configuration. PTP moves are approximated with
``C_PTP`` (``$APO.CPTP``), linear moves with ``C_DIS`` (``$APO.CDIS``); the last
motion of every module stops exactly. Every output switch follows a motion that
stops exactly at its point (grip, release, extruder on and off), and is written
without ``CONTINUE``: the advance run waits, so the output switches when the
robot is there, not up to ``$ADVANCE`` motions early.

The lift: with an external axis (``robot.platform.lift_axis``, say ``E1``) every
target carries the lift height in mm as that axis; without one the program
stops with ``HALT`` before its first motion, after a comment naming the height,
and goes on when the operator presses Start. Programs longer than the
controller profile's motions per module are split between elements into
sub-program modules ``NAME_P01``, ``NAME_P02``, ... called from the main module
between the two HOME moves.
"""

from __future__ import annotations

import numpy as np

from fabflow.programs.ir import (
    Comment,
    Instruction,
    Load,
    Move,
    Program,
    SetOutput,
    SetPayload,
    Wait,
)
from fabflow.programs.ir import sanitize_identifier as _sanitize
from fabflow.programs.writers.base import (
    Writer,
    fixed,
    flange_load,
    lift_axis_value,
    lift_message,
    split_modules,
)
from fabflow.robots.catalog import get_robot
from fabflow.robots.kuka_config import kuka_status_turn
from fabflow.transforms.vendors import to_kuka_xyzabc

MAX_NAME = 24
"""KRL identifiers and module names have at most 24 characters."""

PTP_APPROXIMATION_PERCENT = 10
"""``$APO.CPTP``: how early an approximated PTP move leaves its point (percent)."""

HOME = "XFABHOME"
"""The HOME joint target (not ``XHOME``, which ``$config.dat`` declares)."""


def _frame(values: np.ndarray) -> str:
    x, y, z, a, b, c = values
    xyz = f"X {fixed(x, 3)},Y {fixed(y, 3)},Z {fixed(z, 3)}"
    return f"{xyz},A {fixed(a, 4)},B {fixed(b, 4)},C {fixed(c, 4)}"


def _load(load: Load) -> str:
    cx, cy, cz = load.cog * 1000.0
    cog = f"X {fixed(cx, 3)},Y {fixed(cy, 3)},Z {fixed(cz, 3)},A 0.0,B 0.0,C 0.0"
    return f"$LOAD = {{M {fixed(load.mass, 3)},CM {{{cog}}},J {{X 0.0,Y 0.0,Z 0.0}}}}"


def _axes(q: np.ndarray, extra: str) -> str:
    return ",".join(f"A{i + 1} {fixed(v, 4)}" for i, v in enumerate(np.degrees(q))) + extra


def _module_text(
    name: str, program: Program, body: list[Instruction | str], is_main: bool
) -> tuple[str, str]:
    """The .src and .dat of one module; ``body`` holds instructions and sub-program names."""
    header = [f"; {k}: {v}" for k, v in program.header.items()]
    src = ["&ACCESS RVP", "&REL 1", f"DEF {name}( )", *header]
    dat = ["&ACCESS RVP", "&REL 1", f"DEFDAT {name}", *header]
    base = _frame(to_kuka_xyzabc(program.T_base_world))
    tool = _frame(to_kuka_xyzabc(program.T_flange_tool))
    dat += [f"DECL FRAME BASE_WORLD={{{base}}}", f"DECL FRAME TOOL_TCP={{{tool}}}"]
    if is_main:
        src.append("BAS (#INITMOV,0)")
    src += ["$BASE = BASE_WORLD", "$TOOL = TOOL_TCP"]
    lift = lift_axis_value(program.lift)
    extra = "" if lift is None else f",{program.lift.axis} {fixed(lift, 3)}"  # type: ignore[union-attr]
    if is_main:
        src.append(_load(program.load))
        if program.lift is not None and lift is None:
            src += [f"; OPERATOR: {lift_message(program.lift)}, then press Start", "HALT"]
        for message in program.confirm:
            src += [f"; OPERATOR: {message}, then press Start", "HALT"]
    moves = [i for i in body if isinstance(i, Move)]
    cartesian = [m for m in moves if not m.joint]
    if cartesian:
        values = to_kuka_xyzabc(np.stack([m.T_world_tool for m in cartesian]))
        arm = get_robot(program.robot)
        status, turn = kuka_status_turn(np.stack([m.q for m in cartesian]), arm)
    last_move = moves[-1] if moves else None
    current_speed: float | None = None
    current_axis_speed: float | None = None
    current_blend: float | None = None
    n = 0
    for ins in body:
        if isinstance(ins, str):
            src.append(f"{ins}( )")
        elif isinstance(ins, Comment):
            src.append(f"; {ins.text}")
        elif isinstance(ins, SetOutput):
            number = program.outputs[ins.name]
            src.append(f"$OUT[{number}] = {'TRUE' if ins.value else 'FALSE'}")
        elif isinstance(ins, Wait):
            src.append(f"WAIT SEC {fixed(ins.seconds, 3)}")
        elif isinstance(ins, SetPayload):
            src.append(_load(flange_load(program, ins.payload)))
        else:
            assert isinstance(ins, Move)
            blend = 0.0 if ins is last_move else ins.blend
            if ins.kind == "ptp" and ins.speed != current_axis_speed:
                percent = fixed(min(max(ins.speed, 0.01), 1.0) * 100.0, 1)
                src += [f"$VEL_AXIS[{i}] = {percent}" for i in range(1, 7)]
                current_axis_speed = ins.speed
            if ins.kind == "lin" and ins.speed != current_speed:
                src.append(f"$VEL.CP = {fixed(ins.speed, 4)}")
                current_speed = ins.speed
            if blend > 0 and blend != current_blend:
                src += [
                    f"$APO.CDIS = {fixed(blend * 1000.0, 3)}",
                    f"$APO.CPTP = {PTP_APPROXIMATION_PERCENT}",
                ]
                current_blend = blend
            approx = ""
            if blend > 0:
                approx = " C_PTP" if ins.kind == "ptp" else " C_DIS"
            if ins.joint:
                home = f"DECL E6AXIS {HOME}={{{_axes(ins.q, extra)}}}"
                if home not in dat:
                    dat.append(home)
                src.append(f"PTP {HOME}{approx} ; {ins.label}")
                continue
            point = f"XP{n + 1}"
            if ins.kind == "ptp":
                st = f",S {status[n]},T {turn[n]}"
                dat.append(f"DECL E6POS {point}={{{_frame(values[n])}{st}{extra}}}")
                src.append(f"PTP {point}{approx}")
            else:
                dat.append(f"DECL E6POS {point}={{{_frame(values[n])}{extra}}}")
                if ins.wrist_interpolated:
                    src.append("$ORI_TYPE = #JOINT ; past the wrist singularity")
                src.append(f"LIN {point}{approx}")
            n += 1
            if ins.element:
                src[-1] += f" ; {ins.element} {ins.label}".rstrip()
            if ins.wrist_interpolated:
                src.append("$ORI_TYPE = #VAR")
    src.append("END")
    dat.append("ENDDAT")
    return "\n".join(src) + "\n", "\n".join(dat) + "\n"


def write_krl(program: Program, max_moves: int | None = None) -> dict[str, str]:
    """KRL files for a program.

    Parameters
    ----------
    program
        The program (frames in metres and radians).
    max_moves
        Most motion instructions in one module (default: the program's
        controller profile, ``Program.module_motions``); longer programs are
        split between elements into sub-program modules ``<name>_P01``,
        ``<name>_P02``, ... called in order between the HOME moves.

    Returns
    -------
    dict[str, str]
        File name (``NAME.src``, ``NAME.dat``, ...) to file text.
    """
    name = _sanitize(program.name, MAX_NAME)
    limit = program.module_motions if max_moves is None else max_moves
    instructions = list(program.instructions)
    homes = [k for k, i in enumerate(instructions) if isinstance(i, Move) and i.joint]
    first, last = (homes[0], homes[-1]) if len(homes) >= 2 else (-1, len(instructions))
    body = instructions[first + 1 : last]
    home = instructions[first] if first >= 0 else None
    chunks = split_modules(body, limit, home if isinstance(home, Move) else None)
    if len(chunks) == 1:
        src, dat = _module_text(name, program, instructions, True)
        return {f"{name}.src": src, f"{name}.dat": dat}
    sub_names = [
        _sanitize(f"{name[: MAX_NAME - 4]}_P{i + 1:02d}", MAX_NAME) for i in range(len(chunks))
    ]
    files: dict[str, str] = {}
    for sub, chunk in zip(sub_names, chunks, strict=True):
        src, dat = _module_text(sub, program, list(chunk), False)
        files[f"{sub}.src"] = src
        files[f"{sub}.dat"] = dat
    main: list[Instruction | str] = [*instructions[: first + 1], *sub_names]
    main += instructions[last:]
    src, dat = _module_text(name, program, main, True)
    return {f"{name}.src": src, f"{name}.dat": dat, **files}


WRITER = Writer("krl", write_krl, "KUKA KRL (KSS 8.x): .src/.dat module pairs")
"""The KRL writer behind the common interface."""
