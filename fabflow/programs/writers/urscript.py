"""Universal Robots URScript writer: one ``.script`` file per program.

Units at this edge: metres and rotation vectors (radians). The design world's
pose in the robot base frame (from the localization) is the variable
``world_in_base``; linear targets are written in design coordinates and mapped
with ``pose_trans(world_in_base, p[...])``. Joint moves carry the joint
configuration inverse kinematics chose, so the robot takes that configuration.
Every program starts and ends with an exact ``movej`` to the HOME joint
configuration; ``set_payload`` gives the tool's mass and centre of gravity (flange
frame, metres), the tool and a held element together while the gripper holds
one. The UR has no external axis for the lift: a program with a lift
height opens a blocking ``popup`` naming it before its first motion.
"""

from __future__ import annotations

import numpy as np

from fabflow.programs.ir import Comment, Load, Move, Program, SetOutput, SetPayload, Wait
from fabflow.programs.ir import sanitize_identifier as _sanitize
from fabflow.programs.writers.base import Writer, fixed, flange_load, lift_message
from fabflow.robots.catalog import get_robot
from fabflow.transforms.vendors import to_ur_pose

JOINT_ACCELERATION = 1.4
"""rad/s^2 for ``movej``."""
TOOL_ACCELERATION = 1.2
"""m/s^2 for ``movel``."""


def _p(T: np.ndarray) -> str:
    return "p[" + ", ".join(fixed(v, 7) for v in to_ur_pose(T)) + "]"


def _payload(load: Load) -> str:
    return f"  set_payload({fixed(load.mass, 3)}, [{', '.join(fixed(v, 4) for v in load.cog)}])"


def write_urscript(program: Program) -> dict[str, str]:
    """URScript for a program.

    Parameters
    ----------
    program
        The program (frames in metres and radians).

    Returns
    -------
    dict[str, str]
        ``{"name.script": text}``.
    """

    # movej takes one joint speed: a PTP speed fraction of 1 stands for the
    # slowest joint's limit, as in the program's timing.
    max_joint_speed = float(get_robot(program.robot).velocity_limits.min())
    name = _sanitize(program.name, 63).lower()
    lines = [f"def {name}():"]
    lines += [f"  # {k}: {v}" for k, v in program.header.items()]
    lines += [
        f"  set_tcp({_p(program.T_flange_tool)})",
        f"  world_in_base = {_p(program.T_base_world)}",
        _payload(program.load),
    ]
    if program.lift is not None:
        lines.append(
            f'  popup("fabflow: {lift_message(program.lift)}, then Continue", '
            'title="lift", blocking=True)'
        )
    lines += [
        f'  popup("fabflow: {message}, then Continue", title="fabflow", blocking=True)'
        for message in program.confirm
    ]
    previous: Move | None = None
    current: Move | None = None
    waited = since = 0.0  # seconds of dwell before the current move, since the last
    for ins in program.instructions:
        if isinstance(ins, Comment):
            lines.append(f"  # {ins.text}")
        elif isinstance(ins, SetOutput):
            number = program.outputs[ins.name]
            lines.append(f"  set_standard_digital_out({number}, {ins.value})")
        elif isinstance(ins, Wait):
            lines.append(f"  sleep({fixed(ins.seconds, 3)})")
            since += ins.seconds
        elif isinstance(ins, SetPayload):
            lines.append(_payload(flange_load(program, ins.payload)))
        else:
            assert isinstance(ins, Move)
            previous, current = current, ins
            waited, since = since, 0.0
            text = " ".join(x for x in (ins.element, ins.label) if x)
            comment = f"  # {text}" if text else ""
            r = fixed(ins.blend, 4)
            if ins.kind == "ptp":
                q = "[" + ", ".join(fixed(v, 7) for v in ins.q) + "]"
                v = fixed(ins.speed * max_joint_speed, 4)
                lines.append(f"  movej({q}, a={JOINT_ACCELERATION}, v={v}, r={r}){comment}")
            elif ins.wrist_interpolated and ins.via_q is not None and previous is not None:
                # past the wrist singularity: the joint path fabflow solved (the
                # tool centre point on the line at every sample), blended, at the
                # joint speed that keeps the move's planned time
                path = np.vstack([previous.q, ins.via_q, ins.q])
                moving = ins.time - previous.time - waited
                step_time = max(moving, 1e-3) / (len(path) - 1)
                v = fixed(float(np.abs(np.diff(path, axis=0)).max()) / step_time, 4)
                for q_via in ins.via_q:
                    q = "[" + ", ".join(fixed(x, 7) for x in q_via) + "]"
                    lines.append(f"  movej({q}, a={JOINT_ACCELERATION}, v={v}, r=0.001)")
                q = "[" + ", ".join(fixed(x, 7) for x in ins.q) + "]"
                lines.append(f"  movej({q}, a={JOINT_ACCELERATION}, v={v}, r={r}){comment}")
            else:
                target = f"pose_trans(world_in_base, {_p(ins.T_world_tool)})"
                v = fixed(ins.speed, 4)
                lines.append(f"  movel({target}, a={TOOL_ACCELERATION}, v={v}, r={r}){comment}")
    lines.append("end")
    lines.append(f"{name}()")
    return {f"{name}.script": "\n".join(lines) + "\n"}


WRITER = Writer("urscript", write_urscript, "Universal Robots URScript: one .script file")
"""The URScript writer behind the common interface."""
