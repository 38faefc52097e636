"""The simulated machine gateway: answers, watchdog, stop, RSI clock, malformed input, faults."""

from __future__ import annotations

import csv
import json
import queue
import select
import socket
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from fabflow.errors import InputError
from fabflow.link import gateway as gateway_module
from fabflow.link.gateway import GatewayStats, Impairments, serve_gateway
from fabflow.link.profiles import HYDRAULIC, RSI, LinkProfile
from fabflow.link.protocol import MAX_DATAGRAM, Message, ProtocolError, decode, encode
from fabflow.robots.catalog import get_robot
from fabflow.robots.chain import RobotModel
from fabflow.robots.hydraulic import HydraulicJoints, HydraulicServo

BROKK = get_robot("brokk_170")
KUKA = get_robot("kuka_kr60_3")
RSI_12MS = RSI.with_options(cycle_s=0.012, watchdog_s=0.5)


class Gateway:
    """A gateway running in a thread, and a plain UDP socket talking to it."""

    def __init__(self, robot: RobotModel, profile: LinkProfile, **kwargs: object) -> None:
        self.profile = profile
        self.stats: GatewayStats | None = None
        self._stop = threading.Event()
        ready: queue.Queue[int] = queue.Queue()

        def run() -> None:
            self.stats = serve_gateway(
                robot, profile, on_ready=ready.put, stop_event=self._stop, **kwargs
            )

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()
        self.addr = ("127.0.0.1", ready.get(timeout=5.0))
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.settimeout(1.0)

    def send(self, msg: Message) -> None:
        self.sock.sendto(encode(msg, self.profile.name), self.addr)

    def send_raw(self, data: bytes) -> None:
        self.sock.sendto(data, self.addr)

    def recv(self, timeout: float = 1.0) -> Message:
        self.sock.settimeout(timeout)
        data, _ = self.sock.recvfrom(65536)
        return decode(data, self.profile.name)

    def ask(self, msg: Message) -> Message:
        self.send(msg)
        return self.recv()

    def stop(self) -> GatewayStats:
        """End the gateway; what it sent stays readable on :attr:`sock`."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        assert self.stats is not None
        return self.stats


@pytest.fixture
def gateways():
    """Start gateways with ``gateways(robot, profile, ...)``; all are stopped at the end."""
    started: list[Gateway] = []

    def start(robot: RobotModel, profile: LinkProfile, **kwargs: object) -> Gateway:
        started.append(Gateway(robot, profile, **kwargs))
        return started[-1]

    yield start
    for g in started:
        if g.stats is None:
            g.stop()
        g.sock.close()


def heartbeat(seq: int, t: float = 0.0, ack: int = -1) -> Message:
    return Message(kind="heartbeat", seq=seq, t=t, ack=ack)


def drain(g: Gateway, timeout: float = 0.1, longest: float = 3.0) -> list[Message]:
    """The messages on the test's socket until ``timeout`` of quiet (or ``longest`` s)."""
    out, end = [], time.monotonic() + longest
    while time.monotonic() < end:
        try:
            out.append(g.recv(timeout=timeout))
        except TimeoutError:
            break
    return out


def log_rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


# ---------------------------------------------------------------- hydraulic


def test_a_heartbeat_is_answered_with_feedback_at_home(gateways) -> None:
    g = gateways(BROKK, HYDRAULIC)
    fb = g.ask(heartbeat(0, t=0.5))
    assert (fb.kind, fb.seq, fb.ack, fb.echo_t, fb.state) == ("feedback", 0, -1, 0.0, "running")
    assert np.allclose(fb.q, BROKK.q_home, atol=1e-9)
    assert g.ask(heartbeat(1)).seq == 1  # the gateway's own counter
    stats = g.stop()
    assert (stats.received, stats.sent, stats.malformed, stats.stops) == (2, 2, 0, [])
    assert np.allclose(stats.q, BROKK.q_home)


