"""``fabflow stream``: send a program's setpoints to a machine gateway and watch its feedback.

One loop on a UDP socket (:func:`stream`):

* **hydraulic** profile: the streamer is the clock; every cycle it sends the
  program's configuration at that time (a ``setpoint`` with a sequence number
  and its send time) and reads the ``feedback`` that answers it;
* **rsi** profile: the gateway is the clock; the streamer sends a heartbeat
  until the first state arrives, then answers every state with the setpoint
  of that moment, echoing its ``IPOC``.

The streamer **stops the machine** (sends a ``stop``, three times against
loss, and no setpoint after it) when no valid feedback came for the profile's
watchdog time, when a joint is further than the tracking bound from the
setpoint the feedback acknowledges, when the gateway reports the machine
stopped, when the machine has not settled on the last setpoint within the
settle timeout, or on Ctrl-C. The program has **completed** when the machine
is within the settling tolerance of the last setpoint; the streamer then
sends a ``stop`` with reason ``completed`` so the gateway's watchdog does not
fire. Every datagram sent and received is logged to a CSV.
"""

from __future__ import annotations

import csv
import socket
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np
from numpy.typing import NDArray

from fabflow.errors import InputError
from fabflow.link.profiles import LinkProfile
from fabflow.link.protocol import MAX_DATAGRAM, Message, ProtocolError, decode, encode
from fabflow.link.setpoints import Setpoints

FloatArray = NDArray[np.float64]

STOP_REPEATS = 3
"""A stop is sent this many times, one cycle apart (one lost datagram must not lose it)."""

LOG_COLUMNS = ("t", "direction", "kind", "seq", "ack", "bytes", "status")

MAX_RTT_SAMPLES = 100_000
"""Round trips kept for the report (the latest; a long stream's memory stays bounded)."""


@dataclass
class StreamReport:
    """What a stream did.

    Attributes
    ----------
    completed
        The machine reached the last setpoint; ``False``: the streamer stopped it.
    reason
        ``"completed"`` or why the machine was stopped.
    sent, received, malformed
        Datagrams sent, valid ones received, and invalid ones received (dropped).
    lost
        Setpoints that no feedback acknowledged (hydraulic), or gaps in the
        gateway's state counter (RSI): losses on the link either way.
    rtt_s
        Round-trip times of the acknowledged setpoints (s; hydraulic: send to
        feedback; RSI: answer to the state acknowledging it), one per newly
        acknowledged setpoint, the last :data:`MAX_RTT_SAMPLES` of them.
    max_error
        Largest joint difference seen between an acknowledged setpoint and the
        feedback (radians).
    duration_s
        Wall time of the stream (s).
    """

    completed: bool = False
    reason: str = ""
    sent: int = 0
    received: int = 0
    malformed: int = 0
    lost: int = 0
    rtt_s: deque[float] = field(default_factory=lambda: deque(maxlen=MAX_RTT_SAMPLES))
    max_error: float = 0.0
    duration_s: float = 0.0


class _Log:
    """The packet log: one CSV row per datagram."""

    def __init__(self, f: IO[str] | None, dof: int, t0: float) -> None:
        self.w = csv.writer(f) if f is not None else None
        self.t0 = t0
        if self.w is not None:
            self.w.writerow([*LOG_COLUMNS, *(f"q{i + 1}" for i in range(dof))])

    def row(self, direction: str, m: Message | None, n: int, status: str = "ok") -> None:
        if self.w is None:
            return
        head = [f"{time.monotonic() - self.t0:.6f}", direction]
        if m is None:
            self.w.writerow([*head, "", "", "", n, status])
        else:
            q = [f"{v:.9f}" for v in m.q]
            self.w.writerow([*head, m.kind, m.seq, m.ack, n, status, *q])


