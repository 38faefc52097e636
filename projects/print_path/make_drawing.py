"""Draw ``sine_wall.dxf``: a 4 m long sine-wave wall, 300 mm thick, in millimetres.

Layers: ``WALL_OUTER`` holds the closed outline the printer follows (two SPLINE
faces offset 150 mm either side of the centre line, joined by two ARC end
caps), ``CENTRELINE`` the wall's centre line (an open LWPOLYLINE) and
``ANNOTATION`` a title. Run ``python projects/print_path/make_drawing.py`` to
redraw it.
"""

from __future__ import annotations

import math
from pathlib import Path

import ezdxf
import numpy as np

LENGTH = 4000.0
AMPLITUDE = 250.0
WAVELENGTH = 2000.0
HALF_THICKNESS = 150.0


def centre(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre-line points and unit normals (left of the direction of travel)."""
    k = 2 * math.pi / WAVELENGTH
    p = np.column_stack([x, AMPLITUDE * np.sin(k * x)])
    t = np.column_stack([np.ones_like(x), AMPLITUDE * k * np.cos(k * x)])
    t /= np.linalg.norm(t, axis=1)[:, None]
    return p, np.column_stack([-t[:, 1], t[:, 0]])


def main(path: Path) -> None:
    doc = ezdxf.new("R2010", setup=True, units=ezdxf.units.MM)
    doc.layers.add("WALL_OUTER", color=1)
    doc.layers.add("CENTRELINE", color=4, linetype="CENTER")
    doc.layers.add("ANNOTATION", color=7)
    msp = doc.modelspace()
    x = np.linspace(0.0, LENGTH, 81)
    p, n = centre(x)
    left, right = p + HALF_THICKNESS * n, p - HALF_THICKNESS * n
    msp.add_spline(fit_points=left.tolist(), dxfattribs={"layer": "WALL_OUTER"})
    msp.add_spline(fit_points=right[::-1].tolist(), dxfattribs={"layer": "WALL_OUTER"})
    a_end = math.degrees(math.atan2(-n[-1, 1], -n[-1, 0]))
    msp.add_arc(
        p[-1].tolist(), HALF_THICKNESS, a_end, a_end + 180.0, dxfattribs={"layer": "WALL_OUTER"}
    )
    a_start = math.degrees(math.atan2(n[0, 1], n[0, 0]))
    msp.add_arc(
        p[0].tolist(), HALF_THICKNESS, a_start, a_start + 180.0, dxfattribs={"layer": "WALL_OUTER"}
    )
    msp.add_lwpolyline(p.tolist(), dxfattribs={"layer": "CENTRELINE"})
    msp.add_text(
        "sine wall 4000 x 300 mm", height=100.0, dxfattribs={"layer": "ANNOTATION"}
    ).set_placement((0.0, -700.0))
    doc.saveas(path)


if __name__ == "__main__":
    main(Path(__file__).with_name("sine_wall.dxf"))
