"""slidecal rehearse: the cell's routine through the real ur-rtde client on the loopback
controller, the simulated camera rendering from the controller's pose."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from slidecal.routines import cli
from slidecal.routines.ops.rehearse import rehearse
from slidecal.routines.run import RunRequest, run_calibration
from slidecal.routines.session import load_session
from slidecal.solver.errors import HardwareFault, InputError

pytest.importorskip("rtde_control")


REAL_CELL = {
    "format": "slidecal.cell/1",
    "mount": "eye_in_hand",
    "robot": {"driver": "ur", "host": "192.168.1.10", "model": "UR5e", "speed_mps": 0.25,
              "accel_mps2": 1.0, "settle_s": 0.3,
              "payload": {"mass_kg": 0.4, "cog_m": [0, 0, 0.03]},
              "workspace": {"min_m": [-0.85, -0.45, 0.15], "max_m": [-0.05, 0.45, 0.9]}},
    "cameras": {"driver": "uvc", "list": [{"name": "cam", "width": 1280, "height": 800}]},
    "target": {"kind": "charuco", "squares_x": 11, "squares_y": 8, "square_size_m": 0.03,
               "marker_size_m": 0.022, "dictionary": "DICT_5X5_100"},
    "approximate": {"T_base_board": {"rpy_deg": [180, 0, 0], "t_m": [-0.565, 0.12, 0.0]},
                    "T_tool_cam": {"rpy_deg": [0, 0, 90], "t_m": [0.03, -0.06, 0.04]},
                    "standoff_m": 0.5},
}


def _write(tmp_path, cell) -> str:
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(cell))
    return str(path)


def test_a_real_cell_is_rehearsed_through_its_simulated_twin(tmp_path):
    from slidecal.routines.config import load_config
    from slidecal.routines.ops.rehearse import simulated_twin
    from slidecal.routines.planner import make_plan

    real = load_config(_write(tmp_path, REAL_CELL))
    twin = simulated_twin(real)
    assert twin.simulated and [c.name for c in twin.cameras] == ["cam"]
    assert (twin.cameras[0].width, twin.cameras[0].height) == (1280, 800)
    np.testing.assert_allclose(twin.simulation.T_hand_eye, real.approx_T_hand_eye)
    np.testing.assert_allclose(twin.simulation.T_target, real.approx_T_target)
    # the start pose puts the camera at the stand-off over the middle of the target
    T_base_cam = twin.robot.start_pose @ real.approx_T_hand_eye
    T_cam_board = np.linalg.inv(T_base_cam) @ real.approx_T_target
    pts = real.target.points_m
    mid = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    np.testing.assert_allclose((T_cam_board @ np.append(mid, 1.0))[:3], [0, 0, 0.5], atol=1e-9)
    assert make_plan(twin).n_poses > 0


def test_a_twin_cannot_invent_extrinsics(tmp_path):
    from slidecal.routines.config import load_config
    from slidecal.routines.ops.rehearse import simulated_twin

    cell = {**REAL_CELL, "cameras": {"driver": "uvc", "list": [
        {"name": "a", "width": 640, "height": 480}, {"name": "b", "width": 640, "height": 480}]}}
    with pytest.raises(InputError, match="cannot invent the extrinsics"):
        simulated_twin(load_config(_write(tmp_path, cell)))


@pytest.mark.slow
def test_rehearse_a_real_cell_file(tmp_path):
    """The integrator's cell file as it will run on the real robot, payload included."""
    out = tmp_path / "s"
    outcome = rehearse(_write(tmp_path, REAL_CELL), out, progress=False)
    assert outcome.n_frames > 0 and outcome.result.converged
    info = yaml.safe_load((out / "rehearsal.yaml").read_text())
    assert info["controller"]["payload"] == {"mass_kg": 0.4, "cog_m": [0.0, 0.0, 0.03]}


@pytest.mark.slow
def test_rehearsal_gives_the_calibration_of_the_simulated_run(tmp_path):
    """Same cell, same plan, same truth: the two estimates differ only by their noise (the
    controller draws its own pose errors), so by less than 4 sigma of the difference."""
    reh = rehearse(None, tmp_path / "rehearsal", progress=False)
    run = run_calibration(
        RunRequest(None, out_dir=tmp_path / "run", progress=False, recording=False)
    )
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
    from slidecal.routines.ops import rehearse as rh

    monkeypatch.setattr(rh.LoopbackController, "__init__", _refuse)
    with pytest.raises(HardwareFault, match="did not start"):
        rehearse(None, tmp_path / "s")


def _refuse(self, options, host=None):
    raise HardwareFault("the loopback controller did not start: port 30004 (rtde) is taken")


def _starving(monkeypatch, starve: str) -> None:
    """The loopback controller started on a host that stalls it (``--starve S,EVERY_S``)."""
    from slidecal.routines.ops import rehearse as rh

    start = rh.LoopbackController.__init__
    monkeypatch.setattr(rh.LoopbackController, "__init__",
                        lambda self, options, host=None: start(self, [*options, "--starve",
                                                                      starve], host))


@pytest.mark.slow
def test_a_rehearsal_does_not_fail_for_the_hosts_load(tmp_path, monkeypatch):
    """Issue 36 item 3: a loopback stalled 0.3 s every 2 s (a host at load 5) tripped the
    driver's 0.1 s stale-data limit; the rehearsal's limit fits the loopback's gaps."""
    _starving(monkeypatch, "0.3,2")
    outcome = rehearse(None, tmp_path / "s", progress=False)
    assert outcome.n_frames > 0
    info = yaml.safe_load((tmp_path / "s" / "rehearsal.yaml").read_text())
    assert info["controller_cycle_gap_max_s"] >= 0.3 and info["stale_limit_s"] >= 0.9


@pytest.mark.slow
def test_a_starved_loopback_is_named_in_the_fault(tmp_path, monkeypatch):
    _starving(monkeypatch, "1.5,3")
    with pytest.raises(HardwareFault, match=r"loopback controller itself went 1\.\d\d s "
                       r"unscheduled .* not the driver's fault"):
        rehearse(None, tmp_path / "s", progress=False)
