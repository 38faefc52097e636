"""The cabin built by a KR 60-3 defined in the project file, not taken from the catalogue.

The project is ``projects/cabin`` with ``robot.model: custom`` and the KR 60-3's
OPW parameters, limits, speeds, HOME, payload, reach and link capsules written
out in YAML. Its programs must be the catalogue robot's, byte for byte.
"""

from __future__ import annotations

from pathlib import Path

from custom_robots import KR60_CAPSULES, cabin_with, kr60

from fabflow.build.context import BuildContext
from fabflow.build.runner import run_build
from fabflow.project import load_project


def test_custom_kr60_writes_the_catalogue_robots_programs(
    cabin_build: tuple[Path, BuildContext], tmp_path: Path
) -> None:
    reference, _ = cabin_build
    project = load_project(cabin_with(kr60("opw", capsules=KR60_CAPSULES), tmp_path))
    assert project.robot.name.startswith("custom:kr60_from_yaml@")
    out = tmp_path / "out"
    run_build(project, out, until="program")
    expected = sorted(p.name for p in (reference / "programs").iterdir())
    written = sorted(p.name for p in (out / "programs").iterdir())
    assert written == expected and len(expected) > 10
    for name in expected:
        assert (out / "programs" / name).read_bytes() == (
            reference / "programs" / name
        ).read_bytes(), name
