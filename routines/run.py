"""The calibration routine: plan, move, capture, detect, record, solve, write (``slidecal run``).

Callable from Python for scripted commissioning::

    from slidecal.routines.run import run_calibration
    outcome = run_calibration("cell.yaml", out_dir="sessions/cell7")
    print(outcome.summary)

THE ROBOT NEVER MOVES unless the cell file names real hardware (``robot.driver: ur`` with a
``host``); without a file the packaged simulated cell is used. Every captured frame is on disk
the moment it is captured (:class:`~slidecal.routines.session.SessionWriter`). On a
``HardwareFault``, Ctrl-C, SIGTERM or SIGHUP the robot is stopped, the event is written into
the session (``events``, ``status: aborted``) and the exception raised again with where the
frames are; ``run_calibration(resume=SESSION)`` continues such a session. A dropped frame or an
image without corners is captured again (``retries``). Two runs on one cell cannot interleave
(:mod:`slidecal.routines.lock`).

After the solve the gate of :mod:`slidecal.routines.verdict` decides: ``verdict.yaml`` in the
session; ``result.yaml`` and ``export/`` for an accepted (or drifted) result, ``rejected/``
without exports otherwise; ``report.html`` and ``report.png``; and, with an install store,
the install (:mod:`slidecal.routines.install`). ``docs/UNATTENDED.md`` is the contract.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from datetime import datetime
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from slidecal.routines.config import CellConfig, load_config
from slidecal.routines.plan import Plan, check_plan, read_plan, write_plan
from slidecal.routines.planner import PlanGoal, extend_plan, make_plan, planner_settings
from slidecal.routines.progress import Progress
from slidecal.routines.results_io import (
    RESULT_FILE,
    errors_against_truth,
    read_result,
    summary_text,
    write_result,
)
from slidecal.routines.session import SessionWriter, load_session, load_yaml, write_atomic
from slidecal.routines.verdict import Limits, Verdict, judge, limits_from_dict, write_verdict
from slidecal.solver.errors import DegenerateError, HardwareFault, InputError
from slidecal.solver.result import CalibrationResult

SUMMARY_FILE = "summary.txt"
EXPORT_DIR = "export"
REJECTED_DIR = "rejected"
#: A user's plan: poses of one group may differ in orientation by this much (pendant rounding).
MAX_GROUP_ROTATION_DEG = 0.5
#: A user's plan: the smallest move inside a group that counts as a translation.
MIN_GROUP_MOVE_M = 0.002
#: Captures of one pose tried again after a dropped frame or no corners at all (cell or CLI).
DEFAULT_RETRIES = 2


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, SIGTERM or SIGHUP: the run stops like on Ctrl-C (robot stopped, frames kept)."""

    def __init__(self, how: str = "Ctrl-C") -> None:
        super().__init__(f"stopped by {how}")
        self.how = how


