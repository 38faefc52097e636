"""Shared test fixtures, and the property tests' examples fixed from run to run.

Hypothesis draws its examples from a seed derived from each test
(``derandomize``): a run on a fresh machine tries what the last run tried, so
a red CI is a change, not a draw. ``HYPOTHESIS_PROFILE=explore`` draws fresh
examples instead (look for new counter-examples, then pin them with
``@example``).
"""

from __future__ import annotations

import os

import pytest
from helpers import run_cli
from hypothesis import settings

settings.register_profile("fabflow", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "fabflow"))


@pytest.fixture
def cli():
    """The :func:`helpers.run_cli` helper."""
    return run_cli
