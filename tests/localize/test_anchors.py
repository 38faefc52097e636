"""UWB anchor layouts: given ones checked at every work package, missing ones planned."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import PROJECTS

from fabflow.design.elements import element_boxes, structure_timeline
from fabflow.design.generate import generate_elements
from fabflow.errors import LocalizationError
from fabflow.localize.anchors import (
    ANCHOR_CLEARANCE,
    MIN_PLANNED,
    check_anchors,
    layout_anchors,
    ranging_zone,
    station_tags,
    target_sigma,
)
from fabflow.localize.methods import localizer_arguments
from fabflow.localize.plan import localize_plan
from fabflow.localize.site import anchors_world
from fabflow.localize.uwb import simulate_station
from fabflow.project import load_project
from fabflow.tasks.planner import plan_project


@pytest.fixture(scope="module")
def cabin():
    project = load_project(PROJECTS / "cabin")
    elements = generate_elements(project.elements, project.path)
    return project, elements, plan_project(project, elements)


def _with_anchors(project, anchors):
    uwb = project.localization.uwb.model_copy(update={"anchors": anchors})
    return project.model_copy(
        update={"localization": project.localization.model_copy(update={"uwb": uwb})}
    )


def test_the_papers_anchors_are_checked(cabin) -> None:
    project, elements, plan = cabin
    same, coverage = layout_anchors(project, plan, elements)
    assert same is project and not coverage.planned
    assert coverage.covered.all()
    assert coverage.sigma.max() <= target_sigma(project)
    # the walls block most of them from inside the finished cabin: reported, not hidden
    assert coverage.through_structure.any()
    assert coverage.in_sight.min() < 3


def test_missing_anchors_are_planned_in_sight(cabin) -> None:
    project, elements, plan = cabin
    planned, coverage = layout_anchors(_with_anchors(project, {}), plan, elements)
    assert coverage.planned and len(coverage.anchor_ids) >= MIN_PLANNED
    assert (coverage.sigma_in_sight <= coverage.target).all()
    # the project now names them, in the UWB frame: the world positions come back
    ids, world = anchors_world(planned.localization.uwb)
    assert ids == list(coverage.anchor_ids)
    assert np.allclose(world, coverage.anchors)
    # off the structure (its plan footprint plus the clearance)
    T_box, extents = element_boxes(elements)
    corner = (np.abs(T_box[:, :2, :3]) @ (0.5 * extents)[..., None])[..., 0]
    lo, hi = T_box[:, :2, 3] - corner, T_box[:, :2, 3] + corner
    xy = world[:, None, :2]
    near = ((xy >= lo - ANCHOR_CLEARANCE + 1e-9) & (xy <= hi + ANCHOR_CLEARANCE - 1e-9)).all(2)
    assert not near.any()
    # checked again as given, the planned layout covers every package
    again = check_anchors(planned, plan, elements)
    assert again.covered.all()


def test_a_layout_that_cannot_locate_names_the_station_and_the_field(cabin) -> None:
    project, elements, plan = cabin
    # four anchors in a small cluster 17 m away: every station stands outside them
    bad = {
        "A1": (20.0, 0.0, 1.0),
        "A2": (20.5, 0.0, 3.0),
        "A3": (21.0, 0.5, 1.0),
        "A4": (20.2, 0.6, 2.5),
    }
    with pytest.raises(LocalizationError, match=r"station S\d.*localization.uwb.anchors"):
        layout_anchors(_with_anchors(project, bad), plan, elements)
    # three anchors and the tags' heights cannot fix a 3D position: named before anything
    three = dict(list(bad.items())[:3])
    with pytest.raises(LocalizationError, match=r"localization\.uwb\.anchors: degenerate"):
        layout_anchors(_with_anchors(project, three), plan, elements)


def test_each_tag_ranges_with_the_anchors_it_sees_and_the_fewest_hidden_ones(cabin) -> None:
    project, elements, plan = cabin
    planned, _ = layout_anchors(_with_anchors(project, {}), plan, elements)
    ids, anchors = anchors_world(planned.localization.uwb)
    timeline = structure_timeline(elements, [wp.elements for wp in plan.work_packages])
    zoned = joined = 0
    for wp, (built, _) in zip(plan.work_packages, timeline, strict=True):
        zone = ranging_zone(planned, wp.station, built)
        if not built:  # nothing stands yet: every anchor is in sight
            assert zone is None
        if zone is None:
            continue
        zoned += 1
        # each tag's zone holds every anchor it sees, checked by sampling the sight
        # lines (a line grazing a block within 2 cm counting either way); an anchor
        # hidden from a tag joins the zone of every tag
        tags = station_tags(planned, wp.station)
        T_box, extents = element_boxes(built)
        t = np.linspace(0.0, 1.0, 600)[1:-1]
        everyone = set.intersection(*(set(names) for names in zone))
        for tag, names in zip(tags, zone, strict=True):
            assert len(names) >= MIN_PLANNED
            line = tag + t[:, None, None] * (anchors - tag)[None]  # (t, A, 3)
            local = np.abs(
                np.einsum("kji,takj->taki", T_box[:, :3, :3], line[:, :, None] - T_box[:, :3, 3])
            )
            clear = ~(local <= 0.5 * extents + 0.02).all(axis=3).any(axis=(0, 2))
            blocked = (local <= 0.5 * extents - 0.02).all(axis=3).any(axis=(0, 2))
            assert {k for k, c in zip(ids, clear, strict=True) if c} <= set(names)
            hidden = {k for k, b in zip(ids, blocked, strict=True) if b} & set(names)
            assert hidden <= everyone
            joined += len(hidden)
        # the simulated ranges reach the zone's anchors alone
        rng = np.random.default_rng(wp.index)
        T_base = wp.station.T_world_base(planned.robot.platform.T_platform_base.matrix())
        data = simulate_station(planned, T_base, rng, built, zone)
        ranged = np.isfinite(data.ranges).any(axis=0)
        for k, names in enumerate(zone):
            assert {data.anchor_ids[j] for j in np.flatnonzero(ranged[k])} <= set(names)
        assert min(len(names) for names in zone) < len(ids)  # not every link: a zone
    assert zoned > 0  # the walls hide some anchors from some stations
    assert joined > 0  # and inside the finished cabin some hidden anchors are needed


def test_without_sensor_noise_the_zones_stay_out_of_the_exact_localizer(cabin) -> None:
    project, elements, plan = cabin
    planned, _ = layout_anchors(_with_anchors(project, {}), plan, elements)
    sim = planned.simulation.model_copy(update={"sensor_noise": False})
    exact = planned.model_copy(update={"simulation": sim})
    timeline = structure_timeline(elements, [wp.elements for wp in plan.work_packages])
    zoned = [
        (wp.station, built)
        for wp, (built, _) in zip(plan.work_packages, timeline, strict=True)
        if ranging_zone(planned, wp.station, built) is not None  # a zone with noise on
    ]
    assert zoned
    assert all(localizer_arguments(exact, "uwb", s, built) == {} for s, built in zoned)
    poses = localize_plan(exact, plan, elements, np.random.default_rng(0))
    assert all("exact" in est.integrity.checks for est, _ in poses.values())


def test_multipath_raises_the_predicted_sigma_by_its_share_of_each_range(cabin) -> None:
    """One epoch of ranges carries the multipath too: with ``multipath_sigma`` the
    predicted sigma of every package grows, by no more than the largest factor
    ``sqrt(1 + (field / noise)^2)`` any of its ranges gets, no less than the smallest."""
    project, elements, plan = cabin
    plain = check_anchors(project, plan, elements)
    uwb = project.localization.uwb.model_copy(update={"multipath_sigma": 0.035})
    noisy_project = project.model_copy(
        update={"localization": project.localization.model_copy(update={"uwb": uwb})}
    )
    noisy = check_anchors(noisy_project, plan, elements)
    model = uwb.error_model()
    d = np.linspace(0.5, 15.0, 300)  # every range the cabin's tags and anchors make
    factor = np.sqrt(1.0 + (model.field_sigma(d) / model.sigma(d)) ** 2)
    ratio = noisy.sigma / plain.sigma
    assert np.all(ratio >= factor.min() - 1e-9) and np.all(ratio <= factor.max() + 1e-9)
    assert np.all(ratio > 1.0)
