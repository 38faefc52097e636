"""Program writers, one module per format, behind one interface, and the format registry.

:data:`WRITERS` maps each format of :data:`fabflow.robots.catalog.PROGRAM_FORMATS`
to its :class:`~fabflow.programs.writers.base.Writer`; :func:`writer_for` picks
the writer for a project's format and robot, or names why it cannot.
"""

from __future__ import annotations

from fabflow.errors import UnsupportedError
from fabflow.programs.writers import gcode, json_stream, krl, rapid, urscript
from fabflow.programs.writers.base import Writer

WRITERS: dict[str, Writer] = {
    w.format: w
    for w in (krl.WRITER, rapid.WRITER, urscript.WRITER, json_stream.WRITER, gcode.WRITER)
}
"""Format name to writer, in the order of :data:`~fabflow.robots.catalog.PROGRAM_FORMATS`."""


def writer_for(fmt: str, robot: str) -> Writer:
    """The writer of ``fmt``, checked against the robot.

    Raises
    ------
    UnsupportedError
        For an unknown format, or a vendor format for another vendor's robot.
    """
    if fmt not in WRITERS:
        raise UnsupportedError(f"unknown program format '{fmt}'; known: {', '.join(WRITERS)}")
    writer = WRITERS[fmt]
    writer.check_robot(robot)
    return writer


__all__ = ["WRITERS", "Writer", "writer_for"]
