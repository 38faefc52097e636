"""The integrity record of a localization: was the pose tested, and did it pass?

Every pose fabflow estimates carries an :class:`Integrity`: the outcome of the
tests of :mod:`fabflow.positioning.adjustment_tests` (global test, w-tests,
MDBs, protection level) with the observations left out on the way. The
estimators iterate (test, exclude the worst with :func:`identify`, solve
again) while redundancy remains; :func:`record` writes the outcome, and the
method-specific checks (geometry, prism identification, consistency with the
planned station) are added to it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np

from fabflow.json_format import json_safe
from fabflow.positioning.adjustment_tests import ALPHA, TestResult, chi2_quantile

Status = Literal["ok", "excluded", "failed"]


@dataclass(frozen=True)
class Integrity:
    """The integrity record of a localization: was the pose tested, and did it pass?

    Attributes
    ----------
    status
        ``"ok"`` (every test passed), ``"excluded"`` (passed after leaving out the
        observations in ``excluded``) or ``"failed"`` (do not use the pose).
    reason
        Why, in one sentence, when not ``"ok"``.
    alpha
        Level of the tests.
    redundancy
        Degrees of freedom of the final solution.
    global_test
        ``{"statistic", "threshold", "p_value", "variance_factor", "passed"}``.
    w_test
        ``{"max", "threshold", "suspect", "passed"}``: the largest test value.
    excluded
        ``[{"observation": label, "w": value, "threshold": value}]`` in the order
        they were left out.
    mdb_max
        Largest minimal detectable bias over the tested hypotheses (metres).
    mdb
        The minimal detectable bias of each hypothesis tested (its units).
    protection_level
        ``{"horizontal": m, "vertical": m}``: the largest base shift a fault just
        below detection can cause.
    checks
        Further method-specific checks (geometry, prism identification, scale,
        filter statistics, consistency with the planned station).
    """

    status: Status
    reason: str = ""
    alpha: float = ALPHA
    redundancy: int = 0
    global_test: dict[str, Any] = field(default_factory=dict)
    w_test: dict[str, Any] = field(default_factory=dict)
    excluded: tuple[dict[str, Any], ...] = ()
    mdb_max: float | None = None
    protection_level: dict[str, float] = field(default_factory=dict)
    checks: dict[str, Any] = field(default_factory=dict)
    mdb: dict[str, float] = field(default_factory=dict)

    @property
    def failed(self) -> bool:
        """Whether the pose must not be used."""
        return self.status == "failed"

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-compatible data (non-finite numbers as ``None``)."""
        return json_safe(
            {
                "status": self.status,
                "reason": self.reason,
                "alpha": self.alpha,
                "redundancy": self.redundancy,
                "global_test": self.global_test,
                "w_test": self.w_test,
                "excluded": list(self.excluded),
                "mdb_max": self.mdb_max,
                "protection_level": self.protection_level,
                "mdb": self.mdb,
                "checks": self.checks,
            }
        )

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Integrity:
        """Inverse of :meth:`to_dict`."""
        return cls(
            status=d["status"],
            reason=d.get("reason", ""),
            alpha=float(d.get("alpha", ALPHA)),
            redundancy=int(d.get("redundancy", 0)),
            global_test=dict(d.get("global_test", {})),
            w_test=dict(d.get("w_test", {})),
            excluded=tuple(d.get("excluded", ())),
            mdb_max=d.get("mdb_max"),
            protection_level=dict(d.get("protection_level", {})),
            checks=dict(d.get("checks", {})),
            mdb={k: v for k, v in d.get("mdb", {}).items() if v is not None},
        )

    def failing(self, reason: str, **checks: Any) -> Integrity:
        """This record with status ``"failed"``, the reason, and further checks."""
        return replace(
            self,
            status="failed",
            reason=reason if not self.reason else f"{reason}; {self.reason}",
            checks={**self.checks, **checks},
        )

    def with_checks(self, **checks: Any) -> Integrity:
        """This record with further checks recorded (status unchanged)."""
        return replace(self, checks={**self.checks, **checks})


