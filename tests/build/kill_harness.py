"""Run ``fabflow build`` in forked children and stop each one at a named point or after a delay.

Used by ``test_kill.py`` as ``python kill_harness.py CASES.json``. The harness
imports fabflow and runs one build to load everything, then forks one child per
case (two at a time), so a case costs a build (about 0.1 s), not a start-up of
Python. Threads would not survive a fork: the caller sets the BLAS libraries
to one thread, and the harness checks that it runs a single thread.

A case is ``{"out", "log", "signal", "point" | "delay", "exchange"}``:

* ``point``: the child sends itself ``signal`` when it reaches the point: a
  point of :mod:`fabflow.output` (``staging-created``, ``before-replace``,
  ``moved-aside``, ``replaced``) or ``stage-NAME``, before the build stage NAME;
* ``delay``: the harness sends ``signal`` to the child ``delay`` seconds after
  forking it;
* ``exchange``: ``false`` makes the child replace folders without the atomic
  exchange (two renames), as on a platform that has none.

It prints one JSON line per case: the case and the child's exit code (negative:
killed by that signal).
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path

import fabflow.build.runner as runner
import fabflow.output as output
from fabflow.cli import app


def run_cli(args: list[str]) -> int:
    """Run the command line in this process; return its exit code."""
    try:
        app(args, prog_name="fabflow")
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 1
    return 0


def child(case: dict, project: str) -> None:
    """In the forked child: arm the stop point, run the build, exit (never returns)."""
    code = 1
    try:
        log = os.open(case["log"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(log, 1)
        os.dup2(log, 2)
        signum = getattr(signal, case["signal"])

        def stop(name: str) -> None:
            if name == case.get("point"):
                os.kill(os.getpid(), signum)

        output._reached = stop
        original = runner.stages

        def stages(project=None) -> list:
            def wrap(name, stage):
                def run(ctx):
                    stop(f"stage-{name}")
                    return stage(ctx)

                return run

            return [(name, wrap(name, stage)) for name, stage in original(project)]

        runner.stages = stages
        if not case.get("exchange", True):
            output._exchange = lambda a, b: False
        code = run_cli(["build", project, "-o", case["out"]])
    except BaseException as exc:
        code = exc.code if isinstance(exc, SystemExit) and isinstance(exc.code, int) else 1
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def main() -> None:
    spec = json.loads(Path(sys.argv[1]).read_text())
    project = spec["project"]
    warm = run_cli(["build", project, "-o", spec["warm_up"]])
    assert warm == 0, f"warm-up build failed with {warm}"
    threads = os.listdir("/proc/self/task")
    assert len(threads) == 1, f"cannot fork safely: {len(threads)} threads"
    pending = list(spec["cases"])
    running: dict[int, tuple[dict, float]] = {}
    while pending or running:
        while pending and len(running) < 2:
            case = pending.pop(0)
            sys.stdout.flush()
            sys.stderr.flush()
            pid = os.fork()
            if pid == 0:
                child(case, project)
            running[pid] = (case, time.monotonic())
        for pid, (case, started) in list(running.items()):
            delay = case.get("delay")
            if delay is not None and not case.get("sent") and time.monotonic() - started >= delay:
                os.kill(pid, getattr(signal, case["signal"]))  # a zombie until waited for
                case["sent"] = True
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                del running[pid]
                print(json.dumps({**case, "exit": os.waitstatus_to_exitcode(status)}), flush=True)
        time.sleep(0.002)


if __name__ == "__main__":
    main()
