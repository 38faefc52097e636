"""G-code for print paths: RepRap/Marlin, or a robot's G-code interpreter.

One ``.gcode`` file per program. Positions are the tool centre point in the
robot base frame at the station (``T_base_world @ T_world_tool``), in
millimetres, as the JSON stream's setpoints: G-code has no rotated work offset
that could carry the localized design world as a frame, so the localization is
applied here and ``T_base_world`` is only named in the header. The tool's
orientation is not carried (positions only); the header gives its axis at the
first print move.

Every motion of the program is one line. A joint-interpolated move (PTP,
including HOME) is a travel ``G0`` without feed rate; a linear move, and any
move while the extruder is on, is a straight ``G1`` with its feed rate ``F``
(mm/min, written where it changes). While the extruder is on, ``E`` advances
by the segment's length times the element's bead cross-section
(``Program.beads``, bead width x layer height), absolute from 0 at the start:

* ``marlin``: ``G21``, ``G90``, ``M82``, ``G92 E0``; E is the length of filament
  of ``Program.gcode.filament_diameter`` that holds that volume (mm, 5 decimals).
* ``robot``: ``G21``, ``G90``; E is the deposited volume itself (mm^3, 3
  decimals), which the extruder's controller scales by its displacement.

X, Y and Z have 3 decimals (1 µm), F one. The lift height, and each move the
operator must confirm, is a comment and an ``M0`` stop before the first motion.
Only print paths fit the format: a program holding another element (a block, a
task point, a stone), a payload or an output other than the extruder is refused
with :class:`~fabflow.errors.UnsupportedError`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from fabflow.errors import InputError, UnsupportedError
from fabflow.programs.ir import Comment, Move, Program, SetOutput, SetPayload, Wait
from fabflow.programs.ir import sanitize_identifier as _sanitize
from fabflow.programs.writers.base import Writer, fixed, lift_message
from fabflow.robots.catalog import GCODE_FLAVORS, formats_of

MM_PER_M = 1000.0
FEED_PER_SPEED = 60_000.0
"""mm/min per m/s."""
POSITION_DIGITS = 3
FEED_DIGITS = 1
E_DIGITS = {"marlin": 5, "robot": 3}
EXTRUDER = "extruder"
"""The one output a print program switches (:data:`fabflow.programs.motions.OUTPUTS`)."""

_CONTROL = re.compile(r"[\x00-\x1f\x7f]+")


def _comment(text: object) -> str:
    """``text`` as one comment line (control characters, line breaks among them, as spaces)."""
    return "; " + _CONTROL.sub(" ", str(text)).strip()


def check_print_program(program: Program) -> None:
    """Raise for a program G-code cannot carry.

    Raises
    ------
    UnsupportedError
        For a program with elements other than print paths (``Program.beads``
        names the print paths), a held payload, an output other than the
        extruder, or an unknown flavour.
    InputError
        For a bead, filament or feed rate that is not a finite positive number
        the format can write.
    """
    flavor = program.gcode.flavor
    if flavor not in GCODE_FLAVORS:
        raise UnsupportedError(
            f"unknown G-code flavor '{flavor}'; known: {', '.join(GCODE_FLAVORS)}"
        )
    ins = program.instructions
    others = sorted({i.element for i in ins if i.element is not None} - set(program.beads))
    outputs = sorted({i.name for i in ins if isinstance(i, SetOutput)} - {EXTRUDER})
    held = any(isinstance(i, SetPayload) and i.payload is not None for i in ins)
    if others or outputs or held:
        if others:
            more = " ..." if len(others) > 5 else ""
            what = f"element{'s' * (len(others) > 1)} {', '.join(others[:5])}{more}"
        elif outputs:
            what = f"the output{'s' * (len(outputs) > 1)} {', '.join(outputs)}"
        else:
            what = "a held payload"
        fits = " or ".join(f"'{f}'" for f in formats_of(program.robot))
        raise UnsupportedError(
            f"program {program.name!r}: 'gcode' carries print paths only, but it holds "
            f"{what} (blocks, task points and stones are not print paths); use format {fits}"
        )
    sizes = np.array(
        [[b.width, b.height] for b in program.beads.values()]
        + [[program.gcode.filament_diameter] * 2]
    )
    if not (np.all(np.isfinite(sizes)) and np.all(sizes > 0.0)):
        raise InputError(
            f"program {program.name!r}: a bead width, layer height or filament diameter is "
            "not a finite positive number; no 'gcode' file is written"
        )
    speeds = np.array([m.speed for m in program.moves if m.kind == "lin"])
    if speeds.size and speeds.min() * FEED_PER_SPEED < 0.5 * 10.0**-FEED_DIGITS:
        raise InputError(
            f"program {program.name!r}: a linear speed of {speeds.min():.3g} m/s is below the "
            f"G-code feed rate's resolution ({10.0**-FEED_DIGITS:g} mm/min)"
        )


def _templates(flavor: str) -> np.ndarray:
    """printf templates of a motion line by code: G0; G1; G1 E; G1 F; G1 E F."""
    xyz = " ".join(f"{a}%.{POSITION_DIGITS}f" for a in "XYZ")
    e, f = f" E%.{E_DIGITS[flavor]}f", f" F%.{FEED_DIGITS}f"
    return np.array([f"G0 {xyz}", f"G1 {xyz}", f"G1 {xyz}{e}", f"G1 {xyz}{f}", f"G1 {xyz}{e}{f}"])


def _forward_fill(values: np.ndarray) -> np.ndarray:
    """NaNs take the last value before them (those before any value stay NaN)."""
    index = np.where(np.isnan(values), 0, np.arange(len(values)))
    np.maximum.accumulate(index, out=index)
    return values[index]


def _motion_lines(
    program: Program, moves: list[Move], extruding: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The motion lines, one per move, as printf templates and the numbers they take.

    Parameters
    ----------
    program
        The program (``T_base_world``, beads, flavour).
    moves
        Its N motions, in order.
    extruding
        (N,) whether the extruder is on along each move (from the one before).

    Returns
    -------
    templates
        (N,) printf template per move (:func:`_templates`).
    values
        The numbers the templates take, in order: X Y Z (mm, robot base frame),
        then E (mm of filament or mm^3) and F (mm/min) where the line has them.
    """
    T_world_tool = np.stack([m.T_world_tool for m in moves])
    T_base_world = np.asarray(program.T_base_world, dtype=float)
    p_world = T_world_tool[:, :3, 3]
    positions = (p_world @ T_base_world[:3, :3].T + T_base_world[:3, 3]) * MM_PER_M
    segment = np.r_[0.0, np.linalg.norm(np.diff(positions, axis=0), axis=1)]
    area = {k: b.width * b.height * MM_PER_M**2 for k, b in program.beads.items()}
    bead = np.array([area.get(m.element, 0.0) for m in moves])  # type: ignore[arg-type]
    extruded = np.cumsum(segment * bead * extruding)  # mm^3
    flavor = program.gcode.flavor
    if flavor == "marlin":  # the length of filament holding that volume
        filament = np.pi / 4.0 * (program.gcode.filament_diameter * MM_PER_M) ** 2
        extruded = extruded / filament
    linear = np.array([m.kind == "lin" for m in moves])
    g1 = linear | extruding
    speed = np.array([m.speed for m in moves])
    feed = _forward_fill(np.where(linear, speed * FEED_PER_SPEED, np.nan))
    feed = np.where(np.isnan(feed), _forward_fill(feed[::-1])[::-1], feed)  # none before
    feed = np.round(feed, FEED_DIGITS) + 0.0
    g1_feed = feed[g1]
    changed = np.r_[True, g1_feed[1:] != g1_feed[:-1]] & ~np.isnan(g1_feed)
    has_feed = np.zeros(len(moves), dtype=bool)
    has_feed[g1] = changed
    code = np.where(g1, 1 + extruding + 2 * has_feed, 0)
    columns = np.column_stack(
        [
            np.round(positions, POSITION_DIGITS) + 0.0,
            np.round(extruded, E_DIGITS[flavor]) + 0.0,
            np.nan_to_num(feed),
        ]
    )
    used = np.column_stack([np.ones((len(moves), 3), dtype=bool), extruding, has_feed])
    values = columns[used]
    if not np.all(np.isfinite(values)):
        raise InputError(
            f"program {program.name!r}: a G-code value overflows (a bead or filament size out of "
            "scale); no 'gcode' file is written"
        )
    return _templates(flavor)[code], values


