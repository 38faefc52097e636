"""Localization for the build: from a project and a plan to a base pose per station.

One module per method (:mod:`~fabflow.localize.uwb`,
:mod:`~fabflow.localize.total_station`, :mod:`~fabflow.localize.icp`) joins the
project's setup, the simulated sensors (:mod:`fabflow.sensors`) or measured
files and the estimators (:mod:`fabflow.positioning`);
:mod:`~fabflow.localize.methods` is the registry by method name and
:mod:`~fabflow.localize.plan` localizes every visit of a plan.
"""
