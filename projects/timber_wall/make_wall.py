"""Write wall.json (COMPAS) and wall.3dm (Rhino): a timber wall of 50 blocks.

Ten courses of five 0.60 x 0.105 x 0.105 m blocks in running bond, every other
course shifted half a block: what a designer would draw in Grasshopper or
script with COMPAS. Run it with the interop extra installed:

    python projects/timber_wall/make_wall.py
"""

from __future__ import annotations

from pathlib import Path

import compas
import rhino3dm
from compas.geometry import Box, Frame

LENGTH, WIDTH, HEIGHT = 0.60, 0.105, 0.105
COURSES, PER_COURSE = 10, 5
ORIGIN = (2.0, 3.0, 0.0)


def block_centres() -> list[tuple[float, float, float]]:
    """Centre of every block, course by course, in metres."""
    x0, y0, z0 = ORIGIN
    return [
        (
            x0 + (k + 0.5 + 0.5 * (course % 2)) * LENGTH,
            y0,
            z0 + (course + 0.5) * HEIGHT,
        )
        for course in range(COURSES)
        for k in range(PER_COURSE)
    ]


def write_compas(path: Path) -> None:
    boxes = []
    for i, centre in enumerate(block_centres()):
        box = Box(LENGTH, WIDTH, HEIGHT, frame=Frame(centre, [1, 0, 0], [0, 1, 0]))
        box.name = f"W{i:03d}"
        boxes.append(box)
    compas.json_dump(boxes, str(path), pretty=True)


def write_3dm(path: Path) -> None:
    model = rhino3dm.File3dm()
    model.Settings.ModelUnitSystem = rhino3dm.UnitSystem.Meters
    layer = rhino3dm.Layer()
    layer.Name = "blocks"
    index = model.Layers.Add(layer)
    for i, (x, y, z) in enumerate(block_centres()):
        bbox = rhino3dm.BoundingBox(
            x - LENGTH / 2,
            y - WIDTH / 2,
            z - HEIGHT / 2,
            x + LENGTH / 2,
            y + WIDTH / 2,
            z + HEIGHT / 2,
        )
        attributes = rhino3dm.ObjectAttributes()
        attributes.LayerIndex = index
        attributes.Name = f"W{i:03d}"
        model.Objects.AddBrep(rhino3dm.Brep.CreateFromBox(rhino3dm.Box(bbox)), attributes)
    model.Write(str(path), 8)


if __name__ == "__main__":
    here = Path(__file__).parent
    write_compas(here / "wall.json")
    write_3dm(here / "wall.3dm")
