"""The messages between ``fabflow stream`` and a machine gateway, version 1 (docs/link.md).

Two profiles, one datagram per message, at most :data:`MAX_DATAGRAM` bytes:

* ``hydraulic`` (paper 004's retrofitted machine: a gateway between the control
  computer and the machine's CAN bus): UTF-8 JSON objects. The streamer is the
  clock: it sends a ``setpoint`` (or a ``stop``) every cycle; the gateway
  answers each with ``feedback``.
* ``rsi`` (a KUKA RSI-style exchange, the industry's common case): XML. The
  gateway (the robot controller) is the clock: every 4 or 12 ms it sends its
  state ``<Rob>`` with an ``IPOC`` counter; the streamer must answer within the
  cycle with ``<Sen>`` echoing that ``IPOC``. Joint values are degrees, as on a
  KUKA controller; ``AK`` carries the absolute joint setpoint (real RSI sends
  corrections; fabflow's gateway takes the setpoint itself), ``Stop`` 1 stops.

Every decoded message is a :class:`Message`; anything else, too long, of
another version or with non-finite numbers raises :class:`ProtocolError`, which
both sides count and drop.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Literal

from fabflow.errors import FabflowError
from fabflow.files import strict_json
from fabflow.json_format import json_text

VERSION = 1
"""The message format's version; a message of another version is refused."""

MAX_DATAGRAM = 2048
"""The largest message either side sends or accepts (bytes)."""

MAX_JOINTS = 12
"""The most joint values a message may carry."""

Kind = Literal["setpoint", "stop", "heartbeat", "feedback"]
KINDS: tuple[str, ...] = ("setpoint", "stop", "heartbeat", "feedback")

Profile = Literal["hydraulic", "rsi"]
PROFILES: tuple[str, ...] = ("hydraulic", "rsi")


class ProtocolError(FabflowError):
    """A datagram that is not a valid message of this version (counted and dropped)."""


@dataclass(frozen=True)
class Message:
    """One message of either profile, decoded.

    Attributes
    ----------
    kind
        ``setpoint``, ``stop``, ``heartbeat`` (streamer to gateway) or ``feedback``
        (gateway to streamer).
    seq
        The sender's sequence number (RSI: the ``IPOC``; an answer echoes it).
    t
        The sender's clock when it sent the message (s).
    q
        Joint values (radians): the setpoint, or the machine's measured joints.
    ack
        ``feedback``: the sequence number of the last setpoint the gateway applied
        (-1 before the first); ``setpoint`` of the RSI profile: the ``IPOC`` answered.
    echo_t
        ``feedback``: the ``t`` of that setpoint (for the round trip); else 0.
    state
        ``feedback``: ``"running"`` or ``"stopped"``.
    reason
        Why a ``stop`` was sent, or why the gateway stopped.
    """

    kind: Kind
    seq: int
    t: float
    q: tuple[float, ...] = ()
    ack: int = -1
    echo_t: float = 0.0
    state: str = "running"
    reason: str = ""


def _finite(values: list[float], what: str) -> tuple[float, ...]:
    if len(values) > MAX_JOINTS:
        raise ProtocolError(f"{what}: {len(values)} joint values, at most {MAX_JOINTS}")
    out = tuple(float(v) for v in values)
    if not all(math.isfinite(v) for v in out):
        raise ProtocolError(f"{what}: joint values must be finite")
    return out


def encode(message: Message, profile: Profile) -> bytes:
    """The datagram of a message in a profile's format.

    Raises
    ------
    ProtocolError
        For non-finite values, too many joints or a datagram over :data:`MAX_DATAGRAM`.
    """
    q = _finite(list(message.q), message.kind)
    if not (math.isfinite(message.t) and math.isfinite(message.echo_t)):
        raise ProtocolError("message times must be finite")
    if profile == "rsi":
        data = _encode_rsi(message, q)
    else:
        body: dict[str, object] = {"v": VERSION, "type": message.kind, "seq": int(message.seq)}
        body["t"] = round(message.t, 6)
        if q:
            body["q"] = [round(v, 9) for v in q]
        if message.kind == "feedback":
            body.update(ack=int(message.ack), echo_t=round(message.echo_t, 6), state=message.state)
        elif message.ack != -1:
            body["ack"] = int(message.ack)
        if message.reason:
            body["reason"] = message.reason[:200]
        data = json_text(body, indent=None).rstrip("\n").encode("utf-8")
    if len(data) > MAX_DATAGRAM:
        raise ProtocolError(f"message of {len(data)} bytes, more than {MAX_DATAGRAM}")
    return data


