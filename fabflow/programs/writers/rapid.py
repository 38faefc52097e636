"""ABB RAPID writer: one ``.mod`` module per program (more when it is long).

Units at this edge: millimetres, degrees and unit quaternions (q1 = w first,
q1 >= 0). The work object's user frame is the design world in the robot base
frame (from the localization), so robtargets carry design coordinates;
``tooldata`` holds the tool centre point and the tool's load (mass, centre of
gravity in the flange frame, as a point mass); while the gripper holds an
element with a mass, ``GripLoad`` adds it (``loaddata``, centre of gravity in
the tool frame) and ``GripLoad load0`` takes it off. Each robtarget carries
``confdata`` derived from the joint configuration inverse kinematics chose.
Every program starts and ends with an exact ``MoveAbsJ`` to the HOME
``jointtarget``; the last motion of every procedure is ``fine``.

The lift: with an external axis (``robot.platform.lift_axis``: ``E1`` is
``eax_a``) every robtarget and the HOME jointtarget carry the lift height in mm
in ``extax``; without one ``main`` writes the height on the FlexPendant
(``TPWrite``) and waits for the operator's OK (``TPReadFK``) before its first
motion. Programs longer than the controller profile's motions per module are
split between elements into modules ``NAME_M01``, ... each holding a procedure
``NAME_P01``, ... that ``main`` calls in order between the HOME moves.
"""

from __future__ import annotations

import functools
import re

import numpy as np

from fabflow.errors import UnsupportedError
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
    lift_axis_value,
    lift_message,
    split_modules,
)
from fabflow.robots.catalog import get_robot
from fabflow.robots.joint_boundaries import quadrants, settle_zeros
from fabflow.robots.opw import OPWParameters
from fabflow.transforms.vendors import to_abb_pose

MAX_NAME = 32
"""RAPID identifiers have at most 32 characters."""

SPEEDS_MM_S = (
    5,
    10,
    20,
    30,
    40,
    50,
    60,
    80,
    100,
    150,
    200,
    300,
    400,
    500,
    600,
    800,
    1000,
    1500,
    2000,
    2500,
    3000,
    4000,
    5000,
    6000,
    7000,
)
"""The predefined ``speeddata`` (``v5`` ... ``v7000``)."""

PTP_TCP_SPEED = 2.0
"""TCP speed (m/s) a PTP speed fraction of 1 stands for in ``MoveJ``."""

HOME = "jhome"
"""The HOME joint target."""

EXTERNAL_AXES = ("E1", "E2", "E3", "E4", "E5", "E6")
"""Project external axis names in the order of RAPID's ``extax`` (eax_a ... eax_f)."""

ZONES_MM = (0, 1, 5, 10, 15, 20, 30, 40, 50, 60, 80, 100, 150, 200)
"""The predefined ``zonedata`` (``z0`` ... ``z200``; 0 blending is ``fine``)."""


def confdata(q: np.ndarray, T_base_flange: np.ndarray, arm: OPWParameters) -> tuple[int, ...]:
    """ABB ``confdata`` [cf1, cf4, cf6, cfx] for a 6-axis configuration.

    cf1, cf4, cf6 are the quadrants (``floor(q / 90 deg)``) of axes 1, 4 and 6.
    cfx packs three flags, as ABB's table orders them: 4 when the wrist centre is
    behind axis 1, 2 when it is behind the lower arm (the line from axis 2 to
    axis 3, seen in the arm's plane), 1 when axis 5 is negative.
    A joint within float noise of a quadrant's edge or of 0 is read as on it
    (:mod:`fabflow.robots.joint_boundaries`), so the numbers do not follow rounding.

    Parameters
    ----------
    q
        Joint angles in radians (ABB controller values).
    T_base_flange
        The flange pose at ``q`` (base frame, metres).
    arm
        The arm's geometry: axis 2 offset and height, lower arm length, wrist
        centre to flange.
    """
    return tuple(int(c) for c in confdata_batch(np.asarray(q)[None], T_base_flange[None], arm)[0])


def confdata_batch(q: np.ndarray, T_base_flange: np.ndarray, arm: OPWParameters) -> np.ndarray:
    """:func:`confdata` of ``(n, 6)`` configurations and their ``(n, 4, 4)`` flange poses.

    Returns
    -------
    numpy.ndarray
        ``(n, 4)`` integers [cf1, cf4, cf6, cfx] per configuration.
    """
    q = np.asarray(q, dtype=float)
    quadrant = quadrants(q[:, [0, 3, 5]])
    q = settle_zeros(q)
    wrist = T_base_flange[:, :3, 3] - arm.c4 * T_base_flange[:, :3, 2]
    forward = wrist[:, 0] * np.cos(q[:, 0]) + wrist[:, 1] * np.sin(q[:, 0])
    behind_axis1 = forward < 0.0
    # In the arm's plane (forward, up): axis 2 at (a1, c1), axis 3 along the lower arm.
    to_wrist_x, to_wrist_z = forward - arm.a1, wrist[:, 2] - arm.c1
    behind_lower_arm = np.sin(q[:, 1]) * to_wrist_z - np.cos(q[:, 1]) * to_wrist_x > 0.0
    cfx = 4 * behind_axis1 + 2 * behind_lower_arm + 1 * (q[:, 4] < 0.0)
    return np.c_[quadrant, cfx].astype(np.int64)


