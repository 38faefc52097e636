"""Total station Procedures A and B over repeated moves (paper 001)."""

from __future__ import annotations

import numpy as np

from fabflow.sensors.ts_procedures import simulate_procedures


def test_procedure_a_error_grows_and_b_does_not() -> None:
    study = simulate_procedures(np.random.default_rng(0), n_cycles=4, n_runs=300)
    a = study.deviation_a.mean(axis=0)
    b = study.deviation_b.mean(axis=0)
    assert np.all(np.diff(a) > 0)
    assert a[-1] > 2.5 * a[0]
    assert b.max() < 1.5 * b.min()
    assert a[-1] > 3 * b[-1]
    rows = study.table()
    assert len(rows) == 4 and rows[0][0] == 1