def decode(data: bytes, profile: Profile) -> Message:
    """The message in a datagram.

    Raises
    ------
    ProtocolError
        For anything that is not a valid message of this version and profile.
    """
    if len(data) > MAX_DATAGRAM:
        raise ProtocolError(f"datagram of {len(data)} bytes, more than {MAX_DATAGRAM}")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise ProtocolError("datagram is not UTF-8") from None
    if profile == "rsi":
        return _decode_rsi(text)
    try:
        body = strict_json(text)
    except (ValueError, RecursionError):
        raise ProtocolError("datagram is not JSON") from None
    if not isinstance(body, dict):
        raise ProtocolError("message must be a JSON object")
    if body.get("v") != VERSION:
        raise ProtocolError(f"message version {body.get('v')!r}, this side speaks {VERSION}")
    kind = body.get("type")
    if kind not in KINDS:
        raise ProtocolError(f"unknown message type {kind!r}")
    try:
        seq = _int(body.get("seq"))
        t = _float(body.get("t"))
        q = body.get("q", [])
        if not isinstance(q, list) or not all(isinstance(v, int | float) for v in q):
            raise ProtocolError("q must be a list of numbers")
        msg = Message(
            kind=kind,
            seq=seq,
            t=t,
            q=_finite(q, kind),
            ack=_int(body.get("ack", -1)),
            echo_t=_float(body.get("echo_t", 0.0)),
            state=str(body.get("state", "running"))[:20],
            reason=str(body.get("reason", ""))[:200],
        )
    except (TypeError, ValueError, OverflowError):
        raise ProtocolError("malformed message fields") from None
    if kind == "setpoint" and not msg.q:
        raise ProtocolError("a setpoint needs joint values")
    return msg


def _int(v: object) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not -(2**62) < v < 2**62:
        raise ValueError("not a bounded integer")
    return v


def _float(v: object) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ValueError("not a finite number")
    return float(v)


_AXES = ("A1", "A2", "A3", "A4", "A5", "A6", "A7", "A8", "A9", "A10", "A11", "A12")


def _axes_xml(tag: str, q: tuple[float, ...]) -> str:
    attrs = " ".join(f'{a}="{math.degrees(v):.6f}"' for a, v in zip(_AXES, q, strict=False))
    return f"<{tag} {attrs} />"


def _encode_rsi(m: Message, q: tuple[float, ...]) -> bytes:
    if m.kind == "feedback":
        stop = ' Stopped="1"' if m.state == "stopped" else ""
        reason = f"<Reason>{_xml_text(m.reason)}</Reason>" if m.reason else ""
        xml = (
            f'<Rob Type="fabflow" Version="{VERSION}"{stop}>{_axes_xml("AIPos", q)}'
            f"<Ack>{int(m.ack)}</Ack><T>{m.t:.6f}</T><EchoT>{m.echo_t:.6f}</EchoT>"
            f"{reason}<IPOC>{int(m.seq)}</IPOC></Rob>"
        )
    else:
        stop = 1 if m.kind == "stop" else 0
        axes = _axes_xml("AK", q) if q else ""
        reason = f"<Reason>{_xml_text(m.reason)}</Reason>" if m.reason else ""
        xml = (
            f'<Sen Type="fabflow" Version="{VERSION}">{axes}<Stop>{stop}</Stop>'
            f"<Seq>{int(m.seq)}</Seq><T>{m.t:.6f}</T>{reason}<IPOC>{int(m.ack)}</IPOC></Sen>"
        )
    return xml.encode("utf-8")


def _xml_text(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9 _.,:;()+\-/']", "_", s[:200])


_TAG = re.compile(
    r"<(Rob|Sen) Type=\"fabflow\" Version=\"(\d+)\"( Stopped=\"1\")?>(.*)</\1>\Z", re.S
)
_AX = re.compile(r"<(AIPos|AK) ((?:A\d{1,2}=\"[^\"]{1,32}\" ?){1,12})/>")
_ATTR = re.compile(r"A(\d{1,2})=\"([^\"]{1,32})\"")


def _field(body: str, name: str) -> str | None:
    m = re.search(rf"<{name}>([^<]{{0,200}})</{name}>", body)
    return m.group(1) if m else None


def _decode_rsi(text: str) -> Message:
    m = _TAG.match(text.strip())
    if m is None:
        raise ProtocolError("not an RSI message of fabflow's format")
    root, version, stopped, body = m.groups()
    if int(version) != VERSION:
        raise ProtocolError(f"message version {version}, this side speaks {VERSION}")
    q: tuple[float, ...] = ()
    ax = _AX.search(body)
    if ax is not None:
        pairs = sorted((int(i), v) for i, v in _ATTR.findall(ax.group(2)))
        if [i for i, _ in pairs] != list(range(1, len(pairs) + 1)):
            raise ProtocolError("axes must be A1..An without gaps")
        try:
            q = _finite([math.radians(float(v)) for _, v in pairs], root)
        except ValueError:
            raise ProtocolError("axis values must be numbers") from None
    try:
        ipoc = _int(int(_field(body, "IPOC") or "x"))
        t = _float(float(_field(body, "T") or "nan"))
        reason = _field(body, "Reason") or ""
        if root == "Rob":
            return Message(
                kind="feedback",
                seq=ipoc,
                t=t,
                q=q,
                ack=_int(int(_field(body, "Ack") or "x")),
                echo_t=_float(float(_field(body, "EchoT") or "nan")),
                state="stopped" if stopped else "running",
                reason=reason,
            )
        stop = _field(body, "Stop")
        if stop not in ("0", "1"):
            raise ProtocolError("Stop must be 0 or 1")
        kind: Kind = "stop" if stop == "1" else ("setpoint" if q else "heartbeat")
        return Message(
            kind=kind, seq=_int(int(_field(body, "Seq") or "x")), t=t, q=q, ack=ipoc, reason=reason
        )
    except (TypeError, ValueError, OverflowError):
        raise ProtocolError("malformed RSI message fields") from None
