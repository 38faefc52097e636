"""The tracked print's reference: one Hermite path through the layers at constant speed."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import PROJECTS

from fabflow.design.generate import generate_elements
from fabflow.errors import InputError
from fabflow.project import load_project
from fabflow.tracking.reference import print_reference


@pytest.fixture(scope="module")
def layers():
    project = load_project(PROJECTS / "excavator_print")
    return generate_elements(project.elements, project.path)


def test_the_reference_runs_through_every_layer_at_the_print_speed(layers) -> None:
    ref = print_reference(layers, 0.1)
    step = np.linalg.norm(np.diff(ref.p, axis=0), axis=1)
    # 0.1 m/s at 100 Hz: 1 mm along the curve, a little less as a chord at the sharp join
    assert np.median(step) == pytest.approx(0.001, rel=1e-4)
    assert 0.0009 < step[:-1].min() and step.max() < 0.001 * (1 + 1e-5)
    assert np.allclose(np.diff(ref.t), 0.01)
    z = np.unique(np.round(ref.p[ref.extrude, 2], 6))
    assert np.allclose(z, [e.T_world_element[2, 3] + e.polyline[0, 2] for e in layers])
    assert ref.length == pytest.approx(step.sum(), rel=1e-3)
    speed = np.linalg.norm(ref.v[1:-2], axis=1)  # the last step is shorter
    assert np.mean(np.abs(speed - 0.1) < 1e-3) > 0.99  # all but the sharp joins


def test_the_join_between_layers_does_not_extrude(layers) -> None:
    ref = print_reference(layers, 0.1)
    off = np.flatnonzero(~ref.extrude)
    assert off.size > 0
    # the extruder is off only while the nozzle climbs to the next layer
    assert np.all(np.diff(ref.p[off, 2]) >= -1e-9)


def test_no_print_paths_and_too_long_prints_are_refused(layers) -> None:
    with pytest.raises(InputError, match="has none"):
        print_reference([], 0.1)
    with pytest.raises(InputError, match="max_duration_s = 30"):
        print_reference(layers, 0.1, max_duration_s=30.0)
