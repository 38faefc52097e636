"""Simulated construction runs: exactness without noise, covariance propagation, seeds."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import DATA, PROJECTS

from fabflow.design.generate import generate_elements
from fabflow.errors import InputError
from fabflow.localize import icp
from fabflow.localize.anchors import layout_anchors
from fabflow.localize.methods import localizer_arguments, run_inputs
from fabflow.project import Project, load_project
from fabflow.sim.monte_carlo import run_study
from fabflow.sim.run import Study, prepare_study, run_seed, simulate_run
from fabflow.tasks.planner import plan_project
from fabflow.transforms import FrameGraph, Pose
from fabflow.transforms.se3 import inv_T, perturb

SMALL = DATA / "sim" / "project.yaml"
CABIN = PROJECTS / "cabin" / "project.yaml"


def with_noise(project: Project, **fields: float | bool) -> Project:
    """The project with some ``simulation`` fields replaced."""
    return project.model_copy(update={"simulation": project.simulation.model_copy(update=fields)})


NO_NOISE = dict(
    driving_error=0.0,
    driving_heading_error_deg=0.0,
    robot_repeatability=0.0,
    lift_error=0.0,
    sensor_noise=False,
)


@pytest.fixture(scope="module")
def small() -> Project:
    return load_project(SMALL)


@pytest.fixture(scope="module")
def small_study(small: Project) -> Study:
    return prepare_study(small)


@pytest.fixture(scope="module")
def cabin_study() -> Study:
    return prepare_study(load_project(CABIN))


def test_study_covers_every_robot_built_element_once(cabin_study: Study) -> None:
    st = cabin_study
    assert st.n_elements == len(set(st.element_ids)) > 500
    assert st.T_world_element.shape == (st.n_elements, 4, 4)
    assert st.element_visit.min() == 0 and st.element_visit.max() == st.n_visits - 1
    # every visit sees what was built before it, and more as the build goes on
    sizes = [len(b) for b in st.built_before]
    assert sizes == sorted(sizes) and sizes[-1] > sizes[0]


def test_the_localizer_arguments_worked_out_once_are_those_of_each_visit() -> None:
    """The UWB zones kept with the study are those of each visit's station and
    structure, and a run with them is the run that works them out at every visit
    (the cabin with planned anchors, which the walls hide from some stations)."""
    project = load_project(CABIN)
    elements = generate_elements(project.elements, project.path)
    plan = plan_project(project, elements)
    uwb = project.localization.uwb.model_copy(update={"anchors": {}})
    unplanned = project.model_copy(
        update={"localization": project.localization.model_copy(update={"uwb": uwb})}
    )
    planned, _ = layout_anchors(unplanned, plan, elements)
    st = prepare_study(planned, "uwb", elements, plan)
    assert len(st.visit_arguments) == st.n_visits
    zoned = [v for v, a in enumerate(st.visit_arguments) if "zone" in a]
    assert zoned
    for v in (0, zoned[0], st.n_visits - 1):
        assert st.visit_arguments[v] == localizer_arguments(
            st.project, st.method, st.stations[v], st.built_before[v]
        )
    kept = simulate_run(st, 3, 0)
    again = simulate_run(dataclasses.replace(st, visit_arguments=()), 3, 0)
    for name in ("translation_m", "localization_error", "localization_covariance", "integrity"):
        assert np.array_equal(getattr(kept, name), getattr(again, name))


def test_a_study_of_split_print_paths_simulates_their_pieces() -> None:
    study = prepare_study(load_project(PROJECTS / "print_path"))
    pieces = [i for i in study.element_ids if "." in i]
    assert pieces and study.n_elements == len(set(study.element_ids))
    result = run_study(study, 1, seed=3)
    assert result.runs.tolist() == [0] and not result.failures


@pytest.mark.parametrize("method", ["uwb", "total_station", "icp"])
def test_zero_noise_builds_the_plan_exactly(small: Project, method: str) -> None:
    study = prepare_study(with_noise(small, **NO_NOISE), method)
    result = simulate_run(study, 3, 11, keep_poses=True)
    np.testing.assert_array_equal(result.localization_error, 0.0)
    assert result.T_world_element_asbuilt is not None
    np.testing.assert_allclose(result.T_world_element_asbuilt, study.T_world_element, atol=1e-12)
    assert result.translation_m.max() < 1e-12
    assert result.rotation_rad.max() < 1e-12


def test_zero_noise_on_the_cabin(cabin_study: Study) -> None:
    study = prepare_study(
        with_noise(cabin_study.project, **NO_NOISE),
        elements=None,
        plan=None,
    )
    result = simulate_run(study, 0, 0)
    assert result.translation_m.shape == (study.n_elements,)
    assert result.translation_m.max() < 1e-12 and result.rotation_rad.max() < 1e-12


def test_driving_error_alone_is_absorbed_by_exact_localization(small: Project) -> None:
    """The platform parks off its station, but an exact localization compensates it."""
    noisy_parking = with_noise(small, **{**NO_NOISE, "driving_error": 0.05})
    result = simulate_run(prepare_study(noisy_parking), 0, 1)
    assert result.translation_m.max() < 1e-12


def test_execution_noise_has_the_configured_spread(small: Project) -> None:
    rep, lift = 0.002, 0.003
    project = with_noise(small, **{**NO_NOISE, "robot_repeatability": rep, "lift_error": lift})
    study = prepare_study(project)
    d = np.concatenate([simulate_run(study, i, 2).deviation_xyz for i in range(400)])
    std = d.std(axis=0)
    np.testing.assert_allclose(std, [rep, rep, np.hypot(rep, lift)], rtol=0.1)


def test_localization_error_moves_elements_as_the_frame_graph_predicts(small: Project) -> None:
    """Only localization noise: the as-built scatter of every element equals the base
    pose scatter propagated through the frame graph world -> base -> element (both from
    the same runs, so few runs suffice: the comparison tests the propagation, not sampling)."""
    project = with_noise(
        small,
        driving_error=0.0,
        driving_heading_error_deg=0.0,
        robot_repeatability=0.0,
        lift_error=0.0,
    )
    study = prepare_study(project)
    result = run_study(study, 60, seed=5)
    assert result.failures == ()
    errors = result.localization_error[:, 0]
    assert np.all(errors.std(axis=0)[[0, 1, 2, 5]] > 1e-4)
    C_base = np.cov(errors.T)
    T_world_base = (
        simulate_run(prepare_study(with_noise(project, sensor_noise=False)), 0, 5, keep_poses=True)
        .base_poses[0]
        .T_world_base
    )
    for i in range(study.n_elements):
        graph = FrameGraph()
        graph.add("world", "base", Pose.from_matrix(T_world_base), C_base)
        graph.add(
            "base", "element", Pose.from_matrix(inv_T(T_world_base) @ study.T_world_element[i])
        )
        _, C = graph.get_with_covariance("world", "element")
        C_sample = np.cov(result.deviation_xyz[:, i].T)
        rel = np.linalg.norm(C_sample - C[:3, :3]) / np.linalg.norm(C[:3, :3])
        assert rel < 0.10, (study.element_ids[i], rel)
        # the rotation error of an element is the base heading error
        np.testing.assert_allclose(
            np.sqrt(np.mean(result.rotation_rad[:, i] ** 2)),
            np.sqrt(C[3:, 3:].trace()),
            rtol=0.10,
        )


def test_as_built_follows_the_base_error_exactly(small: Project) -> None:
    """T_asbuilt = T_true @ inv(T_est) @ T_planned, checked against perturb()."""
    project = with_noise(small, robot_repeatability=0.0, lift_error=0.0)
    study = prepare_study(project)
    result = simulate_run(study, 4, 9, keep_poses=True)
    T_est = result.base_poses[0].T_world_base
    T_true = perturb(T_est, result.localization_error[0])
    expected = T_true @ inv_T(T_est) @ study.T_world_element
    np.testing.assert_allclose(result.T_world_element_asbuilt, expected, atol=1e-12)


def test_a_run_is_reproducible_alone(small_study: Study) -> None:
    a = simulate_run(small_study, 7, 123)
    b = simulate_run(small_study, 7, 123)
    c = simulate_run(small_study, 8, 123)
    np.testing.assert_array_equal(a.deviation_xyz, b.deviation_xyz)
    np.testing.assert_array_equal(a.localization_error, b.localization_error)
    assert not np.array_equal(a.deviation_xyz, c.deviation_xyz)
    child = np.random.SeedSequence(123).spawn(8)[7]
    assert run_seed(123, 7).generate_state(4).tolist() == child.generate_state(4).tolist()


def test_unknown_method_and_missing_setup_are_input_errors(small: Project) -> None:
    with pytest.raises(InputError, match="unknown localization method 'gps'"):
        prepare_study(small, "gps")
    no_uwb = small.model_copy(
        update={
            "localization": small.localization.model_copy(update={"method": "icp", "uwb": None})
        }
    )
    with pytest.raises(InputError, match=r"localization\.uwb"):
        prepare_study(no_uwb, "uwb")


def test_covariance_fidelity_draws_the_calibrated_covariance(small: Project) -> None:
    project = with_noise(small, driving_error=0.0, robot_repeatability=0.0, lift_error=0.0)
    study = prepare_study(project, fidelity="covariance", calibration_runs=4)
    assert study.fidelity == "covariance" and study.visit_covariance is not None
    C = study.visit_covariance[0]
    # UWB does not observe roll and pitch (level platform): no error drawn for them
    np.testing.assert_array_equal(C[3:5], 0.0)
    assert np.all(np.diag(C)[[0, 1, 2, 5]] > 0)
    errors = run_study(study, 2000, seed=4).localization_error[:, 0]
    np.testing.assert_allclose(
        errors.std(axis=0)[[0, 1, 2, 5]], np.sqrt(np.diag(C))[[0, 1, 2, 5]], rtol=0.05
    )
    np.testing.assert_allclose(np.cov(errors.T), C, atol=0.1 * np.abs(C).max())
    np.testing.assert_array_equal(errors[:, 3:5], 0.0)


def test_covariance_fidelity_as_built_follows_the_drawn_base_error(small: Project) -> None:
    study = prepare_study(
        with_noise(small, robot_repeatability=0.0, lift_error=0.0),
        fidelity="covariance",
        calibration_runs=2,
    )
    result = simulate_run(study, 1, 2, keep_poses=True)
    T_est = result.base_poses[0].T_world_base
    T_true = perturb(T_est, result.localization_error[0])
    expected = T_true @ inv_T(T_est) @ study.T_world_element
    np.testing.assert_allclose(result.T_world_element_asbuilt, expected, atol=1e-12)
    np.testing.assert_array_equal(result.localization_covariance[0], study.visit_covariance[0])


def test_covariance_fidelity_without_noise_is_exact(small: Project) -> None:
    study = prepare_study(with_noise(small, **NO_NOISE), fidelity="covariance", calibration_runs=1)
    np.testing.assert_array_equal(study.visit_covariance, 0.0)
    assert simulate_run(study, 0, 0).translation_m.max() < 1e-12


def test_unknown_fidelity_is_an_input_error(small: Project) -> None:
    with pytest.raises(InputError, match="unknown fidelity 'fast'"):
        prepare_study(small, fidelity="fast")  # type: ignore[arg-type]


def test_each_icp_run_draws_its_own_mapping_run(small: Project) -> None:
    """A simulated map's errors are shared by the visits that match it; a study that
    kept one map for all its runs would sample that one map's errors only."""
    seen: list[tuple[int, int]] = []

    def recording(project, T, rng, station_id, built=(), **kw):
        seen.append((run, id(kw["scan_map"])))
        return icp.localize_station(project, T, rng, station_id, built, **kw)

    study = prepare_study(small, "icp")
    maps = {}
    for run in (0, 1):
        result = simulate_run(study, run, 7, localize=recording)
        assert result.localization_error.shape[0] == study.n_visits
        maps[run] = {m for r, m in seen if r == run}
    # one map per run, shared by its visits; another for the other run
    assert len(maps[0]) == len(maps[1]) == 1 and maps[0] != maps[1]
    assert len(seen) == 2 * study.n_visits


def test_run_inputs_draw_a_map_only_for_a_simulated_icp_site(small: Project) -> None:
    def draw(project: Project, method: str, seed: int) -> dict:
        return run_inputs(project, method, np.random.default_rng(seed))

    a, b = draw(small, "icp", 1)["scan_map"], draw(small, "icp", 2)["scan_map"]
    again = draw(small, "icp", 1)["scan_map"]
    np.testing.assert_array_equal(a.target.points, again.target.points)  # the seed fixes it
    same_size = a.target.points.shape == b.target.points.shape
    assert not same_size or not np.array_equal(a.target.points, b.target.points)
    # the mapping runs err alike: their maps stand within centimetres of each other
    assert abs(len(a.target.points) - len(b.target.points)) < 0.05 * len(a.target.points)
    assert draw(small, "uwb", 1) == {} and draw(small, "total_station", 1) == {}
    assert draw(with_noise(small, sensor_noise=False), "icp", 1) == {}