def stream(
    setpoints: Setpoints,
    address: tuple[str, int],
    profile: LinkProfile,
    log_path: Path | None = None,
    connect_timeout_s: float = 5.0,
) -> StreamReport:
    """Stream a program to a gateway until it completes or the streamer stops the machine.

    Parameters
    ----------
    setpoints
        The program's joint path.
    address
        The gateway's ``(host, port)``.
    profile
        The link's profile (its cycle, watchdog, tracking bound and settling).
    log_path
        Where to write the packet log (CSV); ``None``: no log.
    connect_timeout_s
        How long to wait for the gateway's first answer (s).

    Returns
    -------
    StreamReport
        ``completed`` is ``True`` only if the machine reached the last setpoint.
    """
    report = StreamReport()
    try:
        f = log_path.open("w", newline="", encoding="utf-8") if log_path is not None else None
    except OSError as e:
        raise InputError(f"cannot write the packet log: {e.strerror or e}", log_path) from None
    t_start = time.monotonic()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.connect(address)
        except OSError as e:
            if f is not None:
                f.close()
            raise InputError(f"cannot reach {address[0]}:{address[1]}: {e.strerror or e}") from None
        try:
            log = _Log(f, setpoints.q.shape[1], t_start)
            run = _Run(sock, setpoints, profile, report, log, connect_timeout_s)
            try:
                run.loop()
            except KeyboardInterrupt:
                run.stop("interrupted (Ctrl-C)")
            except OSError as e:  # the gateway's port closed (ICMP unreachable)
                run.stop(f"link error: {e.strerror or e}")
            except BaseException:  # never leave the machine on its last setpoint
                run.stop("internal error in the streamer")
                raise
        finally:
            if f is not None:
                f.close()
    report.duration_s = time.monotonic() - t_start
    return report