def test_a_setpoint_is_acknowledged_and_a_stale_one_ignored(gateways) -> None:
    g = gateways(BROKK, HYDRAULIC)
    q = tuple(BROKK.q_home + 0.05)
    fb = g.ask(Message(kind="setpoint", seq=5, t=1.25, q=q))
    assert (fb.ack, fb.echo_t) == (5, 1.25)
    fb = g.ask(heartbeat(6, t=1.5))
    assert (fb.ack, fb.echo_t) == (5, 1.25)
    fb = g.ask(Message(kind="setpoint", seq=3, t=1.75, q=q))
    assert (fb.ack, fb.echo_t) == (5, 1.25)


def test_malformed_datagrams_are_counted_and_dropped(gateways) -> None:
    g = gateways(BROKK, HYDRAULIC)
    oversized = encode(heartbeat(1), "hydraulic")[:-1] + b" " * MAX_DATAGRAM + b"}"
    wrong_version = json.dumps({"v": 2, "type": "heartbeat", "seq": 1, "t": 0.0}).encode()
    bad = [
        b"\xff\x00 garbage",
        oversized,
        wrong_version,
        encode(heartbeat(1), "rsi"),
        encode(Message(kind="setpoint", seq=2, t=0.0, q=(0.0, 0.0)), "hydraulic"),  # 2 of 5 joints
        encode(Message(kind="feedback", seq=3, t=0.0), "hydraulic"),
    ]
    q = tuple(BROKK.q_home)
    for i, data in enumerate(bad):
        g.send_raw(data)
        fb = g.ask(Message(kind="setpoint", seq=10 + i, t=float(i), q=q))
        assert (fb.kind, fb.ack, fb.echo_t) == ("feedback", 10 + i, float(i))  # answers this one
    stats = g.stop()
    assert (stats.malformed, stats.received, stats.sent) == (len(bad), 2 * len(bad), len(bad))


def test_the_machine_follows_a_setpoint_after_the_valves_dead_time(gateways) -> None:
    g = gateways(BROKK, HYDRAULIC)
    target = BROKK.q_home.copy()
    target[0] += 0.3
    t0 = time.monotonic()
    g.ask(Message(kind="setpoint", seq=0, t=0.0, q=tuple(target)))
    early = g.ask(heartbeat(1)).q[0]
    while time.monotonic() - t0 < 2.0:
        time.sleep(0.05)
        late = g.ask(heartbeat(2)).q[0]
    assert early == pytest.approx(BROKK.q_home[0], abs=1e-12)
    assert BROKK.q_home[0] + 1e-3 < late < target[0]


def test_the_watchdog_stops_a_silent_streamer_for_good(gateways, tmp_path: Path) -> None:
    watchdog = 0.2
    path = tmp_path / "packets.csv"
    g = gateways(BROKK, HYDRAULIC.with_options(watchdog_s=watchdog), log=path)
    assert g.ask(heartbeat(0)).state == "running"
    time.sleep(0.4)
    fb = g.ask(Message(kind="setpoint", seq=1, t=0.0, q=tuple(BROKK.q_home + 0.1)))
    assert (fb.state, fb.reason, fb.ack) == ("stopped", "watchdog", -1)
    assert g.ask(heartbeat(2)).state == "stopped"
    stats = g.stop()
    assert [r for _, r in stats.stops] == ["watchdog"]
    stop_t = stats.stops[0][0]
    handled = [
        float(r["t"]) for r in log_rows(path) if (r["direction"], r["status"]) == ("in", "ok")
    ]
    t_last_in = max(t for t in handled if t <= stop_t)  # the registering heartbeat, gateway clock
    assert watchdog - 1e-5 <= stop_t - t_last_in < watchdog + 0.15
    assert stop_t < stats.t_end
    assert "stop: watchdog at" in str(stats)


