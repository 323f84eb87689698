"""--fault KIND@FRAME on the simulated cell: every kind stops the arm, keeps the frames captured
before it, records the event in the session and exits with the hardware-fault code."""

from __future__ import annotations

import pytest

from slidecal.mocks import robot as simrobot
from slidecal.routines import cli
from slidecal.routines import run as run_module
from slidecal.routines.ops.faults import FAULT_KINDS, FaultInjector, FaultSpec, parse_fault
from slidecal.routines.plan import write_plan
from slidecal.routines.session import load_session
from slidecal.solver.errors import InputError


def test_parse_fault():
    assert parse_fault("protective_stop@3") == FaultSpec("protective_stop", 3)
    assert str(parse_fault(" camera_lost@0 ")) == "camera_lost@0"
    for bad in ("protective_stop", "meteor@2", "stall@-1", "stall@x", "@3"):
        with pytest.raises(InputError, match="KIND@FRAME"):
            parse_fault(bad)


def test_a_bad_fault_is_bad_input_and_nothing_runs(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(run_module, "make_plan", lambda *a, **k: pytest.fail("planned"))
    code = cli.main(["run", "--out", str(tmp_path / "s"), "--fault", "meteor@1", "--quiet"])
    assert code == 2
    assert "slidecal: --fault: 'meteor@1' is not KIND@FRAME" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_faults_are_never_injected_into_real_hardware():
    class RealRobot:  # what a real driver offers: no inject_fault
        moves = 0

    with pytest.raises(InputError, match="never into real hardware"):
        FaultInjector.for_simulated(["stall@1"], RealRobot(), None)


@pytest.mark.slow
@pytest.mark.parametrize("kind", FAULT_KINDS)
def test_each_fault_stops_keeps_frames_records_and_exits_3(kind, tmp_path, monkeypatch, capsys):
    stops: list[int] = []
    original = simrobot.SimulatedUR.stop

    def spy(self):
        stops.append(self.moves)
        original(self)

    monkeypatch.setattr(simrobot.SimulatedUR, "stop", spy)
    out = tmp_path / "session"
    code = cli.main(["run", "--out", str(out), "--fault", f"{kind}@2", "--quiet",
                     "--no-recording"])
    err = capsys.readouterr().err
    assert code == 3, err
    assert "the 2 frames captured before it are in" in err
    assert len(err.strip().splitlines()) == 1  # one line, no traceback
    assert stops, "the arm was not stopped"
    session = load_session(out, detect_images=False)
    assert len(session.problem.frames) == 2
    assert session.status == "aborted"
    *retries, event = session.events  # a camera fault is first retried (reconnecting)
    assert all(e["kind"] == "retry" for e in retries)
    assert len(retries) == (2 if kind in ("no_frame", "camera_lost") else 0)
    assert event["kind"] == "fault" and event["frames_kept"] == 2
    assert not (out / "result.yaml").exists()


def test_a_camera_lost_for_good_is_reported_by_its_cause(tmp_path, capsys, default_plan):
    # the retries reconnect the camera; when that fails too, the error names what happened
    # (the rig disconnected, and reconnecting found no camera), not the closed rig the last
    # capture would have met
    out = tmp_path / "session"
    write_plan(default_plan, tmp_path / "plan.yaml")
    code = cli.main(["run", "--out", str(out), "--plan", str(tmp_path / "plan.yaml"),
                     "--fault", "camera_lost@1", "--quiet", "--no-recording"])
    err = capsys.readouterr().err
    assert code == 3, err
    assert "camera rig disconnected" in err and "reconnecting failed: no camera found" in err
    assert "closed camera rig" not in err
    event = load_session(out, detect_images=False).events[-1]
    assert "camera rig disconnected" in event["message"]
