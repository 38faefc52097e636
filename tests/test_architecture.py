"""The layout holds: import contracts, one list per idea, small modules, a documented API.

docs/architecture.md describes the rooms and the direction of imports; these
tests keep the code to it.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
import typing
from pathlib import Path

import grimp
from helpers import ROOT

from fabflow.localize.methods import LOCALIZERS
from fabflow.programs.writers import WRITERS
from fabflow.project import LocalizationMethod, ProgramFormat, RobotName
from fabflow.robots.catalog import CUSTOM_MODEL, PROGRAM_FORMATS, ROBOT_NAMES, VENDORS, vendor_of

PACKAGE = ROOT / "fabflow"
MAX_MODULE_LINES = 600
LAZY_IMPORTERS = {"fabflow/__init__.py", "fabflow/cli.py"}
"""The modules allowed to import fabflow inside functions: the top-level API and the
command line load their imports on first use, so that starting up stays fast."""


def test_import_contracts_hold() -> None:
    result = subprocess.run(
        [str(Path(sys.executable).parent / "lint-imports"), "--no-cache"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert "0 broken" in result.stdout


def test_no_fabflow_import_inside_functions_and_no_importlib() -> None:
    offenders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import) and any(a.name == "importlib" for a in node.names):
                offenders.append(f"{rel}:{node.lineno} imports importlib")
            if rel in LAZY_IMPORTERS or not isinstance(
                node, ast.FunctionDef | ast.AsyncFunctionDef
            ):
                continue
            for sub in ast.walk(node):
                if isinstance(sub, ast.ImportFrom) and (sub.module or "").startswith("fabflow"):
                    offenders.append(f"{rel}:{sub.lineno} imports {sub.module} in {node.name}()")
    assert not offenders, "\n".join(offenders)


def test_modules_stay_small() -> None:
    big = {
        p.relative_to(ROOT).as_posix(): n
        for p in PACKAGE.rglob("*.py")
        if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES
    }
    assert not big, big


def test_one_list_of_robots_formats_and_methods() -> None:
    assert typing.get_args(RobotName) == (*ROBOT_NAMES, CUSTOM_MODEL)
    assert typing.get_args(ProgramFormat) == PROGRAM_FORMATS == tuple(WRITERS)
    assert set(typing.get_args(LocalizationMethod)) == set(LOCALIZERS)
    assert all(vendor_of(name) in VENDORS for name in ROBOT_NAMES)
    for fmt, writer in WRITERS.items():
        assert writer.format == fmt
        assert writer.vendor is None or VENDORS[writer.vendor].language == fmt


def test_every_module_is_reachable_from_a_command_or_documented() -> None:
    graph = grimp.build_graph("fabflow", include_external_packages=False)
    reached = {"fabflow.cli", "fabflow.__main__"}
    frontier = set(reached)
    while frontier:
        found = set()
        for module in frontier:
            found |= graph.find_modules_directly_imported_by(module)
        frontier = found - reached
        reached |= found
    api = (ROOT / "docs" / "api.md").read_text(encoding="utf-8")
    documented = set(re.findall(r"`(fabflow(?:\.\w+)+)`", api))
    packages = {m for m in graph.modules if graph.find_children(m)}
    orphans = sorted(graph.modules - reached - documented - packages)
    assert not orphans, f"not reachable from a command and not in docs/api.md: {orphans}"