def test_a_datagram_after_a_stall_past_the_watchdog_does_not_resume_motion(
    gateways, monkeypatch
) -> None:
    stall, stalling = threading.Event(), threading.Event()

    def stalling_select(r, w, x, timeout):  # the gateway's loop, held up once on demand
        if stall.is_set():
            stall.clear()
            stalling.set()
            time.sleep(1.0)
        return select.select(r, w, x, timeout)

    monkeypatch.setattr(gateway_module, "select", SimpleNamespace(select=stalling_select))
    g = gateways(BROKK, HYDRAULIC.with_options(watchdog_s=0.2))
    assert g.ask(heartbeat(0)).state == "running"
    stall.set()
    assert stalling.wait(timeout=5.0)
    g.send(Message(kind="setpoint", seq=1, t=0.0, q=tuple(BROKK.q_home + 0.1)))  # in the stall
    fb = g.recv(timeout=5.0)
    assert (fb.state, fb.reason, fb.ack) == ("stopped", "watchdog", -1)
    stats = g.stop()
    assert [r for _, r in stats.stops] == ["watchdog"]
    assert np.allclose(stats.q, BROKK.q_home)


def test_a_stale_setpoint_after_another_senders_datagram_is_ignored(gateways) -> None:
    g = gateways(BROKK, HYDRAULIC)
    fb = g.ask(Message(kind="setpoint", seq=5, t=1.25, q=tuple(BROKK.q_home + 0.05)))
    assert (fb.ack, fb.echo_t) == (5, 1.25)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
        other.settimeout(5.0)
        other.sendto(encode(heartbeat(0), "hydraulic"), g.addr)
        assert decode(other.recv(65536), "hydraulic").ack == -1  # a new sender starts afresh
        other.sendto(encode(Message(kind="setpoint", seq=0, t=0.5, q=fb.q), "hydraulic"), g.addr)
        assert decode(other.recv(65536), "hydraulic").ack == 0
    stale = Message(kind="setpoint", seq=3, t=1.75, q=tuple(BROKK.q_home + 0.1))
    fb = g.ask(stale)
    assert (fb.ack, fb.echo_t) == (5, 1.25)  # the first sender's own last setpoint
    assert g.ask(Message(kind="setpoint", seq=6, t=2.0, q=fb.q)).ack == 6


def test_a_stop_message_stops_the_machine_with_its_reason(gateways) -> None:
    g = gateways(BROKK, HYDRAULIC)
    g.ask(heartbeat(0))
    fb = g.ask(Message(kind="stop", seq=1, t=0.0, reason="tracking error"))
    assert (fb.state, fb.reason) == ("stopped", "tracking error")
    fb = g.ask(Message(kind="setpoint", seq=2, t=0.0, q=tuple(BROKK.q_home + 0.1)))
    assert (fb.state, fb.reason, fb.ack) == ("stopped", "tracking error", -1)
    assert [r for _, r in g.stop().stops] == ["tracking error"]


def test_the_servo_steps_as_the_simulation_and_closes_the_valves_on_stop() -> None:
    joints = HydraulicJoints.for_robot(BROKK, dead_time=0.2, tau=0.1)
    ref = BROKK.q_home + 0.2
    t, q = joints.simulate([0.0, 1.0], [ref, ref], t_extra=0.0)
    servo = HydraulicServo(joints, ref)
    assert np.array_equal(np.array([servo.q.copy()] + [servo.step(ref).copy() for _ in t[1:]]), q)
    servo = HydraulicServo(joints, BROKK.q_home)
    for _ in range(100):
        servo.step(BROKK.q_home + 0.5)
    servo.stop()
    for _ in range(100):  # the commands in the dead time still act, then the flow dies out
        servo.step(BROKK.q_home + 0.5)
    before = servo.q.copy()
    servo.step(BROKK.q_home + 0.5)
    assert np.all(servo.q > BROKK.q_home)
    assert np.allclose(servo.q, before, atol=1e-4)


# ---------------------------------------------------------------------- rsi


