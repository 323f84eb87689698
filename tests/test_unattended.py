"""A run nobody watches: signals, resume, retries, the cell lock, the install store, check,
one-line errors for what used to be tracebacks, logs a job can keep."""

from __future__ import annotations

import errno
import io
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from slidecal.mocks.cell import SimulatedCell
from slidecal.mocks.scenarios import cell_overrides, same_cell
from slidecal.routines import cli
from slidecal.routines.config import load_config
from slidecal.routines.ops.install import (
    CURRENT,
    NotInstalled,
    history,
    install,
    installed_result,
    rollback,
)
from slidecal.routines.ops.lock import Lock, cell_lock_path
from slidecal.routines.plan import write_plan
from slidecal.routines.progress import Progress
from slidecal.routines.run import RunRequest, run_calibration
from slidecal.routines.session import SessionWriter, load_session, write_atomic
from slidecal.solver.errors import HardwareFault, InputError

sys.path.insert(0, str(Path(__file__).parent))
from unattended_helpers import simulated_run_command  # noqa: E402

DATA = Path(__file__).parent / "data"


def _slidecal(*args: str, cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "slidecal.routines.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, **(env or {})},
    )


def _one_line_exit_2(p: subprocess.CompletedProcess) -> None:
    assert p.returncode == 2, p.stderr
    assert p.stderr.startswith("slidecal: ") and p.stderr.count("\n") == 1, p.stderr
    assert "Traceback" not in p.stderr


# ----------------------------------------------------------------------------- signals, resume


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _start_run(
    out: Path, cwd: Path, lock_dir: Path, sigint_ignored: bool = False
) -> subprocess.Popen:
    return subprocess.Popen(
        simulated_run_command(out),
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "SLIDECAL_LOCK_DIR": str(lock_dir)},
        # what a shell's background job (no job control) or nohup hands its children
        preexec_fn=_ignore_sigint if sigint_ignored else None,
    )


@pytest.mark.slow
@pytest.mark.parametrize(
    ("sig", "name", "after", "sigint_ignored"),
    [
        (signal.SIGTERM, "SIGTERM", 2, False),
        (signal.SIGHUP, "SIGHUP", 5, False),
        (signal.SIGINT, "Ctrl-C", 1, False),
        # started with SIGINT ignored, as a background job is: Ctrl-C still stops the robot
        # (before, such a run went on to its last frame and exited 0)
        (signal.SIGINT, "Ctrl-C", 1, True),
    ],
)
def test_signal_stops_the_run_and_resume_completes(
    tmp_path: Path, sig, name, after, sigint_ignored
) -> None:
    out = tmp_path / "s"
    p = _start_run(out, tmp_path, tmp_path, sigint_ignored)
    # the plain progress lines (stderr is a pipe) say when a frame is done
    lines = []
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        line = p.stderr.readline()
        lines.append(line)
        if f"frame {after} of" in line and "done" in line:
            break
    else:
        p.kill()
        pytest.fail("no progress lines: " + "".join(lines))
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    assert f"interrupted by {name}" in err and "Traceback" not in err
    s = load_session(out, detect_images=False)
    assert s.status == "aborted" and after <= len(s.problem.frames) <= after + 1
    ev = s.events[-1]
    assert (
        ev["kind"] == "interrupted" and name in ev["message"] and "robot stopped" in ev["message"]
    )
    assert not (out / "result.yaml").exists()
    kept = len(s.problem.frames)
    # resume: the plan goes on from the first missing frame; the session completes
    r = _slidecal(
        "run",
        "--resume",
        str(out),
        "--quiet",
        cwd=tmp_path,
        env={"SLIDECAL_LOCK_DIR": str(tmp_path)},
    )
    assert r.returncode == 0, r.stderr
    s = load_session(out, detect_images=False)
    n_plan = sum(len(g) for g in yaml.safe_load((out / "plan.yaml").read_text())["groups"])
    assert s.status == "complete" and len(s.problem.frames) == n_plan
    assert [e["kind"] for e in s.events] == ["interrupted", "resumed"]
    assert yaml.safe_load((out / "verdict.yaml").read_text())["verdict"] == "accepted"
    assert kept < n_plan