_POSE = "[[%.3f,%.3f,%.3f],[%.9f,%.9f,%.9f,%.9f]]"
_NEGATIVE_ZERO = re.compile(r"(?<=[\[,])-(0\.0+)(?=[,\]])")
"""A number written as negative zero (``-0.000``), which :func:`fixed` writes ``0.000``."""


def _pose_text(p: np.ndarray, q: np.ndarray) -> str:
    """``[[x,y,z],[q1,q2,q3,q4]]`` of one ABB position (mm) and quaternion, as
    :func:`fixed` writes each number (one format for all seven: 28,000 poses a print wall)."""
    text = _POSE % (*p, *q)
    return _NEGATIVE_ZERO.sub(r"\1", text) if "-0.0" in text else text


def _pose(T: np.ndarray) -> str:
    return _pose_text(*to_abb_pose(T))


@functools.lru_cache(maxsize=1024)
def _speed(speed: float) -> str:
    """The fastest predefined ``speeddata`` not above ``speed`` (m/s): never faster
    than the inverse kinematics check allowed."""
    mm_s = speed * 1000.0 + 1e-6
    return "v" + str(max((v for v in SPEEDS_MM_S if v <= mm_s), default=SPEEDS_MM_S[0]))


@functools.lru_cache(maxsize=1024)
def _zone(blend: float) -> str:
    if blend <= 0:
        return "fine"
    return "z" + str(min(ZONES_MM[1:], key=lambda v: abs(v - blend * 1000.0)))


def _loaddata(load: Load) -> str:
    """``loaddata``: mass (kg), centre of gravity (mm), a point mass."""
    cog = ",".join(fixed(v, 3) for v in load.cog * 1000.0)
    return f"[{fixed(load.mass, 3)},[{cog}],[1,0,0,0],0,0,0]"


def _extax(program: Program) -> str:
    lift = lift_axis_value(program.lift)
    values = ["9E9"] * 6
    if lift is not None:
        values[EXTERNAL_AXES.index(program.lift.axis)] = fixed(lift, 3)  # type: ignore[union-attr]
    return "[" + ",".join(values) + "]"


def _body(
    program: Program,
    body: list[Instruction | str],
    tool: str,
    first_point: int,
    extax: str,
    declare_home: bool = True,
) -> tuple[list[str], list[str]]:
    """Declarations and statements of ``body`` (instructions and procedure names).

    HOME (a global ``CONST``) is declared in the main module only
    (``declare_home``): a second declaration in another module is a name clash.
    """
    robot = get_robot(program.robot)
    arm = robot.opw
    assert arm is not None  # write_rapid refuses an arm without one
    decl: list[str] = []
    lines: list[str] = []
    moves = [i for i in body if isinstance(i, Move)]
    last_move = moves[-1] if moves else None
    # confdata's wrist centre lies c4 behind the arm's own flange (the last joint frame)
    flanges = (
        robot.frames(np.stack([m.q for m in moves]))[:, robot.dof] if moves else np.zeros((0, 4, 4))
    )
    # every robtarget's position and quaternion in one call, as the KRL writer does
    cartesian = [m.T_world_tool for m in moves if not m.joint]
    positions, quats = (
        to_abb_pose(np.stack(cartesian)) if cartesian else (np.zeros((0, 3)), np.zeros((0, 4)))
    )
    # every robtarget's confdata in one call
    cartesian_k = [k for k, m in enumerate(moves) if not m.joint]
    confs = (
        confdata_batch(np.stack([moves[k].q for k in cartesian_k]), flanges[cartesian_k], arm)
        if cartesian_k
        else np.zeros((0, 4), dtype=np.int64)
    ).tolist()
    n = first_point
    for ins in moves:
        if ins.joint:
            axes = ",".join(fixed(v, 4) for v in np.degrees(ins.q))
            home = f"  CONST jointtarget {HOME} := [[{axes}],{extax}];"
            if declare_home and home not in decl:
                decl.append(home)
            continue
        pose = _pose_text(positions[n - first_point], quats[n - first_point])
        n += 1
        conf = confs[n - 1 - first_point]
        decl.append(
            f"  CONST robtarget p{n} := [{pose[1:-1]},[{','.join(str(c) for c in conf)}],{extax}];"
        )
    for ins in body:
        if isinstance(ins, SetPayload) and ins.payload is not None:
            name = _sanitize(f"load_{ins.element}", MAX_NAME)
            decl.append(f"  PERS loaddata {name} := {_loaddata(ins.payload)};")
    n = first_point
    for ins in body:
        if isinstance(ins, str):
            lines.append(f"    {ins};")
        elif isinstance(ins, SetPayload):
            held = "load0" if ins.payload is None else _sanitize(f"load_{ins.element}", MAX_NAME)
            lines.append(f"    GripLoad {held};")
        elif isinstance(ins, Comment):
            lines.append(f"    ! {ins.text}")
        elif isinstance(ins, SetOutput):
            lines.append(f"    SetDO do_{_sanitize(ins.name, MAX_NAME - 3)}, {int(ins.value)};")
        elif isinstance(ins, Wait):
            lines.append(f"    WaitTime {fixed(ins.seconds, 3)};")
        else:
            assert isinstance(ins, Move)
            zone = "fine" if ins is last_move else _zone(float(ins.blend))
            speed = _speed(float(PTP_TCP_SPEED * ins.speed if ins.kind == "ptp" else ins.speed))
            if ins.joint:
                lines.append(
                    f"    MoveAbsJ {HOME}\\NoEOffs, {speed}, {zone}, {tool}\\WObj:=wobj_world;"
                    f" ! {ins.label}"
                )
                continue
            n += 1
            instr = "MoveJ" if ins.kind == "ptp" else "MoveL"
            comment = f" ! {ins.element} {ins.label}".rstrip() if ins.element else ""
            if ins.wrist_interpolated:
                lines.append("    SingArea \\Wrist; ! past the wrist singularity")
            lines.append(f"    {instr} p{n}, {speed}, {zone}, {tool}\\WObj:=wobj_world;" + comment)
            if ins.wrist_interpolated:
                lines.append("    SingArea \\Off;")
    return decl, lines


