"""The ``slidecal`` command line: ``run``, ``solve``, ``check``, ``rollback`` and the others of
:data:`SUBCOMMANDS` (a subcommand is a module with ``add_arguments(parser)`` and
``main(args) -> int``). Every ``SlidecalError`` and every failure to read or write a file is one
line ``slidecal: <message>`` on stderr, no traceback; the exit codes: docs/UNATTENDED.md."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from slidecal.routines import __version__
from slidecal.routines.progress import signals_as_interrupt
from slidecal.routines.solve import one_line
from slidecal.solver.errors import HardwareFault, SlidecalError

EXIT_INPUT = 2
EXIT_HARDWARE = 3
EXIT_INTERRUPTED = 130


#: Subcommand name -> the module that implements it (``help``, ``add_arguments``, ``main``).
#: Only the module of the command given is imported: ``slidecal solve`` imports what it
#: solves with, not the simulator, the planner or the drivers.
SUBCOMMANDS: dict[str, str] = {
    "run": "slidecal.routines.run",
    "solve": "slidecal.routines.solve",
    "import": "slidecal.routines.importer",
    "check": "slidecal.routines.ops.check",
    "rollback": "slidecal.routines.ops.install",
    "plan": "slidecal.routines.planner",
    "rehearse": "slidecal.routines.ops.rehearse",
    "flash": "slidecal.routines.ops.flash",
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The argument parser with every subcommand of :data:`SUBCOMMANDS` (``command``: only
    that one's module is imported; the others are names)."""
    parser = argparse.ArgumentParser(
        prog="slidecal",
        description="Camera, hand-eye and stereo calibration from robot translations.",
    )
    parser.add_argument("--version", action="version", version=f"slidecal {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, module in SUBCOMMANDS.items():
        if command not in (None, name):
            sub.add_parser(name)
            continue
        mod = importlib.import_module(module)
        doc = getattr(mod, "help", None) or (mod.__doc__ or "").strip().split("\n")[0]
        p = sub.add_parser(name, help=doc, description=doc)
        mod.add_arguments(p)
        p.set_defaults(_main=mod.main)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``slidecal`` console script; returns the exit code."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(argv[0] if argv and argv[0] in SUBCOMMANDS else None).parse_args(argv)
    try:
        with signals_as_interrupt():
            return int(args._main(args) or 0)
    except SlidecalError as e:
        print(f"slidecal: {one_line(e)}", file=sys.stderr)
        return EXIT_HARDWARE if isinstance(e, HardwareFault) else EXIT_INPUT
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


if __name__ == "__main__":
    sys.exit(main())
