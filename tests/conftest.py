"""Test-wide settings: every property test is seeded, so a failure is reproducible and CI never
fails at random (Hypothesis derives its examples from the test's name, not from the clock)."""

from hypothesis import settings

settings.register_profile("slidecal", derandomize=True, deadline=None, print_blob=True)
settings.load_profile("slidecal")
