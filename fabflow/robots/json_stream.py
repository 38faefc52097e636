"""JSON command stream for retrofitted machines driven over a UDP/CAN gateway.

One JSON document per program: a header, the joint names, the design world in
the robot base frame, and a list of timestamped commands. ``setpoint`` commands
carry the joint configuration (radians) and the tool pose in the robot base
frame (metres, quaternion w-x-y-z); linear moves are broken into setpoints at
most one controller step apart (2 cm / 0.015 rad, as in the BROKK paper), so a
machine without Cartesian interpolation can follow them joint by joint.
``io`` commands switch outputs, ``wait`` commands dwell.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from fabflow.robots.program import Comment, Move, Program, SetOutput, Wait
from fabflow.robots.program import sanitize_identifier as _sanitize
from fabflow.transforms.so3 import quat_from_matrix

FORMAT = "fabflow-command-stream"
VERSION = 1


def _r(v: Any, digits: int = 9) -> Any:
    return (np.round(np.asarray(v, dtype=float), digits) + 0.0).tolist()


def _setpoint(t: float, q: np.ndarray, T_base_tool: np.ndarray, move: Move) -> dict[str, Any]:
    return {
        "t": round(float(t), 6),
        "type": "setpoint",
        "kind": move.kind,
        "q": _r(q),
        "position": _r(T_base_tool[:3, 3]),
        "quaternion": _r(quat_from_matrix(T_base_tool[:3, :3])),
        "element": move.element,
        "label": move.label,
    }


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
    t_prev = 0.0
    for ins in program.instructions:
        start, t_prev = t_prev, ins.time
        if isinstance(ins, Move):
            vias = 0 if ins.via_q is None else len(ins.via_q)
            for k in range(vias):
                t = start + (ins.time - start) * (k + 1) / (vias + 1)
                T = T_base_world @ ins.via_T_world_tool[k]
                commands.append(_setpoint(t, ins.via_q[k], T, ins))
            commands.append(_setpoint(ins.time, ins.q, T_base_world @ ins.T_world_tool, ins))
        elif isinstance(ins, SetOutput):
            commands.append(
                {"t": round(ins.time, 6), "type": "io", "name": ins.name, "value": ins.value}
            )
        elif isinstance(ins, Wait):
            commands.append({"t": round(ins.time, 6), "type": "wait", "seconds": ins.seconds})
        elif isinstance(ins, Comment):
            commands.append({"t": round(ins.time, 6), "type": "comment", "text": ins.text})
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
        "commands": [],
    }
    # One command per line keeps long streams readable and diffable.
    head = json.dumps(doc, separators=(", ", ": "))[: -len("[]}")]
    body = ",\n  ".join(json.dumps(c, separators=(", ", ": ")) for c in commands)
    return {f"{name}.json": head + "[\n  " + body + "\n]}\n"}
