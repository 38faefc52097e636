"""Command line start-up and the RAPID writer's pose conversion.

Times, each as the median over repeated runs in fresh processes: a bare Python
start (the floor nothing in fabflow can remove), ``import fabflow`` and
``fabflow --help`` (target: 0.15 s). Then the RAPID robtargets of as many poses
as the print_path example's programs hold (28,503): converted one pose at a
time (the writer's old path, kept here only as the peer) and in one call, as
the writer does now; both give the same text.

    python benchmarks/startup.py [--quick] [--repeats N]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

import numpy as np

from fabflow.programs.writers.rapid import _pose, _pose_text
from fabflow.transforms.so3 import exp_so3
from fabflow.transforms.vendors import to_abb_pose

PRINT_PATH_POSES = 28_503
"""Robtargets in the print_path example's RAPID programs."""


def wall(command: list[str], repeats: int) -> float:
    """Median wall time (s) of running ``command`` in a fresh process."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run(command, stdout=subprocess.DEVNULL, check=True)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def per_pose(T: np.ndarray) -> list[str]:
    """The peer: one conversion per pose."""
    return [_pose(t) for t in T]


def one_call(T: np.ndarray) -> list[str]:
    """What the writer does: every pose in one call, then the text."""
    positions, quats = to_abb_pose(T)
    return [_pose_text(p, q) for p, q in zip(positions, quats, strict=True)]


def timed(func, T: np.ndarray, repeats: int) -> tuple[float, list[str]]:
    times, out = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        out = func(T)
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 runs, 2,000 poses")
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()
    runs = 3 if args.quick else args.repeats
    python = sys.executable

    print(f"{'what':<34} {'median ms':>10} {'runs':>5}")
    for label, command in [
        ("python start (floor)", [python, "-c", "pass"]),
        ("import fabflow", [python, "-c", "import fabflow"]),
        ("fabflow --help (target 150 ms)", [python, "-m", "fabflow", "--help"]),
    ]:
        print(f"{label:<34} {wall(command, runs) * 1000:>10.0f} {runs:>5}")

    n = 2_000 if args.quick else PRINT_PATH_POSES
    rng = np.random.default_rng(0)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = exp_so3(rng.uniform(-np.pi, np.pi, (n, 3)))
    T[:, :3, 3] = rng.uniform(-3.0, 3.0, (n, 3))
    repeats = 1 if args.quick else 3
    old, old_text = timed(per_pose, T, repeats)
    new, new_text = timed(one_call, T, repeats)
    assert old_text == new_text, "the one-call conversion must give the same text"
    print()
    print(f"{'RAPID robtargets':<22} {'poses':>7} {'median s':>9} {'us/pose':>8} {'ratio':>6}")
    print(f"{'one pose at a time':<22} {n:>7} {old:>9.3f} {old / n * 1e6:>8.1f} {1.0:>6.1f}")
    print(f"{'one call':<22} {n:>7} {new:>9.3f} {new / n * 1e6:>8.1f} {old / new:>6.1f}")


if __name__ == "__main__":
    main()
