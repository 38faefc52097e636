"""The DXF reader's bounds: files that are not drawings, odd numbers, the work a drawing asks."""

from __future__ import annotations

import os
from pathlib import Path

import ezdxf
import pytest

from fabflow.design import dxf_in
from fabflow.design.dxf_in import read_dxf_contours
from fabflow.errors import InputError

PATH = {"layer": "PATH"}


def _save(tmp_path: Path, add) -> Path:
    doc = ezdxf.new("R2010", units=4)
    doc.layers.add("PATH")
    add(doc.modelspace())
    path = tmp_path / "d.dxf"
    doc.saveas(path)
    return path


def test_not_a_drawing(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe.dxf"
    os.mkfifo(fifo)
    device = tmp_path / "zero.dxf"
    device.symlink_to("/dev/zero")
    for path in (fifo, device):
        with pytest.raises(InputError, match="not a regular file"):
            read_dxf_contours(path)
    good = _save(tmp_path, lambda m: m.add_circle((0, 0), 100, dxfattribs=PATH))
    data = good.read_bytes()
    broken = data.replace(b"\n 40\n100.0\n", b"\n 40\n1OO.O\n")
    assert broken != data
    poly = _save(tmp_path, lambda m: m.add_lwpolyline([(0, 0), (5, 0), (5, 5)], dxfattribs=PATH))
    nul_type = poly.read_bytes().replace(b"\nLWPOLYLINE\n", b"\n\x00LWPOLYLINE\n")  # fuzz find
    for k, bad in enumerate((b"\x00\xff" * 300, b"hello\n", broken, nul_type)):
        path = tmp_path / f"bad{k}.dxf"
        path.write_bytes(bad)
        with pytest.raises(InputError) as exc:
            read_dxf_contours(path)
        assert exc.value.source == str(path) and len(str(exc.value)) < 400


@pytest.mark.parametrize(
    ("add", "what"),
    [
        (lambda m: m.add_circle((0, 0), 1e8, dxfattribs=PATH), "spans more than"),
        (lambda m: m.add_circle((1e13, 0), 10, dxfattribs=PATH), "beyond 1e\\+07 m"),
        (lambda m: m.add_line((0, 0), (float("nan"), 1), dxfattribs=PATH), "not finite"),
        (
            lambda m: m.add_arc((0, 0), 10, 0, float("inf"), dxfattribs=PATH),
            "angles are not finite",
        ),
        (
            lambda m: m.add_lwpolyline(
                [(0, 0, 0, 0, 1e7), (10, 0, 0, 0, 0)], format="xyseb", dxfattribs=PATH
            ),
            "spans more than",
        ),
        (
            lambda m: m.add_spline([(k, k % 7) for k in range(1200)], dxfattribs=PATH),
            "SPLINE with 1200 points",
        ),
    ],
)
def test_odd_entities_name_their_handle(tmp_path: Path, add, what: str) -> None:
    path = _save(tmp_path, add)
    with pytest.raises(InputError, match=what) as exc:
        read_dxf_contours(path, require_closed=False)
    assert (exc.value.location or "").startswith("entity ")


def test_the_work_is_bounded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def squares(m) -> None:
        for k in range(4):
            m.add_lwpolyline(
                [(k * 100, 0), (k * 100 + 50, 0), (k * 100 + 50, 50)], close=True, dxfattribs=PATH
            )

    path = _save(tmp_path, squares)
    assert len(read_dxf_contours(path)) == 4
    monkeypatch.setattr(dxf_in, "MAX_PATH_ENTITIES", 3)
    with pytest.raises(InputError, match="more than 3 entities"):
        read_dxf_contours(path)
    monkeypatch.undo()
    circle = _save(tmp_path, lambda m: m.add_circle((0, 0), 5000, dxfattribs=PATH))
    with pytest.raises(InputError, match="more than 500000 vertices"):
        read_dxf_contours(circle, flatten_tol=1e-12)  # a 5 m circle at a picometre