@contextmanager
def signals_as_interrupt() -> Iterator[None]:
    """Within the block, SIGINT (Ctrl-C), SIGTERM and SIGHUP raise :class:`Interrupted` (main
    thread only; the previous handlers come back after). SIGINT gets its handler too: a
    process started in the background by a shell or under ``nohup`` inherits SIGINT ignored,
    and Python then installs no Ctrl-C handler of its own: ``kill -INT`` would not stop the
    robot (seen: a run started so went on to its last frame)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    names = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}
    if hasattr(signal, "SIGHUP"):
        names[signal.SIGHUP] = "SIGHUP"

    def handler(signum: int, _frame: Any) -> None:
        raise Interrupted(names.get(signum, f"signal {signum}"))

    old = {s: signal.signal(s, handler) for s in names}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


@dataclass(frozen=True)
class RunOutcome:
    """What a run produced.

    ``errors``: against the simulated truth (simulated cells; see
    :func:`~slidecal.routines.results_io.errors_against_truth`). ``robot_time_s``: the robot's
    (simulated) clock spent moving and settling; ``wall_time_s``: this process's time.
    ``verdict``: the gate's decision (:mod:`slidecal.routines.verdict`); a rejected result is
    written under ``rejected/`` and has no exports. ``installed_to``: the install store's new
    entry (None when not installed; ``install_note`` says why). ``export_errors``: exports
    that failed, one line each. ``exit_code``: what ``slidecal`` exits with.
    """

    session_dir: Path
    result: CalibrationResult
    result_path: Path
    summary: str
    n_frames: int
    wall_time_s: float
    robot_time_s: float | None
    errors: dict[str, float] = field(default_factory=dict)
    recording_path: Path | None = None
    exports: tuple[Path, ...] = ()
    verdict: Verdict | None = None
    installed_to: Path | None = None
    install_note: str | None = None
    export_errors: tuple[str, ...] = ()
    report_path: Path | None = None

    @property
    def exit_code(self) -> int:
        """0 accepted, 4 rejected, 5 drifted, 6 accepted but not installed (docs/UNATTENDED.md)."""
        if self.verdict is None:
            return 0
        code = self.verdict.exit_code
        if code == 0 and self.install_note is not None:
            return EXIT_NOT_INSTALLED
        return code


#: Exit code of an accepted result that the install store refused (less certain than the
#: installed one without ``--force``).
EXIT_NOT_INSTALLED = 6


def default_session_dir() -> Path:
    """``sessions/<date>_<time>`` under the current directory."""
    return Path("sessions") / datetime.now().strftime("%Y%m%d_%H%M%S")


def check_out_dir(out: Path, what: str = "--out") -> None:
    """Refuse an output directory that cannot be one: empty, a file, under a file, or not
    writable (checked on the nearest existing parent; nothing is created here)."""
    if str(out) in ("", "."):
        raise InputError(f"{what} is empty or '.'; name a new directory for the session")
    if out.exists() and not out.is_dir():
        raise InputError(f"is a file; {what} must name a directory", where=str(out))
    p = out
    while not p.exists():
        if p.parent == p:
            break
        p = p.parent
    if p.exists() and not p.is_dir():
        raise InputError(f"{p} is a file; {what} must lie under a directory", where=str(out))
    if p.exists() and not os.access(p, os.W_OK | os.X_OK):
        raise InputError(
            f"cannot be written ({p} is read-only for this user); choose a writable {what}",
            where=str(out),
        )


def check_out_file(path: Path, what: str = "--out") -> None:
    """Refuse an output file that is a directory or lies under a file or a read-only place."""
    if str(path) in ("", "."):
        raise InputError(f"{what} is empty; name a file")
    if path.is_dir():
        raise InputError(f"is a directory; {what} must name a file", where=str(path))
    if str(path.parent) not in ("", "."):
        check_out_dir(path.parent, what)


def _lock_key(config: Any, cfg: CellConfig) -> str | None:
    """What a run locks: a real robot by its address, a simulated cell by its file."""
    if not cfg.simulated:
        return f"ur:{cfg.robot.host}"
    if isinstance(config, str | Path):
        return f"file:{Path(config).resolve()}"
    return None


def _sockets(cfg: CellConfig) -> dict[str, str] | None:
    """Camera name -> OAK socket for OAK rigs (real, or the simulated OAK-D-like head)."""
    from slidecal.routines.exports import OAK_DEFAULT_SOCKETS

    if cfg.camera_driver == "oak":
        return {n: str(o.get("socket")) for n, o in cfg.camera_options.items()}
    names = [c.name for c in cfg.cameras]
    if len(names) > 1 and all(n in OAK_DEFAULT_SOCKETS for n in names):
        return {n: OAK_DEFAULT_SOCKETS[n] for n in names}
    return None


def cell_limits(cfg: CellConfig) -> Limits:
    """The gate's limits of a cell (its ``limits:`` section)."""
    return limits_from_dict(cfg.raw.get("limits"), cfg.source)


def cell_install(cfg: CellConfig) -> dict[str, Any]:
    """The cell's ``install:`` section: ``{dir, accept_drift, retries}`` (all optional)."""
    from slidecal.routines.session import Fields

    raw = cfg.raw.get("install")
    if raw is None:
        return {}
    f = Fields(raw, cfg.source, "install")
    known = ("dir", "accept_drift", "retries")
    for k in f.data:
        if k not in known:
            raise f.error(str(k), f"is not an install field; the fields are {list(known)}")
    out: dict[str, Any] = {}
    if f.has("dir"):
        out["dir"] = f.string("dir")
    out["accept_drift"] = f.boolean("accept_drift", False)
    if f.has("retries"):
        out["retries"] = f.integer("retries", minimum=0)
    return out


def check_user_plan(plan: Plan, cfg: CellConfig, where: str) -> None:
    """Refuse a user's plan that cannot determine the calibration, before the robot moves:
    a group whose poses differ in orientation or hold no translation (the method needs pure
    translations inside each group), or a plan the planner's prediction finds degenerate
    (frames that do not see the target, too few orientations)."""
    from slidecal.routines.planner import predict_std
    from slidecal.solver.geometry import rotation_angle_deg

    for g, group in enumerate(plan.groups):
        T0 = group[0]
        for k, T in enumerate(group[1:], start=1):
            angle = rotation_angle_deg(T[:3, :3], T0[:3, :3])
            if angle > MAX_GROUP_ROTATION_DEG:
                raise InputError(
                    f"pose {k} of group {g} is rotated {angle:.2f} deg from the group's first "
                    "pose; the poses of a group must share one orientation (pure translations), "
                    "start a new group for a new orientation",
                    where=where,
                )
        d = np.array([T[:3, 3] - T0[:3, 3] for T in group[1:]]).reshape(-1, 3)
        d = d[np.linalg.norm(d, axis=1) >= MIN_GROUP_MOVE_M]
        if len(d) == 0:
            raise InputError(
                f"group {g} has no translation (all its poses within "
                f"{MIN_GROUP_MOVE_M * 1000:g} mm of each other): the method needs translated "
                "frames in every orientation group; make a plan with slidecal plan --config CELL",
                where=where,
            )
    try:
        predict_std(plan, cfg)
    except DegenerateError as e:
        raise InputError(
            f"the plan cannot calibrate this cell: {' '.join(str(e).split())}; make a plan "
            "with slidecal plan --config CELL",
            where=where,
        ) from None


