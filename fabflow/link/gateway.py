"""A simulated machine gateway (``fabflow machine-sim``): a UDP peer for ``fabflow stream``.

:func:`serve_gateway` listens on a UDP port and plays the machine behind it,
starting at rest at the robot's HOME:

* profile ``hydraulic``: paper 004's valve-driven joints
  (:class:`~fabflow.robots.hydraulic.HydraulicServo`, 1.3 s dead time, 0.3 s
  lag) stepped every 10 ms of wall-clock time. The streamer is the clock: every
  valid ``setpoint`` or ``heartbeat`` (and ``stop``) is answered with a
  ``feedback`` to its sender.
* profile ``rsi``: an ideal servo. The gateway is the clock: once a streamer
  has sent a valid message, it gets the machine's state every cycle with an
  increasing ``IPOC``; a setpoint answering the latest state (or the one
  before) is applied, the joints moving towards it at most at their speed
  limits; a state without an answer before the next one is a missed cycle.

A ``feedback`` carries the machine's joints, ``ack`` = the ``seq`` of the last
setpoint applied (setpoints older than it are not applied) and ``echo_t`` =
that setpoint's ``t`` (docs/link.md); its ``seq`` is the gateway's own counter
(RSI: the ``IPOC``). The ``ack`` is kept per sender: a setpoint is applied only
if its ``seq`` is above the last one applied from the same address, and a new
sender starts afresh at -1.

Either way a watchdog stops the machine once a registered streamer has been
silent for the profile's ``watchdog_s``, and a ``stop`` message stops it; a
stopped machine stays stopped (its feedback says so, with the reason) until the
gateway ends; a stopped RSI gateway stops sending states once the streamer has
been silent for ``watchdog_s`` since the stop (and sends again if it talks).
Datagrams that are not valid messages are counted and dropped.
:class:`Impairments` adds network faults (loss, delay, jitter, reordering) to
every datagram in both directions, drawn from a seeded generator.
"""

from __future__ import annotations

import contextlib
import csv
import heapq
import itertools
import math
import select
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Literal

import numpy as np
from numpy.typing import NDArray

from fabflow.errors import InputError
from fabflow.link.profiles import LinkProfile
from fabflow.link.protocol import MAX_DATAGRAM, Message, ProtocolError, decode, encode
from fabflow.robots.chain import RobotModel
from fabflow.robots.hydraulic import HydraulicJoints, HydraulicServo

FloatArray = NDArray[np.float64]

DEAD_TIME = 1.3
"""The simulated hydraulic machine's valve dead time (s), paper 004."""

TAU = 0.3
"""The simulated hydraulic machine's flow lag (s)."""

RECV_BUFFER = max(65536, 2 * MAX_DATAGRAM)
"""Receive buffer (bytes): larger than any UDP datagram, so one over
:data:`~fabflow.link.protocol.MAX_DATAGRAM` is seen whole and refused."""

MAX_DRAIN = 256
"""Most datagrams read off the socket in one pass, so a flood cannot stall the clock."""

MAX_PENDING = 10_000
"""Most datagrams held by the simulated network at once; beyond, one is lost."""

MAX_SENDERS = 64
"""Most senders whose last applied setpoint is remembered (:attr:`_Gateway.acks`)."""

Direction = Literal["in", "out"]
Address = tuple[str, int]


@dataclass(frozen=True)
class Impairments:
    """Network faults applied to every datagram, in both directions.

    Attributes
    ----------
    loss
        Fraction of datagrams dropped (0 to below 1).
    delay
        One-way delay added to every datagram (s, 0 to 5).
    jitter
        Extra delay drawn uniformly from ``[0, jitter]`` (s, 0 to 5).
    reorder
        Fraction of datagrams held back by 1 to 3 more cycles, so that later
        ones overtake them (0 to 1).

    Raises
    ------
    InputError
        For a value outside its range.
    """

    loss: float = 0.0
    delay: float = 0.0
    jitter: float = 0.0
    reorder: float = 0.0

    def __post_init__(self) -> None:
        ok = (
            0.0 <= self.loss < 1.0
            and 0.0 <= self.reorder <= 1.0
            and 0.0 <= self.delay <= 5.0
            and 0.0 <= self.jitter <= 5.0
        )
        if not ok:
            raise InputError(
                "network faults: need 0 <= loss < 1, 0 <= reorder <= 1, and a delay and "
                f"jitter of 0 to 5 s (got loss {self.loss}, delay {self.delay}, "
                f"jitter {self.jitter}, reorder {self.reorder})"
            )


