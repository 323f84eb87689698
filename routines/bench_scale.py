"""How solve time grows with the data: 20 to 1000 frames, one to three cameras, against OpenCV.

``slidecal bench scale [--frames 20 100 200 400] [--cameras 1 2 3] [--out docs/SCALE.md]``
builds the OAK-D-like head eye-in-hand on the R1 cell (the simulator's ``oak_rig``), repeats its
20 robot poses with fresh corner noise until the session has the requested number of frames,
and times, in the same process: ``calibrate`` (linear start, refinement, covariance) and
``cv2.calibrateCamera`` on the reference camera's detections of the same session (intrinsics and
per-frame poses only, so it is a floor, not a like-for-like peer). Reported: wall seconds, the
ratio to OpenCV, and the growth from the previous row (time ratio over frame ratio: 1 is
linear in frames).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from slidecal.mocks.scenarios import oak_rig
from slidecal.routines.benchmarks import report_header
from slidecal.solver.calibrate import calibrate
from slidecal.solver.problem import CalibrationProblem, Frame

CAMERA_SETS = {1: ("left",), 2: ("left", "right"), 3: ("left", "right", "rgb")}


def session(n_frames: int, n_cameras: int, seed: int = 7) -> CalibrationProblem:
    """A simulated session of ``n_frames`` frames (R1's 20 poses repeated, new noise each time)."""
    rng = np.random.default_rng(seed)
    frames: list[Frame] = []
    base = None
    while len(frames) < n_frames:
        s = oak_rig(rng, cameras=CAMERA_SETS[n_cameras])
        base = base or s.problem
        for f in s.problem.frames:
            if len(frames) < n_frames:
                frames.append(replace(f, id=len(frames)))
    assert base is not None
    return replace(base, frames=tuple(frames))


def _opencv_s(problem: CalibrationProblem) -> float:
    ref = problem.reference
    spec = problem.camera(ref)
    obj, img = [], []
    for f in problem.frames:
        d = f.detections.get(ref)
        if d is not None and len(d.ids) >= 6:
            obj.append(problem.target.points_m[d.ids].astype(np.float32))
            img.append(d.px.astype(np.float32))
    t = time.perf_counter()
    cv2.calibrateCamera(obj, img, (spec.width, spec.height), None, None)
    return time.perf_counter() - t


def measure(n_frames: int, n_cameras: int) -> dict[str, float]:
    """Wall seconds of one solve and of OpenCV on the same session."""
    problem = session(n_frames, n_cameras)
    t = time.perf_counter()
    calibrate(problem)
    ours = time.perf_counter() - t
    return {"frames": n_frames, "cameras": n_cameras, "slidecal_s": ours,
            "opencv_s": _opencv_s(problem)}


def main(argv: list[str] | None = None) -> int:
    """Run the scaling benchmark and write its report."""
    ap = argparse.ArgumentParser(prog="slidecal bench scale", description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[20, 100, 200, 400])
    ap.add_argument("--cameras", type=int, nargs="+", default=[1, 2, 3], choices=[1, 2, 3])
    ap.add_argument("--out", type=Path, default=None, help="markdown file to write")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    measure(20, 1)  # warm-up: first calls pay for imports and caches, not for the data
    rows = []
    for nc in args.cameras:
        prev = None
        for nf in sorted(args.frames):
            r = measure(nf, nc)
            r["growth"] = (
                (r["slidecal_s"] / prev["slidecal_s"]) / (nf / prev["frames"]) if prev else np.nan
            )
            rows.append(r)
            prev = r
            print(f"{nc} camera(s), {nf} frames: {r['slidecal_s']:.2f} s", file=sys.stderr)
    lines = [
        *report_header("Solve time against the size of the session", "scale", argv,
                       time.perf_counter() - t0),
        "Targets: solve time / cv2.calibrateCamera <= 2 at 400 frames (one camera); "
        "time(400 frames) / time(100 frames) <= 5.",
        "",
        "| cameras | frames | slidecal (s) | cv2.calibrateCamera (s) | ratio | growth |",
        "| ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        g = "" if np.isnan(r["growth"]) else f"{r['growth']:.2f}"
        lines.append(
            f"| {r['cameras']} | {r['frames']} | {r['slidecal_s']:.3f} | {r['opencv_s']:.3f} | "
            f"{r['slidecal_s'] / r['opencv_s']:.1f} | {g} |"
        )
    lines += [
        "",
        "growth: (time ratio) / (frame ratio) against the row above; 1.0 is linear in frames.",
        "",
    ]
    text = "\n".join(lines)
    if args.out is not None:
        args.out.write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
