"""``fabflow stream`` against the simulated gateway on 127.0.0.1 (loopback)."""

from __future__ import annotations

import csv
import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import ROOT

from fabflow.link.gateway import Impairments, serve_gateway
from fabflow.link.profiles import profile_for
from fabflow.link.protocol import Message, decode, encode
from fabflow.link.setpoints import read_setpoints
from fabflow.link.streamer import stream
from fabflow.robots.catalog import get_robot


def write_program(path: Path, robot: str, offsets: list[float], dwell: float = 0.3) -> Path:
    """A program that moves every joint by each offset from HOME in turn, dwelling at each.

    Returns the path; the setpoints are HOME, then HOME + offset (held ``dwell``
    seconds) for each offset, then HOME again, 0.5 s apart.
    """
    home = get_robot(robot).q_home
    commands, t = [], 0.0
    for off in [0.0, *offsets, 0.0]:
        q = (np.asarray(home) + off).tolist()
        commands.append({"t": t, "type": "setpoint", "kind": "ptp", "q": q})
        commands.append({"t": t + dwell, "type": "setpoint", "kind": "ptp", "q": q})
        t += dwell + 0.5
    doc = {"format": "fabflow-command-stream", "version": 1, "robot": robot, "commands": commands}
    path.write_text(json.dumps(doc))
    return path


class Gateway:
    """The simulated gateway in a thread for the length of a test."""

    def __init__(
        self, robot: str, profile, impair: Impairments | None = None, log: Path | None = None
    ) -> None:
        self.stop_event = threading.Event()
        self.port: int | None = None
        ready = threading.Event()

        def on_ready(port: int) -> None:
            self.port = port
            ready.set()

        self.result: list = []
        self.thread = threading.Thread(
            target=lambda: self.result.append(
                serve_gateway(
                    get_robot(robot),
                    profile,
                    impair=impair or Impairments(),
                    seed=1,
                    on_ready=on_ready,
                    stop_event=self.stop_event,
                    log=log,
                )
            ),
            daemon=True,
        )
        self.thread.start()
        assert ready.wait(5.0)

    def close(self):
        self.stop_event.set()
        self.thread.join(5.0)
        return self.result[0]


def _feedback(log: Path) -> tuple[np.ndarray, np.ndarray]:
    with log.open() as f:
        rows = [r for r in csv.DictReader(f) if r["direction"] == "in" and r["status"] == "ok"]
    q = np.array([[float(v) for k, v in r.items() if k.startswith("q") and v] for r in rows])
    return np.array([float(r["t"]) for r in rows]), q


@pytest.mark.parametrize(("robot", "name"), [("kuka_kr60_3", "rsi"), ("brokk_170", "hydraulic")])
def test_the_machine_reaches_every_setpoint_of_a_short_program(tmp_path, robot, name) -> None:
    dwell = 0.3 if name == "rsi" else 3.0  # the hydraulic joints answer after 1.3 s
    program = read_setpoints(write_program(tmp_path / "p.json", robot, [0.05, -0.05], dwell))
    profile = profile_for(robot)
    assert profile.name == name
    # the gateway thread and the streamer share one interpreter on a loaded machine
    profile = profile.with_options(watchdog_s=1.0)
    gw = Gateway(robot, profile)
    try:
        report = stream(program, ("127.0.0.1", gw.port), profile, tmp_path / "log.csv")
    finally:
        stats = gw.close()
    assert report.completed, report.reason
    assert report.malformed == 0 and stats.malformed == 0
    rows = [(r["direction"], r["kind"]) for r in csv.DictReader((tmp_path / "log.csv").open())]
    first_stop = rows.index(("out", "stop"))
    assert ("out", "setpoint") not in rows[first_stop:]  # nothing but stops after the stop
    _, q = _feedback(tmp_path / "log.csv")
    tol = 0.02 if name == "hydraulic" else 0.002
    for target in np.unique(np.round(program.q, 9), axis=0):
        assert np.min(np.max(np.abs(q - target), axis=1)) < tol  # it got there
    assert np.max(np.abs(q[-1] - program.q[-1])) <= profile.settle_tolerance


