"""The calibration routine: plan, move, capture, detect, record, solve, write (``slidecal run``).

Callable from Python for scripted commissioning::

    from slidecal.routines.run import run_calibration
    outcome = run_calibration("cell.yaml", out_dir="sessions/cell7")
    print(outcome.summary)

THE ROBOT NEVER MOVES unless the cell file names real hardware (``robot.driver: ur`` with a
``host``); without a file the packaged simulated cell is used. Every captured frame is on disk
the moment it is captured (:class:`~slidecal.routines.session.SessionWriter`). On a
``HardwareFault`` the robot is stopped, the fault is written into the session
(``events``, ``status: aborted``) and the fault is raised again with where the frames are; on
Ctrl-C the robot is stopped likewise. No result file is written unless the solve succeeded.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from slidecal.routines.config import CellConfig, load_config
from slidecal.routines.plan import Plan, check_plan, read_plan, write_plan
from slidecal.routines.planner import make_plan
from slidecal.routines.progress import Progress
from slidecal.routines.results_io import (
    RESULT_FILE,
    errors_against_truth,
    summary_text,
    write_exports,
    write_result,
)
from slidecal.routines.session import SessionWriter, load_session, write_atomic
from slidecal.solver.errors import HardwareFault, InputError
from slidecal.solver.result import CalibrationResult

SUMMARY_FILE = "summary.txt"
EXPORT_DIR = "export"


@dataclass(frozen=True)
class RunOutcome:
    """What a run produced.

    ``errors``: against the simulated truth (simulated cells; see
    :func:`~slidecal.routines.results_io.errors_against_truth`). ``robot_time_s``: the robot's
    (simulated) clock spent moving and settling; ``wall_time_s``: this process's time.
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


def default_session_dir() -> Path:
    """``sessions/<date>_<time>`` under the current directory."""
    return Path("sessions") / datetime.now().strftime("%Y%m%d_%H%M%S")


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
) -> RunOutcome:
    """Run a calibration end to end and return what it produced.

    Parameters
    ----------
    config
        A cell file, a loaded :class:`CellConfig`, or None for the default simulated cell.
    plan
        A ``plan.yaml``, a :class:`Plan`, or None: the planner chooses one for the cell
        (:func:`slidecal.routines.planner.make_plan`: non-degenerate, reachable, in view, the
        goal of the cell's ``plan:`` block in the least robot time), or refuses with the reason.
    out_dir
        The session directory to create (default ``sessions/<date>_<time>``).
    progress
        True/False to force the terminal progress on/off; None: on when stderr is a terminal.
    recording
        Write ``recording.rrd`` (rerun) into the session; ``spawn`` also opens a viewer.
    seed
        Simulated cells: overrides ``simulation.seed``.
    overrides
        Nested values merged over the cell file (see :func:`load_config`).
    cell
        A prepared :class:`~slidecal.mocks.cell.SimulatedCell` (tests inject faults into it).
    faults
        ``KIND@FRAME`` strings (simulated cells only) or a prepared
        :class:`~slidecal.routines.faults.FaultInjector`: faults to inject (``--fault``).
    """
    t0 = time.monotonic()
    cfg = config if isinstance(config, CellConfig) else load_config(config, overrides)
    if not cfg.simulated:
        from slidecal.routines.devices import check_libraries

        check_libraries(cfg)  # a missing extra is said before planning
    if isinstance(plan, str | Path):
        plan = read_plan(plan)
    plan = plan if plan is not None else make_plan(cfg).plan
    out = Path(out_dir) if out_dir is not None else default_session_dir()

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

    prog = (
        progress
        if isinstance(progress, Progress)
        else Progress(plan.n_poses, quiet=None if progress is None else not progress)
    )
    prog.message("connecting")
    robot.connect()
    try:
        rig.open()
        specs = tuple(rig.specs)
        check_plan(plan, cfg, robot.is_reachable)  # refuse before anything moves
        from slidecal.routines.devices import record_devices

        devices = record_devices(rig, out, cfg.standoff_m)
        writer = SessionWriter(
            out,
            cfg.target,
            specs,
            mount=cfg.mount,
            knowledge="robot",
            options=cfg.options,
            reference_camera=cfg.reference_camera,
            simulation=truth,
            extra={**cfg.session_fields(), **devices, **_controller(robot)},
            sockets=cfg.sockets,
        )
        write_plan(plan, out / "plan.yaml")
        log = None
        if recording or spawn:
            from slidecal.routines.rerun_log import RECORDING_FILE, RerunLog

            log = RerunLog(
                out / RECORDING_FILE if recording else None,
                specs,
                cfg.target,
                cfg.mount,
                cfg.approx_T_hand_eye,
                cfg.approx_T_target,
                spawn=spawn,
            )
        try:
            _acquire(robot, rig, plan, cfg, writer, log, prog, faults)
        except (HardwareFault, KeyboardInterrupt) as e:
            robot.stop()
            kind = "fault" if isinstance(e, HardwareFault) else "interrupted"
            msg = str(e) or "stopped by the operator (Ctrl-C)"
            writer.add_event(kind, msg, frames_kept=writer.n_frames, robot_time_s=_clock(robot))
            writer.finish("aborted")
            if log is not None:
                log.event(f"{kind}: {msg}", level="ERROR")
                log.close()
            prog.done()
            if isinstance(e, KeyboardInterrupt):
                raise
            raise HardwareFault(
                f"{msg} (robot stopped; the {writer.n_frames} frames captured before it are "
                f"in {out})"
            ) from e
        writer.finish("complete")
    finally:
        for closer in (rig.close, robot.close):
            try:
                closer()
            except Exception:  # noqa: BLE001 - closing must not hide the real error
                pass

    prog.message("solving")
    session = load_session(out)  # solve what is on disk: the run can be replayed exactly
    truth = session.simulation  # the truth as recorded, with the poses the arm really reached
    from slidecal.solver.calibrate import calibrate

    result = calibrate(session.problem)
    result_path, summary, exports = write_outputs(result, out, truth, cfg)
    rec_path = None
    if log is not None:
        log.final(session.problem, result, summary)
        rec_path = log.close()
    prog.done(f"done: {result_path}")
    return RunOutcome(
        session_dir=out,
        result=result,
        result_path=result_path,
        summary=summary,
        n_frames=len(session.problem.frames),
        wall_time_s=time.monotonic() - t0,
        robot_time_s=_clock(robot),
        errors=errors_against_truth(result, truth) if truth else {},
        recording_path=rec_path,
        exports=tuple(exports),
    )