class _Run:
    """The state of one stream."""

    def __init__(
        self,
        sock: socket.socket,
        setpoints: Setpoints,
        profile: LinkProfile,
        report: StreamReport,
        log: _Log,
        connect_timeout_s: float,
    ) -> None:
        self.sock = sock
        self.sp = setpoints
        self.p = profile
        self.report = report
        self.log = log
        self.connect_timeout_s = connect_timeout_s
        self.seq = 0
        self.sent_q: dict[int, tuple[float, FloatArray]] = {}
        self.last_feedback: float | None = None
        self.newest_ack = -1
        self.newest_ack_sent: float | None = None
        self.last_state = -1
        self.t_program0: float | None = None
        self.q_final = setpoints.q[-1]
        self.stopped = False

    # ------------------------------------------------------------ sending
    def _send(self, m: Message) -> None:
        data = encode(m, self.p.name)
        try:
            self.sock.send(data)
        except OSError:
            self.log.row("out", m, len(data), "error")
            raise
        self.report.sent += 1
        self.log.row("out", m, len(data))

    def stop(self, reason: str, completed: bool = False) -> None:
        """Send the stop (repeated) and end the stream; no setpoint follows."""
        if self.stopped:
            return
        self.stopped = True
        self.report.completed = completed
        self.report.reason = reason
        for i in range(STOP_REPEATS):
            try:
                m = Message("stop", self.seq, self._now(), reason=reason, ack=self.last_state)
                self.seq += 1
                self._send(m)
                if i + 1 < STOP_REPEATS:
                    time.sleep(self.p.cycle_s)
            except (OSError, KeyboardInterrupt):  # a pending ICMP error, a second Ctrl-C
                continue

    def _now(self) -> float:
        return time.monotonic() - self.log.t0

    def _program_time(self) -> float:
        return 0.0 if self.t_program0 is None else time.monotonic() - self.t_program0

    def _setpoint(self, ack: int = -1) -> None:
        q = self.sp.at(self._program_time())
        t = self._now()
        self._send(Message("setpoint", self.seq, t, tuple(q), ack=ack))
        self.sent_q[self.seq] = (t, q)
        if len(self.sent_q) > 4096:  # keep what feedback can still acknowledge
            for k in sorted(self.sent_q)[:2048]:
                del self.sent_q[k]
        self.seq += 1

    # ------------------------------------------------------------ receiving
    def _receive(self, until: float) -> Message | None:
        """The next valid feedback before ``until`` (monotonic s), or ``None``."""
        while True:
            wait = until - time.monotonic()
            if wait <= 0:
                return None
            self.sock.settimeout(wait)
            try:
                data = self.sock.recv(MAX_DATAGRAM + 1)
            except TimeoutError:
                return None
            try:
                m = decode(data, self.p.name)
            except ProtocolError:
                self.report.malformed += 1
                self.log.row("in", None, len(data), "malformed")
                continue
            if m.kind != "feedback":
                self.report.malformed += 1
                self.log.row("in", m, len(data), "unexpected")
                continue
            self.report.received += 1
            self.log.row("in", m, len(data))
            return m

    def _check(self, m: Message) -> bool:
        """Take in one feedback; ``False`` when the stream must stop (already stopped)."""
        now = time.monotonic()
        self.last_feedback = now
        if m.state == "stopped":
            self.stop(f"the gateway stopped the machine: {m.reason or 'no reason given'}")
            return False
        q = np.asarray(m.q, dtype=float)
        if q.shape != self.q_final.shape:
            self.stop(f"feedback carries {q.size} joints, the program {self.q_final.size}")
            return False
        if m.ack in self.sent_q:
            t_sent, q_sent = self.sent_q[m.ack]
            if m.ack > self.newest_ack:
                self.newest_ack, self.newest_ack_sent = m.ack, t_sent
                self.report.rtt_s.append(self._now() - t_sent)
            err = float(np.max(np.abs(q - q_sent)))
            self.report.max_error = max(self.report.max_error, err)
            if err > self.p.tracking_bound:
                self.stop(
                    f"tracking error {err:.3f} rad beyond the bound {self.p.tracking_bound:g} rad"
                )
                return False
        t = self._program_time()
        if t > self.sp.duration:
            if float(np.max(np.abs(q - self.q_final))) <= self.p.settle_tolerance:
                self.stop("completed", completed=True)
                return False
            if t > self.sp.duration + self.p.settle_timeout_s:
                self.stop(f"the machine did not settle within {self.p.settle_timeout_s:g} s")
                return False
        return True

    def _watchdog(self, started: float) -> bool:
        """``False`` (and the machine stopped) when feedback is later than the watchdog."""
        now = time.monotonic()
        if self.last_feedback is None:
            if now - started > self.connect_timeout_s:
                self.stop(f"no answer from the gateway within {self.connect_timeout_s:g} s")
                return False
            return True
        if now - self.last_feedback > self.p.watchdog_s:
            self.stop(f"watchdog: no valid feedback for {now - self.last_feedback:.3f} s")
            return False
        if self.newest_ack_sent is not None:
            # feedback keeps coming, but about setpoints sent too long ago: a link that lags
            lag = self._now() - self.newest_ack_sent
            if lag > self.p.watchdog_s + self.p.cycle_s:
                self.stop(f"watchdog: the feedback is about setpoints {lag:.3f} s old")
                return False
        return True

    # ------------------------------------------------------------ loops
    def loop(self) -> None:
        if self.p.name == "rsi":
            self._loop_rsi()
        else:
            self._loop_hydraulic()

    def _loop_hydraulic(self) -> None:
        started = time.monotonic()
        next_send = started
        acked = -1
        while not self.stopped:
            now = time.monotonic()
            if now >= next_send:
                if self.t_program0 is None and self.last_feedback is not None:
                    self.t_program0 = now  # the program's clock starts with the link
                self._setpoint()
                next_send += self.p.cycle_s
                if next_send < now:  # fell behind (a stalled machine): skip, do not burst
                    next_send = now + self.p.cycle_s
            m = self._receive(min(next_send, now + self.p.cycle_s))
            if m is not None:
                if m.ack > acked + 1:
                    self.report.lost += m.ack - acked - 1
                acked = max(acked, m.ack)
                if not self._check(m):
                    return
            if not self._watchdog(started):
                return

    def _loop_rsi(self) -> None:
        started = time.monotonic()
        hello_due = started
        while not self.stopped:
            now = time.monotonic()
            if self.last_feedback is None and now >= hello_due:
                self._send(Message("heartbeat", self.seq, self._now()))
                self.seq += 1
                hello_due = now + 0.1
            m = self._receive(now + self.p.cycle_s)
            if m is not None:
                if self.t_program0 is None:
                    self.t_program0 = time.monotonic()
                if self.last_state >= 0 and m.seq > self.last_state + 1:
                    self.report.lost += m.seq - self.last_state - 1
                self.last_state = max(self.last_state, m.seq)
                if not self._check(m):
                    return
                self._setpoint(ack=m.seq)
            if not self._watchdog(started):
                return
