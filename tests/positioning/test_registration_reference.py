"""The vectorised registration returns what the loop-per-hypothesis one returned.

``tests/data/registration/reference.json`` holds the outputs of
``register_points`` and ``localize_three_point`` on seeded cases recorded
before their tests were vectorised (see ``generate.py`` there): poses,
covariances, residuals, test values and statuses must agree within 1e-9
relative, every decision exactly.

One exception, by design: with relative weights the leave-one-out fits were
three Gauss-Newton steps from the full fit, short of their optimum by up to
~1e-6 (relative) when a point is far off; they are now the exact weighted
Kabsch fits (rank-one downdates). Those fields are compared to the recording
within :data:`LOO_RTOL`, and to a brute-force refit of every subset within 1e-9.

A second, later one: the prism identification's distance test now leaves out
the directions its covariance does not determine
(:data:`fabflow.positioning.prism_match.RCOND`). Where the points lie nearly in
one plane its degrees of freedom drop, and the recorded statistic (in the tens
where a handful was due, so no order of the readings fitted) is replaced by a
smaller one; everything else must still agree.
"""

from __future__ import annotations

import json
import math
import runpy
from functools import cache
from typing import Any

import numpy as np
import pytest
from helpers import DATA

from fabflow.errors import LocalizationError
from fabflow.positioning.registration import register_points
from fabflow.positioning.three_point import localize_three_point

REFERENCE = DATA / "registration" / "reference.json"
RTOL = 1e-9
LOO_RTOL = 1e-5
"""Tolerance of the relative-weights leave-one-out fields against the recording."""
F_TEST_FIELDS = ("statistics", "loo_residuals", "p_value")


@cache
def reference() -> dict[str, Any]:
    return json.loads(REFERENCE.read_text())


# the generator's own summary: what was recorded is what is compared
summary = runpy.run_path(str(DATA / "registration" / "generate.py"))["summary"]


def scale_of(value: Any) -> float:
    """Largest magnitude in a (nested) list of numbers: the scale of its rounding."""
    if isinstance(value, list):
        return max((scale_of(v) for v in value), default=0.0)
    return abs(value) if isinstance(value, int | float) and not isinstance(value, bool) else 0.0


def assert_same(
    new: Any, old: Any, path: str, scale: float | None = None, rtol: float = RTOL
) -> None:
    """Equal structure, equal strings and decisions, numbers within ``RTOL`` relative.

    Numbers in an array are compared relative to the array's largest entry (a
    near-zero residual or off-diagonal covariance carries the rounding of the
    large ones); a number alone relative to itself.
    """
    if isinstance(old, dict) and path.endswith("prism_identification") and new != old:
        if new.get("dof") != old.get("dof"):
            assert new["dof"] < old["dof"], f"{path}: {new} != {old}"
            assert new["distance_test"] < old["distance_test"], f"{path}: {new} != {old}"
            assert new["assignment"].startswith("as given"), f"{path}: {new} != {old}"
            return
    if isinstance(old, dict):
        assert isinstance(new, dict) and set(new) == set(old), f"{path}: keys differ"
        f_test = old.get("test") == "F(3, 3n-9)"
        for key in old:
            tol = LOO_RTOL if f_test and key in F_TEST_FIELDS else rtol
            assert_same(new[key], old[key], f"{path}.{key}", rtol=tol)
    elif isinstance(old, list):
        assert isinstance(new, list) and len(new) == len(old), f"{path}: lengths differ"
        s = scale_of(old) if scale is None else scale
        for i, (a, b) in enumerate(zip(new, old, strict=True)):
            assert_same(a, b, f"{path}[{i}]", s, rtol)
    elif isinstance(old, bool) or old is None or isinstance(old, str):
        if isinstance(old, str) and isinstance(new, str) and old != new:
            # numbers inside messages are printed rounded; compare the words
            assert _words(new) == _words(old), f"{path}: {new!r} != {old!r}"
        else:
            assert new == old, f"{path}: {new!r} != {old!r}"
    else:
        assert isinstance(new, int | float), f"{path}: {new!r} is not a number"
        tol = rtol * max(abs(old), scale or 0.0)
        assert math.isclose(new, old, rel_tol=rtol, abs_tol=tol), f"{path}: {new!r} != {old!r}"


def _words(text: str) -> list[str]:
    return [w for w in text.replace("(", " ").replace(")", " ").split() if not _number(w)]


def _number(word: str) -> bool:
    try:
        float(word.strip(",;:=<>"))
    except ValueError:
        return False
    return True


def cases() -> list[tuple[str, dict[str, Any], dict[str, Any]]]:
    out = []
    for i, problem in enumerate(reference()["problems"]):
        for j, variant in enumerate(problem["variants"]):
            out.append((f"{i}-{j}", problem, variant))
    return out


@pytest.mark.parametrize(("name", "problem", "variant"), cases(), ids=[c[0] for c in cases()])
def test_register_points_matches_the_recorded_results(
    name: str, problem: dict[str, Any], variant: dict[str, Any]
) -> None:
    arrays = {"point_cov": np.array(problem["point_cov"])} if "point_cov" in problem else {}
    old = variant["result"]
    try:
        reg = register_points(
            np.array(problem["P"]), np.array(problem["M"]), **arrays, **variant["kwargs"]
        )
    except LocalizationError as exc:
        assert old.get("error") == type(exc).__name__ and old["message"] == exc.message
        return
    assert "error" not in old, old
    assert_same(summary(reg), old, name)


@pytest.mark.parametrize("k", range(8))
def test_three_point_matches_the_recorded_results(k: int) -> None:
    case = reference()["three_point"][k]
    reg = localize_three_point(
        np.array(case["points_world"]),
        np.array(case["p1"]),
        case["d"],
        point_cov=np.array(case["point_cov"]),
        base_sigma=case["base_sigma"],
    )
    assert_same(summary(reg), case["result"], f"three_point[{k}]")


def test_the_reference_covers_every_path() -> None:
    results = [v["result"] for p in reference()["problems"] for v in p["variants"]]
    statuses = {r["integrity"]["status"] for r in results if "integrity" in r}
    assert statuses == {"ok", "excluded", "failed"}
    assert any(len(r.get("rejected", ())) == 2 for r in results)
    assert any(r.get("outlier_test") and r["outlier_test"]["test"] == "F(3, 3n-9)" for r in results)
    checks = [r["integrity"]["checks"].get("prism_identification", {}) for r in results]
    assert any(c.get("assignment") == "reassigned" for c in checks)