def _controller(robot: Any) -> dict[str, Any]:
    """The session's ``controller:`` block: what a real robot controller reported on connect."""
    info = getattr(robot, "controller_info", None)
    return {"controller": dict(info)} if info else {}


def _clock(robot: Any) -> float | None:
    t = getattr(robot, "robot_time_s", None)
    return float(t) if t is not None else None


def _acquire(
    robot, rig, plan: Plan, cfg: CellConfig, writer, log, prog: Progress, faults=None
) -> None:
    from slidecal.solver.detect import detect

    i = 0
    for g, group in enumerate(plan.groups):
        if plan.via is not None:
            prog.step(i, "moving to the via pose")
            robot.move_linear(plan.via, plan.speed_mps, plan.accel_mps2)
        for T in group:
            prog.step(i, f"group {g + 1}: moving")
            if faults is not None:
                faults.before_frame(i)
            robot.move_linear(T, plan.speed_mps, plan.accel_mps2)
            prog.step(i, f"group {g + 1}: settling")
            robot.wait_settled(plan.settle_s)
            T_meas = robot.measured_pose()
            prog.step(i, f"group {g + 1}: capturing")
            images = rig.capture()
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
            T_true = robot.true_pose() if hasattr(robot, "true_pose") else None  # simulated
            fid = writer.append_frame(
                T_meas, images, detections, group=g, quality=quality, T_base_tool_true=T_true
            )
            if log is not None:
                log.frame(fid, T_meas, images, detections, _clock(robot))
            prog.frame_done()
            i += 1


def write_outputs(
    result: CalibrationResult,
    session_dir: Path,
    truth: Mapping[str, Any] | None = None,
    cfg: CellConfig | None = None,
    result_path: Path | None = None,
) -> tuple[Path, str, list[Path]]:
    """``result.yaml``, the exports (``export/``) and ``summary.txt`` of a solved session."""
    result_path = write_result(result, result_path or session_dir / RESULT_FILE)
    oak = None
    if cfg is not None and cfg.camera_driver == "oak":
        oak = {n: o.get("socket") for n, o in cfg.camera_options.items()}
    exports = write_exports(result, result_path.parent / EXPORT_DIR, oak_sockets=oak)
    from slidecal.routines.devices import device_calibration_outputs

    device_exports, device_summary = device_calibration_outputs(
        result, session_dir, result_path.parent / EXPORT_DIR
    )
    exports += [p for p in device_exports if p not in exports]
    summary = summary_text(result, truth) + device_summary
    write_atomic(result_path.parent / SUMMARY_FILE, summary)
    return result_path, summary, exports


def solve_session(session_dir: str | Path, out: str | Path | None = None) -> RunOutcome:
    """Solve a recorded session again (``slidecal solve``): read, calibrate, write outputs."""
    from slidecal.solver.calibrate import calibrate

    t0 = time.monotonic()
    session = load_session(session_dir)
    if not session.problem.frames:
        raise InputError("holds no frames; nothing to solve", where=f"{session_dir}/session.yaml")
    result = calibrate(session.problem)
    path = Path(out) if out is not None else Path(session_dir) / RESULT_FILE
    result_path, summary, exports = write_outputs(
        result, path.parent, session.simulation, result_path=path
    )
    return RunOutcome(
        session_dir=Path(session_dir),
        result=result,
        result_path=result_path,
        summary=summary,
        n_frames=len(session.problem.frames),
        wall_time_s=time.monotonic() - t0,
        robot_time_s=None,
        errors=errors_against_truth(result, session.simulation) if session.simulation else {},
        exports=tuple(exports),
    )


def frames_on_disk(session_dir: str | Path) -> int:
    """Number of frames a session directory holds (for checks after a fault)."""
    return len(load_session(session_dir, detect_images=False).problem.frames)
