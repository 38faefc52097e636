"""Fuzz: DXF drawings with odd entities (ezdxf-written) or damaged bytes, read or refused."""

from __future__ import annotations

import io
import warnings

import ezdxf
from hypothesis import given
from hypothesis import strategies as st
from reader_mutations import check_reader, fuzz_settings, mutated

from fabflow.design.dxf_in import DxfWarning, read_dxf_contours

LAYER = {"layer": "PATH"}
WILD = st.one_of(
    st.floats(-1e4, 1e4),
    st.sampled_from([0.0, 1e-9, 1e12, -1e12, 1e300, float("nan"), float("inf"), -float("inf")]),
)
"""A coordinate in millimetres: mostly plausible, sometimes zero, huge or not finite."""
POINT = st.tuples(WILD, WILD)


def _text(doc: ezdxf.document.Drawing) -> bytes:
    stream = io.StringIO()
    doc.write(stream)
    return stream.getvalue().encode("utf-8")


@st.composite
def drawings(draw: st.DrawFn) -> bytes:
    """An ezdxf drawing of one to four entities with drawn (often odd) parameters."""
    doc = ezdxf.new("R2010", units=draw(st.sampled_from([0, 4, 6, 1])))
    doc.layers.add("PATH")
    msp = doc.modelspace()
    for kind in draw(
        st.lists(st.sampled_from(["line", "circle", "arc", "lw", "poly", "spline"]), max_size=4)
    ):
        if kind == "line":
            msp.add_line(draw(POINT), draw(POINT), dxfattribs=LAYER)
        elif kind == "circle":
            msp.add_circle(draw(POINT), draw(WILD), dxfattribs=LAYER)
        elif kind == "arc":
            msp.add_arc(draw(POINT), draw(WILD), draw(WILD), draw(WILD), dxfattribs=LAYER)
        elif kind == "lw":
            pts = draw(st.lists(st.tuples(WILD, WILD, st.just(0), st.just(0), WILD), max_size=6))
            msp.add_lwpolyline(pts, format="xyseb", close=draw(st.booleans()), dxfattribs=LAYER)
        elif kind == "poly":
            pts = draw(st.lists(POINT, max_size=6))
            msp.add_polyline2d(pts, close=draw(st.booleans()), dxfattribs=LAYER)
        else:
            pts = draw(st.lists(POINT, min_size=2, max_size=8))
            msp.add_spline(pts, dxfattribs=LAYER)
    return _text(doc)


def _read(path: object) -> object:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DxfWarning)
        return read_dxf_contours(path, require_closed=False)


@fuzz_settings(40)
@given(drawings())
def test_drawn_entities(data: bytes) -> None:
    check_reader(_read, data, ".dxf")


def _sample() -> bytes:
    doc = ezdxf.new("R2010", units=4)
    doc.layers.add("PATH")
    msp = doc.modelspace()
    msp.add_lwpolyline(
        [(0, 0, 0, 0, 0), (400, 0, 0, 0, 1), (400, 200, 0, 0, 0), (0, 200, 0, 0, 0)],
        format="xyseb",
        close=True,
        dxfattribs=LAYER,
    )
    msp.add_circle((1000, 0), 100, dxfattribs=LAYER)
    msp.add_spline([(0, 500), (100, 550), (200, 500), (300, 580)], dxfattribs=LAYER)
    msp.add_polyline2d([(3000, 0), (3300, 0), (3300, 300)], close=True, dxfattribs=LAYER)
    return _text(doc)


SAMPLE = _sample()


@fuzz_settings(40)
@given(st.one_of(mutated(SAMPLE), st.binary(max_size=300)))
def test_damaged_files(data: bytes) -> None:
    check_reader(_read, data, ".dxf")
