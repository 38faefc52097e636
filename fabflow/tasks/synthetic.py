"""Larger synthetic projects for scaling tests: a grid of copies of the cabin."""

from __future__ import annotations

import math

from fabflow.design.elements import Element
from fabflow.design.generate import generate_elements
from fabflow.design.specs import ElementSource
from fabflow.project import Project, Site


def cabin_rows(project: Project, n_cabins: int, gap: float = 3.0) -> tuple[Project, list[Element]]:
    """Copies of the project's first cabin on a grid, ``gap`` metres apart.

    Parameters
    ----------
    project
        A project whose first element source is a cabin (e.g. projects/cabin).
    n_cabins
        Number of cabins, laid out in rows of ``ceil(sqrt(n_cabins))``.
    gap
        Clear distance between neighbouring cabins (metres).

    Returns
    -------
    project, elements
        The project with the cabins and a site extent grown to hold them (3 m
        border), and its elements (unique ids, supports computed).
    """
    spec = project.elements[0].cabin
    if spec is None:
        raise ValueError("the project's first element source must be a cabin")
    per_row = math.ceil(math.sqrt(n_cabins))
    dx, dy = spec.length + gap, spec.width + gap
    ox, oy, oz = spec.origin
    sources = [
        ElementSource(
            cabin=spec.model_copy(
                update={"origin": (ox + (i % per_row) * dx, oy + (i // per_row) * dy, oz)}
            )
        )
        for i in range(n_cabins)
    ]
    rows = math.ceil(n_cabins / per_row)
    site = Site(
        frame=project.site.frame,
        extent_min=(ox - 3.0, oy - 3.0),
        extent_max=(ox + per_row * dx - gap + 3.0, oy + rows * dy - gap + 3.0),
        obstacles=[],
    )
    big = project.model_copy(update={"elements": sources, "site": site})
    return big, generate_elements(big.elements, big.path, big.limits)