def test_rsi_states_arrive_every_cycle_with_increasing_ipoc(gateways) -> None:
    g = gateways(KUKA, RSI_12MS)
    g.send(heartbeat(0))
    ipoc, times = [], []
    for k in range(40):
        state = g.recv()
        times.append(state.t)  # the gateway's clock
        ipoc.append(state.seq)
        g.send(heartbeat(k + 1, ack=state.seq))
    assert np.all(np.diff(ipoc) >= 1) and np.mean(np.diff(ipoc) == 1) > 0.9
    assert 0.010 < np.mean(np.diff(times)) < 0.02
    assert np.allclose(state.q, KUKA.q_home, atol=1e-7)
    assert g.stop().missed_cycles <= 10


def test_rsi_setpoints_move_the_ideal_servo_at_the_speed_limit(gateways) -> None:
    g = gateways(KUKA, RSI_12MS)
    target = KUKA.q_home.copy()
    target[0] += 0.4
    g.send(heartbeat(0))
    q1 = []
    for k in range(60):
        state = g.recv()
        q1.append(state.q[0])
        g.send(Message(kind="setpoint", seq=k + 1, t=0.0, q=tuple(target), ack=state.seq))
    steps = np.diff(q1)
    v_step = KUKA.velocity_limits[0] * RSI_12MS.cycle_s
    assert np.all(steps <= v_step + 1e-6) and np.all(steps >= -1e-9)
    assert np.isclose(steps, v_step, atol=1e-6).sum() >= 10
    assert q1[-1] == pytest.approx(target[0], abs=1e-6)
    assert np.allclose(state.q[1:], KUKA.q_home[1:], atol=1e-7)


def test_unanswered_rsi_states_are_missed_cycles_until_the_watchdog(gateways) -> None:
    g = gateways(KUKA, RSI.with_options(cycle_s=0.012, watchdog_s=0.2))
    g.send(heartbeat(0))
    time.sleep(0.5)
    stats = g.stop()
    states = []
    while True:
        try:
            states.append(g.recv(timeout=0.05))
        except TimeoutError:
            break
    assert [r for _, r in stats.stops] == ["watchdog"]
    assert 8 <= stats.missed_cycles <= 22  # 0.2 s of 12 ms cycles, none after the stop
    assert states[0].state == "running"
    assert (states[-1].state, states[-1].reason) == ("stopped", "watchdog")


def test_a_stopped_rsi_gateway_falls_silent_until_the_streamer_talks(gateways) -> None:
    watchdog = 0.2
    g = gateways(KUKA, RSI.with_options(cycle_s=0.012, watchdog_s=watchdog))
    g.send(heartbeat(0))
    time.sleep(1.0)  # the watchdog stops it at 0.2 s; states until 0.4 s, then none
    before = drain(g)
    g.send(heartbeat(1))
    after = drain(g)
    stats = g.stop()
    assert [r for _, r in stats.stops] == ["watchdog"]
    stop_t = stats.stops[0][0]
    assert (before[-1].state, before[-1].reason) == ("stopped", "watchdog")
    assert max(s.t for s in before) <= stop_t + watchdog + 1e-5
    assert after and all(s.state == "stopped" for s in after)
    assert max(s.t for s in after) > max(s.t for s in before)  # it answers again


# ------------------------------------------------------- faults, log, errors


def test_half_the_datagrams_are_lost_each_way(gateways) -> None:
    g = gateways(BROKK, HYDRAULIC, impair=Impairments(loss=0.5), seed=3)
    n = 200
    for k in range(n):
        g.send(heartbeat(k))
        time.sleep(0.0005)
    answers = len(drain(g, timeout=0.3))  # until the gateway is quiet
    stats = g.stop()
    answers += len(drain(g, timeout=0.05))  # all it sent is on the socket by now
    assert stats.received == n
    assert 70 <= stats.lost_in <= 130
    assert stats.lost_out + stats.sent == n - stats.lost_in
    assert answers == stats.sent
    assert 20 <= answers <= 85  # half in, half of the answers out: a quarter


def test_a_delay_holds_every_datagram_each_way(gateways) -> None:
    g = gateways(BROKK, HYDRAULIC, impair=Impairments(delay=0.1))
    t0 = time.monotonic()
    g.ask(heartbeat(0))
    assert 0.2 <= time.monotonic() - t0 < 0.5