def test_resume_of_a_complete_session_refused(tmp_path: Path) -> None:
    import shutil

    shutil.copytree(DATA / "r1_session", tmp_path / "s")
    with pytest.raises(InputError, match="is complete; nothing to resume"):
        run_calibration(RunRequest(resume=tmp_path / "s", progress=False))


@pytest.mark.slow
@pytest.mark.parametrize(("at_move", "kept"), [(4, 3), (0, 0)])
def test_fault_then_resume_in_process(tmp_path: Path, at_move: int, kept: int) -> None:
    cfg = load_config()
    cell = SimulatedCell.from_config(cfg, seed=2)
    cell.robot.inject_fault("protective_stop", at_move=at_move)
    out = tmp_path / "s"
    with pytest.raises(HardwareFault, match="slidecal run --resume"):
        run_calibration(RunRequest(cfg, out_dir=out, progress=False, recording=False, cell=cell))
    n = len(yaml.safe_load((out / "session.yaml").read_text())["frames"])
    assert cell.robot.stopped and n == kept
    o = run_calibration(RunRequest(cfg, resume=out, progress=False))
    assert o.verdict.verdict == "accepted" and o.n_frames == 9
    s = load_session(out, detect_images=False)
    assert [e["kind"] for e in s.events] == ["fault", "resumed"]


# ----------------------------------------------------------------------------- retries


@pytest.mark.slow
def test_dropped_frames_and_a_lost_camera_are_retried(tmp_path: Path) -> None:
    cfg = load_config()
    cell = SimulatedCell.from_config(cfg, seed=0)
    cell.rig.inject_fault("no_frame", at_capture=1)
    cell.rig.inject_fault("disconnect", at_capture=4)
    buf = io.StringIO()
    o = run_calibration(RunRequest(
        cfg, out_dir=tmp_path / "s", progress=Progress(9, stream=buf), recording=False, cell=cell
    ))
    assert o.n_frames == 9 and o.verdict.verdict == "accepted"
    s = load_session(tmp_path / "s", detect_images=False)
    retries = [e for e in s.events if e["kind"] == "retry"]
    assert len(retries) == 2 and "reconnecting" in retries[1]["message"]
    assert "retry 1 of 2" in buf.getvalue()


@pytest.mark.slow
def test_retries_exhausted_is_a_fault_with_frames_kept(tmp_path: Path) -> None:
    cfg = load_config()
    cell = SimulatedCell.from_config(cfg, seed=0)
    cell.rig.inject_fault("disconnect", at_capture=2)
    real_open, opened = cell.rig.open, []

    def open_once() -> None:  # the camera never comes back
        if opened:
            raise HardwareFault("no OAK device found")
        opened.append(1)
        real_open()

    cell.rig.open = open_once
    with pytest.raises(HardwareFault, match="2 frames captured before it"):
        run_calibration(RunRequest(
            cfg, out_dir=tmp_path / "s", progress=False, recording=False, cell=cell, retries=1
        ))
    assert cell.robot.stopped


@pytest.mark.slow
def test_image_without_corners_is_captured_again(tmp_path: Path) -> None:
    import numpy as np

    cfg = load_config()
    cell = SimulatedCell.from_config(cfg, seed=0)
    capture = cell.rig.capture

    def blank_once():
        images = capture()
        if cell.rig.capture_count == 3:
            return {n: np.zeros_like(im) for n, im in images.items()}
        return images

    cell.rig.capture = blank_once
    o = run_calibration(
        RunRequest(cfg, out_dir=tmp_path / "s", progress=False, recording=False, cell=cell)
    )
    assert o.n_frames == 9
    ev = load_session(tmp_path / "s", detect_images=False).events
    assert [e["kind"] for e in ev] == ["retry"] and "no corner" in ev[0]["message"]