def installed_calibration(path: str | Path | None) -> tuple[CalibrationResult | None, str | None]:
    """The installed calibration to compare with: an install store, a directory with a
    ``result.yaml`` or a result file; (None, None) without one."""
    if path is None:
        return None, None
    p = Path(path)
    from slidecal.routines.install import current_dir

    cur = current_dir(p) if p.is_dir() else None
    if cur is not None:
        return read_result(cur / RESULT_FILE), str(cur)
    if p.is_dir() and (p / RESULT_FILE).is_file():
        return read_result(p / RESULT_FILE), str(p / RESULT_FILE)
    if p.is_file():
        return read_result(p), str(p)
    if p.is_dir() or not p.exists():
        return None, None  # an empty (new) install store: nothing installed yet
    raise InputError("is not an install store nor a result file", where=str(p))


def _connect_real(cfg: CellConfig) -> tuple[Any, Any]:
    """The real drivers named by the cell file (imported only here)."""
    from slidecal.routines.devices import camera_rig

    rig = camera_rig(cfg)  # first: refuses a missing library or a bad camera field
    from slidecal.drivers.ur import URRobot, cell_options

    r = cfg.robot
    robot = URRobot(
        r.host,
        max_speed_mps=r.speed_mps,
        max_accel_mps2=r.accel_mps2,
        tcp=r.tcp,
        model=r.model,
        **cell_options(r.raw),  # take_control, payload
    )
    return robot, rig


def run_calibration(
    config: str | Path | CellConfig | None = None,
    plan: str | Path | Plan | None = None,
    out_dir: str | Path | None = None,
    progress: bool | Progress | None = None,
    recording: bool = True,
    spawn: bool = False,
    seed: int | None = None,
    overrides: Mapping[str, Any] | None = None,
    cell: Any = None,
    faults: Any = None,
    install: str | Path | None = None,
    force: bool = False,
    accept_drift: bool | None = None,
    installed: str | Path | None = None,
    resume: str | Path | None = None,
    retries: int | None = None,
) -> RunOutcome:
    """Run a calibration end to end, judge it, and return what it produced.

    Parameters
    ----------
    config
        A cell file, a loaded :class:`CellConfig`, or None for the default simulated cell.
    plan
        A ``plan.yaml``, a :class:`Plan`, or None: the planner chooses one for the cell
        (:func:`slidecal.routines.planner.make_plan`: non-degenerate, reachable, in view, the
        goal of the cell's ``plan:`` block in the least robot time), or refuses with the reason.
        A plan given here is checked for degeneracy before the robot moves.
    out_dir
        The session directory to create (default ``sessions/<date>_<time>``).
    progress
        True/False to force the progress output on/off; None: on (a status line on a
        terminal, plain timestamped lines otherwise).
    recording
        Write ``recording.rrd`` (rerun) into the session; ``spawn`` also opens a viewer.
    seed
        Simulated cells: overrides ``simulation.seed``.
    overrides
        Nested values merged over the cell file (see :func:`load_config`).
    cell
        A prepared :class:`~slidecal.mocks.cell.SimulatedCell` (tests inject faults into it).
    install
        An install store (:mod:`slidecal.routines.install`; default: the cell's
        ``install.dir``): an accepted result is installed there; ``force`` installs one less
        certain than the installed one, ``accept_drift`` a drifted one.
    installed
        The calibration to compare with (default: the install store's current one).
    resume
        A session directory whose run stopped (fault, interrupt): continue its plan from the
        first frame it lacks (``out_dir`` and ``plan`` must be None).
    faults
        ``KIND@FRAME`` strings (simulated cells only) or a prepared
        :class:`~slidecal.routines.faults.FaultInjector`: faults to inject (``--fault``).
    retries
        Captures of a pose tried again after a dropped frame (reconnecting the camera) or an
        image without a single corner (default: the cell's ``install.retries``, else 2).
    """
    t0 = time.monotonic()
    cfg = config if isinstance(config, CellConfig) else load_config(config, overrides)
    if not cfg.simulated:
        from slidecal.routines.devices import check_libraries

        check_libraries(cfg)  # a missing extra is said before planning
    limits = cell_limits(cfg)
    inst = cell_install(cfg)
    install = install if install is not None else inst.get("dir")
    accept_drift = inst.get("accept_drift", False) if accept_drift is None else accept_drift
    retries = int(retries if retries is not None else inst.get("retries", DEFAULT_RETRIES))
    if retries < 0:
        raise InputError(f"--retries must be 0 or more, got {retries}")
    if seed is not None and seed < 0:
        raise InputError(f"--seed must be 0 or a positive integer, got {seed}")
    if install is not None:
        check_out_dir(Path(install), "--install")
    start = 0
    if resume is not None:
        if out_dir is not None or plan is not None:
            raise InputError("--resume continues a session's own plan into it; drop --out/--plan")
        out = Path(resume)
        if not (out / "session.yaml").is_file():
            raise InputError("holds no session.yaml; nothing to resume", where=str(out))
        prior = load_yaml(out / "session.yaml", "session.yaml")
        frames = prior.get("frames") if isinstance(prior, Mapping) else None
        if not isinstance(frames, list):
            raise InputError("is not a slidecal session (no frames list)", where=str(out))
        if prior.get("status") == "complete":
            raise InputError(
                "is complete; nothing to resume (solve it again with slidecal solve)",
                where=str(out),
            )
        plan = read_plan(out / "plan.yaml")
        start = len(frames)
        sim = prior.get("simulation")
        if seed is None and isinstance(sim, Mapping) and isinstance(sim.get("seed"), int):
            seed = int(sim["seed"])  # the same simulated cell (target pose)
        recording = False  # the first part's recording stays as it is
    else:
        out = Path(out_dir) if out_dir is not None else default_session_dir()
        check_out_dir(out)  # before planning: a bad --out is refused at once
        if (out / "session.yaml").exists():
            raise InputError(
                "already holds a session; choose a new --out directory, or continue it with "
                "--resume",
                where=str(out),
            )
        if isinstance(plan, str | Path):
            plan_where = str(plan)
            plan = read_plan(plan)
            check_user_plan(plan, cfg, plan_where)
        elif isinstance(plan, Plan):
            check_user_plan(plan, cfg, "plan")
        plan = plan if plan is not None else make_plan(cfg).plan
    inst_result, inst_path = installed_calibration(installed if installed is not None else install)
    if cfg.simulated and cell is None:  # one simulated cell for the run and its extensions
        from slidecal.mocks.cell import SimulatedCell

        cell = SimulatedCell.from_config(cfg, seed)

    prog = Progress.from_option(progress, plan.n_poses)
    record = partial(
        record_session, cfg, out=out, prog=prog, lock_key=_lock_key(config, cfg), cell=cell
    )
    record = partial(record, retries=retries, faults=faults)
    rec = record(
        plan=plan,
        start=start,
        resume=resume is not None,
        recording=recording,
        spawn=spawn,
        seed=seed,
    )
    truth, robot, log = rec.truth, rec.robot, rec.log

    from slidecal.solver.calibrate import calibrate

    notes: list[str] = []
    for extension in range(EXTEND_ROUNDS + 1):
        prog.message("solving")
        session = load_session(out)  # solve what is on disk: the run can be replayed exactly
        result = calibrate(session.problem)
        if extension == EXTEND_ROUNDS:
            break
        longer, why = extend_for_limits(cfg, plan, result, limits, session)
        if longer is None:
            if why:
                notes.append(why)
                prog.event(why)
            break
        n_done, plan = plan.n_poses, longer
        said = f"extending the plan by {plan.n_poses - n_done} frames: {why}"
        notes.append(said)
        prog.event(said)
        prog.total = plan.n_poses
        rec = record(plan=plan, start=n_done, resume=True, extended=said, log=log)
        robot = rec.robot
    truth = session.simulation  # the truth as recorded, with the poses the arm really reached
    fin = finish_solve(
        result,
        out,
        session,
        limits,
        command="run",
        truth=truth,
        cell_path=config if isinstance(config, str | Path) else None,
        cell_name=cfg.source,
        oak_sockets=_sockets(cfg),
        installed=inst_result,
        installed_path=inst_path,
        plan_poses=plan.n_poses,
        notes=notes,
    )
    rec_path = None
    if log is not None:
        log.final(session.problem, result, fin["summary"])
        log.event(f"verdict: {fin['verdict'].verdict}")
        rec_path = log.close()
    installed_to, note = _install(install, out, fin, force, accept_drift, cfg, session.problem)
    for line in fin["verdict"].lines() + ([f"not installed: {note}"] if note else []):
        prog.event(line)
    prog.done(f"done: {fin['result_path']}")
    return RunOutcome(
        session_dir=out,
        result=result,
        result_path=fin["result_path"],
        summary=fin["summary"],
        n_frames=len(session.problem.frames),
        wall_time_s=time.monotonic() - t0,
        robot_time_s=_clock(robot),
        errors=errors_against_truth(result, truth) if truth else {},
        recording_path=rec_path,
        exports=tuple(fin["exports"]),
        verdict=fin["verdict"],
        installed_to=installed_to,
        install_note=note,
        export_errors=tuple(fin["export_errors"]),
        report_path=fin["report"],
    )