def record(
    test: TestResult,
    excluded: Sequence[dict[str, Any]] = (),
    alpha: float = ALPHA,
    checks: dict[str, Any] | None = None,
) -> Integrity:
    """The integrity record of a final solution and the exclusions that led to it."""
    k = test.worst
    w_max = float(test.w[k]) if k is not None and np.isfinite(test.w[k]) else None
    w_thr = float(test.thresholds[k]) if k is not None else None
    suspect = test.labels[k] if k is not None else None
    w_passed = w_max is None or w_thr is None or w_max <= w_thr
    h, vert = test.protection_level()
    units = test.units or ("m",) * len(test.mdb)
    metres = np.array([unit == "m" for unit in units], dtype=bool)
    finite_mdb = test.mdb[metres & np.isfinite(test.mdb)]
    if test.passed:
        status: Status = "excluded" if excluded else "ok"
        reason = (
            "left out " + ", ".join(str(e["observation"]) for e in excluded) if excluded else ""
        )
    else:
        status = "failed"
        if not test.global_passed and w_passed:
            reason = (
                f"global test failed: variance factor {test.variance_factor:.2f} "
                f"(T = {test.statistic:.1f} > {test.threshold:.1f}, {test.redundancy} dof)"
            )
        elif w_max is None or w_thr is None:
            reason = "the tests could not be evaluated (singular geometry)"
        else:
            reason = f"{suspect} fails its w-test ({w_max:.1f} > {w_thr:.1f})"
            if excluded:
                reason += " after leaving out " + ", ".join(str(e["observation"]) for e in excluded)
    return Integrity(
        status=status,
        reason=reason,
        alpha=alpha,
        redundancy=test.redundancy,
        global_test={
            "statistic": test.statistic,
            "threshold": test.threshold,
            "p_value": test.p_value,
            "variance_factor": test.variance_factor,
            "passed": test.global_passed,
        },
        w_test={"max": w_max, "threshold": w_thr, "suspect": suspect, "passed": w_passed},
        excluded=tuple(excluded),
        mdb_max=float(finite_mdb.max()) if finite_mdb.size else None,
        protection_level={"horizontal": h, "vertical": vert},
        checks=dict(checks or {}),
        mdb={
            label: v
            for label, v, finite in zip(
                test.labels, test.mdb.tolist(), np.isfinite(test.mdb).tolist(), strict=True
            )
            if finite
        },
    )


def guard_exclusion(integrity: Integrity, alert_limit: float) -> Integrity:
    """Fail a solution that passed only by leaving observations out, unless it stays reliable.

    Leaving out the observation with the largest w is right when the fault is
    really there; when the tests' hypotheses are alike (few anchors, weak
    geometry) another one may have been left out, and the remaining solution
    may no longer see the real fault. It is accepted only when its protection
    level is within ``alert_limit`` (metres): a fault it cannot see then moves
    the base by less than that. A solution that needed no exclusion keeps its
    status; a protection level beyond the limit is recorded as ``degraded``.
    """
    levels = [integrity.protection_level.get(k) for k in ("horizontal", "vertical")]
    pl = max(math.inf if v is None else float(v) for v in levels)
    if not math.isfinite(alert_limit) or pl <= alert_limit:
        return integrity
    if math.isfinite(pl):
        note = (
            f"protection level {1e3 * pl:.0f} mm exceeds the alert limit "
            f"{1e3 * alert_limit:.0f} mm: a fault the tests cannot see could move the base "
            "that far"
        )
    else:
        note = (
            "the protection level is unbounded: the observations left cannot see every "
            "fault, and one they miss could move the base by any amount"
        )
    if integrity.status == "excluded":
        return replace(integrity, status="failed", reason=f"{integrity.reason}, but {note}")
    return integrity.with_checks(degraded=note)


def identify(test: TestResult) -> int | None:
    """The hypothesis to exclude next: the worst one failing, if it can be excluded.

    Returns ``None`` when the tests pass, when nothing is left to test, or when
    the worst hypothesis cannot be excluded (the solution then stays failed).
    """
    if test.passed or test.redundancy <= 0:
        return None
    k = test.worst
    if k is None or not np.isfinite(test.w[k]) or not test.excludable[k]:
        return None
    return k


def consistency_tests(
    e: np.ndarray, C: np.ndarray, alpha: float
) -> tuple[np.ndarray, float, np.ndarray]:
    """Chi-square tests of differences ``e`` (n, k) with covariances ``C`` (n, k, k):
    the statistics, the threshold, whether each passed."""
    e = np.asarray(e, dtype=float)
    statistic = np.einsum("ni,nij,nj->n", e, np.linalg.pinv(np.asarray(C, dtype=float)), e)
    threshold = chi2_quantile(e.shape[-1], alpha)
    return statistic, threshold, statistic <= threshold


def unchecked(reason: str, alpha: float = ALPHA, **checks: Any) -> Integrity:
    """A failed record for a pose that could not be tested (no redundancy, bad input)."""
    return Integrity(status="failed", reason=reason, alpha=alpha, checks=dict(checks))


def exact(note: str) -> Integrity:
    """The record of a pose that is exact by construction (a noise-free simulation)."""
    return Integrity(status="ok", reason="", checks={"exact": note})
