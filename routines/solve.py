"""Solve a recorded session, judge it and write what the verdict allows (``slidecal solve``);
what a run or a solve produced (:class:`RunOutcome`).

Imports only what a solve needs: no simulator, planner, drivers or viewer.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from slidecal.routines.devices import device_calibration_outputs
from slidecal.routines.exports import result_header, write_all_exports
from slidecal.routines.ops.install import check_same_cell, current_dir
from slidecal.routines.ops.report import write_report
from slidecal.routines.ops.verdict import Limits, Verdict, judge, limits_from_dict, write_verdict
from slidecal.routines.plan import read_plan
from slidecal.routines.results_io import (
    RESULT_FILE,
    errors_against_truth,
    read_result,
    summary_text,
    write_result,
)
from slidecal.routines.schema import (
    CELL_SECTIONS,
    Fields,
    check_out_file,
    load_yaml,
    write_atomic,
)
from slidecal.routines.session import Session, load_session
from slidecal.solver.calibrate import calibrate
from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.result import CalibrationResult

help = "solve a recorded session directory again"

SUMMARY_FILE = "summary.txt"
EXPORT_DIR = "export"
REJECTED_DIR = "rejected"


@dataclass(frozen=True)
class RunOutcome:
    """What a run produced: ``errors`` against the simulated truth (simulated cells), the robot's
    and this process's time, the gate's ``verdict`` (a rejected result is written under
    ``rejected/`` without exports), ``installed_to`` (None when not installed: ``install_note``
    says why), ``export_errors`` (one line each) and :attr:`exit_code`."""

    session_dir: Path
    result: CalibrationResult
    result_path: Path
    summary: str
    n_frames: int
    wall_time_s: float
    robot_time_s: float | None
    errors: dict[str, float] = field(default_factory=dict)
    exports: tuple[Path, ...] = ()
    verdict: Verdict | None = None
    installed_to: Path | None = None
    install_note: str | None = None
    export_errors: tuple[str, ...] = ()
    report_path: Path | None = None

    @property
    def exit_code(self) -> int:
        """0 accepted (or installed), 4 rejected, 5 drifted, 6 accepted but not installed
        (docs/UNATTENDED.md)."""
        if self.verdict is None:
            return 0
        code = self.verdict.exit_code
        if self.installed_to is not None:
            return 0  # a drifted result installed on request: what the job asked for is done
        if code == 0 and self.install_note is not None:
            return EXIT_NOT_INSTALLED
        return code


#: Exit code of an accepted result that the install store refused (less certain than the
#: installed one without ``--force``).
EXIT_NOT_INSTALLED = 6


def installed_calibration(path: str | Path | None) -> tuple[CalibrationResult | None, str | None]:
    """The installed calibration to compare with: an install store, a directory with a
    ``result.yaml`` or a result file; (None, None) without one."""
    if path is None:
        return None, None
    p = Path(path)
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


def finish_solve(
    result: CalibrationResult,
    session_dir: Path,
    session: Session,
    limits: Limits,
    command: str,
    t0: float,
    cell_path: str | Path | None = None,
    cell_name: str | None = None,
    oak_sockets: Mapping[str, str] | None = None,
    installed: CalibrationResult | None = None,
    installed_path: str | None = None,
    result_path: Path | None = None,
    plan_poses: int | None = None,
    notes: Sequence[str] = (),
) -> RunOutcome:
    """Judge a solved session and write what the verdict allows: always ``verdict.yaml``,
    ``summary.txt`` and the report; ``result.yaml`` and ``export/`` when accepted or drifted,
    ``rejected/`` without exports otherwise. ``t0``: the command's start (``time.monotonic``);
    ``notes``: the run's own notes for the verdict."""
    status = _session_status(session, plan_poses)
    verdict = judge(
        result,
        limits,
        session.problem,
        installed,
        command=command,
        session_status=status,
        installed_path=installed_path,
        sockets=oak_sockets,
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
    device_summary = ""
    if verdict.verdict != "rejected":  # and for an OAK the export on the device's own calibration
        exports, export_errors = write_all_exports(
            result, target.parent / EXPORT_DIR, header, oak_sockets
        )
        device_exports, device_summary = device_calibration_outputs(
            result, session_dir, target.parent / EXPORT_DIR
        )
        exports += [p for p in device_exports if p not in exports]
    lines = [summary_text(result, session.simulation, limits.scale_tolerance).rstrip("\n")]
    if device_summary.strip():
        lines.append(device_summary.rstrip("\n"))
    if status != "complete":
        lines.append(f"SESSION {status.upper()}: solved from the frames it holds")
    # the verdict's notes on what was not determined and on the frames left out repeat the
    # result's own lines above: summary.txt says them once (verdict.yaml keeps them all)
    shown = {f"{k} not determined: {v}" for k, v in result.unobservable.items()}
    shown |= set(result.messages)
    lines += [v for v in verdict.lines() if v.removeprefix("  note: ") not in shown]
    lines += export_errors
    summary = "\n".join(lines) + "\n"
    write_atomic(target.parent / SUMMARY_FILE, summary)
    write_verdict(verdict, session_dir)
    report = None
    try:
        report = write_report(session_dir, result, verdict, session.problem, installed, summary)
    except (OSError, ValueError) as e:
        export_errors.append(f"report failed: {' '.join(str(e).split())}")
    return RunOutcome(
        session_dir=session.directory,
        result=result,
        result_path=target,
        summary=summary,
        n_frames=len(session.problem.frames),
        wall_time_s=time.monotonic() - t0,
        robot_time_s=None,
        errors=errors_against_truth(result, session.simulation) if session.simulation else {},
        exports=tuple(exports),
        verdict=verdict,
        export_errors=tuple(export_errors),
        report_path=report,
    )


def _session_status(session: Session, plan_poses: int | None) -> str:
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
    counted in inner corners, another board size, nothing at all), or "" when it said nothing."""
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

    An existing result is not overwritten without ``force``. ``installed``: an install store or
    result to compare with; ``config``: a cell file whose ``limits:`` apply (default: the
    session's).
    """
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
    if config is not None:
        limits = cell_file_limits(config)
    else:
        limits = limits_from_dict(session.limits, f"{session_dir}/session.yaml")
    plan_poses = None
    if (session_dir / "plan.yaml").is_file():
        plan_poses = read_plan(session_dir / "plan.yaml").n_poses
    inst_result, inst_path = installed_calibration(installed)
    if inst_result is not None:
        check_same_cell(inst_result, inst_path, session.problem.cameras, session.cell)
    try:
        result = calibrate(session.problem)
    except DegenerateError as e:
        hint = detection_hint(session.detect_reasons, len(session.problem.frames))
        if not hint:
            raise
        raise DegenerateError(f"{e}; {hint}") from e
    return finish_solve(
        result,
        session_dir,
        session,
        limits,
        command="solve",
        t0=t0,
        cell_path=config,
        cell_name=session.cell,
        oak_sockets=session.sockets or None,
        installed=inst_result,
        installed_path=inst_path,
        result_path=path,
        plan_poses=plan_poses,
    )


