"""Reading the user's files: devices, folders, size bounds, encodings, CSV fields."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError
from fabflow.files import MAX_FIELD_CHARS, csv_rows, input_file, read_text, show


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
