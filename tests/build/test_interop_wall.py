"""The timber wall from COMPAS JSON and from Rhino .3dm: one plan, one set of programs,
and exports that read back as the same elements."""

from __future__ import annotations

import json
import runpy
import shutil
import subprocess
import sys

import numpy as np
import pytest
from helpers import PROJECTS

from fabflow.design.element_files import file_elements
from fabflow.design.specs import ElementFileSpec

WALL = PROJECTS / "timber_wall"


def _fabflow(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "fabflow", *args], capture_output=True, text=True, timeout=600
    )


@pytest.fixture(scope="module")
def builds(tmp_path_factory):
    """The example built from wall.json, and a copy built from the same wall drawn in Rhino."""
    root = tmp_path_factory.mktemp("wall")
    rhino = root / "rhino"
    rhino.mkdir()
    runpy.run_path(str(WALL / "make_wall.py"))["write_3dm"](rhino / "wall.3dm")
    text = (WALL / "project.yaml").read_text().replace("path: wall.json", "path: wall.3dm")
    assert "wall.3dm" in text
    (rhino / "project.yaml").write_text(text)
    out = {}
    for name, project in (("compas", WALL), ("rhino", rhino)):
        out[name] = root / f"out_{name}"
        result = _fabflow("build", str(project), "-o", str(out[name]))
        assert result.returncode == 0, result.stderr
    return out


def test_compas_and_rhino_walls_build_the_same(builds) -> None:
    a, b = builds["compas"], builds["rhino"]
    elements_a = json.loads((a / "elements.json").read_text())["elements"]
    elements_b = json.loads((b / "elements.json").read_text())["elements"]
    assert len(elements_a) == 50
    for ea, eb in zip(elements_a, elements_b, strict=True):
        assert ea["id"] == eb["id"] and ea["supports"] == eb["supports"]
        assert np.abs(np.subtract(ea["T_world_element"], eb["T_world_element"])).max() < 1e-9
    # the same plan: a box's centre from its corners and from a COMPAS frame may
    # differ in the last bit
    _same(json.loads((a / "plan.json").read_text()), json.loads((b / "plan.json").read_text()))
    programs_a = sorted(p.name for p in (a / "programs").iterdir())
    assert programs_a == sorted(p.name for p in (b / "programs").iterdir())
    assert programs_a
    for name in programs_a:
        assert (a / "programs" / name).read_bytes() == (b / "programs" / name).read_bytes()


def _same(x, y) -> None:
    """Equal JSON documents, numbers within 1e-9."""
    if isinstance(x, dict):
        assert x.keys() == y.keys()
        for k in set(x) - {"time_s"}:  # how long planning took
            _same(x[k], y[k])
    elif isinstance(x, list):
        assert len(x) == len(y)
        for u, v in zip(x, y, strict=True):
            _same(u, v)
    elif isinstance(x, float):
        assert x == pytest.approx(y, abs=1e-9, rel=0.0)
    else:
        assert x == y


@pytest.mark.parametrize("suffix", [".3dm", ".json"])
def test_exports_read_back_as_the_same_elements(builds, tmp_path, suffix) -> None:
    for name, out in builds.items():
        target = tmp_path / f"{name}{suffix}"
        result = _fabflow("export", str(out), "--to", str(target))
        assert result.returncode == 0, result.stderr
        back, given = file_elements(ElementFileSpec(path=target), 0, 1000)
        built = {e["id"]: e for e in json.loads((out / "elements.json").read_text())["elements"]}
        assert given  # the export names every block's supports
        assert {e.id for e in back} == set(built)
        for e in back:
            T = np.asarray(built[e.id]["T_world_element"])
            assert np.abs(e.T_world_element - T).max() < 1e-9
            assert np.abs(e.extents - built[e.id]["extents"]).max() < 1e-9
            assert list(e.supports) == built[e.id]["supports"]
            assert e.layer == built[e.id]["layer"] and e.part == built[e.id]["part"]


def test_the_example_files_are_what_make_wall_writes(tmp_path) -> None:
    shutil.copy(WALL / "make_wall.py", tmp_path / "make_wall.py")
    runpy.run_path(str(tmp_path / "make_wall.py"))["write_compas"](tmp_path / "wall.json")
    fresh, _ = file_elements(ElementFileSpec(path=tmp_path / "wall.json"), 0, 1000)
    shipped, _ = file_elements(ElementFileSpec(path=WALL / "wall.json"), 0, 1000)
    assert [e.id for e in fresh] == [e.id for e in shipped]
    for x, y in zip(fresh, shipped, strict=True):
        assert np.array_equal(x.T_world_element, y.T_world_element)