@dataclass
class GatewayStats:
    """What a gateway saw and did (counts of datagrams unless said otherwise).

    Attributes
    ----------
    received
        Datagrams read off the socket (all of them: valid, malformed or lost).
    malformed
        Of those, the ones that were no valid message for this gateway (not of
        the profile's format or version, oversized, a ``feedback``, or with
        another number of joints than the robot's), dropped.
    lost_in
        Of those, the ones dropped by the simulated network (:class:`Impairments`,
        or more than :data:`MAX_PENDING` datagrams held).
    lost_out
        Answers dropped by the simulated network, or whose encoding or sending failed.
    sent
        Answers sent.
    missed_cycles
        RSI: states that got no valid answer before the next state (counted
        while the machine runs).
    stops
        ``(t, reason)`` of the machine's stop (t in s since the gateway started);
        empty while it runs. A stopped machine stays stopped, so at most one.
    q
        ``(dof,)`` the machine's joints when the gateway ended (radians).
    t_end
        When the gateway ended (s since it started).
    """

    received: int = 0
    malformed: int = 0
    lost_in: int = 0
    lost_out: int = 0
    sent: int = 0
    missed_cycles: int = 0
    stops: list[tuple[float, str]] = field(default_factory=list)
    q: FloatArray = field(default_factory=lambda: np.zeros(0))
    t_end: float = 0.0

    def __str__(self) -> str:
        stop = ", ".join(f"{r} at {t:.3f} s" for t, r in self.stops) or "none"
        q = " ".join(f"{v:.4f}" for v in self.q)
        return (
            f"{self.received} datagrams received ({self.malformed} malformed, {self.lost_in} "
            f"lost), {self.sent} sent ({self.lost_out} lost), {self.missed_cycles} missed "
            f"cycles, stop: {stop}; q [{q}] rad after {self.t_end:.3f} s"
        )


class _HydraulicMachine:
    """Paper 004's hydraulic joints, stepped by the wall clock."""

    def __init__(self, robot: RobotModel, q0: FloatArray) -> None:
        joints = HydraulicJoints.for_robot(robot, dead_time=DEAD_TIME, tau=TAU)
        self.servo = HydraulicServo(joints, q0)
        self.ref = q0.copy()
        self._steps = 0

    @property
    def q(self) -> FloatArray:
        return self.servo.q

    def advance(self, now: float) -> None:
        """Step the servo up to ``now`` (s since the start)."""
        target = math.floor(now / self.servo.joints.dt)
        while self._steps < target:
            self.servo.step(self.ref)
            self._steps += 1

    def stop(self) -> None:
        self.servo.stop()


class _IdealServo:
    """Joints that move towards the setpoint at their speed limits, one cycle at a time."""

    def __init__(self, robot: RobotModel, q0: FloatArray, cycle: float) -> None:
        self.q = q0.copy()
        self.ref = q0.copy()
        self._step = np.asarray(robot.velocity_limits, dtype=float) * cycle

    def advance(self, now: float) -> None:
        """Nothing: this servo moves on the gateway's cycle (:meth:`cycle`)."""

    def cycle(self) -> None:
        self.q = self.q + np.clip(self.ref - self.q, -self._step, self._step)

    def stop(self) -> None:
        self.ref = self.q.copy()