# ----------------------------------------------------------------------------- lock


def test_lock_refuses_a_second_run_and_takes_over_a_stale_one(tmp_path: Path) -> None:
    path = tmp_path / "x.lock"
    with Lock(path, "the cell") as held:
        assert held.stale is None
        with pytest.raises(InputError, match=f"in use by process {os.getpid()}"):
            Lock(path, "the cell").acquire()
    assert not path.exists()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    import socket

    path.write_text(f"{dead.pid} {socket.gethostname()} 0\n")
    lk = Lock(path, "the cell").acquire()
    assert lk.stale is not None and str(dead.pid) in lk.stale
    lk.release()


def test_run_on_a_locked_cell_refused_before_connecting(tmp_path, monkeypatch, default_plan):
    from importlib import resources

    monkeypatch.setenv("SLIDECAL_LOCK_DIR", str(tmp_path))
    cell_file = tmp_path / "cell.yaml"
    cell_file.write_text(
        resources.files("slidecal.mocks").joinpath("default_cell.yaml").read_text()
    )
    cfg = load_config(cell_file)
    cell = SimulatedCell.from_config(cfg, seed=0)
    with Lock(cell_lock_path(f"file:{cell_file.resolve()}"), "the cell"):
        with pytest.raises(InputError, match="is in use by process"):
            run_calibration(
                RunRequest(str(cell_file), plan=default_plan, out_dir=tmp_path / "s",
                           progress=False, cell=cell)
            )
    assert cell.robot.moves == 0 and not (tmp_path / "s").exists()


# ----------------------------------------------------------------------------- install store


@pytest.fixture(scope="module")
def solved_dir(tmp_path_factory):
    import shutil

    from slidecal.routines.solve import solve_session

    d = tmp_path_factory.mktemp("inst") / "s"
    shutil.copytree(DATA / "r1_session", d)
    o = solve_session(d)
    return d, o.result


def test_install_history_and_rollback(solved_dir, tmp_path: Path) -> None:
    d, r = solved_dir
    store = tmp_path / "store"
    first = install(store, d, r, "accepted")
    assert (store / CURRENT).resolve() == first
    assert {p.name for p in (first / "export").iterdir()} >= {"camchain.yaml", "hand_eye.yaml"}
    second = install(store, d, r, "accepted")
    assert history(store) == [first, second] and (store / CURRENT).resolve() == second
    left, now = rollback(store)
    assert (left, now) == (second, first) and (store / CURRENT).resolve() == first
    assert (second / "ROLLED_BACK").is_file()
    with pytest.raises(InputError, match="nothing to roll back"):
        rollback(store)
    assert installed_result(store).cameras["cam"].K[0, 0] == r.cameras["cam"].K[0, 0]


def test_rejected_never_installed_worse_needs_force(solved_dir, tmp_path: Path) -> None:
    import dataclasses

    d, r = solved_dir
    store = tmp_path / "store"
    install(store, d, r, "accepted")
    with pytest.raises(NotInstalled, match="rejected"):
        install(store, d, r, "rejected", force=True)
    with pytest.raises(NotInstalled, match="--accept-drift"):
        install(store, d, r, "drifted")
    cam = r.cameras["cam"]
    worse = dataclasses.replace(
        r, cameras={"cam": dataclasses.replace(cam, std={**cam.std, "cx": 2 * cam.std["cx"]})}
    )
    with pytest.raises(NotInstalled, match="cam.cx_px one-sigma is 2.00 times"):
        install(store, d, worse, "accepted")
    assert len(history(store)) == 1
    install(store, d, worse, "accepted", force=True)
    assert len(history(store)) == 2


