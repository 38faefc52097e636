"""Error propagation of total station localization over repeated moves (paper 001, Fig 4 and 7).

Procedure A (no fixed references): each cycle the instrument is moved and set
up on prism points held by the robot, whose world coordinates come from the
robot's own previous localization; the robot then drives on, is localized by
the instrument, and places its tool at a planned target. Errors of one cycle
become the reference of the next, so the deviation grows.

Procedure B (fixed references): each cycle the instrument is set up on fixed,
surveyed reference points around the site, and the robot is localized from it.
Nothing is inherited between cycles.

Both procedures see the same instrument (levelled: its setup solves position
and Hz orientation), the same robot positioning noise and the same geometry.
Everything is vectorized over Monte Carlo runs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fabflow.positioning.point_selection import Workspace, optimal_points
from fabflow.positioning.polar import INSTRUMENTS, Instrument, polar_covariance, polar_to_cartesian
from fabflow.positioning.rigid_fit import kabsch, refine_registration, register_leveled
from fabflow.sensors.total_station import simulate_polar
from fabflow.transforms.se3 import apply_T, inv_T, make_T
from fabflow.transforms.so3 import exp_so3


@dataclass(frozen=True)
class ProcedureGeometry:
    """Site layout of the study (metres).

    Attributes
    ----------
    step
        Distance the robot drives between cycles (along world x).
    instrument_offset
        Lateral distance of each instrument setup from the robot's path.
    instrument_height
        Height of the trunnion above the ground.
    base_height
        Height of the robot base above the ground.
    target
        Planned target in each cycle, in the base frame of the planned robot pose.
    references
        ``(k, 3)`` fixed reference points of Procedure B (world).
    workspace
        Workspace the localization points are chosen in (eqs 9-11; the In situ
        Fabricator: h = 1 m, r = 2.55 m).
    """

    step: float = 6.0
    instrument_offset: float = 6.0
    instrument_height: float = 1.6
    base_height: float = 0.5
    target: tuple[float, float, float] = (1.5, 0.0, 0.3)
    references: tuple[tuple[float, float, float], ...] = (
        (-8.0, -12.0, 1.0),
        (40.0, -12.0, 1.0),
        (40.0, 18.0, 1.0),
        (-8.0, 18.0, 1.0),
    )
    workspace: Workspace = field(
        default_factory=lambda: Workspace(center=(0.0, 0.0, 1.0), reach=2.55, margin=0.1)
    )


@dataclass(frozen=True, eq=False)
class ProcedureStudy:
    """Deviations of the placed targets per cycle.

    Attributes
    ----------
    deviation_a, deviation_b
        ``(runs, cycles)`` XY distance (metres) between the planned target and
        where the tool really went, for Procedures A and B.
    """

    deviation_a: np.ndarray
    deviation_b: np.ndarray

    def table(self) -> list[tuple[int, float, float, float, float]]:
        """Rows ``(cycle, mean A, 95 % A, mean B, 95 % B)`` in metres."""
        rows = []
        for k in range(self.deviation_a.shape[1]):
            a, b = self.deviation_a[:, k], self.deviation_b[:, k]
            rows.append(
                (
                    k + 1,
                    float(a.mean()),
                    float(np.percentile(a, 95)),
                    float(b.mean()),
                    float(np.percentile(b, 95)),
                )
            )
        return rows

    def run_summary(self) -> dict[str, float]:
        """Per run: mean over the cycles and the peak, averaged over runs (metres)."""
        return {
            "a_mean_over_cycles": float(self.deviation_a.mean()),
            "a_peak_median": float(np.median(self.deviation_a.max(axis=1))),
            "a_peak_p95": float(np.percentile(self.deviation_a.max(axis=1), 95)),
            "b_mean_over_cycles": float(self.deviation_b.mean()),
            "b_peak_median": float(np.median(self.deviation_b.max(axis=1))),
        }


def _measure(
    T_world_instrument: np.ndarray,
    points_world: np.ndarray,
    instrument: Instrument,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Noisy instrument-frame points and their covariances, batched ``(runs, n, 3)``."""
    local = apply_T(inv_T(T_world_instrument)[:, None], points_world)
    hz, v, sd = simulate_polar(local, instrument, rng)
    return polar_to_cartesian(hz, v, sd), polar_covariance(hz, v, sd, instrument)


def _localize(
    P_base: np.ndarray,
    T_world_instrument_est: np.ndarray,
    m_local: np.ndarray,
    C_local: np.ndarray,
    robot_sigma: float,
) -> np.ndarray:
    """Batched 6-DOF localization (Kabsch + Gauss-Newton on the full covariances)."""
    R = T_world_instrument_est[:, None, :3, :3]
    M = apply_T(T_world_instrument_est[:, None], m_local)
    C = R @ C_local @ np.swapaxes(R, -1, -2) + robot_sigma**2 * np.eye(3)
    W = np.linalg.inv(C)
    P = np.broadcast_to(P_base, M.shape)
    w = 3.0 / np.trace(C, axis1=-2, axis2=-1)
    R0, t0 = kabsch(P, M, w)
    R1, t1, _ = refine_registration(R0, t0, P, M, W)
    return make_T(R1, t1)


