"""What the localization puts on the site for a whole build, planned with the plan.

The total station's set-ups (:mod:`fabflow.localize.setups`) and the UWB
anchors (:mod:`fabflow.localize.anchors`): given ones are checked against every
work package, missing ones are planned. ``fabflow plan``, ``fabflow build`` and
``fabflow simulate`` all start from :func:`site_layout`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from fabflow.design.elements import Element
from fabflow.localize.anchors import AnchorCoverage, anchor_rows, layout_anchors
from fabflow.localize.setups import InstrumentSetup, planned_setups, setup_rows, setups_document
from fabflow.output import write_json
from fabflow.project import Project
from fabflow.tasks.plan import Plan


@dataclass(frozen=True)
class SiteLayout:
    """The localization's layout of one build.

    Attributes
    ----------
    project
        The project, its anchors filled in when they were planned.
    setups
        The total station's set-ups, or ``None`` when it does not localize.
    anchors
        The UWB anchors' coverage, or ``None`` when UWB does not localize.
    """

    project: Project
    setups: tuple[InstrumentSetup, ...] | None
    anchors: AnchorCoverage | None

    def rows(self, plan: Plan) -> list[tuple[str, str]]:
        """Summary rows ``(item, value)``."""
        rows = setup_rows(self.setups or ())
        if self.anchors is not None:
            rows += anchor_rows(self.anchors, plan)
        return rows

    def write(self, out: Path, plan: Plan) -> None:
        """``instrument_setups.json`` and ``uwb_anchors.json`` into ``out`` (those that apply)."""
        if self.setups is not None:
            write_json(out / "instrument_setups.json", setups_document(self.project, self.setups))
        if self.anchors is not None:
            stations = [wp.station.id for wp in plan.work_packages]
            write_json(out / "uwb_anchors.json", self.anchors.to_dict(stations))


def site_layout(
    project: Project, plan: Plan, elements: Sequence[Element], method: str | None = None
) -> SiteLayout:
    """Check or plan the set-ups and anchors the localization ``method`` (default: the
    project's) needs at every work package of ``plan``.

    Raises
    ------
    LocalizationError
        When no set-up or anchor layout covers a work package (naming it and the
        field to change).
    """
    method = method or project.localization.method
    anchors = None
    if not plan.work_packages:  # nothing to localize
        return SiteLayout(project, None, None)
    if method == "uwb" and project.localization.uwb is not None:
        project, anchors = layout_anchors(project, plan, elements)
    return SiteLayout(project, planned_setups(project, plan, elements, method), anchors)
