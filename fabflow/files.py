"""Reading the user's files: regular, bounded, UTF-8, with the line of every problem.

Every reader of outside input (the project YAML, ranges, IMU records,
total-station observations, robot points, GSI, point clouds, DXF drawings)
opens its file here, so that one place refuses what must not be read:

- a path that is not a regular file (a folder, a device such as ``/dev/zero``,
  a pipe), which could block or never end;
- a file larger than the reader's bound (``max_bytes``): the work a file can
  ask for is bounded before it is read;
- text that is not UTF-8 (a byte order mark is fine), reported with its line;
- a NUL byte in a text file (a binary file given where text is expected);
- a CSV field over :data:`MAX_FIELD_CHARS` characters, reported with its line.

Each reader passes the bound that suits its file (a point cloud may be
hundreds of megabytes, a file of prism readings is a few kilobytes) and bounds
the rows it accepts; :func:`numbers` turns a column of text fields into finite
floats at once, naming the line of the first field that is not one.

Line numbers are those an editor shows: ``\\n``, ``\\r\\n`` and a lone ``\\r``
end a line (:func:`text_lines`).

Messages quote at most a short token of the file (:func:`show`), never whole
lines: the file may not be what the user thinks it is.
"""

from __future__ import annotations

import csv
import io
import json
import stat
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fabflow.errors import InputError

MAX_TEXT_BYTES = 64 * 2**20
"""Default bound of a text input file (bytes): far above any real record."""
MAX_FIELD_CHARS = 131_072
"""Longest CSV field (characters), Python's ``csv.field_size_limit()`` default."""
MAX_NUMBER_CHARS = 64
"""Longest field :func:`numbers` converts in one array; a column with a longer one is
converted field by field (an array of text is as wide as its longest field)."""


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


def line_at(data: bytes, offset: int) -> int:
    """1-based line of the byte at ``offset`` (``\\n``, ``\\r\\n`` or ``\\r`` end a line)."""
    head = data[:offset]
    return head.count(b"\n") + head.count(b"\r") - head.count(b"\r\n") + 1


def read_text(path: str | Path, what: str = "file", max_bytes: int = MAX_TEXT_BYTES) -> str:
    """The UTF-8 text of a regular file of at most ``max_bytes`` (byte order mark dropped).

    Raises
    ------
    InputError
        As :func:`input_file`, not UTF-8 (naming the line of the first bad
        byte), or holding a NUL byte (a binary file; naming its line).
    """
    data = read_bytes(path, what, max_bytes)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{what} is not UTF-8 text (byte 0x{data[exc.start]:02x})",
            path,
            f"line {line_at(data, exc.start)}",
        ) from None
    nul = data.find(b"\x00")
    if nul >= 0:
        raise InputError(
            f"{what} holds a NUL byte: a binary file, not text", path, f"line {line_at(data, nul)}"
        )
    return text


def text_lines(text: str) -> list[str]:
    """The lines of ``text`` as an editor numbers them (line ``k`` is item ``k - 1``).

    Unlike :meth:`str.splitlines`, only ``\\n``, ``\\r\\n`` and ``\\r`` end a line,
    so the numbers agree with :func:`csv_rows` and :func:`line_at`.
    """
    return text.replace("\r\n", "\n").replace("\r", "\n").split("\n")


def csv_rows(
    text: str, path: str | Path, comment: str | None = None
) -> Iterator[tuple[int, list[str]]]:
    """Non-blank rows of CSV text with their 1-based line numbers.

    Parameters
    ----------
    text
        The file's text.
    path
        The file, named in errors.
    comment
        Lines starting with this (after blanks) are skipped, e.g. ``"#"``.

    Raises
    ------
    InputError
        A malformed line or a field over :data:`MAX_FIELD_CHARS` characters,
        naming the line.
    """
    lines: Iterator[str] = iter(io.StringIO(text, newline=""))
    if comment is not None:
        lines = ("\n" if line.lstrip().startswith(comment) else line for line in lines)
    reader = csv.reader(lines)
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


@dataclass(frozen=True)
class CsvTable:
    """A CSV file with a header line: the header, and the data as columns.

    Attributes
    ----------
    source
        The file.
    header
        The column names, stripped (lower-case when read so).
    header_line
        1-based line of the header.
    lines
        ``(n,)`` 1-based line of each data row.
    columns
        The fields of each column, one per data row, as in the file.
    """

    source: str
    header: list[str]
    header_line: int
    lines: np.ndarray
    columns: dict[str, tuple[str, ...]]

    def __len__(self) -> int:
        return len(self.lines)

    def numbers(self, column: str, allow_empty: bool = False) -> np.ndarray:
        """The column as finite floats (see :func:`numbers`)."""
        return numbers(self.columns[column], self.lines, self.source, column, allow_empty)

    def at(self, k: int) -> str:
        """The location of data row ``k``, ``"line N"``."""
        return f"line {self.lines[k]}"


