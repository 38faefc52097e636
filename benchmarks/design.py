"""Design benchmarks: cabin generation (with supports), print path sampling, DXF in and out.

Run ``python benchmarks/design.py`` (full) or ``--quick`` (a smaller version, a few
seconds). Prints one table of median wall-clock times.
"""

from __future__ import annotations

import argparse
import math
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fabflow.design.cabin import cabin_elements
from fabflow.design.dxf_in import read_dxf_contours
from fabflow.design.generate import with_block_supports
from fabflow.design.hermite import sample_hermite
from fabflow.design.print_path import order_contours
from fabflow.design.site_plan import write_site_plan
from fabflow.design.specs import CabinSpec, Opening

ROOT = Path(__file__).resolve().parents[1]
SINE_WALL = ROOT / "projects" / "print_path" / "sine_wall.dxf"


def median_time(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    """Median wall-clock seconds of ``repeats`` calls, and the last result."""
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), result


def scaled_cabin(factor: float) -> CabinSpec:
    """The default cabin, every dimension scaled by ``sqrt(factor)`` (~``factor`` x blocks)."""
    base = CabinSpec()
    s = math.sqrt(factor)
    openings = [
        Opening(**{**o.model_dump(), "center": o.center * s, "sill": o.sill * s})
        for o in base.openings
    ]
    return CabinSpec(
        length=base.length * s,
        width=base.width * s,
        height=base.height * s,
        eave_height=base.eave_height * s,
        openings=openings,
    )


def long_path(length: float) -> tuple[np.ndarray, np.ndarray]:
    """Copies of the sine-wall outline side by side, joined by travel moves, ~``length`` m."""
    (outline,) = read_dxf_contours(SINE_WALL, ["WALL_OUTER"])
    one = np.linalg.norm(np.diff(outline.points, axis=0), axis=1).sum()
    n = max(1, round(length / one))
    copies = [outline.points + np.array([0.0, 1.0 * i, 0.0]) for i in range(n)]
    path = order_contours(copies, [True] * n)
    return path.points, path.extrude


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small version (CI smoke run)")
    args = parser.parse_args()
    repeats = 1 if args.quick else 5
    big = 3.0 if args.quick else 10.0
    path_length = 20.0 if args.quick else 100.0

    rows: list[tuple[str, str, float]] = []

    def cabin(spec: CabinSpec) -> list:
        return with_block_supports(cabin_elements(spec))

    t, els = median_time(lambda: cabin(CabinSpec()), repeats)
    rows.append(("cabin (default), blocks + supports", f"{len(els)} blocks", t))
    t_big, big_els = median_time(lambda: cabin(scaled_cabin(big)), max(1, repeats // 2))
    rows.append((f"cabin ({big:g}x blocks), blocks + supports", f"{len(big_els)} blocks", t_big))

    pts, extrude = long_path(path_length)
    t, sampled = median_time(lambda: sample_hermite(pts, 0.1, 100.0, extrude), repeats)
    rows.append(
        (
            f"Hermite sampling at 100 Hz, {sampled.length:.0f} m path",
            f"{len(sampled.t)} samples, max dev {sampled.max_deviation * 1e3:.3f} mm",
            t,
        )
    )
    t, contours = median_time(lambda: read_dxf_contours(SINE_WALL, ["WALL_OUTER"]), repeats)
    rows.append(("read sine_wall.dxf", f"{len(contours[0].points)} vertices", t))
    with tempfile.TemporaryDirectory() as tmp:
        target = Path(tmp) / "site_plan.dxf"
        t, _ = median_time(lambda: write_site_plan(target, els), repeats)
        rows.append(("write site plan (default cabin)", f"{target.stat().st_size // 1024} KiB", t))

    width = max(len(r[0]) for r in rows)
    detail = max(len(r[1]) for r in rows)
    print(f"{'benchmark':<{width}}  {'size':<{detail}}  median s")
    print(f"{'-' * width}  {'-' * detail}  --------")
    for name, size, seconds in rows:
        print(f"{name:<{width}}  {size:<{detail}}  {seconds:8.3f}")


if __name__ == "__main__":
    main()
