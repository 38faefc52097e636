"""Plan and localize a project exactly, for the benchmarks that measure what comes after.

Not a benchmark itself (``tests/test_benchmarks.py`` runs every script but this).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fabflow.design.elements import Element
from fabflow.localize.plan import localize_plan
from fabflow.positioning.result import BasePose
from fabflow.project import Project
from fabflow.tasks.plan import Plan
from fabflow.tasks.planner import make_plan
from fabflow.tasks.split import with_pieces


def exact_plan(
    project: Project, elements: Sequence[Element]
) -> tuple[Project, list[Element], Plan, dict[int, BasePose]]:
    """The project with exact localization, its elements (print pieces included), plan and
    the base pose of every visit.

    Localization is exact (the parking error stays), so the figures do not depend on the
    sensor noise, and the UWB anchors of the cabin need not cover a larger site.
    """
    project = project.model_copy(
        update={"simulation": project.simulation.model_copy(update={"sensor_noise": False})}
    )
    plan = make_plan(project, elements)
    elements = with_pieces(elements, plan.split_elements)
    located = localize_plan(project, plan, elements, np.random.default_rng(0))
    return project, elements, plan, {i: pose for i, (pose, _) in located.items()}
