"""Fixtures of the program tests."""

from __future__ import annotations

import pytest
from program_cases import sample_program

from fabflow.programs.ir import Program


@pytest.fixture(scope="module")
def kuka_program() -> Program:
    """The test program of :mod:`program_cases` for the KUKA KR 60-3."""
    return sample_program()