def csv_table(
    path: str | Path,
    what: str,
    max_bytes: int,
    max_rows: int,
    comment: str | None = None,
    lower: bool = False,
) -> CsvTable:
    """Read a CSV file with a header line into columns, bounded in bytes and rows.

    Parameters
    ----------
    path
        The file.
    what
        What the file is, for messages (``"ranges file"``).
    max_bytes
        Largest file read (see :func:`input_file`).
    max_rows
        Most data rows accepted.
    comment
        Lines starting with this are skipped (see :func:`csv_rows`).
    lower
        Lower-case the column names.

    Raises
    ------
    InputError
        As :func:`read_text` and :func:`csv_rows`; an empty file; more than
        ``max_rows`` data rows (naming the first line beyond); a duplicate
        column name; a row with another number of fields than the header.
    """
    rows = list(csv_rows(read_text(path, what, max_bytes), path, comment))
    if not rows:
        raise InputError(f"{what} is empty; expected a header line", path, "line 1")
    header_line, names = rows[0]
    header = [h.strip().lower() if lower else h.strip() for h in names]
    seen: set[str] = set()
    for name in header:
        if name in seen:
            raise InputError(f"column {show(name)} appears twice", path, f"line {header_line}")
        seen.add(name)
    data = rows[1:]
    if len(data) > max_rows:
        raise InputError(
            f"{what} has more than {max_rows} data rows, the most fabflow reads",
            path,
            f"line {data[max_rows][0]}",
        )
    lines = np.fromiter((line for line, _ in data), dtype=np.int64, count=len(data))
    fields = [row for _, row in data]
    width = np.fromiter(map(len, fields), dtype=np.int64, count=len(fields))
    bad = np.flatnonzero(width != len(header))
    if bad.size:
        k = int(bad[0])
        raise InputError(
            f"expected {len(header)} values like the header, got {width[k]}",
            path,
            f"line {lines[k]}",
        )
    by_column = list(zip(*fields, strict=True)) if fields else [()] * len(header)
    return CsvTable(
        str(path), header, header_line, lines, dict(zip(header, by_column, strict=True))
    )


def numbers(
    values: Sequence[str],
    lines: Sequence[int],
    path: str | Path,
    column: str,
    allow_empty: bool = False,
) -> np.ndarray:
    """A column of text fields as finite floats, converted at once.

    Parameters
    ----------
    values
        The fields, one per row.
    lines
        The 1-based line of each row.
    path
        The file, named in errors.
    column
        The column's name, named in errors.
    allow_empty
        Read a blank field as NaN (an optional value) instead of refusing it.

    Returns
    -------
    numpy.ndarray
        ``(len(values),)`` floats: finite, or NaN where a field is blank and allowed.

    Raises
    ------
    InputError
        A field that is not a number, or is NaN or infinite (``nan``, ``inf``,
        ``1e999``), naming the line and quoting the field (:func:`show`).
    """
    if len(values) == 0:
        return np.zeros(0)
    if max(map(len, values)) > MAX_NUMBER_CHARS:
        # one by one: an array of the fields is as wide as the longest of them
        out = _numbers_one_by_one(values, lines, path, column, allow_empty)
        return _finite(out, values, lines, path, column, allow_empty)
    text = np.asarray(values, dtype=str).reshape(-1)
    if allow_empty:
        text = np.where(np.char.str_len(np.char.strip(text)) == 0, "nan", text)
    try:
        out = text.astype(float)
    except ValueError:
        out = _numbers_one_by_one(values, lines, path, column, allow_empty)
    return _finite(out, values, lines, path, column, allow_empty)


def _finite(
    out: np.ndarray,
    values: Sequence[str],
    lines: Sequence[int],
    path: str | Path,
    column: str,
    allow_empty: bool,
) -> np.ndarray:
    """``out``, refusing a value that is not finite (a blank one may be NaN when allowed)."""
    for k in np.flatnonzero(~np.isfinite(out)).tolist():
        if not (allow_empty and not values[k].strip()):
            raise InputError(
                f"column {column!r}: {show(values[k])} is not finite", path, f"line {lines[k]}"
            )
    return out


def _numbers_one_by_one(
    values: Sequence[str],
    lines: Sequence[int],
    path: str | Path,
    column: str,
    allow_empty: bool,
) -> np.ndarray:
    """:func:`numbers` field by field, to name the first field that is not a number."""
    out = np.empty(len(values))
    for k, value in enumerate(values):
        if allow_empty and not value.strip():
            out[k] = np.nan
            continue
        try:
            out[k] = float(value)
        except ValueError:
            what = "is empty" if not value.strip() else "is not a number"
            raise InputError(
                f"column {column!r}: {show(value)} {what}", path, f"line {lines[k]}"
            ) from None
    return out


def strict_json(text: str) -> object:
    """``json.loads`` that refuses ``NaN``, ``Infinity`` and ``-Infinity``.

    Raises
    ------
    ValueError
        For text that is not JSON, holds one of those constants, or nests deeper
        than Python's recursion limit.
    """
    try:
        return json.loads(text, parse_constant=_no_constant)
    except RecursionError:
        raise ValueError("JSON nested too deeply") from None


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number")
