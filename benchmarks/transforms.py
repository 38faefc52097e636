"""Benchmark fabflow.transforms against scipy.spatial.transform.Rotation.

Prints the median wall time (ms) of composing N poses, transforming N points by
one pose, transforming N points by N poses (one each) and building N poses from
validated 4x4 matrices, with scipy ``Rotation`` (+ the translation done in
numpy) as the reference in the same run.

Usage::

    .venv/bin/python benchmarks/transforms.py            # N = 10^6, median of 5
    .venv/bin/python benchmarks/transforms.py --quick    # N = 10^5, median of 3
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from fabflow.transforms import Pose, compose_T


def _median_ms(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up (allocations, lazy imports)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def run(n: int, repeats: int, seed: int = 0) -> list[tuple[str, float, float]]:
    """Time each operation; returns rows ``(name, fabflow_ms, scipy_ms)``."""
    rng = np.random.default_rng(seed)
    r1 = Rotation.random(n, rng=rng)
    r2 = Rotation.random(n, rng=rng)
    t1 = rng.uniform(-5, 5, size=(n, 3))
    t2 = rng.uniform(-5, 5, size=(n, 3))
    pts = rng.uniform(-10, 10, size=(n, 3))
    a = Pose(r1.as_matrix(), t1)
    b = Pose(r2.as_matrix(), t2)
    single = a[0]
    r_single = r1[0]
    t_single = t1[0]
    m1, m2 = a.matrix, b.matrix
    mats = a.matrix

    def scipy_compose() -> object:
        return r1 * r2, r1.apply(t2) + t1

    rows = [
        (
            "compose N poses (Pose @ Pose)",
            _median_ms(lambda: a @ b, repeats),
            _median_ms(scipy_compose, repeats),
        ),
        (
            "compose N 4x4 matrices (compose_T)",
            _median_ms(lambda: compose_T(m1, m2), repeats),
            _median_ms(scipy_compose, repeats),
        ),
        (
            "N points by one pose (Pose.apply)",
            _median_ms(lambda: single.apply(pts), repeats),
            _median_ms(lambda: r_single.apply(pts) + t_single, repeats),
        ),
        (
            "N points by N poses (Pose.apply)",
            _median_ms(lambda: a.apply(pts), repeats),
            _median_ms(lambda: r1.apply(pts) + t1, repeats),
        ),
        (
            "N validated poses from 4x4 (from_matrix)",
            _median_ms(lambda: Pose.from_matrix(mats), repeats),
            _median_ms(lambda: Rotation.from_matrix(mats[:, :3, :3]), repeats),
        ),
    ]
    # correctness guard: the timed operations agree with scipy
    c = a @ b
    ref_r = r1 * r2
    assert np.allclose(c.R, ref_r.as_matrix(), atol=1e-9)
    assert np.allclose(c.t, r1.apply(t2) + t1, atol=1e-9)
    assert np.allclose(single.apply(pts), r_single.apply(pts) + t_single, atol=1e-9)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="N = 10^5, median of 3")
    parser.add_argument("-n", type=int, default=None, help="number of poses / points")
    parser.add_argument("--repeats", type=int, default=None, help="timed repetitions")
    args = parser.parse_args()
    n = args.n or (10**5 if args.quick else 10**6)
    repeats = args.repeats or (3 if args.quick else 5)
    rows = run(n, repeats)
    print(f"fabflow.transforms vs scipy Rotation, N = {n:,}, median of {repeats} (ms)")
    print(f"{'operation':<44} {'fabflow':>10} {'scipy':>10} {'scipy/fabflow':>14}")
    for name, ours, ref in rows:
        print(f"{name:<44} {ours:>10.1f} {ref:>10.1f} {ref / ours:>14.2f}")


if __name__ == "__main__":
    main()
