"""JSON command stream for retrofitted machines driven over a UDP/CAN gateway.

One JSON document per program: a header, the joint names, the design world in
the robot base frame, and a list of timestamped commands. ``setpoint`` commands
carry the joint configuration (radians) and the tool pose in the robot base
frame (metres, quaternion w-x-y-z); linear moves are broken into setpoints at
most one controller step apart (2 cm / 0.015 rad, as in the BROKK paper), so a
machine without Cartesian interpolation can follow them joint by joint.
``io`` commands switch outputs, ``wait`` commands dwell. The first and last
setpoints are the HOME joint configuration (``"joint": true``). The document
carries the tool's ``load`` (kg, centre of gravity in the flange frame, metres)
and the ``lift`` (height above the lowest position, metres, and its external
axis or null); before the first setpoint an ``axis`` command moves an external
lift axis, or a ``confirm`` command waits for the operator to set the lift.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fabflow.json_format import json_text
from fabflow.programs.ir import Comment, Move, Program, SetOutput, SetPayload, Wait
from fabflow.programs.ir import sanitize_identifier as _sanitize
from fabflow.programs.writers.base import Writer, lift_message
from fabflow.transforms.so3 import quat_from_matrix

FORMAT = "fabflow-command-stream"
VERSION = 1


def _line(data: Any) -> str:
    """``data`` as JSON on one line (never NaN or Infinity; :func:`fabflow.output.json_text`)."""
    return json_text(data, indent=None).rstrip("\n")


def _r(v: Any, digits: int = 9) -> Any:
    return (np.round(np.asarray(v, dtype=float), digits) + 0.0).tolist()


def write_json_stream(program: Program) -> dict[str, str]:
    """JSON command stream for a program.

    Returns
    -------
    dict[str, str]
        ``{"name.json": text}``; the text is deterministic for the same program.
    """
    name = _sanitize(program.name, 64).lower()
    T_base_world = np.asarray(program.T_base_world, dtype=float)
    commands: list[dict[str, Any]] = []
    # Setpoints are collected first and converted in one batch.
    setpoints: list[tuple[int, float, np.ndarray, np.ndarray, Move]] = []
    t_prev = 0.0
    lift = program.lift
    if lift is not None and lift.axis is not None:
        commands.append({"t": 0.0, "type": "axis", "name": lift.axis, "value": lift.height})
    elif lift is not None:
        commands.append({"t": 0.0, "type": "confirm", "text": lift_message(lift)})
    commands += [{"t": 0.0, "type": "confirm", "text": m} for m in program.confirm]
    for ins in program.instructions:
        start, t_prev = t_prev, ins.time
        if isinstance(ins, Move):
            vias = 0 if ins.via_q is None else len(ins.via_q)
            for k in range(vias):
                t = start + (ins.time - start) * (k + 1) / (vias + 1)
                setpoints.append((len(commands), t, ins.via_q[k], ins.via_T_world_tool[k], ins))
                commands.append({})
            setpoints.append((len(commands), ins.time, ins.q, ins.T_world_tool, ins))
            commands.append({})
        elif isinstance(ins, SetOutput):
            commands.append(
                {"t": round(ins.time, 6), "type": "io", "name": ins.name, "value": ins.value}
            )
        elif isinstance(ins, Wait):
            commands.append({"t": round(ins.time, 6), "type": "wait", "seconds": ins.seconds})
        elif isinstance(ins, Comment):
            commands.append({"t": round(ins.time, 6), "type": "comment", "text": ins.text})
        elif isinstance(ins, SetPayload):
            held = ins.payload
            commands.append(
                {
                    "t": round(ins.time, 6),
                    "type": "payload",
                    "element": ins.element,
                    "mass": 0.0 if held is None else held.mass,
                    "cog": [0.0, 0.0, 0.0] if held is None else _r(held.cog),
                }
            )
    if setpoints:
        T_base_tool = T_base_world @ np.stack([sp[3] for sp in setpoints])
        q = _r(np.stack([sp[2] for sp in setpoints]))
        position = _r(T_base_tool[:, :3, 3])
        quaternion = _r(quat_from_matrix(T_base_tool[:, :3, :3]))
        for k, (index, t, _, _, move) in enumerate(setpoints):
            commands[index] = {
                "t": round(float(t), 6),
                "type": "setpoint",
                "kind": move.kind,
                "q": q[k],
                "position": position[k],
                "quaternion": quaternion[k],
                "element": move.element,
                "label": move.label,
                **({"joint": True} if move.joint else {}),
                **({"wrist_interpolated": True} if move.wrist_interpolated else {}),
            }
    doc = {
        "format": FORMAT,
        "version": VERSION,
        "name": name,
        "header": program.header,
        "robot": program.robot,
        "tool": program.tool_name,
        "T_base_world": _r(T_base_world),
        "T_flange_tool": _r(program.T_flange_tool),
        "outputs": program.outputs,
        "load": {"mass": program.load.mass, "cog": _r(program.load.cog)},
        "lift": None if lift is None else {"height": lift.height, "axis": lift.axis},
        "commands": [],
    }
    # One command per line keeps long streams readable and diffable.
    head = _line(doc)[: -len("[]}")]
    body = ",\n  ".join(_line(c) for c in commands)
    return {f"{name}.json": head + "[\n  " + body + "\n]}\n"}


WRITER = Writer("json", write_json_stream, "fabflow JSON command stream for a machine gateway")
"""The command stream writer behind the common interface."""