def _extruding(program: Program) -> tuple[list[Move], np.ndarray]:
    """The moves, and whether the extruder is on along each (switched by the outputs before it)."""
    ins = program.instructions
    state = np.array(
        [
            float(i.value) if isinstance(i, SetOutput) else np.nan
            for i in ins
            if isinstance(i, SetOutput | Move)
        ]
    )
    on = np.nan_to_num(_forward_fill(state)) > 0.5
    is_move = np.isnan(state)
    return [i for i in ins if isinstance(i, Move)], on[is_move]


def _header(program: Program, moves: list[Move], extruding: np.ndarray) -> list[str]:
    """The header comments and the preamble: what the numbers mean, then the modes."""
    opts = program.gcode
    flavor = opts.flavor
    beads = ", ".join(
        f"{k} {fixed(b.width * MM_PER_M, 1)} x {fixed(b.height * MM_PER_M, 1)}"
        for k, b in program.beads.items()
    )
    lines = [f"fabflow G-code program {program.name} ({flavor} flavor)"]
    lines += [f"{k}: {v}" for k, v in program.header.items()]
    lines += [
        f"robot: {program.robot}",
        f"tool: {program.tool_name}",
        f"print paths (bead width x height, mm): {beads or 'none'}",
        "units: millimetres (G21), absolute positions (G90), feed rate F in mm/min",
        "frame: X Y Z are the tool centre point in the robot base frame at this station",
        "T_base_world (the design world in the robot base frame; rotation rows, then mm):",
    ]
    T = np.asarray(program.T_base_world, dtype=float)
    rows = [[fixed(v, 7) for v in T[r, :3]] + [fixed(T[r, 3] * MM_PER_M, 3)] for r in range(3)]
    lines += [f"row {r + 1}: {' '.join(row)}" for r, row in enumerate(rows)]
    if flavor == "marlin":
        diameter = fixed(opts.filament_diameter * MM_PER_M, 3)
        lines.append(f"E: length of {diameter} mm filament (mm), absolute (M82), 0 at the start")
    else:
        lines.append("E: deposited volume of the beads (mm^3), absolute, 0 at the start")
    lines.append("G0: travel (a joint move in the robot program); G1: straight line")
    first = np.flatnonzero(extruding)
    if first.size:
        axis = T[:3, :3] @ np.asarray(moves[first[0]].T_world_tool, dtype=float)[:3, 2]
        lines.append(
            "tool axis at the first print move, base frame: "
            + " ".join(fixed(v, 4) for v in axis)
            + " (orientation is not carried)"
        )
    text = [_comment(line) for line in lines]
    text += ["G21", "G90"]
    if flavor == "marlin":
        text += ["M82", "G92 E0"]
    stops = ([lift_message(program.lift)] if program.lift is not None else []) + list(
        program.confirm
    )
    for message in stops:
        text += [_comment(f"OPERATOR: {message}, then resume"), "M0"]
    return text