@dataclass
class Recorded:
    """What :func:`record_session` leaves: the simulated truth (None for real cells), the
    (closed) robot for its clock, the open rerun log (None without recording)."""

    truth: dict[str, Any] | None
    robot: Any
    log: Any


def record_session(
    cfg: CellConfig,
    plan: Plan,
    out: Path,
    prog: Progress,
    lock_key: str | None = None,
    start: int = 0,
    resume: bool = False,
    recording: bool = False,
    spawn: bool = False,
    seed: int | None = None,
    cell: Any = None,
    retries: int = DEFAULT_RETRIES,
    extra: Mapping[str, Any] | None = None,
    faults: Any = None,
    extended: str | None = None,
    log: Any = None,
) -> Recorded:
    """Connect, lock the cell, move through ``plan`` (from pose ``start``), capture, detect and
    write the session ``out`` (``resume``: append to the session there; ``extended``: the plan
    grew, why, and ``plan.yaml`` is rewritten). ``log``: the run's open rerun log, to go on
    with. On a fault or an interrupt (Ctrl-C, SIGTERM, SIGHUP) the robot is stopped, the
    session marked aborted with the event, and the exception raised again."""
    truth: dict[str, Any] | None = None
    if cfg.simulated:
        if cell is None:
            from slidecal.mocks.cell import SimulatedCell

            cell = SimulatedCell.from_config(cfg, seed)
        robot, rig, truth = cell.robot, cell.rig, cell.truth
    else:
        robot, rig = _connect_real(cfg)
    if faults and not hasattr(faults, "before_frame"):
        from slidecal.routines.faults import FaultInjector

        faults = FaultInjector.for_simulated(faults, robot, rig)
    from slidecal.routines.lock import Lock, cell_lock_path

    lock = None
    if lock_key is not None:
        lock = Lock(cell_lock_path(lock_key), f"the cell ({lock_key})")
        lock.acquire()
        if lock.stale:
            prog.event(lock.stale)
    try:
        with signals_as_interrupt():
            prog.message("connecting")
            robot.connect()
            try:
                rig.open()
                specs = tuple(rig.specs)
                check_plan(plan, cfg, robot.is_reachable)  # refuse before anything moves
                from slidecal.routines.devices import record_devices

                found = {**record_devices(rig, out, cfg.standoff_m), **_controller(robot)}
                writer = _open_writer(out, cfg, specs, truth, resume, {**found, **(extra or {})})
                if not resume or extended:
                    write_plan(plan, out / "plan.yaml")
                if extended:
                    writer.add_event("extended", extended)
                elif resume:
                    writer.add_event("resumed", f"resumed at frame {start + 1} of {plan.n_poses}")
                    prog.event(f"resuming {out} at frame {start + 1} of {plan.n_poses}")
                if log is None and (recording or spawn):
                    log = _open_log(out, cfg, specs, recording, spawn, writer)
                try:
                    _acquire(robot, rig, plan, cfg, writer, log, prog, start, retries, faults)
                except (HardwareFault, KeyboardInterrupt, OSError) as e:
                    _abort(robot, writer, log, prog, e, out)
                writer.finish("complete")
            finally:
                for closer in (rig.close, robot.close):
                    try:
                        closer()
                    except Exception:  # noqa: BLE001 - closing must not hide the real error
                        pass
    finally:
        if lock is not None:
            lock.release()
    return Recorded(truth, robot, log)


