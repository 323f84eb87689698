"""slidecal rehearse: the cell's routine through the real ur-rtde client on the loopback
controller, the simulated camera rendering from the controller's pose."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from slidecal.routines import cli
from slidecal.routines.rehearse import rehearse
from slidecal.routines.run import run_calibration
from slidecal.routines.session import load_session
from slidecal.solver.errors import HardwareFault, InputError

pytest.importorskip("rtde_control")


def test_rehearse_refuses_a_cell_without_a_simulation(tmp_path):
    cell = {
        "robot": {"driver": "ur", "host": "192.168.1.10"},
        "cameras": {"driver": "uvc", "list": [{"name": "cam", "width": 640, "height": 480}]},
        "target": {"kind": "chessboard", "squares_x": 9, "squares_y": 6, "square_size_m": 0.03},
        "approximate": {"T_base_board": {"rpy_deg": [180, 0, 0], "t_m": [0.3, 0, 0]}},
    }
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(cell))
    with pytest.raises(InputError, match="rehearse needs a simulated cell"):
        rehearse(path, tmp_path / "s")


@pytest.mark.slow
def test_rehearsal_gives_the_calibration_of_the_simulated_run(tmp_path):
    """Same cell, same plan, same truth: the two estimates differ only by their noise (the
    controller draws its own pose errors), so by less than 4 sigma of the difference."""
    reh = rehearse(None, tmp_path / "rehearsal", progress=False)
    run = run_calibration(None, out_dir=tmp_path / "run", progress=False, recording=False)
    assert reh.n_frames == run.n_frames
    info = yaml.safe_load((tmp_path / "rehearsal" / "rehearsal.yaml").read_text())
    assert info["controller"]["polyscope_version"].startswith("5.12")
    assert info["arm_at_rest"] is True
    for key, err in reh.errors.items():  # against the truth, like the simulated run
        assert np.isfinite(err), key
    compare = _compare(reh.result, run.result)
    assert all(z < 4.0 for z in compare.values()), compare


def _compare(r1, r2) -> dict[str, float]:
    """|difference| / combined one-sigma of K's entries and the hand-eye translation."""
    c1, c2 = r1.cameras["cam"], r2.cameras["cam"]
    out = {}
    for i, j, name in ((0, 0, "fx"), (1, 1, "fy"), (0, 2, "cx"), (1, 2, "cy")):
        s = np.hypot(c1.std[name], c2.std[name])
        out[name] = abs(c1.K[i, j] - c2.K[i, j]) / s
    return out


@pytest.mark.slow
def test_a_fault_in_a_rehearsal_stops_keeps_frames_and_exits_3(tmp_path, capsys):
    out = tmp_path / "s"
    code = cli.main(["rehearse", "--out", str(out), "--fault", "protective_stop@1", "--quiet"])
    err = capsys.readouterr().err
    assert code == 3, err
    assert "protective stop" in err and "the 1 frames captured before it" in err
    session = load_session(out, detect_images=False)
    assert len(session.problem.frames) == 1 and session.status == "aborted"
    assert session.events[0]["kind"] == "fault"
    info = yaml.safe_load((out / "rehearsal.yaml").read_text())
    assert info["controller_events"] == ["protective stop"] and info["arm_at_rest"] is True


def test_a_dead_controller_is_a_hardware_fault(monkeypatch, tmp_path):
    from slidecal.routines import rehearse as rh

    monkeypatch.setattr(rh.LoopbackController, "__init__", _refuse)
    with pytest.raises(HardwareFault, match="did not start"):
        rehearse(None, tmp_path / "s")


def _refuse(self, options, host=None):
    raise HardwareFault("the loopback controller did not start: port 30004 (rtde) is taken")
