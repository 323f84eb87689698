"""The calibration routine: plan, move, capture, detect, record, solve, write (``slidecal run``;
from Python: :func:`run_calibration`, README).

THE ROBOT NEVER MOVES unless the cell file names real hardware (``robot.driver: ur`` with a
``host``). What a run writes and when: docs/UNATTENDED.md.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from slidecal.mocks.cell import SimulatedCell
from slidecal.routines.acquire import (
    DEFAULT_RETRIES,
    cell_key,
    clock,
    new_session_dir,
    record_session,
)
from slidecal.routines.config import CellConfig, PlanGoal, load_config
from slidecal.routines.devices import check_libraries
from slidecal.routines.ops.faults import parse_fault
from slidecal.routines.ops.install import NotInstalled, check_same_cell, install, one_sigmas
from slidecal.routines.ops.verdict import Limits, judge
from slidecal.routines.plan import Plan, plan_from_dict, plan_to_dict, read_plan
from slidecal.routines.planner import extend_plan, make_plan, predict_std
from slidecal.routines.progress import Progress
from slidecal.routines.schema import check_out_dir, load_yaml
from slidecal.routines.session import Session, load_session
from slidecal.routines.solve import (
    RunOutcome,
    finish_solve,
    installed_calibration,
    print_outcome,
)
from slidecal.solver.calibrate import calibrate
from slidecal.solver.drift import chain_rms_px
from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.result import CalibrationResult

help = "move the robot through a plan, capture, calibrate (simulated cell by default)"

#: A user's plan: the smallest move inside a group that counts as a translation.
MIN_GROUP_MOVE_M = 0.002


@dataclass(frozen=True)
class RunRequest:
    """What :func:`run_calibration` is asked to do.

    ``config``: a cell file, a loaded :class:`CellConfig`, or None for the default simulated cell.
    ``plan``: a ``plan.yaml``, a :class:`Plan` (checked for degeneracy before the robot moves), or
    None: the planner's plan for the cell, or a refusal with the reason. ``out_dir``: the session
    directory to create (default ``sessions/<date>_<time>``). ``progress``: force the progress
    output on/off (None: on). ``recording``: write ``recording.rrd`` (rerun); ``spawn`` also opens a
    viewer. ``seed``: overrides ``simulation.seed``. ``overrides``: nested values merged over the
    cell file. ``cell``: a prepared :class:`~slidecal.mocks.cell.SimulatedCell`. ``install``: an
    install store (default: the cell's ``install.dir``); ``force`` installs a less certain result,
    ``accept_drift`` a drifted one. ``installed``: the calibration to compare with (default: the
    store's current one). ``resume``: a stopped session to continue from the first frame it lacks
    (``out_dir`` and ``plan`` None). ``faults``: ``KIND@FRAME`` strings (simulated cells) or a
    :class:`~slidecal.routines.ops.faults.FaultInjector`. ``retries``: captures of a pose tried
    again after a dropped frame or an image without corners (default: ``install.retries``, else 2).
    """

    config: str | Path | CellConfig | None = None
    plan: str | Path | Plan | None = None
    out_dir: str | Path | None = None
    progress: bool | Progress | None = None
    recording: bool = True
    spawn: bool = False
    seed: int | None = None
    overrides: Mapping[str, Any] | None = None
    cell: Any = None
    faults: Any = None
    install: str | Path | None = None
    force: bool = False
    accept_drift: bool | None = None
    installed: str | Path | None = None
    resume: str | Path | None = None
    retries: int | None = None


def check_user_plan(plan: Plan, cfg: CellConfig, where: str) -> None:
    """Refuse, before the robot moves, a user's plan that cannot determine the calibration: a group
    that holds no translation, or a plan the planner's prediction finds degenerate (a group's
    orientation is the plan file's rule, :func:`~slidecal.routines.plan.plan_from_dict`)."""
    for g, group in enumerate(plan.groups):
        T0 = group[0]
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


def run_calibration(request: RunRequest | None = None) -> RunOutcome:
    """Run a calibration end to end (:class:`RunRequest`), judge it, and return what it produced."""
    q = request or RunRequest()
    t0 = time.monotonic()
    cfg = q.config if isinstance(q.config, CellConfig) else load_config(q.config, q.overrides)
    if not cfg.simulated:
        check_libraries(cfg)  # a missing extra is said before planning
    store = q.install if q.install is not None else cfg.install.dir
    accept_drift = cfg.install.accept_drift if q.accept_drift is None else q.accept_drift
    retries = q.retries if q.retries is not None else cfg.install.retries
    retries = int(retries if retries is not None else DEFAULT_RETRIES)
    if retries < 0:
        raise InputError(f"--retries must be 0 or more, got {retries}")
    if q.seed is not None and q.seed < 0:
        raise InputError(f"--seed must be 0 or a positive integer, got {q.seed}")
    if store is not None:
        check_out_dir(Path(store), "--install")
    for spec in q.faults if isinstance(q.faults, list | tuple) else ():
        if isinstance(spec, str):
            parse_fault(spec)  # a bad --fault is refused before the plan is made
    if q.resume is not None:
        out, plan, start, seed = _resumed(q)
    else:
        out = new_session_dir(q.out_dir)
        plan, start, seed = _plan(q.plan, cfg), 0, q.seed
    inst_result, inst_path = installed_calibration(
        q.installed if q.installed is not None else store
    )
    if inst_result is not None:
        check_same_cell(inst_result, inst_path, cfg.cameras, cfg.source)
    cell = q.cell
    if cfg.simulated and cell is None:  # one simulated cell for the run and its extensions
        cell = SimulatedCell.from_config(cfg, seed)

    prog = Progress.from_option(q.progress, plan.n_poses)
    record = partial(
        record_session, cfg, out=out, prog=prog, lock_key=cell_key(q.config, cfg), cell=cell
    )
    record = partial(record, retries=retries, faults=q.faults)
    recording = q.recording and q.resume is None  # a resumed run's recording stays as it was
    robot, log = record(
        plan=plan,
        start=start,
        resume=q.resume is not None,
        recording=recording,
        spawn=q.spawn,
    )
    notes: list[str] = []
    for extension in range(EXTEND_ROUNDS + 1):
        prog.message("solving")
        session = load_session(out)  # solve what is on disk: the run can be replayed exactly
        result = calibrate(session.problem)
        if extension == EXTEND_ROUNDS:
            break
        longer, why = extend_for_limits(cfg, plan, result, cfg.limits, session)
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
        robot, _ = record(plan=plan, start=n_done, resume=True, extended=said, log=log)
    fin = finish_solve(
        result,
        out,
        session,
        cfg.limits,
        command="run",
        t0=t0,
        cell_path=q.config if isinstance(q.config, str | Path) else None,
        cell_name=cfg.source,
        oak_sockets=session.sockets or None,  # as the session recorded them
        installed=inst_result,
        installed_path=inst_path,
        plan_poses=plan.n_poses,
        notes=notes,
    )
    if log is not None:
        log.final(session.problem, result, fin.summary)
        log.event(f"verdict: {fin.verdict.verdict}")
        log.close()
    installed_to, note = _install(store, fin, q.force, accept_drift, cfg, session)
    for line in fin.verdict.lines() + ([f"not installed: {note}"] if note else []):
        prog.event(line)
    prog.done(f"done: {fin.result_path}")
    return replace(
        fin,
        wall_time_s=time.monotonic() - t0,
        robot_time_s=clock(robot),
        installed_to=installed_to,
        install_note=note,
    )


def _resumed(q: RunRequest) -> tuple[Path, Plan, int, int | None]:
    """A stopped session to continue: its directory, its plan, the first frame it lacks and
    its simulated cell's seed (the same target pose)."""
    if q.out_dir is not None or q.plan is not None:
        raise InputError("--resume continues a session's own plan into it; drop --out/--plan")
    out = Path(q.resume)  # type: ignore[arg-type]
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
    seed = q.seed
    sim = prior.get("simulation")
    if seed is None and isinstance(sim, Mapping) and isinstance(sim.get("seed"), int):
        seed = int(sim["seed"])
    return out, read_plan(out / "plan.yaml"), len(frames), seed


def _plan(plan: str | Path | Plan | None, cfg: CellConfig) -> Plan:
    """The plan to run: a user's, checked before the robot moves, or the planner's."""
    if plan is None:
        return make_plan(cfg)
    if isinstance(plan, Plan):  # a plan made in Python meets the plan file's rules too
        plan_from_dict(plan_to_dict(plan), "plan")
    user = plan if isinstance(plan, Plan) else read_plan(plan)
    check_user_plan(user, cfg, "plan" if isinstance(plan, Plan) else str(plan))
    return user


def _install(
    store: str | Path | None,
    fin: RunOutcome,
    force: bool,
    accept_drift: bool,
    cfg: CellConfig,
    session: Session,
) -> tuple[Path | None, str | None]:
    """Install an accepted (or accepted-drift) result; (new entry, None) or (None, why not)."""
    if store is None:
        return None, None
    v = fin.verdict
    if v.verdict == "rejected":
        return None, "the result was rejected; the installed calibration stays"
    try:
        d = install(
            store,
            fin.result_path.parent,
            fin.result,
            v.verdict,
            force=force,
            accept_drift=accept_drift,
            info={"cell": cfg.source, "chain_rms_px": chain_rms_px(fin.result, session.problem)},
        )
    except NotInstalled as e:
        return None, str(e)
    return d, None


#: How many times a run extends its plan when its result misses the gate's one-sigma limits.
EXTEND_ROUNDS = 2
#: An extension plans for this fraction of each one-sigma limit (a margin for levels learned
#: again on more frames; docs/UNATTENDED.md).
EXTEND_MARGIN = 0.9


def extend_for_limits(
    cfg: CellConfig,
    plan: Plan,
    result: CalibrationResult,
    limits: Limits,
    session: Session,
) -> tuple[Plan | None, str]:
    """The longer plan a run records next when its result misses only the gate's one-sigma limits,
    with why; or None and why not (an empty reason when nothing was missed). Planned for the
    accuracy the data showed (:func:`slidecal.routines.planner.extend_plan`) within the cell's
    ``plan.extend_max_s`` of robot time (0: never); only the planner's plans are extended."""
    verdict = judge(result, limits, session.problem, command="run")
    if verdict.verdict != "rejected":
        return None, ""
    failed = verdict.reasons
    if any(c.test != "std" for c in failed):
        return None, ""  # more frames cannot cure a model that does not fit
    budget_s = cfg.plan.extend_max_s
    if budget_s <= 0:
        return None, "not extended: plan.extend_max_s is 0"
    if plan.predicted_std is None:
        return None, "not extended: a plan written by hand is run as written"
    cam = result.cameras.get(cfg.reference_camera)
    he = result.hand_eye
    if cam is None or he is None:
        return None, "not extended: the reference camera or the hand-eye was not determined"
    u, ref, nan = one_sigmas(result), cfg.reference_camera, float("nan")
    rel = [u[k] for k in (f"{ref}.fx_rel", f"{ref}.fy_rel") if k in u]
    achieved = {
        "fx_rel_std": max(rel) if rel else nan,
        "hand_eye_rot_std_deg": u.get(f"{he.name}.rot_deg", nan),
        "hand_eye_t_std_mm": u.get(f"{he.name}.t_mm", nan),
    }
    goal = {k: EXTEND_MARGIN * getattr(limits, k) for k in achieved}
    acc = result.robot_accuracy
    t_mm = acc.translation_mm if acc is not None else cfg.options.robot_noise_m * 1000.0
    rot_deg = acc.rotation_deg if acc is not None else cfg.options.robot_noise_deg
    s = replace(
        cfg.plan,
        goal=PlanGoal(**goal, max_duration_s=budget_s),
        corner_noise_px=float(cam.reproj_rms_px),
        robot_noise=(t_mm, rot_deg),
        robot_levels=acc.levels if acc is not None else None,
    )
    try:
        longer = extend_plan(cfg, plan, s, achieved)
    except InputError as e:
        return None, f"not extended: {e}"
    if longer.n_poses == plan.n_poses:
        return None, "not extended: the planner predicts no gain from more frames"
    missed = "; ".join(c.message for c in failed)
    return longer, (
        f"{missed} (robot accuracy {t_mm:.2f} mm / {rot_deg:.3f} deg as the data shows it)"
    )


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``slidecal run`` options."""
    p.add_argument("--config", help="cell description (default: the simulated default cell)")
    p.add_argument(
        "--out",
        dest="out_dir",
        metavar="OUT",
        help="session directory to create (default: sessions/<time>)",
    )
    p.add_argument(
        "--plan",
        help="plan.yaml to execute, checked before the robot moves (default: the planner "
        "makes one for the cell; see slidecal plan)",
    )
    p.add_argument("--spawn", action="store_true", help="open the rerun viewer live")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument(
        "--no-recording", dest="recording", action="store_false", help="do not write recording.rrd"
    )
    p.add_argument(
        "--seed",
        type=int,
        help="simulated cells: the random seed (0 or more; it draws the arm's error and the "
        "board's placement too: another seed is another cell)",
    )
    p.add_argument(
        "--fault",
        dest="faults",
        action="append",
        metavar="KIND@FRAME",
        help="simulated cells: inject a hardware fault (see slidecal.routines.ops.faults)",
    )
    p.add_argument(
        "--install",
        metavar="STORE",
        help="install an accepted result into this store (default: the cell's install.dir)",
    )
    p.add_argument(
        "--installed",
        metavar="STORE",
        help="compare with this install store or result.yaml (default: --install's)",
    )
    p.add_argument(
        "--force", action="store_true", help="install even if less certain than the installed"
    )
    p.add_argument(
        "--accept-drift",
        action="store_const",
        const=True,
        help="install a result that differs from the installed one (verdict drifted)",
    )
    p.add_argument(
        "--resume",
        metavar="SESSION_DIR",
        help="continue a stopped run's session from its first missing frame",
    )
    p.add_argument(
        "--retries",
        type=int,
        help="captures tried again per pose after a dropped frame or no corners (default 2)",
    )


def main(args: argparse.Namespace) -> int:
    """Run, print the summary, exit with the verdict's code."""
    given = {f.name: getattr(args, f.name) for f in fields(RunRequest) if hasattr(args, f.name)}
    outcome = run_calibration(RunRequest(**given, progress=False if args.quiet else None))
    print_outcome(outcome, args.quiet)
    return outcome.exit_code
