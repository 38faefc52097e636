"""Registering the total station where it stands, through a whole (simulated) build.

:func:`register_setup` simulates the registration of one set-up
(:class:`~fabflow.localize.setups.InstrumentSetup`): free stationing on the
control points (Procedure B of paper 001) or on the prisms the robot holds at
its last station (Procedure A), or the project's given pose.
:class:`InstrumentTrack` follows the set-ups through a build and registers each
one when it is put up: the registered pose and its covariance, not the true
one, turn every later reading into the world, so a set-up's error is shared by
all its visits, and with Procedure A it is inherited by the next set-up.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fabflow.design.elements import Element
from fabflow.localize.prism_points import instrument_for, station_points, total_station_setup
from fabflow.localize.setups import (
    InstrumentSetup,
    control_points,
    instrument_covariance,
    plan_setups,
)
from fabflow.positioning.polar import polar_covariance, polar_to_cartesian
from fabflow.positioning.rigid_fit import register_leveled
from fabflow.project import Project
from fabflow.sensors.total_station import simulate_polar
from fabflow.tasks.plan import Plan
from fabflow.transforms.se3 import compose_covariance, inv_T, make_T, perturb


@dataclass(frozen=True)
class InstrumentPose:
    """Where the instrument stands at a visit and what is known of it.

    Attributes
    ----------
    T_true
        4x4 pose it really has (trunnion, world).
    T_est
        4x4 pose its registration gives; readings are turned into the world with it.
    covariance
        6x6 covariance of ``T_est`` (fabflow's convention).
    setup
        Id of the set-up.
    """

    T_true: np.ndarray
    T_est: np.ndarray
    covariance: np.ndarray
    setup: str


def register_setup(
    project: Project,
    setup: InstrumentSetup,
    rng: np.random.Generator,
    survey_error: dict[str, np.ndarray],
    previous: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    built: Sequence[Element] = (),
) -> InstrumentPose:
    """Simulate registering a set-up where it stands; its estimated pose and covariance.

    - ``given``: the project's pose with its ``setup_sigma_mm/arcsec`` (the
      instrument really stands off by a draw of that covariance).
    - ``control_points``: free stationing. The levelled instrument measures the
      control points it sights (instrument noise); their surveyed coordinates
      are off by ``survey_error`` (drawn once per build); the levelled 4-DOF fit
      (:func:`~fabflow.positioning.rigid_fit.register_leveled`) and its
      first-order covariance.
    - ``robot_points``: the robot, still at its last station (true base
      ``previous[0]``, estimate ``previous[1]`` with covariance ``previous[2]``),
      holds prisms the new set-up measures; their world positions come from the
      robot's estimate, so the estimate's error and covariance carry over.

    Parameters
    ----------
    survey_error
        Per control point id, its survey error (world, metres).
    built
        The structure standing (for the robot's prism points).
    """
    ts = total_station_setup(project)
    instrument = instrument_for(ts)
    T_true = np.asarray(setup.T_world_instrument, dtype=float)
    if setup.registration == "given":
        C = instrument_covariance(ts)
        T_actual = perturb(T_true, rng.normal(0.0, 1.0, 6) * np.sqrt(np.diag(C)))
        return InstrumentPose(T_actual, T_true, C, setup.id)
    if setup.registration == "control_points":
        controls = control_points(project)
        true_world = np.stack([controls[k] for k in setup.control_points])
        known_world = true_world + np.stack([survey_error[k] for k in setup.control_points])
        extra = np.eye(3) * (ts.control_sigma_mm * 1e-3) ** 2
        transfer = np.zeros((6, 6))
    else:
        assert previous is not None
        T_base_true, T_base_est, C_base = previous
        pts = station_points(project, T_base_true, built, sight_from=T_true[:3, 3])
        P = pts.points
        noise = rng.normal(0.0, 1.0, P.shape) * project.simulation.robot_repeatability
        true_world = (P + noise) @ T_base_true[:3, :3].T + T_base_true[:3, 3]
        known_world = P @ T_base_est[:3, :3].T + T_base_est[:3, 3]
        extra = np.eye(3) * project.simulation.robot_repeatability**2
        # the known points share the base estimate's error: the new set-up inherits it
        T_base_instrument = inv_T(T_base_est) @ T_true
        transfer = compose_covariance(T_base_est, C_base, T_base_instrument, None)
    local_true = (true_world - T_true[:3, 3]) @ T_true[:3, :3]
    hz, v, sd = simulate_polar(local_true, instrument, rng)
    local = polar_to_cartesian(hz, v, sd)
    C_local = polar_covariance(hz, v, sd, instrument)
    W = np.linalg.inv(C_local + extra)
    R, t = register_leveled(local, known_world, np.trace(W, axis1=1, axis2=2))
    T_est = make_T(R, t)
    rotated = local @ R.T
    J = np.zeros((len(local), 3, 4))
    J[:, :, :3] = np.eye(3)
    J[:, 0, 3], J[:, 1, 3] = -rotated[:, 1], rotated[:, 0]
    cov4 = np.linalg.inv(np.einsum("nai,nab,nbj->ij", J, W, J))
    C = np.zeros((6, 6))
    sel = [0, 1, 2, 5]
    C[np.ix_(sel, sel)] = cov4
    C[np.ix_(sel, sel)] += transfer[np.ix_(sel, sel)]
    return InstrumentPose(T_true, T_est, 0.5 * (C + C.T), setup.id)


class InstrumentTrack:
    """The instrument through one (simulated) build: each set-up registered when put up.

    Holds the state a build carries from visit to visit: the survey error of
    the control points (drawn once), the set-up standing and its registration.
    """

    def __init__(self, project: Project, setups: Sequence[InstrumentSetup]) -> None:
        self.project = project
        self.by_package = {k: s for s in setups for k in s.packages}
        self._current: InstrumentSetup | None = None
        self._pose: InstrumentPose | None = None
        self._survey: dict[str, np.ndarray] | None = None

    def pose_at(
        self,
        package: int,
        rng: np.random.Generator,
        built: Sequence[Element] = (),
        previous: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> InstrumentPose | None:
        """The instrument at work package ``package`` (``None`` when no set-up covers it).

        ``previous``: the robot's true base pose, its estimate and covariance at
        the last localized package (for a set-up registered on robot points).
        """
        setup = self.by_package.get(package)
        if setup is None:
            return None
        if setup is not self._current:
            if self._survey is None:
                sigma = total_station_setup(self.project).control_sigma_mm * 1e-3
                self._survey = {k: rng.normal(0.0, sigma, 3) for k in control_points(self.project)}
            self._pose = register_setup(
                self.project, setup, rng, self._survey, previous=previous, built=built
            )
            self._current = setup
        return self._pose


def track_for(
    project: Project,
    method: str,
    plan: Plan,
    elements: Sequence[Element],
    setups: Sequence[InstrumentSetup] | None = None,
) -> InstrumentTrack | None:
    """The instrument track of a simulated build with ``method``, or ``None`` when the
    method is not the total station, the sensors are exact, or readings are measured.

    ``setups``: the plan's set-ups when already planned (:func:`plan_setups` otherwise).
    """
    ts = total_station_setup(project)
    if method != "total_station" or not project.simulation.sensor_noise:
        return None
    if ts.observations is not None:
        return None
    return InstrumentTrack(
        project, plan_setups(project, plan, elements) if setups is None else setups
    )
