"""Record the outputs of the point registration on seeded cases (run from the repository root).

``reference.json`` holds what :func:`fabflow.positioning.registration.register_points`
and :func:`fabflow.positioning.three_point.localize_three_point` returned on these
cases before their tests were vectorised (pose, covariance, residuals, test
values, statuses); ``tests/positioning/test_registration_reference.py`` checks
that the current code still returns the same within floating point. Regenerate
only when a change of the results is intended, and say so in the change.

The cases: 3 to 8 prism points in a robot's workspace, the base anywhere on a
30 x 30 m site, points measured by a Leica MS50 (needle-shaped covariances) or
with isotropic or unknown noise; clean, with one or two bad readings, with two
readings swapped; relative weights, zero weights, known sigma, the optimizer.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from fabflow.errors import LocalizationError
from fabflow.json_format import json_safe
from fabflow.positioning.polar import INSTRUMENTS, cartesian_to_polar, polar_covariance
from fabflow.positioning.registration import Registration, register_points
from fabflow.positioning.three_point import localize_three_point, three_point_base_points
from fabflow.transforms.se3 import apply_T, inv_T, make_T
from fabflow.transforms.so3 import exp_so3

HERE = Path(__file__).parent
T_WORLD_INSTRUMENT = make_T(exp_so3([0.0, 0.0, 0.4]), [-8.0, -6.0, 1.6])


def random_pose(rng: np.random.Generator) -> np.ndarray:
    """A base pose on a 30 x 30 m site: any heading, up to ~1 degree of tilt."""
    tilt = rng.normal(0.0, np.radians(0.5), 2)
    R = exp_so3([*tilt, 0.0]) @ exp_so3([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
    return make_T(R, [rng.uniform(-15, 15), rng.uniform(2, 32), 0.6])


def workspace_points(rng: np.random.Generator, n: int) -> np.ndarray:
    """Prism points in the base frame (metres)."""
    return rng.uniform([0.3, -2.0, 0.1], [2.2, 2.0, 2.0], (n, 3))


def measure(
    rng: np.random.Generator, T: np.ndarray, P: np.ndarray, instrument: str = "leica_ms50"
) -> tuple[np.ndarray, np.ndarray]:
    """World points measured by the instrument and their covariances (m, m^2)."""
    T_iw = inv_T(T_WORLD_INSTRUMENT)
    local = apply_T(T_iw, apply_T(T, P))
    C_local = polar_covariance(*cartesian_to_polar(local), INSTRUMENTS[instrument])
    R = T_WORLD_INSTRUMENT[:3, :3]
    C = R @ C_local @ R.T
    noise = np.einsum("nij,nj->ni", np.linalg.cholesky(C), rng.normal(size=P.shape))
    return apply_T(T, P) + noise, C


def problems() -> list[dict[str, Any]]:
    """The seeded problems: inputs (``P``, ``M``, optionally ``point_cov``) and the
    keyword arguments of each call made on them."""
    out: list[dict[str, Any]] = []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        n = 3 + seed % 6
        T = random_pose(rng)
        P = workspace_points(rng, n)
        kind = seed % 5
        if kind in (0, 1, 2):
            M, C = measure(rng, T, P, "leica_ms50" if seed % 2 else "hilti_pos150")
            fault = seed % 4
            if fault == 1 and n >= 4:
                M[seed % n] += rng.normal(0.0, 0.01, 3)
            elif fault == 2 and n >= 5:
                M[[0, 2]] += rng.normal(0.0, 0.02, (2, 3))
            elif fault == 3 and n >= 4:
                M[[1, 2]] = M[[2, 1]]
            base_sigma = 2e-4 if seed % 3 else 0.0
            labels = [f"prism P{i + 1}" for i in range(n)]
            variants = [
                {
                    "base_sigma": base_sigma,
                    "reject_outlier": reject,
                    "identify_prisms": ident,
                    "point_labels": labels,
                }
                for reject, ident in ((False, True), (True, True), (True, False))
            ]
            out.append({"P": P, "M": M, "point_cov": C, "variants": variants})
        elif kind == 3:
            M = apply_T(T, P) + rng.normal(0.0, 1e-3, P.shape)
            if seed % 4 == 3 and n >= 5:
                M[n - 1] += rng.normal(0.0, 0.02, 3)
            w = rng.uniform(0.5, 2.0, n).tolist()
            variants = [
                {},
                {"weights": w},
                {"reject_outlier": True},
                {"weights": w, "reject_outlier": True},
                {"sigma": 1e-3},
                {"sigma": 1e-3, "weights": w, "reject_outlier": True},
            ]
            out.append({"P": P, "M": M, "variants": variants})
        else:
            M, C = measure(rng, T, P)
            out.append({"P": P, "M": M, "point_cov": C, "variants": [{"method": "optimize"}]})
            variants: list[dict[str, Any]] = [{"method": "optimize"}]
            if n >= 5:
                w = [0.0] + [1.0] * (n - 1)
                variants += [{"weights": w}, {"weights": w, "sigma": 1e-3}]
            out.append({"P": P, "M": M, "variants": variants})
    # four points on a line and one off it, two faults (the weakest geometry the tests see)
    rng = np.random.default_rng(100)
    P = np.array([[0, 0, 0.5], [0.5, 0, 0.5], [1.0, 0, 0.5], [1.5, 0, 0.5], [0.7, 0.8, 0.9]])
    C = np.array([np.eye(3) * (5e-4) ** 2] * 5)
    for _ in range(12):
        M = P + rng.normal(0, 5e-4, P.shape)
        k = rng.choice(5, 2, replace=False)
        M[k] += rng.normal(0, 0.02, (2, 3))
        variants = [{"reject_outlier": True, "identify_prisms": False}]
        out.append({"P": P, "M": M, "point_cov": C, "variants": variants})
    return out


def three_point_cases() -> list[dict[str, Any]]:
    """Seeded three-point procedures (eqs 1-6) with measured covariances."""
    out = []
    for seed in range(8):
        rng = np.random.default_rng(1000 + seed)
        T = random_pose(rng)
        P = three_point_base_points([0.8, -0.4, 0.9], 0.8)
        M, C = measure(rng, T, P)
        if seed % 2:
            M[seed % 3] += rng.normal(0.0, 0.005, 3)
        out.append(
            {"points_world": M, "p1": P[0], "d": 0.8, "point_cov": C, "base_sigma": 1e-4 * seed}
        )
    return out


def summary(reg: Registration) -> dict[str, Any]:
    """What is compared: every number and decision of the result."""
    test = reg.outlier_test
    return json_safe(
        {
            "T_world_base": reg.T_world_base,
            "covariance": reg.covariance,
            "residuals": reg.residuals,
            "rmse": reg.rmse,
            "variance_factor": reg.variance_factor,
            "rejected": list(reg.rejected),
            "iterations": reg.iterations,
            "outlier_test": None if test is None else test.to_dict(),
            "integrity": None if reg.integrity is None else reg.integrity.to_dict(),
        }
    )


def run_case(problem: dict[str, Any], kwargs: dict[str, Any]) -> dict[str, Any]:
    """The result of one call, or the error it raised."""
    arrays = {k: problem[k] for k in ("point_cov",) if k in problem}
    try:
        return summary(register_points(problem["P"], problem["M"], **arrays, **kwargs))
    except LocalizationError as exc:
        return {"error": type(exc).__name__, "message": exc.message}


def run_three_point(case: dict[str, Any]) -> dict[str, Any]:
    """The result of one three-point case."""
    return summary(localize_three_point(**case))


def main() -> None:
    data = {
        "problems": [
            {
                **json_safe({k: v for k, v in p.items() if k != "variants"}),
                "variants": [
                    {"kwargs": json_safe(kw), "result": run_case(p, kw)} for kw in p["variants"]
                ],
            }
            for p in problems()
        ],
        "three_point": [
            {**json_safe(c), "result": run_three_point(c)} for c in three_point_cases()
        ],
    }
    (HERE / "reference.json").write_text(json.dumps(data) + "\n")
    calls = sum(len(p["variants"]) for p in data["problems"])
    print(f"{calls} registrations and {len(data['three_point'])} three-point cases written")


if __name__ == "__main__":
    main()
