"""JSON text: finite numbers only, indented for reading, written at C speed.

Python's ``json`` module encodes in C only when it does not indent; indented, it
walks every number in Python, which made the build's large files (a print
path's elements and plan, about 3 MB each) one of its slowest steps.
:func:`json_text` indents only the structure: a list of plain values (numbers,
strings, booleans, null), a point or a pose row, is encoded in one C call and
written on one line. The files are also a third of the size they were with one
number per line.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

_PLAIN = (int, float, str, bool, type(None), np.generic)
"""Values written as they are: a list of only these goes on one line."""


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot serialise {type(obj).__name__} to JSON")


def json_safe(data: Any) -> Any:
    """``data`` with numpy arrays and scalars as lists and numbers, NaN and infinity as None.

    JSON has no NaN or infinity (Python's ``json`` would write the invalid
    tokens ``NaN`` and ``Infinity``); a number that is not available or not
    bounded is written as ``null``.
    """
    if isinstance(data, dict):
        return {k: json_safe(v) for k, v in data.items()}
    if isinstance(data, list | tuple):
        return [json_safe(v) for v in data]
    if isinstance(data, np.ndarray):
        return json_safe(data.tolist())
    if isinstance(data, np.generic):
        data = data.item()
    if isinstance(data, float) and not math.isfinite(data):
        return None
    return data


def json_text(data: Any, indent: int | None = 2) -> str:
    """JSON text of ``data`` (see :func:`json_safe`), with a final newline.

    Parameters
    ----------
    data
        JSON-compatible data, possibly holding numpy arrays, NaN or infinity.
    indent
        Spaces per level of dictionaries and of lists that hold lists or
        dictionaries; a list of plain values is written on one line. ``None``:
        all of it on one line.
    """
    try:  # most data holds only finite numbers: written as is, without a converted copy
        text = _text(data, indent)
    except ValueError:
        text = _text(json_safe(data), indent)
    return text + "\n"


def _text(data: Any, indent: int | None) -> str:
    if indent is None:
        return _encoder().encode(data)
    parts: list[str] = []
    _indented(data, 0, " " * indent, parts)
    return "".join(parts)


def _indented(value: Any, level: int, step: str, parts: list[str]) -> None:
    """Append the indented text of ``value`` at nesting ``level`` to ``parts``."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, dict) and value:
        inner = "\n" + step * (level + 1)
        parts.append("{")
        for i, (key, item) in enumerate(value.items()):
            parts.append(("," if i else "") + inner + _encoder().encode(_key(key)) + ": ")
            _indented(item, level + 1, step, parts)
        parts.append("\n" + step * level + "}")
    elif isinstance(value, list | tuple) and not all(isinstance(v, _PLAIN) for v in value):
        inner = "\n" + step * (level + 1)
        if isinstance(value[0], list | tuple) and (rows := _rows(value, inner)) is not None:
            parts.append(rows + "\n" + step * level + "]")
            return
        parts.append("[")
        for i, item in enumerate(value):
            parts.append(("," if i else "") + inner)
            _indented(item, level + 1, step, parts)
        parts.append("\n" + step * level + "]")
    else:
        parts.append(_encoder().encode(value))


def _rows(value: list | tuple, inner: str) -> str | None:
    """``value`` as a list of rows of plain values, one row per line, less its
    closing bracket; None if it is not one.

    One C call for all rows (a path of 10,000 points), where :func:`_indented`
    would make one per row; the text is the same.
    """
    text = _encoder().encode(value)
    if '"' in text or "{" in text or text.count("[") != len(value) + 1:
        return None  # a string (which may hold brackets), a row holding lists or dicts
    if not all(isinstance(row, list | tuple) for row in value):
        return None
    return "[" + inner + text[1:-1].replace("], [", "]," + inner + "[")


def _key(key: Any) -> str:
    """A dictionary key as ``json`` writes it (numbers, booleans and None as text)."""
    if isinstance(key, str):
        return key
    if not isinstance(key, int | float | None):
        raise TypeError(f"keys must be str, int, float, bool or None, not {type(key).__name__}")
    return _encoder().encode(key)


@functools.cache
def _encoder() -> json.JSONEncoder:
    """One encoder, reused (a program's stream writes thousands of lines)."""
    return json.JSONEncoder(default=_json_default, allow_nan=False)
