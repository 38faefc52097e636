"""How the work is split: stations, work packages, build order."""

from fabflow.tasks.plan import Plan, Station, WorkPackage

__all__ = ["Plan", "Station", "WorkPackage"]
