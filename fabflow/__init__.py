"""fabflow: from an architectural design to a mobile construction robot.

The package has one room per stage (see docs/architecture.md): ``design`` (what
to build), ``tasks`` (stations and work packages), ``positioning`` (estimators),
``sensors`` (sensor models and simulators), ``localize`` (a base pose per
station), ``programs`` (robot programs and their writers), ``preview`` (the
browser scene), ``sim`` (simulated runs) and ``build`` (the stage runner behind
``fabflow build``), on top of ``transforms`` (poses and frames) and ``robots``
(machine models and kinematics).

The names below are the short way in; each is documented where it lives::

    import numpy as np
    import fabflow

    project = fabflow.load_project("projects/cabin")
    elements = fabflow.generate_elements(project.elements, project.path)
    plan = fabflow.make_plan(project, elements)
    poses = fabflow.localize_plan(project, plan, elements, np.random.default_rng(0))
    base_poses = {visit: estimate for visit, (estimate, _) in poses.items()}
    programs, files = fabflow.write_programs(plan, elements, project, base_poses)

They are loaded on first use, so that ``import fabflow`` (and every command
line start) stays fast.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from fabflow.version import __version__

if TYPE_CHECKING:
    from fabflow.design.elements import Element
    from fabflow.design.generate import generate_elements
    from fabflow.localize.plan import localize_plan
    from fabflow.positioning.result import BasePose
    from fabflow.programs.compile import write_programs
    from fabflow.project import Project, load_project
    from fabflow.tasks.plan import Plan
    from fabflow.tasks.planner import make_plan

__all__ = [
    "BasePose",
    "Element",
    "Plan",
    "Project",
    "__version__",
    "generate_elements",
    "load_project",
    "localize_plan",
    "make_plan",
    "write_programs",
]


def __getattr__(name: str) -> Any:
    # Explicit imports, one per name, so that readers and the import contracts
    # see where each comes from; deferred so that ``import fabflow`` stays cheap.
    if name in ("Project", "load_project"):
        from fabflow import project as module
    elif name == "Element":
        from fabflow.design import elements as module
    elif name == "generate_elements":
        from fabflow.design import generate as module
    elif name == "Plan":
        from fabflow.tasks import plan as module
    elif name == "make_plan":
        from fabflow.tasks import planner as module
    elif name == "BasePose":
        from fabflow.positioning import result as module
    elif name == "localize_plan":
        from fabflow.localize import plan as module
    elif name == "write_programs":
        from fabflow.programs import compile as module
    else:
        raise AttributeError(f"module 'fabflow' has no attribute {name!r}")
    return getattr(module, name)
