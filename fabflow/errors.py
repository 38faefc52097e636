"""Named errors that fabflow reports to the user.

Every error a user can cause by what they hand to fabflow (a project file, a
DXF drawing, a CSV of measurements, an infeasible project) derives from
:class:`FabflowError`. The CLI prints such errors as one clear message and exits
with code 2, never with a traceback. Anything else is a bug in fabflow.
"""

from __future__ import annotations

from pathlib import Path


class FabflowError(Exception):
    """Base class of every error that is the user's input, not a bug.

    Parameters
    ----------
    message
        What is wrong and what was expected, in one or two sentences.
    source
        The file (or other source) the problem is in, if any.
    location
        Where in the source: a field path such as ``elements[2].cabin.block.length``,
        ``line 14``, or a DXF entity handle.
    """

    exit_code = 2

    def __init__(
        self, message: str, source: str | Path | None = None, location: str | None = None
    ) -> None:
        self.message = message
        self.source = None if source is None else str(source)
        self.location = location
        super().__init__(self.__str__())

    def __str__(self) -> str:
        where = ""
        if self.source and self.location:
            where = f"{self.source}: {self.location}: "
        elif self.source:
            where = f"{self.source}: "
        elif self.location:
            where = f"{self.location}: "
        return f"{where}{self.message}"


class InputError(FabflowError):
    """A file or value handed to fabflow is malformed or inconsistent."""


class InfeasibleError(FabflowError):
    """The project cannot be carried out as specified (unreachable elements, cycles).

    ``element`` is the id of the element it concerns, where there is one.
    """

    element: str | None = None


class UnsupportedError(FabflowError):
    """A feature was asked of a backend (a robot, a writer, a method) that lacks it."""


class LocalizationError(FabflowError):
    """A localization failed its quality checks (degenerate geometry, poor fit)."""
