"""Draw ``wall.dxf``: the outline of a 1.6 m long, 0.4 m thick wall with round ends, in mm.

Layer ``WALL`` holds the closed outline the print head follows: two straight
faces joined by two half-circle ARC end caps. Run
``python projects/excavator_print/make_drawing.py`` to redraw it.
"""

from __future__ import annotations

from pathlib import Path

import ezdxf

LENGTH = 1600.0
"""Straight part of each face (mm)."""
HALF_THICKNESS = 200.0


def main(path: Path) -> None:
    doc = ezdxf.new("R2010", setup=True, units=ezdxf.units.MM)
    doc.layers.add("WALL", color=1)
    msp = doc.modelspace()
    h = HALF_THICKNESS
    msp.add_line((0.0, -h), (LENGTH, -h), dxfattribs={"layer": "WALL"})
    msp.add_arc((LENGTH, 0.0), h, -90.0, 90.0, dxfattribs={"layer": "WALL"})
    msp.add_line((LENGTH, h), (0.0, h), dxfattribs={"layer": "WALL"})
    msp.add_arc((0.0, 0.0), h, 90.0, 270.0, dxfattribs={"layer": "WALL"})
    doc.saveas(path)


if __name__ == "__main__":
    main(Path(__file__).with_name("wall.dxf"))