def simulate_procedures(
    rng: np.random.Generator,
    instrument: Instrument | str = "hilti_pos150",
    n_cycles: int = 5,
    n_runs: int = 1000,
    n_points: int = 4,
    robot_sigma: float = 0.001,
    geometry: ProcedureGeometry | None = None,
) -> ProcedureStudy:
    """Monte Carlo of Procedure A (robot as reference) against Procedure B (fixed references).

    Parameters
    ----------
    rng
        Source of all noise.
    instrument
        Accuracy model or preset name (the paper: Hilti POS 150, 2 mm, 5").
    n_cycles
        Cycles of move / set up / localize / place (the paper: 5).
    n_runs
        Monte Carlo runs.
    n_points
        Localization points per setup and per localization, chosen by eqs 9-11.
    robot_sigma
        Robot positioning error per axis (metres), for every prism point and
        the tool at the target.
    geometry
        Site layout; the defaults are described in :class:`ProcedureGeometry`.
    """
    inst = INSTRUMENTS[instrument] if isinstance(instrument, str) else instrument
    g = geometry or ProcedureGeometry()
    P = optimal_points(n_points, g.workspace, np.random.default_rng(0))
    refs = np.asarray(g.references, dtype=float)
    target = np.asarray(g.target, dtype=float)
    runs = n_runs
    eye = np.broadcast_to(np.eye(3), (runs, 3, 3))

    def robot_pose(k: int) -> np.ndarray:
        # true pose: along x with a small random heading and parking offset
        yaw = rng.normal(0.0, np.radians(3.0), runs)
        t = np.stack(
            [
                np.full(runs, k * g.step) + rng.normal(0, 0.05, runs),
                rng.normal(0, 0.05, runs),
                np.full(runs, g.base_height),
            ],
            axis=-1,
        )
        return make_T(exp_so3(yaw[:, None] * np.array([0.0, 0.0, 1.0])), t)

    def instrument_pose(k: int) -> np.ndarray:
        side = g.instrument_offset * (1 if k % 2 else -1)
        t = np.array([(k - 0.5) * g.step, side, g.instrument_height])
        return make_T(eye, np.broadcast_to(t, (runs, 3)))

    def noisy(points: np.ndarray) -> np.ndarray:
        return points + rng.normal(0.0, robot_sigma, points.shape)

    T_true = robot_pose(0)
    T_est = T_true.copy()  # the start pose is known (surveyed)
    dev_a = np.zeros((runs, n_cycles))
    dev_b = np.zeros((runs, n_cycles))
    for k in range(1, n_cycles + 1):
        T_wi = instrument_pose(k)
        # A1: set up on the robot's prism points; their world coordinates come from T_est
        prism_true = apply_T(T_true[:, None], noisy(np.broadcast_to(P, (runs, *P.shape))))
        m, _ = _measure(T_wi, prism_true, inst, rng)
        R_s, t_s = register_leveled(m, apply_T(T_est[:, None], P))
        T_wi_a = make_T(R_s, t_s)
        # B1: set up on fixed references
        m_ref, _ = _measure(T_wi, np.broadcast_to(refs, (runs, *refs.shape)), inst, rng)
        R_b, t_b = register_leveled(m_ref, np.broadcast_to(refs, m_ref.shape))
        T_wi_b = make_T(R_b, t_b)
        # A2/A3: drive on, localize
        T_true = robot_pose(k)
        prism_true = apply_T(T_true[:, None], noisy(np.broadcast_to(P, (runs, *P.shape))))
        m, C = _measure(T_wi, prism_true, inst, rng)
        T_est = _localize(P, T_wi_a, m, C, robot_sigma)
        m, C = _measure(T_wi, prism_true, inst, rng)
        T_est_b = _localize(P, T_wi_b, m, C, robot_sigma)
        # A4: place the tool at the planned target (planned from the nominal pose)
        goal = apply_T(robot_pose_nominal(k, g), target)
        for T_e, dev in ((T_est, dev_a), (T_est_b, dev_b)):
            cmd = apply_T(inv_T(T_e), goal)
            reached = apply_T(T_true, noisy(cmd))
            dev[:, k - 1] = np.linalg.norm((reached - goal)[:, :2], axis=-1)
    return ProcedureStudy(dev_a, dev_b)


def robot_pose_nominal(k: int, geometry: ProcedureGeometry) -> np.ndarray:
    """Planned robot base pose of cycle ``k`` (heading 0, on the path)."""
    return make_T(np.eye(3), [k * geometry.step, 0.0, geometry.base_height])
