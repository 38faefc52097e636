"""Hypothesis strategies that damage measurement files, and the checks every reader must pass.

Shared by ``tests/fuzz/``: each test starts from a valid sample file (``tests/data``
or one written by fabflow) and applies one to three mutations drawn here
(truncate, flip bytes, drop or repeat lines, replace numbers by NaN, infinity, huge,
tiny or negative ones, byte order mark, CRLF or CR line ends, an extremely long
field, an empty file, NUL and non-UTF-8 bytes, swapped header columns, junk).
:func:`check_reader` then runs the reader in-process and holds it to the rules of
issue 17: it returns, or raises a user error (exit code 2) that names the file and
quotes no more than a short token of it; it prints no numpy warning; and every
number it returns is finite.

By default every fuzz test runs a fixed set of examples (the same on every run);
``FABFLOW_FUZZ_EXAMPLES=2000`` runs that many fresh ones per test instead.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from fabflow.errors import FabflowError

NUMBER = re.compile(rb"[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
REPLACEMENTS = [
    b"nan",
    b"NaN",
    b"inf",
    b"-inf",
    b"1e308",
    b"-1e308",
    b"1e999",
    b"1e-320",
    b"0",
    b"-0",
    b"",
    b"-5",
    b"1e5",
    b"1000",
    b"0.000001",
    b"12345.678",
    b"9" * 400,
    b"x",
    b".nan",
    b".inf",
    b"1_000",
    b"\xd9\xa1\xd9\xa2",  # Arabic-Indic digits: a number to Python's float()
]
LONG_FIELD = b"9" * 200_000
"""Longer than Python's CSV field limit (131,072 characters)."""
MAX_MESSAGE = 600
"""Longest message (characters, without the file's path) a reader may print."""


def fuzz_settings(examples: int) -> settings:
    """Settings of a fuzz test: ``examples`` cases, the same on every run.

    With ``FABFLOW_FUZZ_EXAMPLES`` set, that many cases, drawn afresh on every run
    (``pytest --hypothesis-seed=N`` repeats one).
    """
    larger = os.environ.get("FABFLOW_FUZZ_EXAMPLES")
    return settings(
        max_examples=int(larger or examples),
        deadline=None,
        derandomize=larger is None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


def _lines(data: bytes) -> list[bytes]:
    return data.split(b"\n")


@st.composite
def mutated(draw: st.DrawFn, sample: bytes, line_ops: bool = True) -> bytes:
    """``sample`` after one to three mutations (see the module docstring)."""
    data = sample
    ops = ["trunc", "flip", "number", "number", "number", "bom", "crlf", "cr", "empty"]
    ops += ["nul", "latin1", "junk", "long"]
    if line_ops:
        ops += ["drop_line", "repeat_line", "swap_header", "drop_column"]
    for op in draw(st.lists(st.sampled_from(ops), min_size=1, max_size=3)):
        data = _apply(draw, op, data)
    return data


@st.composite
def renumbered(draw: st.DrawFn, sample: bytes) -> bytes:
    """``sample`` with one to four of its numbers replaced: the file stays readable, but odd.

    Replacements are the tokens of :data:`REPLACEMENTS` or drawn floats (any
    magnitude, NaN and infinity included), written as Python writes them.
    """
    data = sample
    values = st.one_of(
        st.sampled_from(REPLACEMENTS),
        st.floats(allow_nan=True, allow_infinity=True).map(lambda x: repr(x).encode()),
        st.floats(-1e4, 1e4).map(lambda x: f"{x:.6g}".encode()),
    )
    for _ in range(draw(st.integers(1, 4))):
        found = list(NUMBER.finditer(data))
        if not found:
            break
        m = found[draw(st.integers(0, len(found) - 1))]
        data = data[: m.start()] + draw(values) + data[m.end() :]
    return data


def _apply(draw: st.DrawFn, op: str, data: bytes) -> bytes:
    """One mutation of ``data``."""
    n = len(data)
    lines = _lines(data)
    where = draw(st.integers(0, max(n, 1)))
    if op == "trunc":
        return data[:where]
    if op == "flip" and n:
        out = bytearray(data)
        for k in draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=8)):
            out[k] = draw(st.integers(0, 255))
        return bytes(out)
    if op == "number":
        found = list(NUMBER.finditer(data))
        if not found:
            return data
        m = found[draw(st.integers(0, len(found) - 1))]
        return data[: m.start()] + draw(st.sampled_from(REPLACEMENTS)) + data[m.end() :]
    if op == "bom":
        return b"\xef\xbb\xbf" + data
    if op == "crlf":
        return data.replace(b"\n", b"\r\n")
    if op == "cr":
        return data.replace(b"\n", b"\r")
    if op == "empty":
        return b""
    if op == "nul":
        return data[:where] + b"\x00" + data[where:]
    if op == "latin1":
        return data[:where] + b"\xe9\xff\xfe" + data[where:]
    if op == "junk":
        return data[:where] + draw(st.binary(min_size=1, max_size=40)) + data[where:]
    if op == "long":
        return data[:where] + LONG_FIELD + data[where:]
    k = draw(st.integers(0, len(lines) - 1))
    if op == "drop_line":
        del lines[k]
    elif op == "repeat_line":
        lines[k:k] = [lines[k]] * draw(st.integers(1, 3))
    elif op == "swap_header" and lines:
        lines[0] = b",".join(reversed(lines[0].split(b",")))
    elif op == "drop_column" and lines:
        cols = lines[0].split(b",")
        j = draw(st.integers(0, len(cols) - 1))
        lines[0] = b",".join(cols[:j] + cols[j + 1 :])
    return b"\n".join(lines)


def all_finite(value: Any, skip: tuple[str, ...] = ()) -> bool:
    """Whether every number in ``value`` (arrays, dataclasses, pydantic models, ...) is finite.

    Fields named in ``skip`` are not looked at.
    """
    if isinstance(value, np.ndarray):
        return value.dtype.kind not in "fc" or bool(np.all(np.isfinite(value)))
    if isinstance(value, float):
        return math.isfinite(value)
    if isinstance(value, dict):
        return all(all_finite(v, skip) for k, v in value.items() if k not in skip)
    if isinstance(value, list | tuple):
        return all(all_finite(v, skip) for v in value)
    if hasattr(value, "model_dump"):
        return all_finite(value.model_dump(), skip)
    if dataclasses.is_dataclass(value):
        return all(
            all_finite(getattr(value, f.name), skip)
            for f in dataclasses.fields(value)
            if f.name not in skip
        )
    return True


def check_reader(
    read: Callable[[Path], Any],
    data: bytes,
    suffix: str,
    finite: Callable[[Any], bool] = all_finite,
) -> Any:
    """Run ``read`` on ``data`` written to a file; hold it to the rules (module docstring).

    Returns
    -------
    What the reader returned, or ``None`` when it refused the file.
    """
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"input{suffix}"
        path.write_bytes(data)
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            try:
                result = read(path)
            except FabflowError as exc:
                check_user_error(exc, path)
                return None
    assert finite(result), f"a non-finite number was returned for {data[:200]!r}"
    return result


def check_user_error(exc: FabflowError, path: Path) -> None:
    """A user error: exit code 2, naming ``path``, quoting at most a short token of it."""
    assert exc.exit_code == 2
    assert exc.source == str(path), f"the message does not name the file: {exc}"
    message = str(exc).replace(str(path), "")
    assert len(message) < MAX_MESSAGE, f"the message quotes too much: {message[:300]}"
    assert "9" * 100 not in message
