"""The one interface every program writer sits behind.

A :class:`Writer` turns a checked :class:`~fabflow.programs.ir.Program` into
files for one controller. :meth:`Writer.validate` refuses what the format
cannot carry (a program for another vendor's robot, a number that is not
finite) with a named error before anything is written; :meth:`Writer.write`
validates, then renders. Vendor units and pose conventions come from
:mod:`fabflow.transforms.vendors`, the one converter the writers share.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fabflow.errors import InputError, UnsupportedError
from fabflow.programs.ir import Move, Program
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
        values += [m.T_world_tool for m in moves] + [m.q for m in moves]
        values.append(np.array([[m.speed, m.blend] for m in moves], dtype=float))
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