class _Gateway:
    """The state and event loop of one running gateway."""

    def __init__(
        self,
        robot: RobotModel,
        profile: LinkProfile,
        sock: socket.socket,
        impair: Impairments,
        seed: int,
        writer: Callable[[list[object]], object] | None,
    ) -> None:
        self.profile = profile
        self.sock = sock
        self.impair = impair
        self.rng = np.random.default_rng(seed)
        self.writer = writer
        self.stats = GatewayStats()
        q0 = np.asarray(
            robot.q_home if robot.q_home is not None else np.zeros(robot.dof), dtype=float
        )
        self.dof = robot.dof
        self.limits = np.asarray(robot.joint_limits, dtype=float)
        self.ideal = _IdealServo(robot, q0, profile.cycle_s) if profile.name == "rsi" else None
        self.machine: _HydraulicMachine | _IdealServo = (
            self.ideal if self.ideal is not None else _HydraulicMachine(robot, q0)
        )
        self.t0 = time.monotonic()
        self.addr: Address | None = None
        self.last_valid = 0.0
        self.out_seq = 0
        self.ack = -1
        self.ack_t = 0.0
        self.acks: dict[Address, tuple[int, float]] = {}
        self.reason = ""
        self.answered = True
        self.next_state = math.inf
        self.pending: list[tuple[float, int, Direction, bytes, Address, Message | None]] = []
        self.counter = itertools.count()

    # ------------------------------------------------------------------ loop
    def now(self) -> float:
        return time.monotonic() - self.t0

    def run(self, stop_event: threading.Event) -> None:
        while not stop_event.is_set():
            ready, _, _ = select.select([self.sock], [], [], self._timeout(self.now()))
            if ready:
                self._receive(self.now())
            now = self.now()
            self.machine.advance(now)
            self._release(now)
            self._watchdog(now)
            if self.profile.name == "rsi":
                self._rsi_tick(now)
                self._release(now)

    def _timeout(self, now: float) -> float:
        deadlines = [now + self.profile.cycle_s, self.next_state]
        if self.pending:
            deadlines.append(self.pending[0][0])
        if self.addr is not None and not self.stopped:
            deadlines.append(self.last_valid + self.profile.watchdog_s)
        return max(0.0, min(deadlines) - now)

    @property
    def stopped(self) -> bool:
        return bool(self.stats.stops)

    # ------------------------------------------------------------- datagrams
    def _receive(self, now: float) -> None:
        for _ in range(MAX_DRAIN):
            try:
                data, addr = self.sock.recvfrom(RECV_BUFFER)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                # E.g. an ICMP "port unreachable" reported on the next read: no datagram,
                # and a persistent error must not spin; the next select() tells.
                return
            self.stats.received += 1
            if len(data) > MAX_DATAGRAM:  # refused before it takes room in the queue
                self.stats.malformed += 1
                self._log(now, "in", None, data, "malformed")
            elif self.rng.random() < self.impair.loss:
                self.stats.lost_in += 1
                self._log(now, "in", _try_decode(data, self.profile), data, "lost")
            else:
                self._push(now, "in", data, addr[:2], None)

    def _push(
        self, now: float, direction: Direction, data: bytes, addr: Address, msg: Message | None
    ) -> None:
        if len(self.pending) >= MAX_PENDING:
            if direction == "in":
                self.stats.lost_in += 1
                msg = _try_decode(data, self.profile)
            else:
                self.stats.lost_out += 1
            self._log(now, direction, msg, data, "lost")
            return
        d = self.impair.delay
        if self.impair.jitter > 0:
            d += self.rng.uniform(0.0, self.impair.jitter)
        if self.impair.reorder > 0 and self.rng.random() < self.impair.reorder:
            d += int(self.rng.integers(1, 4)) * self.profile.cycle_s
        entry = (now + d, next(self.counter), direction, data, addr, msg)
        heapq.heappush(self.pending, entry)

    def _release(self, now: float) -> None:
        while self.pending and self.pending[0][0] <= now:
            _, _, direction, data, addr, msg = heapq.heappop(self.pending)
            if direction == "in":
                self._handle(data, addr, now)
                continue
            try:
                self.sock.sendto(data, addr)
            except OSError:
                self.stats.lost_out += 1
                self._log(now, "out", msg, data, "lost")
            else:
                self.stats.sent += 1
                self._log(now, "out", msg, data, "ok")

    def _send(self, msg: Message, addr: Address, now: float) -> None:
        try:
            data = encode(msg, self.profile.name)
        except ProtocolError:  # e.g. non-finite joints: counted, never a crash
            self.stats.lost_out += 1
            self._log(now, "out", msg, b"", "lost")
            return
        if self.rng.random() < self.impair.loss:
            self.stats.lost_out += 1
            self._log(now, "out", msg, data, "lost")
        else:
            self._push(now, "out", data, addr, msg)

    def _log(
        self, now: float, direction: Direction, msg: Message | None, data: bytes, status: str
    ) -> None:
        if self.writer is None:
            return
        head: list[object] = [f"{now:.6f}", direction]
        if msg is None:
            head += ["", "", ""]
        else:
            head += [msg.kind, msg.seq, msg.ack]
        q = [f"{v:.9g}" for v in (msg.q if msg is not None else ())]
        self.writer([*head, len(data), status, *q, *([""] * (self.dof - len(q)))])

    # --------------------------------------------------------------- machine
    def _handle(self, data: bytes, addr: Address, now: float) -> None:
        # A stalled loop may release a datagram after the watchdog's deadline: the
        # silence before it stops the machine before the datagram can count.
        self._watchdog(now)
        try:
            msg = decode(data, self.profile.name)
            if msg.kind == "feedback":
                raise ProtocolError("a gateway takes no feedback")
            if msg.q and len(msg.q) != self.dof:
                raise ProtocolError(f"{len(msg.q)} joint values for a robot of {self.dof}")
        except ProtocolError:
            self.stats.malformed += 1
            self._log(now, "in", None, data, "malformed")
            return
        self._log(now, "in", msg, data, "ok")
        if addr != self.addr:
            self._switch_sender(addr)
        self.last_valid = now
        if msg.kind == "stop":
            self._stop(now, msg.reason or "stop")
        if self.profile.name == "hydraulic":
            if msg.kind == "setpoint" and msg.seq > self.ack:
                self._apply(msg)
            self._send(self._feedback(self.out_seq, now), addr, now)
            self.out_seq += 1
            return
        if self.next_state == math.inf:
            self.next_state = now
        if self.out_seq > 0 and msg.ack == self.out_seq:
            self.answered = True
        answers = self.out_seq > 0 and msg.ack in (self.out_seq, self.out_seq - 1)
        if msg.kind == "setpoint" and answers and msg.seq > self.ack:
            self._apply(msg)

    def _switch_sender(self, addr: Address) -> None:
        """Answer ``addr`` from now on, with its own last applied setpoint (-1 if none)."""
        if self.addr is not None:
            self.acks[self.addr] = (self.ack, self.ack_t)
            while len(self.acks) > MAX_SENDERS:
                del self.acks[next(iter(self.acks))]
        self.ack, self.ack_t = self.acks.pop(addr, (-1, 0.0))
        self.addr = addr

    def _apply(self, msg: Message) -> None:
        if self.stopped:
            return
        q = np.clip(np.asarray(msg.q, dtype=float), self.limits[:, 0], self.limits[:, 1])
        self.machine.ref = q
        self.ack = msg.seq
        self.ack_t = msg.t

    def _feedback(self, seq: int, now: float) -> Message:
        return Message(
            kind="feedback",
            seq=seq,
            t=now,
            q=tuple(float(v) for v in self.machine.q),
            ack=self.ack,
            echo_t=self.ack_t,
            state="stopped" if self.stopped else "running",
            reason=self.reason,
        )

    def _stop(self, now: float, reason: str) -> None:
        if self.stopped:
            return
        self.stats.stops.append((round(now, 6), reason))
        self.reason = reason
        self.machine.stop()

    def _watchdog(self, now: float) -> None:
        if self.addr is None or self.stopped:
            return
        if now - self.last_valid > self.profile.watchdog_s:
            self._stop(now, "watchdog")

    def _rsi_tick(self, now: float) -> None:
        if self.ideal is None or self.addr is None or now < self.next_state:
            return
        if self.out_seq > 0 and not self.answered and not self.stopped:
            self.stats.missed_cycles += 1
        self.ideal.cycle()
        self.out_seq += 1
        self.answered = False
        # Once stopped, states only while the streamer talks (or just after the stop).
        since = max(self.last_valid, self.stats.stops[0][0]) if self.stopped else now
        if now - since <= self.profile.watchdog_s:
            self._send(self._feedback(self.out_seq, now), self.addr, now)
        self.next_state += self.profile.cycle_s
        if self.next_state <= now:
            self.next_state = now + self.profile.cycle_s


