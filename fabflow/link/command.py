"""What ``fabflow stream`` and ``fabflow machine-sim`` do."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
from rich.console import Console

from fabflow.errors import InputError
from fabflow.link.gateway import Impairments, serve_gateway
from fabflow.link.profiles import profile_for
from fabflow.link.setpoints import read_setpoints
from fabflow.link.streamer import stream
from fabflow.robots.catalog import get_robot

EXIT_STOPPED = 3
"""``fabflow stream``'s exit code when it stopped the machine (any reason but Ctrl-C)."""

EXIT_INTERRUPTED = 130
"""``fabflow stream``'s exit code after Ctrl-C (the machine was stopped)."""


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` as a ``(host, port)`` pair.

    Raises
    ------
    InputError
        When it is not ``HOST:PORT`` with a port of 1 to 65535.
    """
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"--to must be HOST:PORT (e.g. 127.0.0.1:49152), not {text!r}")
    return host, int(port)


def run_stream(
    program: Path,
    to: str,
    profile_name: str | None,
    cycle_s: float | None,
    watchdog_s: float | None,
    bound: float | None,
    log: Path | None,
    console: Console,
) -> int:
    """Stream a program; returns the exit code (0 completed, else the machine was stopped).

    The packet log goes to ``log``, by default beside the program (``NAME.stream.csv``).
    """
    address = parse_address(to)
    setpoints = read_setpoints(program)
    log = log if log is not None else program.with_suffix(".stream.csv")
    profile = profile_for(setpoints.robot, profile_name).with_options(cycle_s, watchdog_s, bound)
    console.print(
        f"streaming {program.name} ({setpoints.robot}, {len(setpoints.t)} setpoints, "
        f"{setpoints.duration:.1f} s) to {address[0]}:{address[1]}, profile {profile.name} "
        f"({1e3 * profile.cycle_s:g} ms cycle, watchdog {profile.watchdog_s:g} s)"
    )
    r = stream(setpoints, address, profile, log)
    rtt = np.asarray(r.rtt_s) * 1e3
    timing = (
        f"round trip median {np.median(rtt):.1f} ms, p99 {np.percentile(rtt, 99):.1f} ms"
        if rtt.size
        else "no round trip measured"
    )
    console.print(
        f"sent {r.sent}, received {r.received}, malformed {r.malformed}, lost {r.lost}; "
        f"{timing}; largest tracking error {r.max_error:.4f} rad; {r.duration_s:.1f} s"
    )
    console.print(f"packet log: {log.resolve()}")
    if r.completed:
        console.print("[green]completed[/]: the machine reached the last setpoint")
        return 0
    console.print(f"[red]stopped the machine[/]: {r.reason}")
    return EXIT_INTERRUPTED if r.reason.startswith("interrupted") else EXIT_STOPPED


def run_machine_sim(
    port: int,
    host: str,
    robot: str,
    profile_name: str | None,
    cycle_s: float | None,
    watchdog_s: float | None,
    impair: Impairments,
    seed: int,
    log: Path | None,
    console: Console,
    stop_event: threading.Event | None = None,
) -> int:
    """Serve the simulated gateway until Ctrl-C; returns the exit code (0)."""
    model = get_robot(robot)
    profile = profile_for(robot, profile_name).with_options(cycle_s, watchdog_s)

    def ready(bound: int) -> None:
        console.print(
            f"machine-sim: {robot} behind a {profile.name} gateway on {host}:{bound} "
            f"({1e3 * profile.cycle_s:g} ms cycle, watchdog {profile.watchdog_s:g} s); "
            "Ctrl-C ends it",
            highlight=False,
        )

    stats = serve_gateway(
        model,
        profile,
        host=host,
        port=port,
        impair=impair,
        seed=seed,
        on_ready=ready,
        stop_event=stop_event,
        log=log,
    )
    console.print(f"machine-sim ended: {stats}")
    return 0
