"""Scripted commissioning of a cell: run the calibration, read its verdict, install it.

    python examples/commission.py [cell.yaml] [--out sessions/commissioning] [--install STORE]

Without a cell file this runs the packaged simulated cell (no robot moves). The verdict is
slidecal's own gate (``docs/UNATTENDED.md``): the limits come from the cell file's ``limits:``
section, so a commissioning script sets its process's tolerances there instead of checking the
result again itself. An accepted result goes to the install store when one is given.
"""

from __future__ import annotations

import argparse
import sys

from slidecal.routines.run import RunRequest, run_calibration
from slidecal.solver.errors import HardwareFault, SlidecalError


def main() -> int:
    """Run, print the verdict and its reasons; exit with slidecal's code (0 accepted)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config", nargs="?", help="cell file (default: simulated cell)")
    ap.add_argument("--out", default=None, help="session directory")
    ap.add_argument("--install", default=None, help="install store for an accepted result")
    args = ap.parse_args()
    try:
        outcome = run_calibration(RunRequest(args.config, out_dir=args.out, install=args.install))
    except HardwareFault as e:
        print(f"commissioning stopped (robot stopped, frames kept): {e}", file=sys.stderr)
        return 3
    except SlidecalError as e:
        print(f"commissioning failed: {e}", file=sys.stderr)
        return 2
    print(outcome.summary)  # ends with the verdict and its reasons
    if outcome.installed_to is not None:
        print(f"installed: {outcome.installed_to}")
    print(
        f"session archived in {outcome.session_dir} ({outcome.wall_time_s:.1f} s wall, "
        f"{outcome.robot_time_s or 0:.1f} s robot); report: {outcome.report_path}"
    )
    return outcome.exit_code


if __name__ == "__main__":
    sys.exit(main())