def test_a_crash_while_installing_leaves_current_intact(solved_dir, tmp_path, monkeypatch):
    import slidecal.routines.ops.install as inst

    d, r = solved_dir
    store = tmp_path / "store"
    first = install(store, d, r, "accepted")
    calls = {"n": 0}
    real = inst.write_atomic

    def dies_midway(dst, data):  # noqa: ANN001
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(dst))
        real(dst, data)

    monkeypatch.setattr(inst, "write_atomic", dies_midway)
    with pytest.raises(OSError):
        install(store, d, r, "accepted")
    assert (store / CURRENT).resolve() == first and history(store) == [first]
    assert not [p for p in store.iterdir() if p.name.startswith(".staging")]


@pytest.mark.slow
def test_run_install_then_check_ok_then_drifted(tmp_path: Path) -> None:
    from slidecal.routines.ops.check import run_check

    store = tmp_path / "store"
    cfg = load_config()
    o = run_calibration(RunRequest(
        cfg,
        out_dir=tmp_path / "s",
        progress=False,
        recording=False,
        install=store,
        cell=same_cell(cfg, 3, 1),
    ))
    assert o.installed_to is not None and o.exit_code == 0
    info = yaml.safe_load((store / CURRENT / "installed.yaml").read_text())
    assert info["chain_rms_px"]["cam"] > 0
    # the same cell (arm, board) checked again with fresh noise
    v, d = run_check(cfg, store, tmp_path / "c1", progress=False, cell=same_cell(cfg, 3, 2))
    assert v.verdict == "ok", v.lines()
    chk = yaml.safe_load((d / "verdict.yaml").read_text())["check"]
    assert chk["robot_time_s"] <= 15.0 and chk["frames"] == 6
    assert chk["paired"]["usable"] and chk["paired"]["cameras"]["cam"]["max_px"] < 0.5
    # the camera's principal point moved by 1 px since the install
    moved = load_config(overrides=cell_overrides(cx_px=1.0))
    v, _ = run_check(moved, store, tmp_path / "c2", progress=False, cell=same_cell(moved, 3, 3))
    assert v.verdict == "drifted" and v.exit_code == 5
    assert [c.test for c in v.reasons] == ["paired"]


def test_install_keeps_the_session_without_images(solved_dir, tmp_path: Path) -> None:
    from slidecal.routines.ops.install import installed_session
    from slidecal.routines.ops.verdict import judge

    d, r = solved_dir
    doc = yaml.safe_load((d / "session.yaml").read_text())
    doc["frames"][0]["images"] = {"cam": "images/0000_cam.png"}  # not copied into the store
    src = tmp_path / "src"
    src.mkdir()
    for p in d.iterdir():
        if p.is_file():
            (src / p.name).write_bytes(p.read_bytes())
    (src / "session.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    entry = install(tmp_path / "store", src, r, "accepted")
    kept = yaml.safe_load((entry / "session.yaml").read_text())
    assert not any("images" in f for f in kept["frames"])
    mine, theirs = load_session(d).problem, installed_session(entry)
    assert len(theirs.frames) == len(mine.frames)
    f0, g0 = mine.frames[0], theirs.frames[0]
    assert (f0.T_base_tool == g0.T_base_tool).all()
    assert (f0.detections["cam"].px == g0.detections["cam"].px).all()
    # the gate finds the session beside the installed result: the same frames, no drift
    v = judge(r, problem=mine, installed=r, installed_path=str(entry))
    assert v.installed["paired"]["usable"] and v.verdict == "accepted"
    assert installed_session(tmp_path) is None  # no session kept there


# ----------------------------------------------------------------------------- one line, exit 2


def test_out_naming_a_file_or_empty(tmp_path: Path, capsys) -> None:
    f = tmp_path / "file"
    f.write_text("x")
    for out in (str(f), str(f / "under"), ""):
        assert cli.main(["run", "--quiet", "--out", out]) == 2
        err = capsys.readouterr().err
        assert err.startswith("slidecal: ") and err.count("\n") == 1
    assert f.read_text() == "x"


def test_read_only_out(tmp_path: Path, capsys, monkeypatch) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, m: False if Path(p) == ro else real(p, m))
    assert cli.main(["run", "--quiet", "--out", str(ro / "s")]) == 2
    assert "read-only" in capsys.readouterr().err


