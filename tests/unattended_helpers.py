"""Sessions for the verdict tests: the garbage a user can feed slidecal (see
:mod:`slidecal.routines.bench_verdict`, which makes the same for its figures)."""

from __future__ import annotations

from pathlib import Path

from slidecal.routines.bench_verdict import (  # noqa: F401 - re-exported for the tests
    copy_session,
    edit_session,
    record_without_translation,
    rotations_in_degrees,
    square_size,
)

DATA = Path(__file__).parent / "data"
