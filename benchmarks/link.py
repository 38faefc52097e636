"""The machine link on 127.0.0.1: round-trip latency, jitter and missed cycles per profile.

Starts ``fabflow machine-sim`` in its own process (as on a site: another program
on another computer) and streams a short program to it with ``fabflow.link``'s
streamer, for

* the hydraulic profile (paper 004's BROKK 170, 30 Hz) and the RSI profile at
  12 ms and 4 ms (a KUKA arm), on a clean link;
* the same with 5 % loss and 20 ms jitter in both directions (hydraulic and
  RSI at 12 ms).

Per case it prints whether the program completed, the round trip (hydraulic:
setpoint sent to its feedback; RSI: answer sent to the state acknowledging
it) as median and p99, the jitter of the feedback's arrival (p99 of the
deviation from the cycle), the losses the streamer saw, and the gateway's
missed cycles (RSI states without an answer in time). Timings are wall-clock
on whatever machine runs this: the load average at the start is printed.

Run: ``.venv/bin/python benchmarks/link.py [--quick]``.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from fabflow.link.profiles import profile_for
from fabflow.link.setpoints import Setpoints
from fabflow.link.streamer import stream
from fabflow.robots.catalog import get_robot


def _program(robot: str, seconds: float) -> Setpoints:
    """From HOME, every joint 0.1 rad on and 0.05 rad back, over ``seconds``.

    It ends away from where it starts: a machine that did not move cannot complete it.
    """
    home = np.asarray(get_robot(robot).q_home, dtype=float)
    t = np.array([0.0, 0.4, 0.6, 1.0]) * seconds
    q = np.vstack([home, home + 0.1, home + 0.1, home + 0.05])
    return Setpoints(robot=robot, t=t, q=q)


def _case(robot: str, profile_name: str, cycle: float, seconds: float, faults: list[str]) -> dict:
    profile = profile_for(robot, profile_name).with_options(cycle_s=cycle)
    if faults:  # a lossy link needs room for a few missing answers
        profile = profile.with_options(watchdog_s=max(profile.watchdog_s, 0.3))
    args = ["machine-sim", "--port", "0", "--robot", robot, "--profile", profile_name]
    args += ["--cycle", str(cycle), "--watchdog", str(profile.watchdog_s), *faults]
    sim = subprocess.Popen(
        [sys.executable, "-m", "fabflow", *args],
        stdout=subprocess.PIPE,
        text=True,
        env=dict(os.environ, COLUMNS="300", NO_COLOR="1"),
    )
    try:
        port = int(re.search(r"127\.0\.0\.1:(\d+)", sim.stdout.readline()).group(1))
        with tempfile.TemporaryDirectory() as tmp:
            log = Path(tmp) / "log.csv"
            r = stream(_program(robot, seconds), ("127.0.0.1", port), profile, log)
            with log.open() as f:
                t_in = [float(row["t"]) for row in csv.DictReader(f) if row["direction"] == "in"]
    finally:
        sim.send_signal(signal.SIGINT)
        out = sim.communicate(timeout=10)[0]
    missed = re.search(r"(\d+) missed cycles", out)
    rtt = 1e3 * np.asarray(r.rtt_s)
    dev = 1e3 * np.abs(np.diff(t_in) - cycle) if len(t_in) > 2 else np.zeros(1)
    return {
        "completed": r.completed,
        "reason": r.reason,
        "rtt_med": float(np.median(rtt)) if rtt.size else float("nan"),
        "rtt_p99": float(np.percentile(rtt, 99)) if rtt.size else float("nan"),
        "jitter_p99": float(np.percentile(dev, 99)),
        "lost": r.lost,
        "missed": int(missed.group(1)) if missed else -1,
        "cycles": len(t_in),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 s programs (hydraulic: 4 s)")
    args = ap.parse_args()
    print(f"load average at start: {os.getloadavg()[0]:.2f}")
    seconds = 1.0 if args.quick else 5.0
    faults = ["--loss", "0.05", "--jitter", "0.02", "--seed", "1"]
    cases = [
        ("hydraulic 30 Hz (brokk_170)", "brokk_170", "hydraulic", 1 / 30, []),
        ("rsi 12 ms (kuka_kr60_3)", "kuka_kr60_3", "rsi", 0.012, []),
        ("rsi 4 ms (kuka_kr60_3)", "kuka_kr60_3", "rsi", 0.004, []),
        ("hydraulic, 5 % loss, 20 ms jitter", "brokk_170", "hydraulic", 1 / 30, faults),
        ("rsi 12 ms, 5 % loss, 20 ms jitter", "kuka_kr60_3", "rsi", 0.012, faults),
    ]
    print(f"\n{seconds:g} s programs streamed to machine-sim on 127.0.0.1 (ms)")
    head = f"{'case':36s} {'done':>5s} {'rtt med':>8s} {'rtt p99':>8s} {'jit p99':>8s}"
    print(f"{head} {'lost':>5s} {'missed':>7s} {'states':>7s}  stopped because")
    for name, robot, profile, cycle, f in cases:
        if args.quick and profile == "hydraulic" and f:
            continue
        # the hydraulic joints answer 1.3 s late: their program must outlast that
        length = max(seconds, 4.0) if profile == "hydraulic" else seconds
        c = _case(robot, profile, cycle, length, f)
        print(
            f"{name:36s} {'yes' if c['completed'] else 'no':>5s} {c['rtt_med']:8.2f} "
            f"{c['rtt_p99']:8.2f} {c['jitter_p99']:8.2f} {c['lost']:5d} {c['missed']:7d} "
            f"{c['cycles']:7d}  {'' if c['completed'] else c['reason']}"
        )


if __name__ == "__main__":
    main()
