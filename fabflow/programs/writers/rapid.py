"""ABB RAPID writer: one ``.mod`` module per program.

Units at this edge: millimetres and unit quaternions (q1 = w first, q1 >= 0).
The work object's user frame is the design world in the robot base frame
(from the localization), so robtargets carry design coordinates; ``tooldata``
holds the tool centre point. Each robtarget carries ``confdata`` derived from
the joint configuration inverse kinematics chose.
"""

from __future__ import annotations

import numpy as np

from fabflow.errors import UnsupportedError
from fabflow.programs.ir import Comment, Move, Program, SetOutput, Wait
from fabflow.programs.ir import sanitize_identifier as _sanitize
from fabflow.programs.writers.base import Writer, fixed
from fabflow.robots.catalog import IRB4600_60_205_OPW, get_robot
from fabflow.robots.opw import OPWParameters
from fabflow.transforms.vendors import to_abb_pose

MAX_NAME = 32
"""RAPID identifiers have at most 32 characters."""

ARM_GEOMETRY = {"abb_irb4600_60_205": IRB4600_60_205_OPW}
"""Geometry of the ABB arms, for the ``confdata`` flags."""

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

ZONES_MM = (0, 1, 5, 10, 15, 20, 30, 40, 50, 60, 80, 100, 150, 200)
"""The predefined ``zonedata`` (``z0`` ... ``z200``; 0 blending is ``fine``)."""


def confdata(q: np.ndarray, T_base_flange: np.ndarray, arm: OPWParameters) -> tuple[int, ...]:
    """ABB ``confdata`` [cf1, cf4, cf6, cfx] for a 6-axis configuration.

    cf1, cf4, cf6 are the quadrants (``floor(q / 90 deg)``) of axes 1, 4 and 6.
    cfx packs three flags, as ABB's table orders them: 4 when the wrist centre is
    behind axis 1, 2 when it is behind the lower arm (the line from axis 2 to
    axis 3, seen in the arm's plane), 1 when axis 5 is negative.

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
    cf1, cf4, cf6 = (int(np.floor(np.degrees(q[i]) / 90.0)) for i in (0, 3, 5))
    wrist = T_base_flange[:3, 3] - arm.c4 * T_base_flange[:3, 2]
    heading = np.array([np.cos(q[0]), np.sin(q[0]), 0.0])
    forward = float(wrist @ heading)
    behind_axis1 = forward < 0.0
    # In the arm's plane (forward, up): axis 2 at (a1, c1), axis 3 along the lower arm.
    axis2 = np.array([arm.a1, arm.c1])
    lower_arm = np.array([np.sin(q[1]), np.cos(q[1])])
    to_wrist = np.array([forward, wrist[2]]) - axis2
    behind_lower_arm = lower_arm[0] * to_wrist[1] - lower_arm[1] * to_wrist[0] > 0.0
    cfx = 4 * behind_axis1 + 2 * behind_lower_arm + 1 * bool(q[4] < 0.0)
    return cf1, cf4, cf6, cfx


def _pose(T: np.ndarray) -> str:
    p, q = to_abb_pose(T)
    return "[[" + ",".join(fixed(v, 3) for v in p) + "],[" + ",".join(fixed(v, 9) for v in q) + "]]"


def _speed(speed: float) -> str:
    """The fastest predefined ``speeddata`` not above ``speed`` (m/s): never faster
    than the inverse kinematics check allowed."""
    mm_s = speed * 1000.0 + 1e-6
    return "v" + str(max((v for v in SPEEDS_MM_S if v <= mm_s), default=SPEEDS_MM_S[0]))


def _zone(blend: float) -> str:
    if blend <= 0:
        return "fine"
    return "z" + str(min(ZONES_MM[1:], key=lambda v: abs(v - blend * 1000.0)))


def write_rapid(program: Program) -> dict[str, str]:
    """RAPID module for a program.

    Parameters
    ----------
    program
        The program (frames in metres and radians).

    Returns
    -------
    dict[str, str]
        ``{"NAME.mod": text}``.
    """

    robot = get_robot(program.robot)
    arm = ARM_GEOMETRY.get(program.robot)
    if arm is None:
        raise UnsupportedError(
            f"RAPID programs need an ABB arm's geometry; '{program.robot}' has none"
        )
    name = _sanitize(program.name, MAX_NAME)
    tool = _sanitize(f"t_{program.tool_name}", MAX_NAME)
    lines = [f"MODULE {name}"]
    lines += [f"  ! {k}: {v}" for k, v in program.header.items()]
    lines += [
        f"  PERS tooldata {tool} := [TRUE,{_pose(program.T_flange_tool)},"
        "[20,[0,0,100],[1,0,0,0],0,0,0]];",
        f'  PERS wobjdata wobj_world := [FALSE,TRUE,"",{_pose(program.T_base_world)},'
        "[[0,0,0],[1,0,0,0]]];",
    ]
    body = ["  PROC main()", "    ConfJ \\On;", "    ConfL \\On;"]
    moves = [i for i in program.instructions if isinstance(i, Move)]
    flanges = robot.fk(np.stack([m.q for m in moves])) if moves else np.zeros((0, 4, 4))
    n = 0
    for ins in program.instructions:
        if isinstance(ins, Comment):
            body.append(f"    ! {ins.text}")
        elif isinstance(ins, SetOutput):
            body.append(f"    SetDO do_{_sanitize(ins.name, MAX_NAME - 3)}, {int(ins.value)};")
        elif isinstance(ins, Wait):
            body.append(f"    WaitTime {fixed(ins.seconds, 3)};")
        else:
            assert isinstance(ins, Move)
            conf = confdata(ins.q, flanges[n], arm)
            n += 1
            point = f"p{n}"
            lines.append(
                f"  CONST robtarget {point} := [{_pose(ins.T_world_tool)[1:-1]},"
                f"[{','.join(str(c) for c in conf)}],[9E9,9E9,9E9,9E9,9E9,9E9]];"
            )
            instr = "MoveJ" if ins.kind == "ptp" else "MoveL"
            speed = _speed(PTP_TCP_SPEED * ins.speed if ins.kind == "ptp" else ins.speed)
            comment = f" ! {ins.element} {ins.label}".rstrip() if ins.element else ""
            body.append(
                f"    {instr} {point}, {speed}, {_zone(ins.blend)}, {tool}\\WObj:=wobj_world;"
                + comment
            )
    body.append("  ENDPROC")
    text = "\n".join([*lines, *body, "ENDMODULE"]) + "\n"
    return {f"{name}.mod": text}


WRITER = Writer("rapid", write_rapid, "ABB RAPID (RobotWare 6): one .mod module")
"""The RAPID writer behind the common interface."""
