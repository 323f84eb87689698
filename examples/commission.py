"""Scripted commissioning of a cell: run the calibration, check it, archive the session.

    python examples/commission.py [cell.yaml] [--out sessions/commissioning]

Without a cell file this runs the packaged simulated cell (no robot moves). The acceptance
thresholds below are examples; set them from your process's tolerances.
"""

from __future__ import annotations

import argparse
import sys

from slidecal.routines.run import run_calibration
from slidecal.solver.errors import SlidecalError

MAX_REPROJ_RMS_PX = 0.5
MAX_HAND_EYE_STD_MM = 0.5
MAX_SCALE_DEVIATION = 0.005


def main() -> int:
    """Run, check, print a verdict; exit code 0 when the cell passes."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("config", nargs="?", help="cell file (default: simulated cell)")
    ap.add_argument("--out", default=None, help="session directory")
    args = ap.parse_args()
    try:
        outcome = run_calibration(args.config, out_dir=args.out)
    except SlidecalError as e:
        print(f"commissioning failed: {e}", file=sys.stderr)
        return 2
    r = outcome.result
    checks = {
        f"reprojection rms {r.reproj_rms_px:.3f} px <= {MAX_REPROJ_RMS_PX}": r.reproj_rms_px
        <= MAX_REPROJ_RMS_PX,
        "solver converged": r.converged,
    }
    if r.hand_eye is not None and r.hand_eye.std_t_mm is not None:
        checks[f"hand-eye std {r.hand_eye.std_t_mm:.3f} mm <= {MAX_HAND_EYE_STD_MM}"] = (
            r.hand_eye.std_t_mm <= MAX_HAND_EYE_STD_MM
        )
    for s in r.scale_checks:
        if abs(s.ratio - 1.0) > MAX_SCALE_DEVIATION:
            checks[f"scale check frames {s.frame_a}-{s.frame_b}: ratio {s.ratio:.4f}"] = False
    print(outcome.summary)
    for text, ok in checks.items():
        print(f"[{'PASS' if ok else 'FAIL'}] {text}")
    print(
        f"session archived in {outcome.session_dir} ({outcome.wall_time_s:.1f} s wall, "
        f"{outcome.robot_time_s or 0:.1f} s robot)"
    )
    return 0 if all(checks.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
