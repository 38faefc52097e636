"""Reading the user's files: regular, bounded, UTF-8, with the line of every problem.

Every reader of outside input (the project YAML, ranges, IMU records,
total-station observations, robot points, GSI, point clouds, DXF drawings)
opens its file here, so that one place refuses what must not be read:

- a path that is not a regular file (a folder, a device such as ``/dev/zero``,
  a pipe), which could block or never end;
- a file larger than the reader's bound (``max_bytes``): the work a file can
  ask for is bounded before it is read;
- text that is not UTF-8 (a byte order mark is fine), reported with its line;
- a CSV field over :data:`MAX_FIELD_CHARS` characters, reported with its line.

Messages quote at most a short token of the file (:func:`show`), never whole
lines: the file may not be what the user thinks it is.
"""

from __future__ import annotations

import csv
import io
import stat
from collections.abc import Iterator
from pathlib import Path

from fabflow.errors import InputError

MAX_TEXT_BYTES = 64 * 2**20
"""Default bound of a text input file (bytes): far above any real record."""
MAX_FIELD_CHARS = 131_072
"""Longest CSV field (characters), Python's ``csv.field_size_limit()`` default."""


def show(value: str, limit: int = 40) -> str:
    """``repr`` of a token from a file, shortened for a message."""
    return repr(value) if len(value) <= limit else repr(value[:limit]) + "..."


def input_file(path: str | Path, what: str = "file", max_bytes: int = MAX_TEXT_BYTES) -> Path:
    """The path of a regular, readable file of at most ``max_bytes``.

    Raises
    ------
    InputError
        Missing, not a regular file, unreadable, or too large; names the file.
    """
    path = Path(path)
    try:
        info = path.stat()
    except FileNotFoundError:
        raise InputError(f"{what} does not exist", path) from None
    except OSError as exc:
        raise InputError(f"cannot read {what}: {exc.strerror or exc}", path) from None
    if stat.S_ISDIR(info.st_mode):
        raise InputError(f"{what} is a folder, not a file", path)
    if not stat.S_ISREG(info.st_mode):
        raise InputError(f"{what} is not a regular file (a device, pipe or socket)", path)
    if info.st_size > max_bytes:
        raise InputError(
            f"{what} is {info.st_size / 2**20:.1f} MiB, more than the "
            f"{max_bytes / 2**20:.1f} MiB fabflow reads",
            path,
        )
    return path


def read_bytes(path: str | Path, what: str = "file", max_bytes: int = MAX_TEXT_BYTES) -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (see :func:`input_file`)."""
    path = input_file(path, what, max_bytes)
    try:
        with path.open("rb") as fh:
            data = fh.read(max_bytes + 1)
    except OSError as exc:
        raise InputError(f"cannot read {what}: {exc.strerror or exc}", path) from None
    if len(data) > max_bytes:  # grew while being read
        raise InputError(f"{what} is larger than the {max_bytes} bytes fabflow reads", path)
    return data


def read_text(path: str | Path, what: str = "file", max_bytes: int = MAX_TEXT_BYTES) -> str:
    """The UTF-8 text of a regular file of at most ``max_bytes`` (byte order mark dropped).

    Raises
    ------
    InputError
        As :func:`input_file`, or not UTF-8 (naming the line of the first bad byte).
    """
    data = read_bytes(path, what, max_bytes)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise InputError(
            f"{what} is not UTF-8 text (byte 0x{data[exc.start]:02x})", path, f"line {line}"
        ) from None


def csv_rows(text: str, path: str | Path) -> Iterator[tuple[int, list[str]]]:
    """Non-blank rows of CSV text with their 1-based line numbers.

    Raises
    ------
    InputError
        A malformed line or a field over :data:`MAX_FIELD_CHARS` characters,
        naming the line.
    """
    reader = csv.reader(io.StringIO(text, newline=""))
    while True:
        try:
            row = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            reason = str(exc)
            if "field larger than field limit" in reason:
                reason = f"a field is longer than {MAX_FIELD_CHARS} characters"
            raise InputError(
                f"not a valid CSV line: {reason}", path, f"line {reader.line_num}"
            ) from None
        if row and any(c.strip() for c in row):
            yield reader.line_num, row
