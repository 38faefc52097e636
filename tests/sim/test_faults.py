"""Fault injection: every fault above its MDB is caught, clean stations pass."""

from __future__ import annotations

import pytest
from helpers import PROJECTS

from fabflow.project import load_project
from fabflow.sim.faults import FAULTS, fault_study


@pytest.fixture(scope="module")
def projects():
    cabin = load_project(PROJECTS / "cabin")
    loc = cabin.localization.model_copy(update={"method": "total_station"})
    return {"uwb": cabin, "total_station": cabin.model_copy(update={"localization": loc})}


@pytest.mark.parametrize(
    ("method", "fault"), [(m, f) for m, faults in FAULTS.items() for f in faults]
)
def test_no_fault_above_its_mdb_passes_silently(projects, method: str, fault: str) -> None:
    r = fault_study(projects[method], method, fault, n=12, seed=3)
    assert r.injected == 12
    assert r.silently_wrong_above_mdb == 0
    if fault == "clean":
        # false alarms are rare (alpha = 0.001 per test) and clean poses are right
        assert r.failed + r.raised <= 1 and r.silently_wrong == 0
    elif fault in ("anchor NLOS", "random NLOS", "outside coverage"):
        assert r.failed + r.raised == 12
    elif fault in ("robot point off", "prism reading off"):
        # four prism points: the faulty one is found and left out, or the pose fails
        assert r.correctly_excluded + r.failed == 12 and r.correctly_excluded >= 8
