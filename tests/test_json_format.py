"""JSON text: what ``json`` reads back, never NaN, the structure indented, rows on one line."""

from __future__ import annotations

import json
import math

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from fabflow.json_format import json_safe, json_text

PLAIN = (
    st.none()
    | st.booleans()
    | st.integers(-(2**60), 2**60)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(alphabet=st.sampled_from('ab"[],{}: \\\n\u00e9'), max_size=6)
)
KEYS = st.text(max_size=4) | st.integers(-5, 5) | st.floats(-2.0, 2.0) | st.booleans() | st.none()
DATA = st.recursive(
    PLAIN,
    lambda inner: (
        st.lists(inner, max_size=5)
        | st.tuples(inner, inner)
        | st.dictionaries(KEYS, inner, max_size=4)
    ),
    max_leaves=30,
)


def _no_constant(name: str) -> None:
    raise AssertionError(f"{name} written as a JSON value")


@settings(max_examples=400, deadline=None)
@given(DATA)
@example({"NaN": None})  # a key may spell it; a value may not
def test_reads_back_as_json_writes_it(data) -> None:
    text = json_text(data)
    assert text.endswith("\n")
    json.loads(text, parse_constant=_no_constant)  # no NaN, Infinity or -Infinity value
    expected = json.loads(json.dumps(json_safe(data)))
    assert json.loads(text) == expected
    assert json.loads(json_text(data, indent=None)) == expected


@settings(max_examples=200, deadline=None)
@given(DATA)
@example([[{}], [1]])  # an empty dict has no bracket to count
@example([[[]], [1, 2]])
def test_a_line_holds_one_plain_list_or_one_key_or_item(data) -> None:
    # every line is a bracket, or one value (a key with it), never two containers
    for line in json_text(data).splitlines():
        stripped = line.strip().rstrip(",")
        if stripped.startswith("[") and len(stripped) > 2:
            row = json.loads(stripped)  # a whole list of plain values on the line
            assert all(not isinstance(v, list | dict) for v in row)


def test_rows_of_numbers_one_per_line_and_numpy_arrays() -> None:
    data = {
        "T": np.eye(4)[:2],
        "points": [[0.0, -1.5, 2], [3, 4, 5]],
        "empty": {},
        "none": [],
        "mixed": [1, [2, 3], {"a": [math.nan]}],
        "scalar": np.float64(1.25),
    }
    assert json_text(data) == (
        "{\n"
        '  "T": [\n'
        "    [1.0, 0.0, 0.0, 0.0],\n"
        "    [0.0, 1.0, 0.0, 0.0]\n"
        "  ],\n"
        '  "points": [\n'
        "    [0.0, -1.5, 2],\n"
        "    [3, 4, 5]\n"
        "  ],\n"
        '  "empty": {},\n'
        '  "none": [],\n'
        '  "mixed": [\n'
        "    1,\n"
        "    [2, 3],\n"
        "    {\n"
        '      "a": [null]\n'
        "    }\n"
        "  ],\n"
        '  "scalar": 1.25\n'
        "}\n"
    )
