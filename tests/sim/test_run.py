"""Simulated construction runs: exactness without noise, covariance propagation, seeds."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import DATA, PROJECTS

from fabflow.design.generate import generate_elements
from fabflow.errors import InputError
from fabflow.localize import icp, uwb
from fabflow.localize.anchors import layout_anchors
from fabflow.localize.methods import localizer_arguments, run_inputs
from fabflow.localize.plan import check_visit, parked_pose
from fabflow.project import Project, load_project
from fabflow.sim.monte_carlo import run_study
from fabflow.sim.run import Study, prepare_study, run_seed, simulate_run, study_localizer
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


def _drawn_per_run(study: Study, key: str, localize) -> list[list]:
    """Runs 0 and 1 of ``study``: per run, the keyword argument ``key`` each of its
    visits' localizations got (``localize``: the method's ``localize_station``)."""
    seen: list[tuple[int, object]] = []

    def recording(project, T, rng, station_id, built=(), **kw):
        seen.append((run, kw[key]))
        return localize(project, T, rng, station_id, built, **kw)

    for run in (0, 1):
        result = simulate_run(study, run, 7, localize=recording)
        assert result.localization_error.shape[0] == study.n_visits
    assert len(seen) == 2 * study.n_visits
    return [[x for r, x in seen if r == run] for run in (0, 1)]


def test_each_icp_run_draws_its_own_mapping_run(small: Project) -> None:
    """A simulated map's errors are shared by the visits that match it; a study that
    kept one map for all its runs would sample that one map's errors only."""
    maps = _drawn_per_run(prepare_study(small, "icp"), "scan_map", icp.localize_station)
    # one map per run, shared by its visits; another for the other run
    assert all(m is maps[0][0] for m in maps[0]) and all(m is maps[1][0] for m in maps[1])
    a, b = maps[0][0].target.points, maps[1][0].target.points
    assert a.shape != b.shape or not np.array_equal(a, b)


def test_run_inputs_draw_an_icp_map_per_run_for_a_simulated_site(small: Project) -> None:
    """Each ICP run its own mapping run, the seed fixing it; nothing for the total
    station (its set-ups are its track's) nor without sensor noise."""

    def draw(project: Project, method: str, seed: int) -> dict:
        return run_inputs(project, method, np.random.default_rng(seed))

    a, b = draw(small, "icp", 1)["scan_map"], draw(small, "icp", 2)["scan_map"]
    again = draw(small, "icp", 1)["scan_map"]
    np.testing.assert_array_equal(a.target.points, again.target.points)  # the seed fixes it
    same_size = a.target.points.shape == b.target.points.shape
    assert not same_size or not np.array_equal(a.target.points, b.target.points)
    # the mapping runs err alike: their maps stand within centimetres of each other
    assert abs(len(a.target.points) - len(b.target.points)) < 0.05 * len(a.target.points)
    assert draw(small, "total_station", 1) == {}
    assert draw(with_noise(small, sensor_noise=False), "icp", 1) == {}
    assert draw(with_noise(small, sensor_noise=False), "uwb", 1) == {}


def test_a_uwb_run_shares_its_installation_between_its_visits(small: Project) -> None:
    """Anchors are put up and calibrated once per site: every visit of a run ranges
    with the same biases and calibration, the next run with others; drawn off a
    spawned generator, they leave the run's own stream (its parking errors) alone."""
    rng = np.random.default_rng(3)
    a = run_inputs(small, "uwb", rng)["installation"]
    assert rng.normal() == np.random.default_rng(3).normal()  # the run's stream untouched
    again = run_inputs(small, "uwb", np.random.default_rng(3))["installation"]
    other = run_inputs(small, "uwb", np.random.default_rng(4))["installation"]
    np.testing.assert_array_equal(a.bias.offset, again.bias.offset)
    np.testing.assert_array_equal(a.calibration.offset, again.calibration.offset)
    assert not np.array_equal(a.bias.offset, other.bias.offset)
    n = len(small.localization.uwb.anchors)
    assert a.bias.offset.shape == a.calibration.offset.shape == (n,)
    # the calibration fits the installation's own bias (a few millimetres off)
    np.testing.assert_allclose(a.calibration.offset, a.bias.offset, atol=0.02)

    study = prepare_study(small, "uwb")
    per_run = _drawn_per_run(study, "installation", uwb.localize_station)
    assert all(i is per_run[0][0] for i in per_run[0]) and per_run[0] and per_run[1]
    assert all(i is per_run[1][0] for i in per_run[1])
    assert not np.array_equal(per_run[0][0].bias.offset, per_run[1][0].bias.offset)


