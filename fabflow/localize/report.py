"""What ``fabflow localize`` reports: the rows of its summary, and the alert limit.

Plain data for the command line (:mod:`fabflow.cli` prints them): the pose with
its uncertainty, then the integrity block (status and reason, global test,
largest w-test, what was left out, protection level; docs/integrity.md).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from fabflow.errors import InputError
from fabflow.positioning.integrity import Integrity, guard_exclusion
from fabflow.positioning.result import BasePose
from fabflow.project import Project, Tolerances


def alert_limit_for(value: float | None, project: Project | None) -> float:
    """The alert limit (metres): ``--alert-limit``, else the project's position tolerance.

    Raises
    ------
    InputError
        A limit that is not a positive finite number.
    """
    if value is None:
        return (Tolerances() if project is None else project.tolerances).position
    if not (math.isfinite(value) and value > 0):
        raise InputError(
            f"expected a positive length in metres, got {value}", location="--alert-limit"
        )
    return value


def guarded(pose: BasePose, alert_limit: float) -> BasePose:
    """The pose with its exclusions judged against ``alert_limit`` (metres).

    A pose that passed its tests only by leaving observations out fails when its
    protection level exceeds the limit
    (:func:`~fabflow.positioning.integrity.guard_exclusion`).
    """
    if pose.integrity is None:
        return pose
    return replace(pose, integrity=guard_exclusion(pose.integrity, alert_limit))


def pose_rows(pose: BasePose) -> list[tuple[str, str]]:
    """Summary rows of a base pose: position, heading, sigmas, RMSE, then its integrity."""
    T = pose.T_world_base
    sd = np.sqrt(np.diag(pose.covariance))
    return [
        ("position (m)", ", ".join(f"{v:.4f}" for v in T[:3, 3])),
        ("heading (deg)", f"{np.degrees(np.arctan2(T[1, 0], T[0, 0])):.4f}"),
        ("sigma xyz (mm)", ", ".join(f"{1e3 * v:.2f}" for v in sd[:3])),
        ("sigma heading (deg)", f"{np.degrees(sd[5]):.4f}"),
        ("rmse (mm)", f"{1e3 * pose.rmse:.2f}"),
        *integrity_rows(pose.integrity),
    ]


def integrity_rows(integrity: Integrity | None) -> list[tuple[str, str]]:
    """Rows of the integrity block: status, tests, exclusions, protection level."""
    if integrity is None:
        return [("integrity", "untested")]
    rows = [("integrity", integrity.status + (f": {integrity.reason}" if integrity.reason else ""))]
    g = integrity.global_test
    if g.get("statistic") is not None and g.get("threshold") is not None:
        rows.append(
            (
                "global test",
                f"{g['statistic']:.1f} {'<=' if g['passed'] else '>'} {g['threshold']:.1f} "
                f"({integrity.redundancy} dof, variance factor {g['variance_factor']:.2f})",
            )
        )
    w = integrity.w_test
    if w.get("max") is not None:
        rows.append(
            (
                "largest w-test",
                f"{w['max']:.2f} {'<=' if w['passed'] else '>'} {w['threshold']:.2f} "
                f"({w['suspect']})",
            )
        )
    for e in integrity.excluded:
        rows.append(("left out", str(e["observation"])))
    pl = integrity.protection_level
    if "horizontal" in pl:
        rows.append(
            (
                "protection level (mm)",
                f"horizontal {_millimetres(pl.get('horizontal'))}, "
                f"vertical {_millimetres(pl.get('vertical'))}",
            )
        )
    reassigned = integrity.checks.get("prism_identification", {}).get("reassigned")
    if reassigned and reassigned not in (integrity.reason or ""):
        rows.append(("prisms", reassigned))
    if integrity.checks.get("degraded"):
        rows.append(("degraded", integrity.checks["degraded"]))
    return rows


def _millimetres(value: float | None) -> str:
    """A length in metres as millimetres; ``None`` or infinity (no bound) as ``unbounded``."""
    if value is None or not math.isfinite(value):
        return "unbounded"
    return f"{1e3 * value:.1f}"
