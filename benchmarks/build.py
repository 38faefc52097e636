"""CPU time of ``fabflow build`` on the example projects, and where it goes.

Each build runs as ``fabflow build PROJECT -o OUT`` in a fresh process, as a
user runs it: with Python's compiled bytecode cached (one warm-up run writes it;
``PYTHONDONTWRITEBYTECODE`` is dropped from the children's environment, as
compiling the package's modules from source would add about 0.3 CPU s a run).
The CPU time (user + system of the child) is the median over the repeats.
Targets: the cabin at most 1.5 CPU s, the print wall at most 2.5.
Then one build per project in this process, timed stage by stage (and the site
plan it writes at the end), after the imports a build needs (timed in a fresh
process: ``import fabflow.cli`` and the build runner), to show where the time
goes. The imports' peer: the third-party packages those imports load, imported
alone in a fresh process (what no change to fabflow's own modules can take off
a build).

    python benchmarks/build.py [--quick] [--repeats N] [--projects cabin,print_path]
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from fabflow.build import runner
from fabflow.build.context import BuildContext
from fabflow.project import load_project

ROOT = Path(__file__).resolve().parents[1]
TARGETS = {"cabin": 1.5, "print_path": 2.5}
"""CPU seconds a build may take (issue 25)."""
ENV = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def child_cpu(command: list[str]) -> tuple[float, float]:
    """CPU seconds (user + system) and wall seconds of running ``command``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(
        command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True, env=ENV
    )
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, wall


LOADED_THIRD_PARTY = """
import sys
import fabflow.cli, fabflow.build.runner
names = {n.split(".")[0] for n in sys.modules} - set(sys.stdlib_module_names)
# a module a C extension registers at run time (no spec) cannot be imported by name
names = [n for n in names if not n.startswith(("_", "fabflow")) and sys.modules[n].__spec__]
print(", ".join(sorted(names)))
"""
"""Prints the third-party packages a build's imports load (importable top-level names)."""


def stage_times(project: str, out: Path) -> dict[str, float]:
    """CPU seconds of each stage of one build of ``project`` in this process, and of
    writing the site plan the stages drew (after the last stage)."""
    loaded = load_project(ROOT / "projects" / project)
    times: dict[str, float] = {}
    stages = runner.stages

    def timed(p=None):
        def wrap(name, stage):
            def run(ctx):
                start = time.process_time()
                stage(ctx)
                times[name] = time.process_time() - start

            return run

        return [(name, wrap(name, stage)) for name, stage in stages(p)]

    finish = BuildContext.finish

    def timed_finish(ctx: BuildContext) -> None:
        start = time.process_time()
        finish(ctx)
        times["site plan"] = time.process_time() - start

    runner.stages = timed
    BuildContext.finish = timed_finish  # type: ignore[method-assign]
    try:
        runner.run_build(loaded, out)
    finally:
        runner.stages = stages
        BuildContext.finish = finish  # type: ignore[method-assign]
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the timber wall, one run")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--projects", default="cabin,print_path")
    args = parser.parse_args()
    projects = ["timber_wall"] if args.quick else args.projects.split(",")
    repeats = 1 if args.quick else args.repeats
    python = sys.executable

    importing = [python, "-c", "import fabflow.cli, fabflow.build.runner"]
    child_cpu(importing)  # the warm-up: writes the bytecode caches
    imports = [child_cpu(importing)[0] for _ in range(repeats)]
    loaded = subprocess.run(
        [python, "-c", LOADED_THIRD_PARTY], capture_output=True, text=True, check=True, env=ENV
    ).stdout.strip()
    peer = [child_cpu([python, "-c", f"import {loaded}"])[0] for _ in range(repeats)]
    print(f"{'project':<12} {'CPU s (median)':>15} {'wall s':>8} {'target':>7} {'runs':>5}")
    with tempfile.TemporaryDirectory() as tmp:
        for project in projects:
            command = [python, "-m", "fabflow", "build", str(ROOT / "projects" / project)]
            runs = [child_cpu([*command, "-o", str(Path(tmp) / project)]) for _ in range(repeats)]
            cpu = statistics.median(r[0] for r in runs)
            wall = statistics.median(r[1] for r in runs)
            target = f"{TARGETS[project]:.1f}" if project in TARGETS else "-"
            print(f"{project:<12} {cpu:>15.2f} {wall:>8.2f} {target:>7} {repeats:>5}")

        print()
        print("CPU s per stage, one build in this process (imports: a fresh process, median)")
        table = {p: stage_times(p, Path(tmp) / f"{p}-stages") for p in projects}
        names = list(dict.fromkeys(n for t in table.values() for n in t))
        print(f"{'stage':<10}" + "".join(f" {p:>12}" for p in projects))
        print(f"{'imports':<10}" + f" {statistics.median(imports):>12.2f}" * len(projects))
        print(f"{'  3rd party':<10}" + f" {statistics.median(peer):>12.2f}" * len(projects))
        for name in names:
            cells = "".join(
                f" {table[p][name]:>12.2f}" if name in table[p] else f" {'-':>12}" for p in projects
            )
            print(f"{name:<10}{cells}")


if __name__ == "__main__":
    main()