def test_loss_and_jitter_are_ridden_out_and_logged(tmp_path) -> None:
    robot = "kuka_kr60_3"
    program = read_setpoints(write_program(tmp_path / "p.json", robot, [0.05], 0.5))
    profile = profile_for(robot, "hydraulic").with_options(watchdog_s=0.5, tracking_bound=0.3)
    gw = Gateway(robot, profile, Impairments(loss=0.05, jitter=0.02))
    try:
        report = stream(program, ("127.0.0.1", gw.port), profile, tmp_path / "log.csv")
    finally:
        stats = gw.close()
    assert report.completed, report.reason
    assert report.lost > 0  # the log's sequence numbers show the losses
    assert stats.lost_in + stats.lost_out > 0


def _cli(*args: str) -> subprocess.Popen:
    env = dict(os.environ, COLUMNS="200", NO_COLOR="1")
    return subprocess.Popen(
        [sys.executable, "-m", "fabflow", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def _wait_for(predicate, seconds: float = 30.0) -> None:
    deadline = time.monotonic() + seconds
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def _has_feedback(log: Path) -> bool:
    return log.exists() and any(",in,feedback," in line for line in log.read_text().splitlines())


def test_killing_the_streamer_makes_the_gateway_stop_the_machine(tmp_path) -> None:
    robot = "kuka_kr60_3"
    path = write_program(tmp_path / "p.json", robot, [0.2], 20.0)
    profile = profile_for(robot, "rsi").with_options(cycle_s=0.012, watchdog_s=0.2)
    gw = Gateway(robot, profile, log=tmp_path / "gateway.csv")
    try:
        proc = _cli(
            "stream", str(path), "--to", f"127.0.0.1:{gw.port}", "--cycle", "0.012",
            "--watchdog", "1",
        )  # fmt: skip
        _wait_for(lambda: _has_feedback(tmp_path / "p.stream.csv"))
        time.sleep(0.5)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGKILL)
        proc.wait(5.0)
        time.sleep(1.5)  # many watchdog times
    finally:
        stats = gw.close()
    assert stats.stops[0][1] == "watchdog"
    # on the gateway's clock: the stop came one watchdog after the last datagram it got
    with (tmp_path / "gateway.csv").open() as f:
        t_in = [float(r["t"]) for r in csv.DictReader(f) if r["direction"] == "in"]
    silence = stats.stops[0][0] - max(t for t in t_in if t <= stats.stops[0][0])
    assert 0.2 <= silence < 0.2 + 0.15


def test_a_silent_gateway_trips_the_streamers_watchdog(tmp_path) -> None:
    """A gateway that answers a few setpoints and then goes silent (it hangs)."""
    program = read_setpoints(write_program(tmp_path / "p.json", "brokk_170", [0.05], 3.0))
    profile = profile_for("brokk_170").with_options(watchdog_s=0.3)
    home = get_robot("brokk_170").q_home
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gateway:
        gateway.bind(("127.0.0.1", 0))
        gateway.settimeout(5.0)

        def answer_five() -> None:
            for k in range(5):
                data, addr = gateway.recvfrom(4096)
                m = decode(data, "hydraulic")
                fb = Message("feedback", k, 0.0, tuple(home), ack=m.seq, echo_t=m.t)
                gateway.sendto(encode(fb, "hydraulic"), addr)

        helper = threading.Thread(target=answer_five, daemon=True)
        helper.start()
        t0 = time.monotonic()
        report = stream(program, gateway.getsockname(), profile, tmp_path / "log.csv")
        helper.join(5.0)
    assert not report.completed
    assert report.reason.startswith("watchdog")
    assert report.received == 5
    assert time.monotonic() - t0 < 3.0  # it did not wait for the program to run out


def test_killing_the_gateway_makes_the_streamer_stop_and_exit_non_zero(tmp_path) -> None:
    robot = "kuka_kr60_3"
    path = write_program(tmp_path / "p.json", robot, [0.2], 20.0)
    sim = _cli("machine-sim", "--port", "0", "--robot", robot, "--cycle", "0.012")
    try:
        assert select.select([sim.stdout], [], [], 30.0)[0], "machine-sim did not start"
        line = sim.stdout.readline()
        port = int(line.split("127.0.0.1:")[1].split()[0])
        proc = _cli(
            "stream", str(path), "--to", f"127.0.0.1:{port}", "--cycle", "0.012",
            "--watchdog", "1",
        )  # fmt: skip
        _wait_for(lambda: _has_feedback(tmp_path / "p.stream.csv"))
        sim.send_signal(signal.SIGKILL)
        out, err = proc.communicate(timeout=30)
    finally:
        sim.kill()
        sim.wait(5)
    assert proc.returncode == 3, out + err
    assert "stopped the machine" in out
    assert "Traceback" not in out + err
