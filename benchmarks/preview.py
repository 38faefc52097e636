"""Preview benchmark: scene build time, step update time and exported HTML size.

For the cabin and for a project ten times larger (ten cabins in a row, the
cabin's plan shifted to each), prints the median time to precompute the model
(IK for every target), to build the viser scene (server side), to move one
step (sequential play, and random slider jumps), to export the offline HTML
file, and the file's size. Targets: cabin scene under 1 s, a step under 20 ms,
the cabin's file under 20 MB.

    .venv/bin/python benchmarks/preview.py           # cabin and 10x cabin
    .venv/bin/python benchmarks/preview.py --quick   # synthetic wall, 1x and 2x (CI smoke run)
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from fabflow.design.elements import Element
from fabflow.preview.arm import RobotArm
from fabflow.preview.export import MAX_EXPORT_BYTES, export_html, quiet_server
from fabflow.preview.model import PreviewModel, build_model
from fabflow.preview.scene import PreviewScene
from fabflow.project import Project, load_project
from fabflow.robots import get_robot
from fabflow.tasks.plan import Plan, Station, WorkPackage

ROOT = Path(__file__).resolve().parents[1]


def shifted_copies(
    elements: list[Element], plan: Plan, n: int, dx: float
) -> tuple[list[Element], Plan]:
    """``n`` copies of a design and its plan, copy ``i`` shifted by ``i * dx`` along x."""
    out_e: list[Element] = []
    out_p: list[WorkPackage] = []
    for i in range(n):
        T = np.eye(4)
        T[0, 3] = i * dx
        out_e += [
            dataclasses.replace(
                e,
                id=f"C{i}_{e.id}",
                T_world_element=T @ e.T_world_element,
                supports=tuple(f"C{i}_{s}" for s in e.supports),
            )
            for e in elements
        ]
        for wp in plan.work_packages:
            station = Station(
                f"C{i}_{wp.station.id}", T @ wp.station.T_world_platform, wp.station.lift
            )
            out_p.append(
                WorkPackage(
                    index=len(out_p),
                    station=station,
                    elements=tuple(f"C{i}_{e}" for e in wp.elements),
                    T_world_targets=T @ wp.T_world_targets,
                    travel=wp.travel,
                )
            )
    return out_e, Plan(work_packages=tuple(out_p))


def median_time(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def measure(
    label: str,
    elements: list[Element],
    plan: Plan,
    project: Project | None,
    repeats: int,
    rng: np.random.Generator,
) -> dict[str, object]:
    platform = project.robot.platform if project else None
    T_ft = project.robot.tool.T_flange_tool.matrix() if project else np.eye(4)
    arm = RobotArm(get_robot(project.robot.model if project else "kuka_kr60_3"), T_ft)

    def make_model() -> PreviewModel:
        return build_model(
            elements, plan, name=label, platform=platform, T_flange_tool=T_ft, arm=arm
        )

    t_model = median_time(make_model, repeats)
    model = make_model()
    with quiet_server() as server:
        scene_times = []
        for r in range(repeats):
            t0 = time.perf_counter()
            scene = PreviewScene(server, model, project, colour_mode="state")
            scene_times.append(time.perf_counter() - t0)
            if r < repeats - 1:
                server.scene.reset()
        seq = []
        for k in range(model.n_steps + 1):
            t0 = time.perf_counter()
            scene.set_step(k)
            seq.append(time.perf_counter() - t0)
        jumps = []
        for k in rng.integers(0, model.n_steps + 1, size=min(200, model.n_steps)):
            t0 = time.perf_counter()
            scene.set_step(int(k))
            jumps.append(time.perf_counter() - t0)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "preview.html"
        t0 = time.perf_counter()
        result = export_html(model, path, project)
        t_export = time.perf_counter() - t0
    return {
        "project": label,
        "elements": len(elements),
        "steps": model.n_steps,
        "model s": t_model,
        "scene s": float(np.median(scene_times)),
        "step ms": 1000 * float(np.median(seq)),
        "step p95 ms": 1000 * float(np.percentile(seq, 95)),
        "jump ms": 1000 * float(np.median(jumps)),
        "export s": t_export,
        "html MB": result.size_bytes / 1e6,
        "under 20 MB": result.size_bytes < MAX_EXPORT_BYTES,
    }


def print_table(rows: list[dict[str, object]]) -> None:
    keys = list(rows[0])
    cells = [[f"{r[k]:.3f}" if isinstance(r[k], float) else str(r[k]) for k in keys] for r in rows]
    widths = [max(len(k), *(len(c[i]) for c in cells)) for i, k in enumerate(keys)]
    print("  ".join(k.rjust(w) for k, w in zip(keys, widths, strict=True)))
    for c in cells:
        print("  ".join(v.rjust(w) for v, w in zip(c, widths, strict=True)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small synthetic run (CI)")
    parser.add_argument("--repeats", type=int, default=None)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    rows = []
    if args.quick:
        from fabflow.preview.synthetic import wall_design

        repeats = args.repeats or 1
        elements, plan = wall_design(n_rows=12, n_per_row=12, n_stations=3, n_prebuilt=40)
        for n in (1, 2):
            e, p = shifted_copies(elements, plan, n, 8.0)
            rows.append(measure(f"wall x{n}", e, p, None, repeats, rng))
    else:
        from fabflow.design.generate import generate_elements
        from fabflow.tasks.planner import plan_project

        repeats = args.repeats or 3
        project = load_project(ROOT / "projects" / "cabin")
        elements = generate_elements(project.elements, project.path)
        plan = plan_project(project, elements)
        rows.append(measure("cabin", elements, plan, project, repeats, rng))
        e, p = shifted_copies(elements, plan, 10, 8.0)
        big = project.model_copy(
            update={"site": project.site.model_copy(update={"extent_max": (8.0 * 10 + 8.0, 9.0)})}
        )
        rows.append(measure("cabin x10", e, p, big, max(1, repeats - 2), rng))
    print_table(rows)
    print(
        "model: IK for every target; scene: server-side build; step: one slider step while "
        "playing; jump: a random slider jump; export: whole offline HTML file (medians)"
    )


if __name__ == "__main__":
    main()
