"""The ``slidecal`` command line.

``slidecal run [--config cell.yaml] [--out SESSION_DIR] [--plan plan.yaml] [--install STORE]
[--resume SESSION_DIR] ...``, ``slidecal solve SESSION_DIR [--out result.yaml]``, ``slidecal
check --config CELL --installed STORE``, ``slidecal rollback STORE``. Every ``SlidecalError``
(and every failure to read or write a file) is printed as one line ``slidecal: <message>`` on
stderr, no traceback.

Exit codes (docs/UNATTENDED.md): 0 accepted (run, solve) or ok (check); 2 bad input; 3 hardware
fault; 4 rejected; 5 drifted; 6 accepted but not installed (less certain than the installed
calibration: ``--force``); 130 interrupted (Ctrl-C, SIGTERM or SIGHUP: the robot is stopped,
the frames kept, the session marked aborted; ``slidecal run --resume`` continues it).

Adding a subcommand: write a module with ``add_arguments(parser)`` and ``main(args) -> int``
and name it in :data:`SUBCOMMANDS`.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from types import SimpleNamespace

from slidecal.solver.errors import HardwareFault, SlidecalError

EXIT_INPUT = 2
EXIT_HARDWARE = 3
EXIT_INTERRUPTED = 130


def _run_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", help="cell description (default: the simulated default cell)")
    p.add_argument("--out", help="session directory to create (default: sessions/<time>)")
    p.add_argument(
        "--plan",
        help="plan.yaml to execute, checked before the robot moves (default: the planner "
        "makes one for the cell; see slidecal plan)",
    )
    p.add_argument("--spawn", action="store_true", help="open the rerun viewer live")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--no-recording", action="store_true", help="do not write recording.rrd")
    p.add_argument(
        "--seed",
        type=int,
        help="simulated cells: the random seed (0 or more; it draws the arm's error and the "
        "board's placement too: another seed is another cell)",
    )
    p.add_argument("--fault", action="append", metavar="KIND@FRAME",
                   help="simulated cells: inject a hardware fault (see slidecal.routines.faults)")
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
        action="store_true",
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


def _print_outcome(outcome, quiet: bool) -> None:  # noqa: ANN001 - a RunOutcome
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
        print(f"not installed: {_one_line(outcome.install_note)}")


def _run_main(args: argparse.Namespace) -> int:
    from slidecal.routines.run import run_calibration

    outcome = run_calibration(
        args.config,
        plan=args.plan,
        out_dir=args.out,
        progress=False if args.quiet else None,
        recording=not args.no_recording,
        spawn=args.spawn,
        seed=args.seed,
        install=args.install,
        force=args.force,
        accept_drift=True if args.accept_drift else None,
        installed=args.installed,
        resume=args.resume,
        retries=args.retries,
        faults=args.fault,
    )
    _print_outcome(outcome, args.quiet)
    return outcome.exit_code


def _solve_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("session", help="session directory (holds session.yaml)")
    p.add_argument("--out", help="result file (default: SESSION_DIR/result.yaml)")
    p.add_argument("--quiet", action="store_true", help="print only the verdict")
    p.add_argument("--force", action="store_true", help="replace an existing result file")
    p.add_argument(
        "--installed", metavar="STORE", help="compare with this install store or result.yaml"
    )
    p.add_argument("--config", help="cell file whose limits: apply (default: the session's)")


def _solve_main(args: argparse.Namespace) -> int:
    from slidecal.routines.run import solve_session

    outcome = solve_session(
        args.session, args.out, force=args.force, installed=args.installed, config=args.config
    )
    _print_outcome(outcome, args.quiet)
    return outcome.exit_code


#: Subcommand name -> a module path (with ``add_arguments`` and ``main``) or a namespace of them.
SUBCOMMANDS: dict[str, str | SimpleNamespace] = {
    "run": SimpleNamespace(
        add_arguments=_run_arguments,
        main=_run_main,
        help="move the robot through a plan, capture, calibrate (simulated cell by default)",
    ),
    "solve": SimpleNamespace(
        add_arguments=_solve_arguments,
        main=_solve_main,
        help="solve a recorded session directory again",
    ),
    "check": "slidecal.routines.check",
    "rollback": "slidecal.routines.install",
    "plan": "slidecal.routines.planner",
    "rehearse": "slidecal.routines.rehearse",
    "flash": "slidecal.routines.flash",
}


def _module(entry: str | SimpleNamespace):
    return importlib.import_module(entry) if isinstance(entry, str) else entry


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand of :data:`SUBCOMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="slidecal",
        description="Camera, hand-eye and stereo calibration from robot translations.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name, entry in SUBCOMMANDS.items():
        mod = _module(entry)
        doc = getattr(mod, "help", None) or (mod.__doc__ or "").strip().split("\n")[0]
        p = sub.add_parser(name, help=doc, description=doc)
        mod.add_arguments(p)
        p.set_defaults(_main=mod.main)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``slidecal`` console script; returns the exit code."""
    from slidecal.routines.run import signals_as_interrupt

    args = build_parser().parse_args(argv)
    try:
        with signals_as_interrupt():
            return int(args._main(args) or 0)
    except HardwareFault as e:
        print(f"slidecal: {_one_line(e)}", file=sys.stderr)
        return EXIT_HARDWARE
    except SlidecalError as e:
        print(f"slidecal: {_one_line(e)}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt as e:
        how = getattr(e, "how", "Ctrl-C")
        print(
            f"\nslidecal: interrupted by {how}; a moving robot was stopped, its frames kept",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
    except OSError as e:  # a file that cannot be read or written: one line, not a traceback
        where = f"{e.filename}: " if e.filename else ""
        print(
            f"slidecal: {where}{e.strerror or e}; check the path, its rights and the free disk "
            "space",
            file=sys.stderr,
        )
        return EXIT_INPUT
    except UnicodeDecodeError as e:
        print(
            f"slidecal: a file is not UTF-8 text ({e.reason} at byte {e.start}); save it as UTF-8",
            file=sys.stderr,
        )
        return EXIT_INPUT


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


if __name__ == "__main__":
    sys.exit(main())