def test_negative_seed_and_retries(capsys) -> None:
    assert cli.main(["run", "--quiet", "--seed", "-1"]) == 2
    assert "--seed must be 0 or a positive integer" in capsys.readouterr().err
    assert cli.main(["run", "--quiet", "--retries", "-1"]) == 2


def test_solve_out_under_a_file(tmp_path: Path, capsys) -> None:
    import shutil

    shutil.copytree(DATA / "r1_session", tmp_path / "s")
    (tmp_path / "f").write_text("x")
    assert cli.main(["solve", str(tmp_path / "s"), "--out", str(tmp_path / "f" / "r.yaml")]) == 2
    err = capsys.readouterr().err
    assert "is a file" in err and err.count("\n") == 1


def test_plan_out_naming_a_directory_leaves_nothing(tmp_path: Path, capsys) -> None:
    (tmp_path / "d").mkdir()
    assert cli.main(["plan", "--out", str(tmp_path / "d")]) == 2
    assert "is a directory" in capsys.readouterr().err
    assert list(tmp_path.glob(".*")) == [] and list((tmp_path / "d").iterdir()) == []


def test_plan_suggests_a_working_run_command(tmp_path: Path, capsys) -> None:
    from importlib import resources

    cell = tmp_path / "my cell.yaml"
    cell.write_text(resources.files("slidecal.mocks").joinpath("default_cell.yaml").read_text())
    assert cli.main(["plan", "--config", str(cell), "--out", str(tmp_path / "p.yaml")]) == 0
    out = capsys.readouterr().out
    assert f"slidecal run --config '{cell}' --plan {tmp_path / 'p.yaml'}" in out


def test_run_help_speaks_of_the_planner(capsys) -> None:
    with pytest.raises(SystemExit):
        cli.main(["run", "--help"])
    text = capsys.readouterr().out
    assert "fixed default plan" not in text and "planner" in text and "--resume" in text


def test_degenerate_user_plan_refused_before_the_robot_moves(tmp_path: Path, default_plan):
    from slidecal.routines.plan import Plan

    cfg = load_config()
    plan = default_plan
    flat = Plan(groups=tuple(tuple(g[0] for _ in g) for g in plan.groups), via=plan.via)
    write_plan(flat, tmp_path / "flat.yaml")
    cell = SimulatedCell.from_config(cfg, seed=0)
    with pytest.raises(InputError, match="flat.yaml: group 0 has no translation"):
        run_calibration(
            RunRequest(cfg, plan=tmp_path / "flat.yaml", out_dir=tmp_path / "s", cell=cell)
        )
    assert cell.robot.moves == 0 and not (tmp_path / "s").exists()


def test_a_python_plan_whose_group_turns_is_refused_before_the_robot_moves(tmp_path, default_plan):
    """A Plan made in Python meets the plan file's rule: a group's poses share one orientation."""
    import math
    from dataclasses import replace

    from slidecal.solver.geometry import R_from_rvec, T_from_Rt

    first, *rest = default_plan.groups
    turn = R_from_rvec([0.0, 0.0, math.radians(0.3)])  # 0.3 deg about the optical axis
    turned = T_from_Rt(first[1][:3, :3] @ turn, first[1][:3, 3])
    plan = replace(default_plan, groups=((first[0], turned, *first[2:]), *rest))
    cell = SimulatedCell.from_config(load_config(), seed=0)
    with pytest.raises(InputError, match=r"plan: groups\[0\]\[1\]: turns 0.3 deg"):
        run_calibration(RunRequest(plan=plan, out_dir=tmp_path / "s", cell=cell))
    assert cell.robot.moves == 0 and not (tmp_path / "s").exists()