def _open_writer(
    out: Path,
    cfg: CellConfig,
    specs: tuple,
    truth: Mapping[str, Any] | None,
    resume: bool,
    more: Mapping[str, Any] | None = None,
) -> SessionWriter:
    if resume:
        return SessionWriter.reopen(out)
    extra: dict[str, Any] = cfg.session_fields()
    if cfg.raw.get("limits") is not None:
        extra["limits"] = dict(cfg.raw["limits"])
    extra.update(more or {})
    try:
        return SessionWriter(
            out,
            cfg.target,
            specs,
            mount=cfg.mount,
            knowledge="robot",
            options=cfg.options,
            reference_camera=cfg.reference_camera,
            simulation=truth,
            extra=extra,
            sockets=_sockets(cfg) or {},
        )
    except OSError as e:
        raise InputError(
            f"cannot be written ({e.strerror}); choose a writable --out", where=str(out)
        ) from None


def _open_log(out: Path, cfg: CellConfig, specs: tuple, recording: bool, spawn: bool, writer):
    from slidecal.routines.rerun_log import RECORDING_FILE, RerunLog

    try:
        return RerunLog(
            out / RECORDING_FILE if recording else None,
            specs,
            cfg.target,
            cfg.mount,
            cfg.approx_T_hand_eye,
            cfg.approx_T_target,
            spawn=spawn,
        )
    except Exception as e:  # noqa: BLE001 - rerun raises its own types for a missing viewer
        msg = " ".join(str(e).split()).split(". ")[0] or type(e).__name__
        writer.add_event("fault", f"rerun viewer: {msg}", frames_kept=0)
        writer.finish("aborted")
        raise InputError(
            f"--spawn could not start the rerun viewer ({msg}); install it (pip install "
            "rerun-sdk puts `rerun` on PATH) or run without --spawn"
        ) from None


def _abort(robot, writer, log, prog: Progress, e: BaseException, out: Path) -> None:
    """Stop the robot, record what happened, mark the session aborted, raise again."""
    robot.stop()
    if isinstance(e, KeyboardInterrupt):
        kind = "interrupted"
        msg = str(e) if isinstance(e, Interrupted) else "stopped by Ctrl-C"
        msg = f"{msg} (robot stopped)"
    elif isinstance(e, OSError):
        kind = "fault"
        msg = f"writing the session failed: {e.strerror or e} ({e.filename})"
    else:
        kind = "fault"
        msg = str(e)
    n = writer.n_frames
    try:
        writer.add_event(kind, msg, frames_kept=n, robot_time_s=_clock(robot))
        writer.finish("aborted")
    except OSError:  # the disk that failed the frame may fail the event too
        pass
    if log is not None:
        log.event(f"{kind}: {msg}", level="ERROR")
        log.close()
    prog.event(f"{kind}: {msg}; {n} frames kept in {out}")
    prog.done()
    resume = f"; continue with slidecal run --resume {out}"
    if isinstance(e, KeyboardInterrupt):
        raise e
    if isinstance(e, OSError):
        raise InputError(
            f"{msg}; the robot was stopped, the {n} frames before it are in {out}; free disk "
            f"space or fix the rights{resume}"
        ) from None
    raise HardwareFault(
        f"{msg} (robot stopped; the {n} frames captured before it are in {out}{resume})"
    ) from e