def test_a_zone_ranges_with_its_anchors_share_of_the_installation(small: Project) -> None:
    """Tags' ranging zones pick their anchors' biases and calibration out of the site's
    by name, whatever order the zones list them in; an installation of another
    layout is refused."""
    installation = uwb.draw_installation(small, np.random.default_rng(0))
    ids = list(small.localization.uwb.anchors)
    n_tags = len(small.localization.uwb.tags)
    zone = [[ids[3], ids[0]], [ids[2]], *([[ids[1]]] * (n_tags - 2))][:n_tags]
    T = np.eye(4)
    T[:3, 3] = [1.0, 1.0, 0.5]
    data = uwb.simulate_station(small, T, np.random.default_rng(1), zone=zone,
                                installation=installation)  # fmt: skip
    ranged = sorted({k for z in zone for k in z}, key=ids.index)
    assert data.anchor_ids == ranged  # the installation's (the layout's) order
    pick = [ids.index(k) for k in ranged]
    np.testing.assert_array_equal(data.calibration.offset, installation.calibration.offset[pick])
    np.testing.assert_array_equal(data.calibration.scale, installation.calibration.scale[pick])
    bias, _ = installation.of(ranged)
    np.testing.assert_array_equal(bias.offset, installation.bias.offset[pick])
    other = dataclasses.replace(installation, anchor_ids=("X1", *installation.anchor_ids[1:]))
    with pytest.raises(InputError, match="no anchor A1: it was drawn for another anchor layout"):
        uwb.simulate_station(small, T, np.random.default_rng(1), installation=other)


def test_a_run_estimates_its_uwb_visits_together_as_one_at_a_time(cabin_study: Study) -> None:
    # the visits are measured in order (every random number), then estimated
    # together: one cleaning, NLOS correction and start for all of them. The poses,
    # covariances and tests must be those of estimating each visit on its own.
    assert cabin_study.method == "uwb"
    one_at_a_time = study_localizer(cabin_study)
    for run in (0, 1):
        together = simulate_run(cabin_study, run, 3, keep_poses=True)
        alone = simulate_run(cabin_study, run, 3, keep_poses=True, localize=one_at_a_time)
        assert any(p.quality["n_occluded_links"] > 0 for p in together.base_poses)
        np.testing.assert_array_equal(together.localization_error, alone.localization_error)
        np.testing.assert_array_equal(
            together.localization_covariance, alone.localization_covariance
        )
        np.testing.assert_array_equal(together.integrity, alone.integrity)
        np.testing.assert_array_equal(together.deviation_xyz, alone.deviation_xyz)
        for a, b in zip(together.base_poses, alone.base_poses, strict=True):
            assert a.quality == b.quality


def test_estimates_without_records_have_the_statuses_poses_and_covariances_of_full_ones(
    cabin_study: Study,
) -> None:
    # a simulated run that keeps no poses skips the hidden-mirror search of the fixes
    # that left nothing out: it can raise only their protection level, which decides
    # the status of a fix that left ranges out alone. One link's ranges 0.4 m long at
    # every other visit make such fixes; the poses, covariances and (after the check
    # against the planned station) statuses must be the same, and so the records of
    # the fixes that left ranges out.
    project = cabin_study.project
    rng = np.random.default_rng(5)
    installation = uwb.draw_installation(project, rng)
    planned, measured = [], []
    for v, station in enumerate(cabin_study.stations[:16]):
        T_planned, T_true = parked_pose(project, station, rng)
        planned.append(T_planned)
        built = cabin_study.built_before[v]
        extra = {**cabin_study.visit_arguments[v], "installation": installation}
        measured.append(uwb.measure_station(project, T_true, rng, station.id, built, **extra))
    for m in measured[::2]:
        m.data.ranges[:, 0, 1] += 0.4
    full = uwb.estimate_measured(project, measured)
    lean = uwb.estimate_measured(project, measured, records=False)
    statuses = []
    for a, b, T in zip(full, lean, planned, strict=True):
        left_out = a.integrity.status == "excluded"
        a, b = check_visit(project, a, T), check_visit(project, b, T)
        np.testing.assert_array_equal(a.T_world_base, b.T_world_base)
        np.testing.assert_array_equal(a.covariance, b.covariance)
        assert a.integrity.status == b.integrity.status
        if left_out:
            assert a.integrity.to_dict() == b.integrity.to_dict()
        statuses.append(("left out " if left_out else "") + a.integrity.status)
    assert "ok" in statuses and any(s.startswith("left out") for s in statuses), statuses
    # the lean poses lack the residuals and the quality, their records only the search's check
    assert all(p.quality and p.residuals.size for p in full)
    assert not any(p.quality or p.residuals.size for p in lean)
    assert any("mirror_by_one_fault" in p.integrity.checks for p in full)
    assert not any(
        "mirror_by_one_fault" in p.integrity.checks
        for p in lean
        if p.integrity.status != "excluded"
    )
