"""``python -m tests.bench NAME [options]``: run one benchmark (``--list`` names them)."""

from __future__ import annotations

import argparse
import importlib
import sys

from slidecal.solver.errors import InputError
from tests.bench.report import BENCHMARKS


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tests.bench", description=__doc__)
    p.add_argument("name", nargs="?", choices=sorted(BENCHMARKS), help="the benchmark to run")
    p.add_argument("--list", action="store_true", help="list the benchmarks and what they measure")
    p.add_argument(
        "options", nargs=argparse.REMAINDER, help="the benchmark's own options (NAME --help)"
    )
    args = p.parse_args(argv)
    if args.list or not args.name:
        width = max(len(n) for n in BENCHMARKS)
        for n, what in sorted(BENCHMARKS.items()):
            print(f"{n:<{width}}  {what}")
        return 0
    module = importlib.import_module(f"tests.bench.{args.name}")
    try:
        return int(module.main(list(args.options)) or 0)
    except InputError as e:  # bad input: one line, as the slidecal command gives it
        print(f"python -m tests.bench {args.name}: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