def _install(
    store, out: Path, fin: dict, force: bool, accept_drift: bool, cfg, problem=None
) -> tuple:
    """Install an accepted (or accepted-drift) result; (new entry, None) or (None, why not)."""
    if store is None:
        return None, None
    from slidecal.routines.install import NotInstalled, install
    from slidecal.solver.drift import chain_rms_px

    v: Verdict = fin["verdict"]
    if v.verdict == "rejected":
        return None, "the result was rejected; the installed calibration stays"
    try:
        d = install(
            store,
            fin["result_path"].parent,
            fin["result"],
            v.verdict,
            force=force,
            accept_drift=accept_drift,
            info={
                "cell": cfg.source if cfg is not None else None,
                "chain_rms_px": chain_rms_px(fin["result"], problem) if problem else {},
            },
        )
    except NotInstalled as e:
        return None, str(e)
    return d, None


def _controller(robot: Any) -> dict[str, Any]:
    """The session's ``controller:`` block: what a real robot controller reported on connect."""
    info = getattr(robot, "controller_info", None)
    return {"controller": dict(info)} if info else {}


def _clock(robot: Any) -> float | None:
    t = getattr(robot, "robot_time_s", None)
    return float(t) if t is not None else None


def _detect_all(images, cfg: CellConfig):
    from slidecal.solver.detect import detect

    detections, quality = {}, {}
    for name, img in images.items():
        rep = detect(img, cfg.target)
        detections[name] = rep.detection
        quality[name] = {
            "ok": bool(rep.ok),
            "reasons": list(rep.reasons),
            "homography_rms_px": float(rep.homography_rms_px),
            "coverage": float(rep.coverage),
            "n_corners": int(len(rep.detection.ids)),
        }
    return detections, quality


def _capture(rig, cfg: CellConfig, writer, prog: Progress, i: int, retries: int):
    """Capture and detect at the current pose; a dropped frame is captured again after
    reopening the camera, an image set without a single corner is captured again; each retry
    is an event of the session. The last failure of a dropped frame is raised."""

    def retry(what: str) -> None:  # an event of the session and a line of progress
        msg = f"frame {i + 1}: {what}"
        writer.add_event("retry", msg, frame_index=i)
        prog.event(msg)

    failure = ""  # the capture's own fault, kept while the camera is reconnected
    for attempt in range(retries + 1):
        if failure:  # reconnect before capturing again (a camera may come back after a while)
            try:
                rig.close()
                rig.open()
                failure = ""
            except HardwareFault as e:
                reason = " ".join(str(e).split())
                if attempt == retries:  # the root cause first, not "capture on a closed rig"
                    raise HardwareFault(f"{failure}; reconnecting failed: {reason}") from None
                retry(
                    f"reconnecting the camera failed ({reason}); retry {attempt + 1} of {retries}"
                )
                continue
        try:
            images = rig.capture()
        except HardwareFault as e:
            if attempt == retries:
                raise
            failure = " ".join(str(e).split())
            retry(
                f"capture failed ({failure}); reconnecting the camera, retry {attempt + 1} of "
                f"{retries}"
            )
            continue
        detections, quality = _detect_all(images, cfg)
        if any(q["n_corners"] > 0 for q in quality.values()) or attempt == retries:
            return images, detections, quality
        retry(f"no corner detected; capturing again, retry {attempt + 1} of {retries}")
    raise AssertionError("unreachable")  # the loop returns or raises


def _acquire(
    robot,
    rig,
    plan: Plan,
    cfg: CellConfig,
    writer,
    log,
    prog: Progress,
    start: int = 0,
    retries: int = DEFAULT_RETRIES,
    faults: Any = None,
) -> None:
    """Move through the plan from pose ``start`` (execution order), capture, detect, record;
    ``faults``: a fault injector (``--fault``) told before each frame's move."""
    i = 0
    for g, group in enumerate(plan.groups):
        if i + len(group) <= start:
            i += len(group)
            continue
        if plan.via is not None:
            prog.step(i, "moving to the via pose")
            robot.move_linear(plan.via, plan.speed_mps, plan.accel_mps2)
        for T in group:
            if i < start:
                i += 1
                continue
            prog.step(i, f"group {g + 1}: moving")
            if faults is not None:
                faults.before_frame(i)
            robot.move_linear(T, plan.speed_mps, plan.accel_mps2)
            prog.step(i, f"group {g + 1}: settling")
            robot.wait_settled(plan.settle_s)
            T_meas = robot.measured_pose()
            prog.step(i, f"group {g + 1}: capturing")
            images, detections, quality = _capture(rig, cfg, writer, prog, i, retries)
            T_true = robot.true_pose() if hasattr(robot, "true_pose") else None  # simulated
            fid = writer.append_frame(
                T_meas, images, detections, group=g, quality=quality, T_base_tool_true=T_true
            )
            if log is not None:
                log.frame(fid, T_meas, images, detections, _clock(robot))
            counts = ", ".join(f"{n} {q['n_corners']} corners" for n, q in quality.items())
            prog.frame_done(f"group {g + 1}, frame id {fid}: {counts}")
            i += 1


#: How many times a run extends its plan when its result misses the gate's one-sigma limits.
EXTEND_ROUNDS = 2
#: An extension plans for this fraction of each one-sigma limit (the prediction is a model).
EXTEND_MARGIN = 0.7


