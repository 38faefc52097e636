"""The link's messages: round trips in both profiles, and nothing but ProtocolError from junk."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError
from fabflow.link.protocol import (
    MAX_DATAGRAM,
    PROFILES,
    Message,
    ProtocolError,
    decode,
    encode,
)
from fabflow.link.setpoints import read_setpoints

joints = st.lists(st.floats(-6.0, 6.0, allow_nan=False), min_size=1, max_size=12)
seqs = st.integers(0, 2**40)
times = st.floats(0.0, 1e6, allow_nan=False)


@given(
    kind=st.sampled_from(["setpoint", "feedback", "stop", "heartbeat"]),
    q=joints,
    seq=seqs,
    ack=seqs,
    t=times,
    profile=st.sampled_from(PROFILES),
    stopped=st.booleans(),
)
@settings(max_examples=200, deadline=None)
def test_every_message_comes_back_as_it_was_sent(kind, q, seq, ack, t, profile, stopped) -> None:
    if kind in ("stop", "heartbeat"):
        q = []
    state = "stopped" if stopped and kind == "feedback" else "running"
    m = Message(kind, seq, t, tuple(q), ack=ack, echo_t=t / 2 if kind == "feedback" else 0.0,
                state=state, reason="watchdog" if kind == "stop" else "")  # fmt: skip
    data = encode(m, profile)
    assert len(data) <= MAX_DATAGRAM
    back = decode(data, profile)
    assert (back.kind, back.seq, back.state, back.reason) == (m.kind, m.seq, m.state, m.reason)
    if profile == "rsi" and kind != "feedback":
        assert back.ack == ack  # the IPOC answered
    elif kind == "feedback" or profile == "hydraulic":
        assert back.ack == m.ack
    assert np.allclose(back.q, m.q, atol=2e-8, rtol=0)  # RSI: degrees with 6 decimals
    assert math.isclose(back.t, t, abs_tol=1e-6)


@given(data=st.binary(max_size=3000), profile=st.sampled_from(PROFILES))
@settings(max_examples=300, deadline=None)
def test_junk_is_refused_with_a_protocol_error_only(data: bytes, profile: str) -> None:
    try:
        decode(data, profile)
    except ProtocolError:
        pass


@given(
    cut=st.integers(0, 400),
    byte=st.integers(0, 255),
    profile=st.sampled_from(PROFILES),
)
@settings(max_examples=300, deadline=None)
def test_mutated_messages_are_refused_or_read_finite(cut: int, byte: int, profile: str) -> None:
    data = bytearray(encode(Message("feedback", 7, 1.5, (0.1, -0.2, 0.3), ack=6), profile))
    data[cut % len(data)] = byte
    try:
        m = decode(bytes(data), profile)
    except ProtocolError:
        return
    assert all(math.isfinite(v) for v in m.q) and math.isfinite(m.t)


@pytest.mark.parametrize(
    "body",
    [
        {"v": 2, "type": "setpoint", "seq": 1, "t": 0.0, "q": [0.0]},
        {"v": 1, "type": "launch", "seq": 1, "t": 0.0},
        {"v": 1, "type": "setpoint", "seq": 1, "t": 0.0},
        {"v": 1, "type": "setpoint", "seq": 1.5, "t": 0.0, "q": [0.0]},
        {"v": 1, "type": "setpoint", "seq": 1, "t": 0.0, "q": [1e400]},
        {"v": 1, "type": "setpoint", "seq": 1, "t": 0.0, "q": [0.0] * 13},
    ],
)
def test_bad_json_messages_are_named(body: dict) -> None:
    with pytest.raises(ProtocolError):
        decode(json.dumps(body).encode().replace(b"Infinity", b"1e400"), "hydraulic")


def test_oversized_datagrams_and_non_finite_values_are_refused() -> None:
    with pytest.raises(ProtocolError, match="bytes"):
        decode(b" " * (MAX_DATAGRAM + 1), "hydraulic")
    with pytest.raises(ProtocolError, match="finite"):
        encode(Message("setpoint", 1, 0.0, (float("nan"),)), "rsi")


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ("[1, 2]", "not a fabflow command stream"),
        ('{"format": "fabflow-command-stream", "version": 2}', "version 2"),
        ('{"format": "fabflow-command-stream", "version": 1, "robot": "r2d2"}', "unknown robot"),
        (
            '{"format": "fabflow-command-stream", "version": 1, "robot": "ur10e", "commands": []}',
            "setpoints",
        ),
        (
            '{"format": "fabflow-command-stream", "version": 1, "robot": "ur10e", "commands": '
            '[{"t": 0, "type": "setpoint", "q": [0, 0, 0]}]}',
            "6 finite joint values",
        ),
        (
            '{"format": "fabflow-command-stream", "version": 1, "robot": "ur10e", "commands": '
            '[{"t": 1, "type": "setpoint", "q": [0, 0, 0, 0, 0, 0]}, '
            '{"t": 0, "type": "setpoint", "q": [0, 0, 0, 0, 0, 0]}]}',
            "never decrease",
        ),
        (
            '{"format": "fabflow-command-stream", "version": 1, "robot": "ur10e", "commands": '
            '[{"t": 0, "type": "setpoint", "q": [0, 0, 0, 0, 0, 99]}]}',
            "joint limits",
        ),
        ("{not json", "not a JSON file"),
    ],
)
def test_bad_programs_are_input_errors(tmp_path, doc: str, match: str) -> None:
    path = tmp_path / "p.json"
    path.write_text(doc)
    with pytest.raises(InputError, match=match):
        read_setpoints(path)
