"""Shared test fixtures."""

from __future__ import annotations

import pytest
from helpers import run_cli


@pytest.fixture
def cli():
    """The :func:`helpers.run_cli` helper."""
    return run_cli
