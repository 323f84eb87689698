"""slidecal.routines.testing, as a user's CI imports it: the fixture runs a simulated cell end to
end; a cell naming real hardware is refused before anything starts."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import pytest
import yaml

from slidecal.routines.testing import simulated_run, simulated_run_fixture  # noqa: F401
from slidecal.solver.errors import InputError


def test_real_hardware_is_refused(tmp_path: Path) -> None:
    d = yaml.safe_load(resources.files("slidecal.mocks").joinpath("default_cell.yaml").read_text())
    d["robot"] = {"driver": "ur", "host": "192.0.2.10"}
    d["cameras"] = {"driver": "uvc", "list": [{"name": "cam", "width": 1280, "height": 800}]}
    cell = tmp_path / "cell.yaml"
    cell.write_text(yaml.safe_dump(d))
    with pytest.raises(InputError, match="names real hardware .*simulated_run only runs"):
        simulated_run(tmp_path, cell)
    assert not (tmp_path / "session").exists()


@pytest.mark.slow
def test_fixture_runs_the_eye_to_hand_cell(simulated_run_fixture, tmp_path: Path) -> None:  # noqa: F811
    cell = resources.files("slidecal.mocks").joinpath("eye_to_hand_cell.yaml")
    o = simulated_run_fixture(config=str(cell), seed=3)
    assert o.session_dir == tmp_path / "session" and (o.session_dir / "result.yaml").is_file()
    assert o.result.mount == "eye_to_hand" and o.result.converged
    assert o.errors["cam.fx_rel"] < 1e-3
    assert o.errors["T_base_cam.rot_deg"] < 0.05 and o.errors["T_base_cam.t_mm"] < 1.0
    assert o.errors["T_tool_board.t_mm"] < 1.0
