"""YAML from users: nesting, duplicate keys, aliases, non-finite numbers, each with its line."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fabflow.errors import InputError
from fabflow.yaml_input import MAX_DEPTH, MAX_NODES, parse_yaml, read_yaml


@pytest.mark.parametrize(
    ("text", "line", "what"),
    [
        ("[" * 5000, "line 1", "nest deeper than"),
        ("a:\n" + "".join(" " * k + "- \n" for k in range(MAX_DEPTH + 2)), "line", "nest deeper"),
        ("a: 1\nb: 2\na: 3\n", "line 3", r"duplicate key 'a' \(first on line 1\)"),
        ("a: {b: 1, b: 2}\n", "line 1", "duplicate key 'b'"),
        ("a: &x [1, *x]\n", "line 1", "refers to the collection it is in"),
        ("a: .nan\n", "line 1", "'.nan' is not a finite number"),
        ("a:\n  - 1.0e+999\n", "line 2", "not a finite number"),
        ("a: " + "9" * 5000 + "\n", "line 1", "not a valid int"),
        ("a: !!timestamp 2020-99-99\n", "line 1", "not a valid timestamp"),
        ("a: 1\n\x01b: 2\n", "line 2", "does not allow the character #x0001"),
        ("a: [1, 2\n", "line 2", "does not parse"),
    ],
)
def test_refused_with_the_line(text: str, line: str, what: str) -> None:
    with pytest.raises(InputError, match=what) as exc:
        parse_yaml(text, "f.yaml", finite=True)
    assert exc.value.source == "f.yaml" and (exc.value.location or "").startswith(line)


def test_alias_bombs_are_bounded() -> None:
    rows = ["a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    rows += [
        f"{c}: &{c} [{', '.join([f'*{p}'] * 10)}]" for p, c in zip("abcdef", "bcdefg", strict=True)
    ]
    with pytest.raises(InputError, match=f"more than {MAX_NODES} values"):
        parse_yaml("\n".join(rows) + "\n", "f.yaml")
    assert parse_yaml("a: &a [1, 2]\nb: *a\n").data == {"a": [1, 2], "b": [1, 2]}


def test_merge_keys_are_not_duplicates_and_lines_are_found() -> None:
    doc = parse_yaml("base: &b {x: 1}\nitem:\n  <<: *b\n  x: 2\n  list:\n    - 5\n    - 6\n")
    assert doc.data["item"] == {"x": 2, "list": [5, 6]}
    assert doc.line_of(("item", "list", 1)) == 7
    assert doc.line_of(("item", "nope")) == 3  # an unknown key: its mapping
    assert doc.line_of(("item", "list", 9)) == 6
    assert parse_yaml("").data is None


def test_read_yaml_is_bounded(tmp_path: Path) -> None:
    f = tmp_path / "a.yaml"
    f.write_text("a: " + "x" * 2000 + "\n")
    with pytest.raises(InputError, match="more than"):
        read_yaml(f, "anchors file", max_bytes=1000)
    with pytest.raises(InputError, match="not a regular file"):
        read_yaml("/dev/zero")


@settings(max_examples=200, deadline=None, derandomize=True, database=None)
@given(st.text(alphabet="[]{}:,-&*!?|>'\"# \n\tab1.e+", max_size=200))
def test_anything_is_data_or_an_input_error(text: str) -> None:
    try:
        parse_yaml(text, "f.yaml", finite=True)
    except InputError as exc:
        assert exc.source == "f.yaml"
