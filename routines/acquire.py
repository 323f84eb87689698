"""The capture loop of ``slidecal run`` and ``slidecal check``: connect the cell's robot and
cameras, lock the cell, move through a plan, capture, detect and write the session frame by
frame; on a fault or an interrupt stop the robot and mark the session aborted."""

from __future__ import annotations

from collections.abc import Mapping
from contextlib import nullcontext, suppress
from datetime import datetime
from pathlib import Path
from typing import Any

from slidecal.drivers.oak import DEFAULT_SOCKETS
from slidecal.drivers.ur import URRobot
from slidecal.routines.config import CellConfig, limits_to_dict
from slidecal.routines.devices import camera_rig, record_devices
from slidecal.routines.ops.faults import FaultInjector
from slidecal.routines.ops.lock import Lock, cell_lock_path
from slidecal.routines.ops.verdict import Limits
from slidecal.routines.plan import Plan, check_plan, write_plan
from slidecal.routines.progress import Interrupted, Progress, signals_as_interrupt
from slidecal.routines.schema import check_out_dir
from slidecal.routines.session import SessionWriter
from slidecal.solver.detect import detect
from slidecal.solver.errors import HardwareFault, InputError

#: Captures of one pose tried again after a dropped frame or no corners at all (cell or CLI).
DEFAULT_RETRIES = 2


def new_session_dir(
    out_dir: str | Path | None, prefix: str = "", resume: str = ", or continue it with --resume"
) -> Path:
    """The new session's directory (default ``sessions/<prefix><date>_<time>``), refused at once
    when it cannot be one; ``resume``: how the refusal offers to continue the one there."""
    stamp = datetime.now().strftime(f"{prefix}%Y%m%d_%H%M%S")
    out = Path(out_dir) if out_dir is not None else Path("sessions") / stamp
    check_out_dir(out)
    if (out / "session.yaml").exists():
        raise InputError(
            f"already holds a session; choose a new --out directory{resume}", where=str(out)
        )
    return out


def cell_key(config: Any, cfg: CellConfig) -> str | None:
    """What a run locks: a real robot by its address, a simulated cell by its file."""
    if not cfg.simulated:
        return f"ur:{cfg.robot.host}"
    if isinstance(config, str | Path):
        return f"file:{Path(config).resolve()}"
    return None


def sockets(cfg: CellConfig) -> dict[str, str] | None:
    """Camera name -> OAK socket for OAK rigs (real, or the simulated OAK-D-like head)."""
    if cfg.camera_driver == "oak":
        return {n: str(o.get("socket")) for n, o in cfg.camera_options.items()}
    names = [c.name for c in cfg.cameras]
    if len(names) > 1 and all(n in DEFAULT_SOCKETS for n in names):
        return {n: DEFAULT_SOCKETS[n] for n in names}
    return None


def _connect_real(cfg: CellConfig) -> tuple[Any, Any]:
    """The real drivers named by the cell file."""
    rig = camera_rig(cfg)  # first: refuses a missing library or a bad camera field
    r = cfg.robot
    robot = URRobot(
        r.host,
        max_speed_mps=r.speed_mps,
        max_accel_mps2=r.accel_mps2,
        tcp=r.tcp,
        model=r.model,
        **r.ur_options,  # take_control, payload
    )
    return robot, rig


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
    cell: Any = None,
    retries: int = DEFAULT_RETRIES,
    extra: Mapping[str, Any] | None = None,
    faults: Any = None,
    extended: str | None = None,
    log: Any = None,
) -> tuple[Any, Any]:
    """Connect, lock the cell, move through ``plan`` from pose ``start``, capture, detect and write
    the session ``out`` (``resume``: append to it; ``extended``: the plan grew, why). ``log``: the
    run's open rerun log. Returns the (closed) robot, for its clock, and the open rerun log (None
    without recording). On a fault or an interrupt the robot is stopped, the session marked
    aborted with the event, and the exception raised again."""
    truth: dict[str, Any] | None = None
    if cfg.simulated:  # the caller's simulated cell (one for a run and its extensions)
        robot, rig, truth = cell.robot, cell.rig, cell.truth
    else:
        robot, rig = _connect_real(cfg)
    if faults and not hasattr(faults, "before_frame"):
        faults = FaultInjector.for_simulated(faults, robot, rig)
    lock = Lock(cell_lock_path(lock_key), f"the cell ({lock_key})") if lock_key else None
    with lock or nullcontext(), signals_as_interrupt():
        if lock is not None and lock.stale:
            prog.event(lock.stale)
        prog.message("connecting")
        robot.connect()
        try:
            rig.open()
            specs = tuple(rig.specs)
            check_plan(plan, cfg, robot.is_reachable)  # refuse before anything moves
            found = {} if resume else record_devices(rig, out, cfg.standoff_m)  # a new session
            if getattr(robot, "controller_info", None):  # what a real controller reported
                found["controller"] = dict(robot.controller_info)
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
                acquire(robot, rig, plan, cfg, writer, log, prog, start, retries, faults)
            except (HardwareFault, KeyboardInterrupt, OSError) as e:
                _abort(robot, writer, log, prog, e, out)
            writer.finish("complete")
        finally:
            for closer in (rig.close, robot.close):
                with suppress(Exception):  # closing must not hide the real error
                    closer()
    return robot, log


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
    if cfg.limits != Limits():
        extra["limits"] = limits_to_dict(cfg.limits)
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
            sockets=sockets(cfg) or {},
        )
    except OSError as e:
        raise InputError(
            f"cannot be written ({e.strerror}); choose a writable --out", where=str(out)
        ) from None


def _open_log(out: Path, cfg: CellConfig, specs: tuple, recording: bool, spawn: bool, writer):
    from slidecal.routines.rerun_log import RECORDING_FILE, RerunLog  # rerun: optional library

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
    kind, msg = "fault", str(e)
    if isinstance(e, KeyboardInterrupt):
        kind = "interrupted"
        msg = f"{msg if isinstance(e, Interrupted) else 'stopped by Ctrl-C'} (robot stopped)"
    elif isinstance(e, OSError):
        msg = f"writing the session failed: {e.strerror or e} ({e.filename})"
    n = writer.n_frames
    with suppress(OSError):  # the disk that failed the frame may fail the event too
        writer.add_event(kind, msg, frames_kept=n, robot_time_s=clock(robot))
        writer.finish("aborted")
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


def clock(robot: Any) -> float | None:
    t = getattr(robot, "robot_time_s", None)
    return float(t) if t is not None else None


def _detect_all(images, cfg: CellConfig):
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


def acquire(
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
    n = 0  # poses up to the end of this group
    for g, group in enumerate(plan.groups):
        n += len(group)
        if n <= start:
            continue
        if plan.via is not None:
            prog.step(n - len(group), "moving to the via pose")
            robot.move_linear(plan.via, plan.speed_mps, plan.accel_mps2)
        for i, T in enumerate(group, start=n - len(group)):
            if i < start:
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
                log.frame(fid, T_meas, images, detections, clock(robot))
            counts = ", ".join(f"{n} {q['n_corners']} corners" for n, q in quality.items())
            prog.frame_done(f"group {g + 1}, frame id {fid}: {counts}")
