"""Reader for Leica GSI-8 and GSI-16 observation files.

A GSI file holds one block per line; a block is a sequence of words separated
by blanks. A word is a two-digit word index (WI), four characters of additional
information, a sign and 8 (GSI-8) or 16 (GSI-16, lines start with ``*``) data
characters. The last information character gives the unit.

Words read here:

=====  ===============================  ==========================================
WI     meaning                          units (last info character)
=====  ===============================  ==========================================
11     point id                         text, leading zeros dropped
21     horizontal angle Hz              2 gon, 3 decimal degrees, 4 DDD MM SS.s
22     vertical (zenith) angle V        as 21
31     slope distance                   0 m (1 mm), 1 ft (0.001 ft), 6 m (0.1 mm),
                                        7 ft (0.0001 ft), 8 m (0.01 mm)
81-83  target easting, northing, height as 31
84-86  station easting, northing, height as 31
87     reflector (prism) height         as 31
88     instrument height                as 31
=====  ===============================  ==========================================

Other words (codes 41-49, ppm 51, time 19, ...) are skipped. A block with Hz, V
and slope distance or with coordinates 81-83 is one observation; a block with
only station words sets the station. Angles use five implied decimals (gon and
decimal degrees) or tenths of a second (sexagesimal).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from fabflow.errors import InputError, UnsupportedError
from fabflow.files import read_bytes, show, text_lines
from fabflow.positioning.polar import (
    DEG,
    GON,
    MAX_COORDINATE_M,
    MAX_HEIGHT_M,
    MAX_READINGS,
    MAX_READINGS_BYTES,
    Observations,
    reading_problem,
)

_ANGLE_WORDS = {"21", "22"}
_LENGTH_WORDS = {"31", "81", "82", "83", "84", "85", "86", "87", "88"}
_LENGTH_UNITS = {"0": (1.0, 3), "1": (0.3048, 3), "6": (1.0, 4), "7": (0.3048, 4), "8": (1.0, 5)}


def _digits(digits: str) -> int:
    """The data of a numeric word as an integer; ValueError unless it is ASCII digits."""
    if not (digits.isascii() and digits.isdigit()):
        raise ValueError("invalid literal")
    return int(digits)


def _angle(unit: str, digits: str, negative: bool) -> float:
    value = _digits(digits)
    if unit == "2":
        rad = value * 1e-5 * GON
    elif unit == "3":
        rad = value * 1e-5 * DEG
    elif unit == "4":
        degrees, rest = divmod(value, 100000)
        minutes, tenth_seconds = divmod(rest, 1000)
        if minutes >= 60 or tenth_seconds >= 600:
            raise ValueError("minutes or seconds out of range in a sexagesimal angle")
        rad = (degrees + minutes / 60.0 + tenth_seconds / 36000.0) * DEG
    elif unit == "5":
        raise UnsupportedError("angles in mil (unit 5) are not supported; export gon or degrees")
    else:
        raise ValueError(f"unknown angle unit {unit!r} (expected 2 gon, 3 degrees, 4 DMS)")
    return -rad if negative else rad


def _length(unit: str, digits: str, negative: bool) -> float:
    if unit not in _LENGTH_UNITS:
        raise ValueError(f"unknown length unit {unit!r} (expected 0, 6, 8 metres or 1, 7 feet)")
    scale, decimals = _LENGTH_UNITS[unit]
    value = _digits(digits) * 10.0**-decimals * scale
    return -value if negative else value


def _parse_word(word: str, gsi16: bool) -> tuple[str, str, str, bool]:
    """Split one word into (WI, info, data, negative); raises ValueError if malformed."""
    expected = 16 if gsi16 else 8
    if len(word) != 7 + expected:
        raise ValueError(
            f"word {show(word, 30)} has {len(word)} characters, expected {7 + expected} "
            f"for GSI-{expected}"
        )
    wi, info, sign, data = word[:2], word[2:6], word[6], word[7:]
    if not (wi.isascii() and wi.isdigit()):
        raise ValueError(f"word {show(word, 30)} does not start with a two-digit word index")
    if sign not in "+-":
        raise ValueError(f"word {show(word, 30)} has no sign at position 7")
    return wi, info, data, sign == "-"


def parse_gsi(text: str, source: str | Path = "<string>") -> Observations:
    """Parse GSI-8 or GSI-16 text into :class:`~fabflow.positioning.polar.Observations`.

    Parameters
    ----------
    text
        The file contents.
    source
        File name for error messages.

    Raises
    ------
    InputError
        On a malformed word, an unknown unit, a block without point id, a
        station or instrument height beyond its bound, more than
        :data:`~fabflow.positioning.polar.MAX_READINGS` observations, or a
        file without observations; the message names the line.
    """
    ids: list[str] = []
    rows: list[list[float]] = []
    lines: list[int] = []
    station = [math.nan, math.nan, math.nan]
    instrument_height = 0.0
    for lineno, raw in enumerate(text_lines(text), start=1):
        line = raw.strip()
        if not line:
            continue
        gsi16 = line.startswith("*")
        words = line.lstrip("*").split()
        values: dict[str, float] = {}
        point_id: str | None = None
        for word in words:
            try:
                wi, info, data, negative = _parse_word(word, gsi16)
                if wi == "11":
                    point_id = data.lstrip("0") or "0"
                elif wi in _ANGLE_WORDS:
                    values[wi] = _angle(info[3], data, negative)
                elif wi in _LENGTH_WORDS:
                    values[wi] = _length(info[3], data, negative)
            except UnsupportedError as exc:
                raise UnsupportedError(exc.message, source, f"line {lineno}") from None
            except ValueError as exc:
                msg = str(exc)
                if "invalid literal" in msg:
                    msg = f"word {show(word, 30)}: data is not a number"
                raise InputError(msg, source, f"line {lineno}") from None
        for k, wi in enumerate(("84", "85", "86")):
            if wi in values:
                if abs(values[wi]) > MAX_COORDINATE_M:
                    raise InputError(
                        f"station coordinate (word {wi}) is beyond {MAX_COORDINATE_M:g} m",
                        source,
                        f"line {lineno}",
                    )
                station[k] = values[wi]
        if "88" in values:
            instrument_height = values["88"]
            if abs(instrument_height) > MAX_HEIGHT_M:
                raise InputError(
                    f"instrument height (word 88) {instrument_height:.6g} m is beyond "
                    f"{MAX_HEIGHT_M:g} m",
                    source,
                    f"line {lineno}",
                )
        has_polar = any(w in values for w in ("21", "22", "31"))
        has_coords = any(w in values for w in ("81", "82", "83"))
        if not (has_polar or has_coords):
            continue
        if point_id is None:
            raise InputError(
                "observation block has no point id (word 11)", source, f"line {lineno}"
            )
        if len(rows) == MAX_READINGS:
            raise InputError(
                f"more than {MAX_READINGS} observations, the most fabflow reads from a file",
                source,
                f"line {lineno}",
            )
        if has_polar and not all(w in values for w in ("21", "22", "31")):
            missing = [w for w in ("21", "22", "31") if w not in values]
            raise InputError(
                f"point {show(point_id)}: polar observation lacks word(s) {', '.join(missing)} "
                "(21 Hz, 22 V, 31 slope distance)",
                source,
                f"line {lineno}",
            )
        if has_coords and not has_polar and not all(w in values for w in ("81", "82", "83")):
            raise InputError(
                f"point {show(point_id)}: coordinates need all of words 81, 82, 83",
                source,
                f"line {lineno}",
            )
        ids.append(point_id)
        lines.append(lineno)
        rows.append(
            [values.get(w, math.nan) for w in ("21", "22", "31", "81", "82", "83")]
            + [values.get("87", 0.0)]
        )
    if not rows:
        raise InputError(
            "no observations found (expected blocks with words 21, 22, 31 or 81-83)", source
        )
    a = np.asarray(rows, dtype=float)
    station_xyz = np.asarray(station) if np.all(np.isfinite(station)) else None
    return Observations(
        point_ids=tuple(ids),
        hz=a[:, 0],
        v=a[:, 1],
        sd=a[:, 2],
        xyz=a[:, 3:6],
        prism_height=a[:, 6],
        instrument_height=instrument_height,
        station_xyz=station_xyz,
        source=str(source),
        lines=tuple(lines),
    )


def read_gsi(path: str | Path) -> Observations:
    """Read a Leica GSI-8/GSI-16 file; see :func:`parse_gsi`.

    The file holds at most :data:`~fabflow.positioning.polar.MAX_READINGS_BYTES`
    bytes. GSI is ASCII; its bytes are read as Latin-1, so that any byte is a
    character and a bad one is reported by :func:`parse_gsi` with its line. The
    readings are checked by :func:`~fabflow.positioning.polar.reading_problem`.
    """
    path = Path(path)
    obs = parse_gsi(read_bytes(path, "GSI file", MAX_READINGS_BYTES).decode("latin-1"), path)
    problem = reading_problem(obs)
    if problem is not None:
        raise InputError(problem[1], path, obs.at(problem[0]))
    return obs
