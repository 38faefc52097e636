"""Reading the user's files: devices, folders, size bounds, encodings, CSV fields, numbers."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError
from fabflow.files import (
    MAX_FIELD_CHARS,
    csv_rows,
    csv_table,
    input_file,
    numbers,
    read_text,
    show,
    text_lines,
)


def test_devices_folders_and_missing_files_are_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not a regular file"):
        input_file("/dev/zero", "DXF drawing")
    with pytest.raises(InputError, match="is a folder"):
        input_file(tmp_path)
    with pytest.raises(InputError, match="does not exist"):
        input_file(tmp_path / "nope.csv")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="not a regular file"):
        read_text(fifo)  # would block forever if opened


def test_size_bound(tmp_path: Path) -> None:
    f = tmp_path / "big.csv"
    f.write_bytes(b"x" * 2048)
    with pytest.raises(InputError, match="more than"):
        read_text(f, max_bytes=1024)
    assert len(read_text(f, max_bytes=4096)) == 2048


def test_not_utf8_names_the_line_without_echoing_content(tmp_path: Path) -> None:
    f = tmp_path / "r.csv"
    f.write_bytes(b"t,anchor,range\nsecret line\n0,A1,\xff\n")
    with pytest.raises(InputError) as exc:
        read_text(f, "ranges file")
    assert exc.value.location == "line 3" and "secret" not in str(exc.value)
    f.write_bytes(b"\xef\xbb\xbft,x\n1,2\n")
    assert read_text(f).startswith("t,x")


def test_oversize_csv_field_names_its_line() -> None:
    text = "a,b\n1,2\n" + "3," + "9" * (MAX_FIELD_CHARS + 1) + "\n"
    with pytest.raises(InputError, match="longer than") as exc:
        list(csv_rows(text, "f.csv"))
    assert exc.value.location == "line 3"


@settings(max_examples=200, deadline=None)
@given(st.text(max_size=300))
def test_csv_rows_never_raise_anything_but_input_error(text: str) -> None:
    try:
        rows = list(csv_rows(text, "f.csv"))
    except InputError:
        return
    assert all(line >= 1 and any(c.strip() for c in row) for line, row in rows)


def test_show_shortens() -> None:
    assert show("abc") == "'abc'"
    assert show("x" * 100, 10) == "'xxxxxxxxxx'..."


def test_nul_bytes_and_lone_cr_lines(tmp_path: Path) -> None:
    f = tmp_path / "r.csv"
    f.write_bytes(b"a,b\r1,2\r3,\x004\r")
    with pytest.raises(InputError, match="NUL byte") as exc:
        read_text(f, "ranges file")
    assert exc.value.location == "line 3"
    f.write_bytes(b"a\r\nb\rc\n\xff\n")
    with pytest.raises(InputError, match="not UTF-8") as exc:
        read_text(f)
    assert exc.value.location == "line 4"  # the same numbers as text_lines and csv_rows
    assert text_lines("a\r\nb\rc\nd") == ["a", "b", "c", "d"]
    assert [n for n, _ in csv_rows("a\r\nb\rc\n\nd", "f.csv")] == [1, 2, 3, 5]


def test_csv_rows_skips_comments_keeping_line_numbers() -> None:
    rows = list(csv_rows('# a "quoted, comment\nx,y\n  # indented\n1,2\n', "f.csv", "#"))
    assert rows == [(2, ["x", "y"]), (4, ["1", "2"])]


def test_numbers_at_once_with_the_line_of_a_bad_one() -> None:
    lines = [4, 5, 6]
    np.testing.assert_array_equal(
        numbers([" 1.5", "-2", "3e2"], lines, "f.csv", "x"), [1.5, -2, 300]
    )
    for bad, what in (("abc", "is not a number"), ("", "is empty"), ("nan", "is not finite")):
        with pytest.raises(InputError, match=what) as exc:
            numbers(["1", bad, "2"], lines, "f.csv", "x")
        assert exc.value.location == "line 5" and "column 'x'" in str(exc.value)
    got = numbers(["1", " ", "2"], lines, "f.csv", "x", allow_empty=True)
    assert np.isnan(got[1]) and got[2] == 2.0
    long = "9" * 400  # converted field by field, refused as infinite, quoted short
    with pytest.raises(InputError, match="not finite") as exc:
        numbers(["1", long, "1"], lines, "f.csv", "x")
    assert long not in str(exc.value)


def test_csv_table_bounds_rows_and_checks_the_header(tmp_path: Path) -> None:
    f = tmp_path / "t.csv"
    f.write_text("a,b\n1,2\n3,4\n5,6\n")
    table = csv_table(f, "table", 1000, max_rows=3)
    assert table.header == ["a", "b"] and table.columns["b"] == ("2", "4", "6")
    assert table.lines.tolist() == [2, 3, 4] and table.at(1) == "line 3"
    with pytest.raises(InputError, match="more than 2 data rows") as exc:
        csv_table(f, "table", 1000, max_rows=2)
    assert exc.value.location == "line 4"
    with pytest.raises(InputError, match="more than"):
        csv_table(f, "table", 10, max_rows=10)
    f.write_text("a,A\n1,2\n")
    with pytest.raises(InputError, match="column 'a' appears twice") as exc:
        csv_table(f, "table", 1000, 10, lower=True)
    assert exc.value.location == "line 1"
    f.write_text("a,b\n1,2\n3\n")
    with pytest.raises(InputError, match="expected 2 values like the header, got 1") as exc:
        csv_table(f, "table", 1000, 10)
    assert exc.value.location == "line 3"
    f.write_text("")
    with pytest.raises(InputError, match="empty"):
        csv_table(f, "table", 1000, 10)
