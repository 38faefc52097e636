"""The one interface every program writer sits behind.

A :class:`Writer` turns a checked :class:`~fabflow.programs.ir.Program` into
files for one controller. :meth:`Writer.validate` refuses what the format
cannot carry (a program for another vendor's robot, a number that is not
finite) with a named error before anything is written; :meth:`Writer.write`
validates, then renders. Vendor units and pose conventions come from
:mod:`fabflow.transforms.vendors`, the one converter the writers share.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fabflow.errors import InputError, UnsupportedError
from fabflow.programs.ir import Instruction, Lift, Load, Move, Program, SetPayload
from fabflow.robots.catalog import format_mismatch, format_vendor


def fixed(value: float, digits: int) -> str:
    """``value`` with ``digits`` decimals, never as negative zero (``-0.000`` reads ``0.000``)."""
    text = f"{value:.{digits}f}"
    return "0." + "0" * digits if text == "-0." + "0" * digits else text


@dataclass(frozen=True)
class Writer:
    """One program format.

    Attributes
    ----------
    format
        The format's name in :data:`fabflow.robots.catalog.PROGRAM_FORMATS`.
    render
        Program to ``{file name: text}``; called only with a validated program.
    description
        One line for the docs and messages.
    """

    format: str
    render: Callable[[Program], dict[str, str]]
    description: str

    @property
    def vendor(self) -> str | None:
        """The vendor whose controllers run this format, ``None`` for a neutral format."""
        return format_vendor(self.format)

    def check_robot(self, robot: str) -> None:
        """Raise :class:`UnsupportedError` when the format does not run on ``robot``."""
        why = format_mismatch(self.format, robot)
        if why is not None:
            raise UnsupportedError(why)

    def validate(self, program: Program) -> None:
        """Raise for a program this format cannot carry.

        Raises
        ------
        UnsupportedError
            When the robot is not one of the format's vendor.
        InputError
            When a frame, joint value, speed or blend distance is not finite (it
            came from bad input: no file may hold NaN or infinity).
        """
        self.check_robot(program.robot)
        moves = [i for i in program.instructions if isinstance(i, Move)]
        values = [program.T_base_world, program.T_flange_tool]
        if moves:  # every move's frame and joints in one array each (28,000 on a print wall)
            values.append(np.concatenate([np.ravel(m.T_world_tool) for m in moves]))
            values.append(np.concatenate([np.ravel(m.q) for m in moves]))
        values.append(np.array([[m.speed, m.blend] for m in moves], dtype=float))
        values += [np.array([program.load.mass]), program.load.cog]
        for ins in program.instructions:
            if isinstance(ins, SetPayload) and ins.payload is not None:
                values += [np.array([ins.payload.mass]), ins.payload.cog]
        if program.lift is not None:
            values.append(np.array([program.lift.height]))
        bad = next((k for k, v in enumerate(values) if not np.all(np.isfinite(v))), None)
        if bad is not None:
            raise InputError(
                f"program {program.name!r} holds a value that is not finite; "
                f"no '{self.format}' file is written"
            )

    def write(self, program: Program) -> dict[str, str]:
        """The files of ``program``: ``{file name: text}`` (validated first)."""
        self.validate(program)
        return self.render(program)


def flange_load(program: Program, payload: Load | None) -> Load:
    """The whole load at the flange: the tool's plus a held payload (tool frame), as one point."""
    if payload is None:
        return program.load
    cog = program.T_flange_tool[:3, :3] @ payload.cog + program.T_flange_tool[:3, 3]
    mass = program.load.mass + payload.mass
    return Load(mass, (program.load.mass * program.load.cog + payload.mass * cog) / mass)


def lift_message(lift: Lift) -> str:
    """What the operator must do before the program's first motion (at most 60 characters)."""
    return f"set the lift to {lift.height * 1000.0:.0f} mm above its lowest position"


def lift_axis_value(lift: Lift | None) -> float | None:
    """The lift's external axis value (mm), or ``None`` when no axis drives the lift."""
    return None if lift is None or lift.axis is None else lift.height * 1000.0


def split_modules(
    instructions: list[Instruction], limit: int | None, before: Move | None = None
) -> list[list[Instruction]]:
    """Cut instructions into modules of at most ``limit`` motions, between elements.

    An element's instructions stay in one module unless the element alone holds
    more than ``limit`` motions; it is then cut where the limit falls. A module
    whose first motion is linear (a cut inside an element, or an element that
    starts with one, such as a tucked route's "tuck in") starts with a PTP to
    the point the previous one ended at (the robot is there already), so no
    module starts with a linear move.

    Parameters
    ----------
    instructions
        The instructions of the program's body, in order.
    limit
        Most motions per module (``None``: one module).
    before
        The motion the robot stands at before the instructions (the program's
        HOME), which the first module re-enters if it starts with a linear move.

    Returns
    -------
    list[list[Instruction]]
        The modules, in order; their motions are the program's, plus one PTP
        at each cut inside an element.
    """
    if limit is None or sum(isinstance(i, Move) for i in instructions) <= limit:
        return [list(instructions)]
    groups: list[list[Instruction]] = []
    for ins in instructions:
        if groups and groups[-1][-1].element == ins.element:
            groups[-1].append(ins)
        else:
            groups.append([ins])
    modules: list[list[Instruction]] = [[]]
    count = 0
    last = before
    for group in groups:
        n = sum(isinstance(i, Move) for i in group)
        if count and count + n > limit:
            modules.append([])
            count = 0
        for ins in group:
            if isinstance(ins, Move):
                if count == limit:
                    modules.append([])
                    count = 0
                if count == 0 and ins.kind == "lin" and last is not None:
                    reentry = dataclasses.replace(
                        last, kind="ptp", blend=0.0, label=f"{last.label} (module start)"
                    )
                    modules[-1].append(reentry)
                    count += 1
                last = ins
                count += 1
            modules[-1].append(ins)
    return modules