def _line(ins: Comment | SetOutput | SetPayload | Wait) -> str:
    """The line of an instruction other than a motion, ready for printf ('%' escaped)."""
    if isinstance(ins, SetOutput):
        text = _comment(f"{ins.name} {'on' if ins.value else 'off'}")
    elif isinstance(ins, Comment):
        text = _comment(ins.text)
    elif isinstance(ins, Wait):
        text = f"G4 P{round(ins.seconds * 1000.0)}"
    else:  # a payload let go: nothing to say in G-code
        text = _comment("payload released")
    return text.replace("%", "%%")


def _joint_note(move: Move) -> str:
    """The comment before a joint target's travel (HOME): its joints (deg), '%' escaped."""
    q = " ".join(fixed(v, 3) for v in np.degrees(move.q))
    return _comment(f"joint target ({move.label or 'home'}): {q} deg").replace("%", "%%")


def write_gcode(program: Program) -> dict[str, str]:
    """G-code for a print program, in the flavour of ``program.gcode``.

    Parameters
    ----------
    program
        A checked program of print paths (frames in metres, speeds in m/s).

    Returns
    -------
    dict[str, str]
        ``{"name.gcode": text}``; the text is deterministic for the same program.
    """
    name = _sanitize(program.name, 64).lower()
    moves, extruding = _extruding(program)
    head = [line.replace("%", "%%") for line in _header(program, moves, extruding)]
    ins = program.instructions
    is_move = np.array([isinstance(i, Move) for i in ins], dtype=bool)
    body = np.empty(len(ins), dtype=object)
    body[~is_move] = [_line(i) for i in ins if not isinstance(i, Move)]
    values = np.zeros(0)
    if moves:
        templates, values = _motion_lines(program, moves, extruding)
        joint = np.flatnonzero([m.joint for m in moves])
        templates = templates.astype(object)
        templates[joint] = [_joint_note(moves[k]) + "\n" + templates[k] for k in joint]
        body[is_move] = templates
    text = "\n".join([*head, *body.tolist(), _comment("end of program")]) + "\n"
    return {f"{name}.gcode": text % tuple(values.tolist())}


@dataclass(frozen=True)
class GcodeWriter(Writer):
    """The writer with the print-path checks of :func:`check_print_program`."""

    def validate(self, program: Program) -> None:
        """Raise for a program this format cannot carry (see :meth:`Writer.validate`)."""
        super().validate(program)
        check_print_program(program)


WRITER = GcodeWriter(
    "gcode", write_gcode, "G-code for print paths (RepRap/Marlin or a robot's interpreter)"
)
"""The G-code writer behind the common interface."""
