"""The ``slidecal`` command line.

``slidecal run [--config cell.yaml] [--out SESSION_DIR] [--plan plan.yaml] [--spawn] [--quiet]
[--seed N]`` and ``slidecal solve SESSION_DIR [--out result.yaml]``. Every ``SlidecalError`` is
printed as one line ``slidecal: <message>`` on stderr, exit code 2 (hardware faults 3), no
traceback and no result file; Ctrl-C stops the robot (the routine does) and exits with 130.

Adding a subcommand: write a module with ``add_arguments(parser)`` and ``main(args) -> int``
and name it in :data:`SUBCOMMANDS` (``"plan"``, ``"bench"`` are meant to go there).
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
    p.add_argument("--plan", help="plan.yaml to execute (default: the fixed default plan)")
    p.add_argument("--spawn", action="store_true", help="open the rerun viewer live")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--no-recording", action="store_true", help="do not write recording.rrd")
    p.add_argument("--seed", type=int, help="simulated cells: the random seed")
    p.add_argument("--fault", action="append", metavar="KIND@FRAME",
                   help="simulated cells: inject a hardware fault (see slidecal.routines.faults)")


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
        faults=args.fault,
    )
    if not args.quiet:
        print(outcome.summary, end="")
        robot = f", robot time {outcome.robot_time_s:.1f} s" if outcome.robot_time_s else ""
        print(
            f"session: {outcome.session_dir}  result: {outcome.result_path}  "
            f"({outcome.n_frames} frames, {outcome.wall_time_s:.1f} s{robot})"
        )
    return 0


def _solve_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("session", help="session directory (holds session.yaml)")
    p.add_argument("--out", help="result file (default: SESSION_DIR/result.yaml)")
    p.add_argument("--quiet", action="store_true", help="do not print the summary")


def _solve_main(args: argparse.Namespace) -> int:
    from slidecal.routines.run import solve_session

    outcome = solve_session(args.session, args.out)
    if not args.quiet:
        print(outcome.summary, end="")
        print(f"result: {outcome.result_path}")
    return 0


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
    "bench": "slidecal.routines.benchmarks",
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
    args = build_parser().parse_args(argv)
    try:
        return int(args._main(args) or 0)
    except HardwareFault as e:
        print(f"slidecal: {_one_line(e)}", file=sys.stderr)
        return EXIT_HARDWARE
    except SlidecalError as e:
        print(f"slidecal: {_one_line(e)}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print("\nslidecal: interrupted; the robot was stopped", file=sys.stderr)
        return EXIT_INTERRUPTED


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


if __name__ == "__main__":
    sys.exit(main())