def extend_for_limits(
    cfg: CellConfig,
    plan: Plan,
    result: CalibrationResult,
    limits: Limits,
    session: Any,
) -> tuple[Plan | None, str]:
    """The longer plan a run records next when its result misses only the gate's one-sigma
    limits (the data is sound but not enough of it: an arm less accurate than the plan was made
    for), with why; or None and why not (an empty reason when nothing was missed).

    Planned for the accuracy the data showed (:func:`slidecal.routines.planner.extend_plan`):
    the reference camera's residual rms, the robot's learned accuracy, the one-sigma each limit
    asks for times :data:`EXTEND_MARGIN`, within the cell's ``plan.extend_max_s`` of robot time
    (0: never extend). Only the planner's plans are extended (they carry its prediction,
    ``predicted_std``); a plan written by hand is run as written. Simulated and real cells
    alike: the extension is checked like any plan before the robot moves.
    """
    verdict = judge(result, limits, session.problem, command="run")
    if verdict.verdict != "rejected":
        return None, ""
    failed = verdict.reasons
    if any(c.test != "std" for c in failed):
        return None, ""  # more frames cannot cure a model that does not fit
    budget_s = planner_settings(cfg).extend_max_s
    if budget_s <= 0:
        return None, "not extended: plan.extend_max_s is 0"
    if plan.predicted_std is None:
        return None, "not extended: a plan written by hand is run as written"
    cam = result.cameras.get(cfg.reference_camera)
    he = result.hand_eye
    if cam is None or he is None:
        return None, "not extended: the reference camera or the hand-eye was not determined"
    K = np.asarray(cam.K, dtype=float)
    rel = [
        float(cam.std[p]) / abs(v)
        for p, v in (("fx", K[0, 0]), ("fy", K[1, 1]))
        if cam.std.get(p) is not None
    ]
    achieved = {
        "fx_rel_std": max(rel) if rel else float("nan"),
        "hand_eye_rot_std_deg": he.std_rot_deg if he.std_rot_deg is not None else float("nan"),
        "hand_eye_t_std_mm": he.std_t_mm if he.std_t_mm is not None else float("nan"),
    }
    goal = PlanGoal(
        fx_rel_std=EXTEND_MARGIN * limits.fx_rel_std,
        hand_eye_rot_std_deg=EXTEND_MARGIN * limits.hand_eye_rot_std_deg,
        hand_eye_t_std_mm=EXTEND_MARGIN * limits.hand_eye_t_std_mm,
    )
    acc = result.robot_accuracy
    t_mm = acc.translation_mm if acc is not None else cfg.options.robot_noise_m * 1000.0
    rot_deg = acc.rotation_deg if acc is not None else cfg.options.robot_noise_deg
    try:
        report = extend_plan(
            cfg, plan, goal, achieved, float(cam.reproj_rms_px), t_mm, rot_deg, budget_s
        )
    except InputError as e:
        return None, f"not extended: {e}"
    if report.plan.n_poses == plan.n_poses:
        return None, "not extended: the planner predicts no gain from more frames"
    missed = "; ".join(c.message for c in failed)
    return report.plan, (
        f"{missed} (robot accuracy {t_mm:.2f} mm / {rot_deg:.3f} deg as the data shows it)"
    )


def finish_solve(
    result: CalibrationResult,
    session_dir: Path,
    session: Any,
    limits: Limits,
    command: str,
    truth: Mapping[str, Any] | None = None,
    cell_path: str | Path | None = None,
    cell_name: str | None = None,
    oak_sockets: Mapping[str, str] | None = None,
    installed: CalibrationResult | None = None,
    installed_path: str | None = None,
    result_path: Path | None = None,
    plan_poses: int | None = None,
    notes: Sequence[str] = (),
) -> dict[str, Any]:
    """Judge a solved session and write what the verdict allows (``notes``: what the run
    itself has to say, e.g. that it extended its plan, added to the verdict's notes).

    Always: ``verdict.yaml`` in the session, ``summary.txt`` next to the result, the report
    (``report.html``, ``report.png``) in the session. Accepted or drifted: ``result.yaml`` and
    ``export/``. Rejected: ``rejected/result.yaml`` and its summary, no exports.
    """
    from slidecal.routines.exports import result_header, write_all_exports

    status = _session_status(session, plan_poses)
    verdict = judge(
        result,
        limits,
        session.problem,
        installed,
        command=command,
        session_status=status,
        installed_path=installed_path,
    )
    if notes:
        verdict = replace(verdict, notes=tuple(notes) + verdict.notes)
    target = result_path or session_dir / RESULT_FILE
    if verdict.verdict == "rejected":
        target = target.parent / REJECTED_DIR / target.name
    header = result_header(cell_path, cell_name)
    header["verdict"] = verdict.verdict
    write_result(result, target, header=header)
    exports: list[Path] = []
    export_errors: list[str] = []
    if verdict.verdict != "rejected":
        exports, export_errors = write_all_exports(
            result, target.parent / EXPORT_DIR, header, oak_sockets
        )
    device_summary = ""
    if verdict.verdict != "rejected":  # an OAK: the export on the device's own calibration
        from slidecal.routines.devices import device_calibration_outputs

        device_exports, device_summary = device_calibration_outputs(
            result, session_dir, target.parent / EXPORT_DIR
        )
        exports += [p for p in device_exports if p not in exports]
    lines = [summary_text(result, truth, limits.scale_tolerance).rstrip("\n")]
    if device_summary.strip():
        lines.append(device_summary.rstrip("\n"))
    if status != "complete":
        lines.append(f"SESSION {status.upper()}: solved from the frames it holds")
    # the verdict's notes on what was not determined and on the frames left out repeat the
    # result's own lines above: summary.txt says them once (verdict.yaml keeps them all)
    shown = {f"{k} not determined: {v}" for k, v in result.unobservable.items()}
    shown |= set(result.messages)
    lines += [v for v in verdict.lines() if v.removeprefix("  note: ") not in shown]
    lines += [f"error: {e}" for e in export_errors]
    summary = "\n".join(lines) + "\n"
    write_atomic(target.parent / SUMMARY_FILE, summary)
    write_verdict(verdict, session_dir)
    report = None
    try:
        from slidecal.routines.report import write_report

        report = write_report(session_dir, result, verdict, session.problem, installed, summary)
    except (OSError, ValueError) as e:
        export_errors.append(f"report failed: {' '.join(str(e).split())}")
    return {
        "verdict": verdict,
        "result": result,
        "result_path": target,
        "summary": summary,
        "exports": exports,
        "export_errors": export_errors,
        "report": report,
    }


