"""What ``fabflow localize`` takes and reports: its numeric options, its summary, the alert limit.

Plain data for the command line (:mod:`fabflow.cli` prints them): the pose with
its uncertainty, then the integrity block (status and reason, global test,
largest w-test, what was left out, protection level; docs/integrity.md).
:func:`check_options` holds the numeric options of the three ``localize``
commands (and the same parameters of the library) to :data:`OPTION_BOUNDS`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from fabflow.errors import InputError
from fabflow.positioning.integrity import Integrity, guard_exclusion
from fabflow.positioning.polar import INSTRUMENT_BOUNDS, MAX_COORDINATE_M, MAX_HEIGHT_M
from fabflow.positioning.result import BasePose
from fabflow.project import Project, Tolerances

Bound = tuple[float, float, str, bool]
"""``(low, high, unit, low_open)``: a value in ``[low, high]``, or ``(low, high]``."""

_ANGLE: Bound = (-360.0, 360.0, "degrees", False)
_SITE: Bound = (-1e7, 1e7, "metres", False)
OPTION_BOUNDS: dict[str, tuple[Bound, ...]] = {
    "robot_sigma": ((0.0, 1.0, "metres", False),),
    **{name: ((low, high, unit, False),) for name, (low, high, unit) in INSTRUMENT_BOUNDS.items()},
    "instrument_height": ((-MAX_HEIGHT_M, MAX_HEIGHT_M, "metres", False),),
    "instrument_xyz": ((-MAX_COORDINATE_M, MAX_COORDINATE_M, "metres", False),) * 3,
    "instrument_abc_deg": (_ANGLE,) * 3,
    "tcp_xyz": ((-10.0, 10.0, "metres", False),) * 3,
    "init": (_SITE, _SITE, _ANGLE),
    "lift": ((-100.0, 100.0, "metres", False),),
}
"""Accepted values of the numeric options of ``fabflow localize`` (by parameter
name; one bound per component of a vector): finite, with the sign and size the
quantity can have. A robot sigma of more than a metre, a zero instrument sigma
(every covariance singular) or a prism 10 m from the flange is a mistake."""


def parse_numbers(text: str, option: str, names: str, units: str = "") -> tuple[float, ...]:
    """Comma-separated finite numbers given to ``option``, one per name in ``names``.

    Parameters
    ----------
    text
        What the user typed, e.g. ``"1, -2.5,30"`` (``;`` also separates).
    option
        The option, named in the error (``--init``).
    names
        What the numbers are, comma-separated (``"x,y,yaw"``).
    units
        Their units, shown in the error (``" (metres, metres, degrees)"``).

    Raises
    ------
    InputError
        Not exactly that many finite numbers.
    """
    expected = len(names.split(","))
    try:
        values = [float(v) for v in text.replace(";", ",").split(",")]
    except ValueError:
        values = []
    if len(values) != expected or not all(math.isfinite(v) for v in values):
        raise InputError(f"expected '{names}'{units}, got {text!r}", location=option)
    return tuple(values)


def optional_numbers(
    text: str | None, option: str, names: str, units: str
) -> tuple[float, ...] | None:
    """:func:`parse_numbers` of ``text``, or ``None`` when the option was not given."""
    return None if text is None else parse_numbers(text, option, names, units)


def check_options(values: Mapping[str, float | Sequence[float] | None], cli: bool = False) -> None:
    """Refuse option values outside :data:`OPTION_BOUNDS` (``None`` is not given).

    Parameters
    ----------
    values
        Values by parameter name (``robot_sigma``); a vector option is a sequence.
    cli
        Name the command-line option (``--robot-sigma``) instead of the parameter.

    Raises
    ------
    InputError
        A value that is not a finite number within its bounds, naming the option.
    """
    for name, value in values.items():
        if value is None:
            continue
        option = "--" + name.replace("_", "-") if cli else name
        parts = [value] if isinstance(value, int | float) else list(value)
        for x, (low, high, unit, low_open) in zip(parts, OPTION_BOUNDS[name], strict=True):
            inside = x > low if low_open else x >= low
            if not (math.isfinite(x) and inside and x <= high):
                shown = ", ".join(f"{v:g}" for v in parts)
                raise InputError(
                    f"expected {'more than' if low_open else 'at least'} {low:g} and at most "
                    f"{high:g} {unit}, got {shown}",
                    location=option,
                )


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
    sd = np.sqrt(np.maximum(np.diag(pose.covariance), 0.0))
    return [
        ("position (m)", ", ".join(_num(v, ".4f") for v in T[:3, 3])),
        ("heading (deg)", _num(np.degrees(np.arctan2(T[1, 0], T[0, 0])), ".4f")),
        ("sigma xyz (mm)", ", ".join(_num(1e3 * v, ".2f") for v in sd[:3])),
        ("sigma heading (deg)", _num(np.degrees(sd[5]), ".4f")),
        ("rmse (mm)", _num(1e3 * pose.rmse, ".2f")),
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
                f"{_num(g['statistic'], '.1f')} {'<=' if g['passed'] else '>'} "
                f"{_num(g['threshold'], '.1f')} ({integrity.redundancy} dof, variance factor "
                f"{_num(g.get('variance_factor'), '.2f')})",
            )
        )
    w = integrity.w_test
    if w.get("max") is not None:
        rows.append(
            (
                "largest w-test",
                f"{_num(w['max'], '.2f')} {'<=' if w['passed'] else '>'} "
                f"{_num(w.get('threshold'), '.2f')} ({w.get('suspect')})",
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


def _num(value: float | None, fmt: str) -> str:
    """``value`` formatted with ``fmt``; ``n/a`` when it is missing or not finite."""
    if value is None or not math.isfinite(value):
        return "n/a"
    return format(value, fmt)