def write_rapid(program: Program, max_moves: int | None = None) -> dict[str, str]:
    """RAPID modules for a program.

    Parameters
    ----------
    program
        The program (frames in metres and radians).
    max_moves
        Most motions (robtargets) in one module (default: the program's
        controller profile, ``Program.module_motions``); longer programs are
        split between elements into modules ``<name>_M01``, ... each with one
        procedure ``<name>_P01``, ..., called in order between the HOME moves.

    Returns
    -------
    dict[str, str]
        ``{"NAME.mod": text, "NAME_M01.mod": text, ...}``.
    """
    if get_robot(program.robot).opw is None:
        raise UnsupportedError(
            f"RAPID programs need an ABB arm's geometry (OPW); '{program.robot}' has none"
        )
    name = _sanitize(program.name, MAX_NAME)
    tool = _sanitize(f"t_{program.tool_name}", MAX_NAME)
    extax = _extax(program)
    limit = program.module_motions if max_moves is None else max_moves
    instructions = list(program.instructions)
    homes = [k for k, i in enumerate(instructions) if isinstance(i, Move) and i.joint]
    first, last = (homes[0], homes[-1]) if len(homes) >= 2 else (-1, len(instructions))
    home = instructions[first] if first >= 0 else None
    body = instructions[first + 1 : last]
    chunks = split_modules(body, limit, home if isinstance(home, Move) else None)
    files: dict[str, str] = {}
    main: list[Instruction | str] = instructions
    if len(chunks) > 1:
        stem = name[: MAX_NAME - 4]
        points = 0
        procs = []
        for i, chunk in enumerate(chunks):
            module, proc = f"{stem}_M{i + 1:02d}", f"{stem}_P{i + 1:02d}"
            decl, lines = _body(program, list(chunk), tool, points, extax, declare_home=False)
            points += sum(isinstance(m, Move) and not m.joint for m in chunk)
            text = [f"MODULE {module}", *decl, f"  PROC {proc}()", *lines, "  ENDPROC"]
            files[f"{module}.mod"] = "\n".join([*text, "ENDMODULE"]) + "\n"
            procs.append(proc)
        main = [*instructions[: first + 1], *procs, *instructions[last:]]
    decl, lines = _body(program, main, tool, 0, extax)
    load = _loaddata(program.load)
    head = [f"MODULE {name}", *(f"  ! {k}: {v}" for k, v in program.header.items())]
    head += [
        f"  PERS tooldata {tool} := [TRUE,{_pose(program.T_flange_tool)},{load}];",
        f'  PERS wobjdata wobj_world := [FALSE,TRUE,"",{_pose(program.T_base_world)},'
        "[[0,0,0],[1,0,0,0]]];",
        *decl,
        "  PROC main()",
    ]
    operator: list[str] = []
    if program.lift is not None and program.lift.axis is None:
        operator = [
            f'    TPWrite "fabflow: {lift_message(program.lift)}";',
            f'    TPReadFK answer, "Lift at {program.lift.height * 1000.0:.0f} mm?", "OK", '
            "stEmpty, stEmpty, stEmpty, stEmpty;",
        ]
    for message in program.confirm:
        operator += [
            f'    TPWrite "fabflow: {message}";',
            '    TPReadFK answer, "Continue?", "OK", stEmpty, stEmpty, stEmpty, stEmpty;',
        ]
    if operator:
        head.append("    VAR num answer;")
    text = [*head, "    ConfJ \\On;", "    ConfL \\On;", *operator, *lines, "  ENDPROC"]
    return {f"{name}.mod": "\n".join([*text, "ENDMODULE"]) + "\n", **files}


WRITER = Writer("rapid", write_rapid, "ABB RAPID (RobotWare 6): .mod modules")
"""The RAPID writer behind the common interface."""