def _session_status(session: Any, plan_poses: int | None) -> str:
    """``complete``, or what is wrong with the session: aborted (why), cut off (n of m)."""
    n = len(session.problem.frames)
    if session.status == "aborted":
        why = next(
            (e.get("message") for e in reversed(session.events) if e.get("kind") != "retry"),
            None,
        )
        of = f"{n} of {plan_poses} planned frames" if plan_poses else f"{n} frames"
        return f"aborted ({of}{'; ' + str(why) if why else ''})"
    if session.status != "complete":
        return f"cut off (status {session.status}: the run never finished; {n} frames)"
    if plan_poses is not None and n < plan_poses:
        return f"cut off ({n} of {plan_poses} planned frames)"
    return "complete"


def detection_hint(reasons: Mapping[tuple[int, str], Sequence[str]], n_frames: int) -> str:
    """What the detector said most often of the images it found nothing usable in (a board
    counted in inner corners, another board size, nothing at all), or "" when it said nothing.
    """
    counts: dict[str, int] = {}
    for why in reasons.values():
        if why:
            counts[why[0]] = counts.get(why[0], 0) + 1
    if not counts:
        return ""
    reason = max(counts, key=lambda r: counts[r])
    return f"the detector says of {counts[reason]} of {n_frames} images: {reason}"


def solve_session(
    session_dir: str | Path,
    out: str | Path | None = None,
    force: bool = False,
    installed: str | Path | None = None,
    config: str | Path | None = None,
) -> RunOutcome:
    """Solve a recorded session again (``slidecal solve``): read, calibrate, judge, write.

    An existing result file is not overwritten without ``force``. ``installed``: an install
    store or result to compare with; ``config``: a cell file whose ``limits:`` apply (default:
    the limits the session recorded, else the defaults).
    """
    from slidecal.solver.calibrate import calibrate

    t0 = time.monotonic()
    session_dir = Path(session_dir)
    session = load_session(session_dir)
    if not session.problem.frames:
        raise InputError("holds no frames; nothing to solve", where=f"{session_dir}/session.yaml")
    path = Path(out) if out is not None else session_dir / RESULT_FILE
    check_out_file(path)
    for p in (path, path.parent / REJECTED_DIR / path.name):
        if p.exists() and not force:
            raise InputError(
                "already holds a result; give another --out, or --force to replace it",
                where=str(p),
            )
    raw = load_yaml(session_dir / "session.yaml", "session.yaml")
    if config is not None:
        limits = cell_limits(load_config(config))
    else:
        limits = limits_from_dict(raw.get("limits"), f"{session_dir}/session.yaml")
    sockets = session.sockets or None
    plan_poses = None
    if (session_dir / "plan.yaml").is_file():
        plan_poses = read_plan(session_dir / "plan.yaml").n_poses
    inst_result, inst_path = installed_calibration(installed)
    try:
        result = calibrate(session.problem)
    except DegenerateError as e:
        hint = detection_hint(session.detect_reasons, len(session.problem.frames))
        if not hint:
            raise
        raise DegenerateError(f"{e}; {hint}") from e
    fin = finish_solve(
        result,
        session_dir,
        session,
        limits,
        command="solve",
        truth=session.simulation,
        cell_path=config,
        cell_name=raw.get("cell"),
        oak_sockets=sockets,
        installed=inst_result,
        installed_path=inst_path,
        result_path=path,
        plan_poses=plan_poses,
    )
    return RunOutcome(
        session_dir=session_dir,
        result=result,
        result_path=fin["result_path"],
        summary=fin["summary"],
        n_frames=len(session.problem.frames),
        wall_time_s=time.monotonic() - t0,
        robot_time_s=None,
        errors=errors_against_truth(result, session.simulation) if session.simulation else {},
        exports=tuple(fin["exports"]),
        verdict=fin["verdict"],
        export_errors=tuple(fin["export_errors"]),
        report_path=fin["report"],
    )


def frames_on_disk(session_dir: str | Path) -> int:
    """Number of frames a session directory holds (for checks after a fault)."""
    return len(load_session(session_dir, detect_images=False).problem.frames)
