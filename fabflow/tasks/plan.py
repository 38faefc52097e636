"""The plan: stations where the platform parks and the work package of each visit.

``T_world_platform`` is the platform origin on the ground (z = ground height,
z axis up, x forward). The arm base of a station sits at
``T_world_base = T_world_platform @ Lift(station.lift) @ T_platform_base``
(:meth:`Station.T_world_base`, the chain of :mod:`fabflow.robots.platform`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fabflow.design.elements import Element
from fabflow.robots import platform


@dataclass(frozen=True, eq=False)
class Station:
    """A place the platform parks.

    Attributes
    ----------
    id
        Station id (``"S1"``, ...).
    T_world_platform
        4x4 planned platform pose in the world frame (metres).
    lift
        Lift height in metres above the platform's lowest position.
    """

    id: str
    T_world_platform: np.ndarray
    lift: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-compatible data."""
        return {
            "id": self.id,
            "T_world_platform": np.asarray(self.T_world_platform, dtype=float).tolist(),
            "lift": float(self.lift),
        }

    def T_world_base(self, T_platform_base: np.ndarray) -> np.ndarray:
        """Planned arm base pose in the world (metres) for the arm mounting ``T_platform_base``."""
        return platform.T_world_base(self.T_world_platform, self.lift, T_platform_base)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Station:
        """Inverse of :meth:`to_dict`."""
        return cls(
            id=str(d["id"]),
            T_world_platform=np.asarray(d["T_world_platform"], dtype=float).reshape(4, 4),
            lift=float(d.get("lift", 0.0)),
        )


@dataclass(frozen=True, eq=False)
class WorkPackage:
    """One station visit and the elements built during it, in build order.

    Attributes
    ----------
    index
        Position of the visit in the whole sequence (0-based).
    station
        Where the platform parks.
    elements
        Element ids in build order.
    T_world_targets
        (n, 4, 4) tool target poses in the world frame, one per element (for a
        block: the tool frame when the block is placed).
    travel
        Platform travel from the previous visit (metres, 0 for the first).
    """

    index: int
    station: Station
    elements: tuple[str, ...]
    T_world_targets: np.ndarray
    travel: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-compatible data."""
        return {
            "index": self.index,
            "station": self.station.to_dict(),
            "elements": list(self.elements),
            "T_world_targets": np.asarray(self.T_world_targets, dtype=float).tolist(),
            "travel": float(self.travel),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> WorkPackage:
        """Inverse of :meth:`to_dict`."""
        return cls(
            index=int(d["index"]),
            station=Station.from_dict(d["station"]),
            elements=tuple(d["elements"]),
            T_world_targets=np.asarray(d["T_world_targets"], dtype=float).reshape(-1, 4, 4),
            travel=float(d.get("travel", 0.0)),
        )


@dataclass(frozen=True, eq=False)
class Plan:
    """The whole plan: work packages in execution order, plus summary notes.

    ``split_elements`` holds the pieces of print paths that no single station
    can print (see :mod:`fabflow.tasks.split`): work packages name these pieces
    instead of their parent; :func:`fabflow.tasks.split.with_pieces` gives the
    element list to build from.
    """

    work_packages: tuple[WorkPackage, ...]
    notes: tuple[str, ...] = ()
    summary: dict[str, Any] = field(default_factory=dict)
    split_elements: tuple[Element, ...] = ()

    @property
    def stations(self) -> list[Station]:
        """Distinct stations in order of first visit."""
        seen: dict[str, Station] = {}
        for wp in self.work_packages:
            seen.setdefault(wp.station.id, wp.station)
        return list(seen.values())

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-compatible data (the schema of ``plan.json``)."""
        d: dict[str, Any] = {
            "work_packages": [wp.to_dict() for wp in self.work_packages],
            "notes": list(self.notes),
            "summary": self.summary,
        }
        if self.split_elements:
            d["split_elements"] = [e.to_dict() for e in self.split_elements]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Plan:
        """Inverse of :meth:`to_dict`."""
        return cls(
            work_packages=tuple(WorkPackage.from_dict(w) for w in d["work_packages"]),
            notes=tuple(d.get("notes", ())),
            summary=dict(d.get("summary", {})),
            split_elements=tuple(Element.from_dict(e) for e in d.get("split_elements", ())),
        )
