"""The typed context the build stages share.

A stage is a function ``stage(ctx) -> None``: it reads the project and what the
stages before it produced from the context, writes its files under ``ctx.out``
and sets its own result field. The order is fixed by
:func:`fabflow.build.runner.stages`; a stage that finds a field it needs unset
was run out of order, which is a bug, not a user error.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from fabflow.design.elements import Element
from fabflow.localize.plan import VisitPoses
from fabflow.localize.setups import InstrumentSetup
from fabflow.preview.export import ExportResult
from fabflow.programs.ir import Program
from fabflow.project import Project
from fabflow.stones.run import StoneRun
from fabflow.tasks.plan import Plan


@dataclass
class BuildContext:
    """What the stages of one build share.

    Attributes
    ----------
    project
        The validated project.
    out
        The staging folder the stages write into (moved to the real output at the end).
    elements
        Every element, world frame (``design``; the ``plan`` stage replaces print
        paths no single station can print by their per-station pieces).
    plan
        Stations and work packages (``plan``).
    setups
        The total station's set-ups (``plan``; None for the other methods).
    localization
        Per work package, the estimated base pose and the true one (``localize``).
    programs
        One checked program per non-empty work package (``program``).
    stones
        The stone wall's run: objects, grasps, releases (``stones``; stone walls only).
    preview
        The exported preview file (``preview``).
    site_plan
        Draws ``site_plan.dxf`` (it takes the file's path): set by the last stage
        that drew it (``design``; ``plan`` adds the stations), drawn once by
        :meth:`finish`; a build draws the site plan once, not once per stage.
    summary
        Rows ``(stage, item, value)`` for the summary table.
    """

    project: Project
    out: Path
    elements: list[Element] | None = None
    plan: Plan | None = None
    setups: tuple[InstrumentSetup, ...] | None = None
    localization: VisitPoses | None = None
    programs: list[Program] | None = None
    stones: StoneRun | None = None
    preview: ExportResult | None = None
    site_plan: Callable[[Path], Path] | None = None
    summary: list[tuple[str, str, str]] = field(default_factory=list)

    def finish(self) -> None:
        """Write what the stages left to the end: the site plan, as the last stage drew it."""
        if self.site_plan is not None:
            self.site_plan(self.out / "site_plan.dxf")

    def add(self, stage: str, item: str, value: object) -> None:
        """Add one row to the build summary."""
        self.summary.append((stage, item, str(value)))

    def need_elements(self) -> list[Element]:
        """The elements of the ``design`` stage."""
        if self.elements is None:
            raise RuntimeError("the design stage must run before this stage")
        return self.elements

    def need_plan(self) -> Plan:
        """The plan of the ``plan`` stage."""
        if self.plan is None:
            raise RuntimeError("the plan stage must run before this stage")
        return self.plan

    def need_stones(self) -> StoneRun:
        """The stone wall's run of the ``stones`` stage."""
        if self.stones is None:
            raise RuntimeError("the stones stage must run before this stage")
        return self.stones

    def need_localization(self) -> VisitPoses:
        """The base poses of the ``localize`` stage."""
        if self.localization is None:
            raise RuntimeError("the localize stage must run before this stage")
        return self.localization


Stage = Callable[[BuildContext], None]
"""A build stage: reads and extends the context, writes under ``ctx.out``."""
