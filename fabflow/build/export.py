"""``fabflow export``: a build's elements, plan and site layout as a Rhino or COMPAS file.

Reads a ``fabflow build`` output folder (:mod:`fabflow.build.export_inputs`),
optionally the simulated as-built poses of a ``fabflow simulate`` folder, makes
one :class:`~fabflow.design.export_data.StationRecord` per station of the plan
and hands it all to the writer the target's suffix names: ``.3dm``
(:func:`fabflow.design.rhino_out.write_3dm`) or ``.json``
(:func:`fabflow.design.compas_out.write_compas_json`). The file is written
beside the target and renamed into place.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fabflow.build.export_inputs import asbuilt_file, read_asbuilt, read_build_folder
from fabflow.design.compas_out import write_compas_json
from fabflow.design.export_data import StationRecord, platform_footprints
from fabflow.design.rhino_out import write_3dm
from fabflow.errors import InputError
from fabflow.tasks.plan import Plan

WRITERS: dict[str, tuple[str, Callable[..., Path]]] = {
    ".3dm": ("Rhino .3dm", write_3dm),
    ".json": ("COMPAS JSON", write_compas_json),
}
"""Export format by the target's suffix (lower case): its name and writer."""


@dataclass(frozen=True)
class ExportResult:
    """What an export wrote.

    Attributes
    ----------
    path
        The file.
    format
        ``"Rhino .3dm"`` or ``"COMPAS JSON"``.
    elements, unplanned, stations, anchors, setups, as_built
        How many of each it holds (``unplanned``: elements no station builds).
    size
        File size (bytes).
    seconds
        Time taken to read, check and write.
    """

    path: Path
    format: str
    elements: int
    unplanned: int
    stations: int
    anchors: int
    setups: int
    as_built: int
    size: int
    seconds: float

    def line(self) -> str:
        """One line for the terminal."""
        parts = [f"{self.elements} elements ({self.unplanned} unplanned)"]
        parts.append(f"{self.stations} stations")
        if self.anchors:
            parts.append(f"{self.anchors} UWB anchors")
        if self.setups:
            parts.append(f"{self.setups} instrument set-ups")
        if self.as_built:
            parts.append(f"{self.as_built} as-built poses")
        return (
            f"{self.format}: {', '.join(parts)}; {self.size / 1e6:.2f} MB in {self.seconds:.2f} s"
        )


def station_records(plan: Plan, footprint: tuple[float, float]) -> list[StationRecord]:
    """One record per station of ``plan``, in order of first visit.

    Parameters
    ----------
    plan
        The plan.
    footprint
        The platform's plan rectangle (length along its x, width along y; metres),
        centred on the platform origin.

    Returns
    -------
    list of StationRecord
        Pose of the first visit, the footprint's four corners at ground level
        (:func:`~fabflow.design.export_data.platform_footprints`), and the
        elements of every visit in build order.
    """
    stations = plan.stations
    built: dict[str, list[str]] = {s.id: [] for s in stations}
    for wp in plan.work_packages:
        built[wp.station.id].extend(wp.elements)
    if not stations:
        return []
    T = np.stack([np.asarray(s.T_world_platform, dtype=float) for s in stations])
    corners = platform_footprints(T, footprint)
    return [
        StationRecord(s.id, T[k], corners[k], tuple(built[s.id])) for k, s in enumerate(stations)
    ]


def export_format(target: Path) -> tuple[str, Callable[..., Path]]:
    """The format name and writer for ``target``'s suffix.

    Raises
    ------
    InputError
        For a suffix other than ``.3dm`` or ``.json``.
    """
    suffix = target.suffix.lower()
    if suffix not in WRITERS:
        raise InputError(
            f"unknown export format {suffix or '(no suffix)'!r}: "
            "expected .3dm (Rhino) or .json (COMPAS JSON)",
            target,
        )
    return WRITERS[suffix]


def _same_file(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def export_build(
    build_dir: str | Path, target: str | Path, asbuilt: str | Path | None = None
) -> ExportResult:
    """Export a build output folder to ``target`` (``.3dm`` or ``.json``).

    Parameters
    ----------
    build_dir
        A ``fabflow build`` output folder.
    target
        The file to write; replaced atomically.
    asbuilt
        A ``fabflow simulate`` output folder (or its ``asbuilt_run0.csv``): the
        simulated as-built poses of run 0 are exported too.

    Raises
    ------
    InputError
        For an unknown suffix, a target that is one of the files read, or a
        missing or malformed input (naming the file).
    UnsupportedError
        When the writer's library (rhino3dm, compas) is not installed.
    """
    t0 = time.perf_counter()
    target = Path(target)
    name, writer = export_format(target)
    build = read_build_folder(build_dir)
    as_built: dict[str, Any] = {}
    files = list(build.files)
    if asbuilt is not None:
        table = asbuilt_file(asbuilt)
        files.append(table)
        as_built = read_asbuilt(table)
        known = {e.id for e in build.elements}
        unknown = next((k for k in as_built if k not in known), None)
        if unknown is not None:
            raise InputError(
                f"element {unknown!r} is not in the build: the simulation was run on "
                "another design",
                table,
            )
    if any(_same_file(target, f) for f in files):
        raise InputError("is one of the export's inputs; choose another file name", target)
    stations = []
    if build.plan is not None and build.footprint is not None:
        stations = station_records(build.plan, build.footprint)
    writer(target, build.elements, stations, build.anchors, build.setups, as_built)
    planned = len({eid for s in stations for eid in s.elements})
    return ExportResult(
        path=target,
        format=name,
        elements=len(build.elements),
        unplanned=len(build.elements) - planned,
        stations=len(stations),
        anchors=len(build.anchors),
        setups=len(build.setups),
        as_built=len(as_built),
        size=target.stat().st_size,
        seconds=time.perf_counter() - t0,
    )