def _try_decode(data: bytes, profile: LinkProfile) -> Message | None:
    try:
        return decode(data, profile.name)
    except ProtocolError:
        return None


@contextlib.contextmanager
def _packet_log(path: Path | None, dof: int) -> Iterator[Callable[[list[object]], object] | None]:
    if path is None:
        yield None
        return
    try:
        f: IO[str] = path.open("w", newline="", encoding="utf-8")
    except OSError as e:
        raise InputError(f"cannot write the packet log: {e.strerror}", source=path) from None
    with f:
        writer = csv.writer(f)
        header = ["t", "direction", "kind", "seq", "ack", "bytes", "status"]
        writer.writerow(header + [f"q{i + 1}" for i in range(dof)])
        yield writer.writerow
        f.flush()


def serve_gateway(
    robot: RobotModel,
    profile: LinkProfile,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    impair: Impairments = Impairments(),
    seed: int = 0,
    on_ready: Callable[[int], None] | None = None,
    stop_event: threading.Event | None = None,
    log: Path | None = None,
) -> GatewayStats:
    """Run a simulated machine gateway until ``stop_event`` is set or Ctrl-C.

    Parameters
    ----------
    robot
        The machine; it starts at rest at its HOME (``robot.q_home``), and
        setpoints are clipped to its joint limits.
    profile
        ``hydraulic`` (the streamer is the clock; paper 004's valve-driven
        joints) or ``rsi`` (the gateway sends its state every ``cycle_s``; an
        ideal servo); its ``watchdog_s`` is the silence after which the
        machine stops.
    host, port
        Where to listen (UDP); port 0 takes any free port.
    impair
        Network faults applied to every datagram received and sent.
    seed
        Seed of the network faults.
    on_ready
        Called once with the bound port, when the gateway can be reached.
    stop_event
        Set it to end the gateway (checked at least every cycle).
    log
        CSV file of every datagram received or sent: ``t`` (s since the start),
        ``direction`` (in/out), ``kind``, ``seq``, ``ack``, ``bytes``,
        ``status`` (ok/malformed/lost) and the message's joint values
        ``q1..qn`` (radians).

    Returns
    -------
    GatewayStats
        Counts, the stop and the machine's final joints.

    Raises
    ------
    InputError
        If the address cannot be bound or the log cannot be written.
    """
    event = stop_event if stop_event is not None else threading.Event()
    with _packet_log(log, robot.dof) as writer:
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            try:
                sock.bind((host, port))
            except OSError as e:
                raise InputError(f"cannot listen on {host}:{port}: {e.strerror or e}") from None
            sock.setblocking(False)
            gateway = _Gateway(robot, profile, sock, impair, seed, writer)
            if on_ready is not None:
                on_ready(int(sock.getsockname()[1]))
            with contextlib.suppress(KeyboardInterrupt):
                gateway.run(event)
        finally:
            sock.close()
    gateway.stats.q = np.array(gateway.machine.q, dtype=float)
    gateway.stats.t_end = round(gateway.now(), 6)
    return gateway.stats