def cell_file_limits(path: str | Path) -> Limits:
    """The gate's limits of a cell file (its ``limits:`` section): what a solve takes of a
    cell (the rest of the cell, checked by every run, describes hardware a solve does not use)."""
    data = load_yaml(Path(path), "cell file")
    Fields(data, Path(path).name).only(CELL_SECTIONS)  # a misspelt limits: is not ignored
    return limits_from_dict(data.get("limits"), Path(path).name)


def print_outcome(outcome: RunOutcome, quiet: bool) -> None:
    """What ``slidecal run`` and ``slidecal solve`` print of an outcome."""
    if not quiet:
        print(outcome.summary, end="")
        robot = f", robot time {outcome.robot_time_s:.1f} s" if outcome.robot_time_s else ""
        print(
            f"session: {outcome.session_dir}  result: {outcome.result_path}  "
            f"({outcome.n_frames} frames, {outcome.wall_time_s:.1f} s{robot})"
        )
    elif outcome.verdict is not None:
        print(f"verdict: {outcome.verdict.verdict}")
    for e in outcome.export_errors:
        print(f"slidecal: {e}", file=sys.stderr)
    if outcome.installed_to is not None:
        print(f"installed: {outcome.installed_to}")
    if outcome.install_note is not None:
        print(f"not installed: {one_line(outcome.install_note)}")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``slidecal solve`` options."""
    p.add_argument("session", help="session directory (holds session.yaml)")
    p.add_argument("--out", help="result file (default: SESSION_DIR/result.yaml)")
    p.add_argument("--quiet", action="store_true", help="print only the verdict")
    p.add_argument("--force", action="store_true", help="replace an existing result file")
    p.add_argument(
        "--installed", metavar="STORE", help="compare with this install store or result.yaml"
    )
    p.add_argument("--config", help="cell file whose limits: apply (default: the session's)")


def main(args: argparse.Namespace) -> int:
    """Solve, print the summary, exit with the verdict's code."""
    outcome = solve_session(
        args.session, args.out, force=args.force, installed=args.installed, config=args.config
    )
    print_outcome(outcome, args.quiet)
    return outcome.exit_code


def one_line(e: BaseException) -> str:
    """An error message on one line."""
    return " ".join(str(e).split())