def test_an_oversized_datagram_is_refused_on_arrival_not_queued(gateways, tmp_path: Path) -> None:
    path = tmp_path / "packets.csv"
    g = gateways(BROKK, HYDRAULIC, impair=Impairments(delay=0.3), log=path)
    g.send_raw(b"x" * 60_000)
    g.send(heartbeat(0))
    assert g.recv(timeout=5.0).kind == "feedback"
    stats = g.stop()
    assert (stats.received, stats.malformed, stats.sent) == (2, 1, 1)
    rows = log_rows(path)
    brief = [(r["direction"], r["status"], r["bytes"]) for r in rows[:2]]
    assert brief[0] == ("in", "malformed", "60000") and brief[1][:2] == ("in", "ok")
    assert float(rows[0]["t"]) + 0.3 <= float(rows[1]["t"]) + 1e-5  # not held by the delay


def test_datagrams_beyond_a_full_network_queue_are_lost(gateways, monkeypatch) -> None:
    monkeypatch.setattr(gateway_module, "MAX_PENDING", 5)
    g = gateways(BROKK, HYDRAULIC, impair=Impairments(delay=5.0))  # none released in the test
    for k in range(20):
        g.send(heartbeat(k))
    time.sleep(0.3)
    stats = g.stop()
    assert stats.lost_in == max(0, stats.received - 5)
    assert (stats.malformed, stats.sent) == (0, 0)


def test_an_answer_that_cannot_be_encoded_is_counted_and_dropped(gateways, monkeypatch) -> None:
    refused = threading.Event()

    def refuse(message: Message, profile: str) -> bytes:
        refused.set()
        raise ProtocolError("joint values must be finite")

    monkeypatch.setattr(gateway_module, "encode", refuse)
    g = gateways(BROKK, HYDRAULIC)
    g.send(heartbeat(0))
    assert refused.wait(timeout=5.0)
    stats = g.stop()  # the gateway ran on and ended normally
    assert (stats.received, stats.sent, stats.lost_out) == (1, 0, 1)


def test_reordered_datagrams_are_overtaken(gateways) -> None:
    g = gateways(BROKK, HYDRAULIC, impair=Impairments(reorder=1.0), seed=1)
    for k in range(20):
        g.send(heartbeat(k))
    order = [g.recv().seq for _ in range(20)]  # the gateway numbers its answers
    assert sorted(order) == list(range(20))
    assert order != sorted(order)


@pytest.mark.parametrize(
    "bad",
    [
        {"loss": 1.5},
        {"loss": 1.0},
        {"loss": -0.1},
        {"delay": 6.0},
        {"jitter": -1.0},
        {"reorder": 1.5},
    ],
)
def test_impossible_faults_are_refused(bad) -> None:
    with pytest.raises(InputError):
        Impairments(**bad)


def test_the_packet_log_has_a_row_per_datagram(gateways, tmp_path: Path) -> None:
    path = tmp_path / "packets.csv"
    g = gateways(BROKK, HYDRAULIC, log=path)
    g.send_raw(b"nonsense")
    g.ask(heartbeat(7, t=0.25))
    g.stop()
    rows = log_rows(path)
    assert list(rows[0]) == ["t", "direction", "kind", "seq", "ack", "bytes", "status"] + [
        f"q{i}" for i in range(1, 6)
    ]
    brief = [(r["direction"], r["kind"], r["seq"], r["status"]) for r in rows]
    assert brief == [
        ("in", "", "", "malformed"),
        ("in", "heartbeat", "7", "ok"),
        ("out", "feedback", "0", "ok"),
    ]
    assert float(rows[2]["q2"]) == pytest.approx(BROKK.q_home[1])
    assert rows[0]["bytes"] == "8"


def test_a_taken_port_is_an_input_error() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        with pytest.raises(InputError, match="cannot listen"):
            serve_gateway(KUKA, RSI, port=taken.getsockname()[1], stop_event=threading.Event())