def test_disk_full_while_rewriting_session_yaml(tmp_path: Path, monkeypatch) -> None:
    w = SessionWriter(tmp_path / "s", load_config().target, load_config().cameras)
    before = (tmp_path / "s" / "session.yaml").read_text()

    def full(fd):  # noqa: ANN001
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError):
        w.add_event("x", "y")
    assert (tmp_path / "s" / "session.yaml").read_text() == before
    assert not (tmp_path / "s" / ".session.yaml.tmp").exists()
    monkeypatch.undo()
    write_atomic(tmp_path / "s" / "t.txt", "ok")
    assert (tmp_path / "s" / "t.txt").read_text() == "ok"


def test_disk_full_mid_run_stops_the_robot_one_line(tmp_path, monkeypatch, default_plan):
    import slidecal.routines.session as session_mod

    cfg = load_config()
    cell = SimulatedCell.from_config(cfg, seed=0)
    real = session_mod.SessionWriter.append_frame
    count = {"n": 0}

    def append(self, *a, **k):  # noqa: ANN001, ANN002, ANN003
        count["n"] += 1
        if count["n"] == 3:
            raise OSError(errno.ENOSPC, "No space left on device", "session.yaml")
        return real(self, *a, **k)

    monkeypatch.setattr(session_mod.SessionWriter, "append_frame", append)
    with pytest.raises(InputError, match="No space left on device.*robot was stopped"):
        run_calibration(
            RunRequest(cfg, plan=default_plan, out_dir=tmp_path / "s", progress=False,
                       recording=False, cell=cell)
        )
    assert cell.robot.stopped and _frames(tmp_path / "s") == 2


# ----------------------------------------------------------------------------- logs


def test_progress_lines_off_a_terminal() -> None:
    buf = io.StringIO()
    p = Progress(3, stream=buf)
    p.step(0, "group 1: moving")
    p.frame_done("cam 70 corners")
    p.event("verdict: accepted")
    p.done("done")
    lines = buf.getvalue().splitlines()
    assert len(lines) == 4 and "\r" not in buf.getvalue()
    assert all(len(ln) > 25 and ln[:4].isdigit() and ln[23] == "Z" for ln in lines)
    assert "cam 70 corners" in lines[1] and lines[2].endswith("verdict: accepted")
    quiet = io.StringIO()
    Progress(3, stream=quiet, quiet=True).event("x")
    assert quiet.getvalue() == ""


def test_hardware_fault_cli_exit_3_kept(monkeypatch, capsys) -> None:
    import slidecal.routines.run as run

    def boom(*a, **k):  # noqa: ANN002, ANN003
        raise HardwareFault("protective stop during move 3")

    monkeypatch.setattr(run, "run_calibration", boom)
    assert cli.main(["run", "--quiet"]) == 3


def test_spawn_without_a_viewer_is_one_line(tmp_path: Path, default_plan) -> None:
    write_plan(default_plan, tmp_path / "plan.yaml")  # planning is not what this is about
    p = _slidecal(
        "run",
        "--out",
        str(tmp_path / "s"),
        "--plan",
        str(tmp_path / "plan.yaml"),
        "--spawn",
        "--quiet",
        cwd=tmp_path,
        env={"PATH": str(tmp_path), "SLIDECAL_LOCK_DIR": str(tmp_path)},
    )
    _one_line_exit_2(p)
    assert "--spawn could not start the rerun viewer" in p.stderr
    doc = yaml.safe_load((tmp_path / "s" / "session.yaml").read_text())
    assert doc["status"] == "aborted" and doc["frames"] == []
    assert "rerun viewer" in doc["events"][-1]["message"]


def test_board_bigger_than_the_view_is_not_a_workspace_problem() -> None:
    from slidecal.routines.planner import make_plan

    cfg = load_config(overrides={"target": {"square_size_m": 0.1}})
    with pytest.raises(InputError) as e:
        make_plan(cfg)
    msg = str(e.value)
    assert "more than the 1280 x 800 px image holds" in msg and "standoff_m to at least" in msg
    assert "widen" not in msg


def _frames(session_dir) -> int:  # noqa: ANN001
    """Number of frames a session directory holds (for checks after a fault)."""
    return len(load_session(session_dir, detect_images=False).problem.frames)
