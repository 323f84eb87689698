"""Test-wide settings: every property test is seeded, so a failure is reproducible and CI never
fails at random (Hypothesis derives its examples from the test's name, not from the clock)."""

import pytest
from hypothesis import settings

from slidecal.routines.config import load_config
from slidecal.routines.planner import make_plan

settings.register_profile("slidecal", derandomize=True, deadline=None, print_blob=True)
settings.load_profile("slidecal")


@pytest.fixture(scope="session")
def default_plan():
    """The planner's plan for the default simulated cell (a second of planning), for the tests
    that run that cell only to meet a fault or a refusal; a Plan is frozen, so sharing it
    couples no test to another."""
    return make_plan(load_config())
