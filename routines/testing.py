"""Helpers for users' CI: a whole calibration run on the simulated cell, as a pytest fixture.

In a project's ``conftest.py``::

    from slidecal.routines.testing import simulated_run_fixture  # noqa: F401

then in a test::

    def test_our_cell_calibrates(simulated_run_fixture):
        outcome = simulated_run_fixture(config="cells/line4.yaml")
        assert outcome.verdict.verdict == "accepted", outcome.verdict.lines()
        assert outcome.errors["cam.fx_rel"] < 1e-3

or call :func:`simulated_run` directly with a temporary directory. Only simulated cells are
accepted here: a CI job must never move a robot.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from slidecal.routines.config import CellConfig, load_config
from slidecal.routines.run import RunRequest, run_calibration
from slidecal.routines.solve import RunOutcome
from slidecal.solver.errors import InputError


def simulated_run(
    tmp_path: str | Path,
    config: str | Path | CellConfig | None = None,
    seed: int = 0,
    recording: bool = False,
    **overrides: Any,
) -> RunOutcome:
    """Run the routine end to end on a simulated cell into ``tmp_path/session`` and return the
    outcome; ``overrides``: top-level cell sections merged over the file (e.g. ``plan={"tilts_deg":
    [20, 30]}``, ``limits={"max_rms_px": 0.5}``). Refuses real hardware."""
    cfg = config if isinstance(config, CellConfig) else load_config(config, overrides)
    if not cfg.simulated:
        raise InputError(
            f"{cfg.source} names real hardware (robot.driver: {cfg.robot.driver}); "
            "simulated_run only runs simulated cells"
        )
    return run_calibration(
        RunRequest(
            cfg, out_dir=Path(tmp_path) / "session", progress=False, recording=recording, seed=seed
        )
    )


@pytest.fixture
def simulated_run_fixture(tmp_path: Path):
    """A callable ``(**kwargs) -> RunOutcome`` running :func:`simulated_run` in ``tmp_path``."""

    def _run(**kwargs: Any) -> RunOutcome:
        return simulated_run(tmp_path, **kwargs)

    return _run
