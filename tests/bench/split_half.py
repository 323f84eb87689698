"""Honesty on real data: split a session's frames at random into halves, solve each half, and ask
whether the reported std explains the halves' difference.

    python -m tests.bench split_half SESSION_DIR [--seeds 40] [--by-group]
    python -m tests.bench split_half IMAGE_DIR --chessboard 10x7 [--square-m 0.025]

Per split (seeds 0..N-1): within each orientation group half of its frames at random (a hand-held
or image-only session is one group; ``--by-group``: half of the groups, whole), each half solved
by slidecal (``calibrate`` with default options; without robot poses the board poses are free)
and by OpenCV (``cv2.calibrateCameraExtended``, default flags, and ``cv2.calibrateHandEye``,
Park, where there are poses), and for fx, fy, cx, cy z = (A - B) / sqrt(std_A^2 + std_B^2) with
each solver's own std (per axis of the hand-eye for slidecal; OpenCV reports none for it, so its
halves' difference is shown in degrees and millimetres beside slidecal's). An honest std gives an
rms z of about 1; what both halves share (the arm's smooth error) lowers it.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from slidecal.mocks.truth import INTRINSICS, halves_z, hand_eye_errors, rms, split_halves
from slidecal.solver.calibrate import calibrate
from slidecal.solver.detect import detect
from slidecal.solver.errors import InputError, SlidecalError
from slidecal.solver.geometry import inv_T, rotation_angle_deg
from slidecal.solver.problem import CalibrationProblem, CameraSpec, Frame, Target
from slidecal.solver.refine import orientation_groups
from tests.bench.report import RESULTS, publish_report, report_header
from tests.session_io import read_session

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
AXES = ("rx", "ry", "rz", "tx", "ty", "tz")
#: OpenCV's intrinsics' std: the first four of calibrateCameraExtended's stdDeviationsIntrinsics
CV_ORDER = ("fx", "fy", "cx", "cy")


def image_session(folder: Path, chessboard: str, square_m: float) -> CalibrationProblem:
    """A session without robot poses from a folder of chessboard photographs (squares
    ``COLSxROWS``): one camera, free board poses; images without the board are left out."""
    try:
        cols, rows = (int(v) for v in chessboard.lower().split("x"))
    except ValueError:
        raise InputError(f"{chessboard!r} is not COLSxROWS (squares), e.g. 10x7",
                         where="--chessboard") from None
    target = Target.chessboard(cols, rows, square_m)
    frames, size = [], None
    for k, path in enumerate(sorted(p for p in folder.iterdir()
                                    if p.suffix.lower() in IMAGE_SUFFIXES)):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        size = size or (image.shape[1], image.shape[0])
        d = detect(image, target).detection
        if len(d.ids):
            frames.append(Frame(k, {"cam": d}))
    if len(frames) < 6:
        raise InputError(f"{folder}: {len(frames)} images show a {chessboard} chessboard; a split "
                         "needs at least 6", where="--chessboard")
    return CalibrationProblem(target, (CameraSpec("cam", *size),), tuple(frames), knowledge="none")


def opencv_half(problem: CalibrationProblem, cam: str) -> dict | None:
    """OpenCV on one half: intrinsics with their std, and the hand-eye (Park) where there are
    poses; None when OpenCV fails."""
    spec = problem.camera(cam)
    used = [f for f in problem.frames if cam in f.detections and len(f.detections[cam].ids) >= 6]
    obj = [problem.target.points_m[f.detections[cam].ids].astype(np.float32) for f in used]
    img = [f.detections[cam].px.astype(np.float32).reshape(-1, 1, 2) for f in used]
    try:
        out = cv2.calibrateCameraExtended(obj, img, (spec.width, spec.height), None, None)
    except cv2.error:
        return None
    K, rvecs, tvecs, std = out[1], out[3], out[4], np.ravel(out[5])
    res = {"K": K, "std": dict(zip(CV_ORDER, std[:4], strict=True))}
    if all(f.T_base_tool is not None for f in used):
        T = [f.T_base_tool if problem.mount == "eye_in_hand" else inv_T(f.T_base_tool)
             for f in used]
        R, t = cv2.calibrateHandEye([x[:3, :3] for x in T], [x[:3, 3] for x in T],
                                    [cv2.Rodrigues(r)[0] for r in rvecs], list(tvecs),
                                    method=cv2.CALIB_HAND_EYE_PARK)
        res["hand_eye"] = np.eye(4)
        res["hand_eye"][:3, :3], res["hand_eye"][:3, 3] = R, np.ravel(t)
    return res


def split_half(problem: CalibrationProblem, seeds: int, by_group: bool) -> dict:
    """The z of every split (slidecal's and OpenCV's) and the halves' hand-eye differences."""
    cam = problem.reference
    poses = [f.T_base_tool for f in problem.frames]
    groups = (orientation_groups(np.stack(poses)) if all(p is not None for p in poses)
              else np.zeros(len(poses), dtype=int))
    z: dict[str, list[float]] = {f"{s} {p}": [] for s in ("slidecal", "OpenCV") for p in INTRINSICS}
    z.update({f"slidecal {a}": [] for a in AXES})
    diff: dict[str, list[float]] = {"slidecal deg": [], "slidecal mm": [], "OpenCV deg": [],
                                    "OpenCV mm": []}
    failed = 0
    for seed in range(seeds):
        in_a = split_halves(groups, np.random.default_rng(seed), by_group)
        halves = [replace(problem, frames=tuple(f for f, a in zip(problem.frames, in_a,
                                                                  strict=True) if a == side))
                  for side in (True, False)]
        try:
            A, B = (calibrate(h) for h in halves)
        except SlidecalError:
            failed += 1
            continue
        ca, cb = A.cameras[cam], B.cameras[cam]
        for p, (i, j) in INTRINSICS.items():
            z[f"slidecal {p}"].append(halves_z(ca.K[i, j], ca.std[p], cb.K[i, j], cb.std[p]))
        cv = [opencv_half(h, cam) for h in halves]
        if all(cv):
            for p, (i, j) in INTRINSICS.items():
                z[f"OpenCV {p}"].append(halves_z(cv[0]["K"][i, j], cv[0]["std"][p],
                                                 cv[1]["K"][i, j], cv[1]["std"][p]))
        if A.hand_eye is None or B.hand_eye is None:
            continue
        T_b = np.eye(4)
        T_b[:3, :3] = B.hand_eye.R
        T_b[:3, 3] = B.hand_eye.t_m if B.hand_eye.t_m is not None else 0.0
        d_a, d_b = hand_eye_errors(A, T_b), hand_eye_errors(B, T_b)
        for key, axes in (("rot", AXES[:3]), ("t", AXES[3:])):
            if key in d_a and key in d_b:
                d, C = d_a[key][0], d_a[key][1] + d_b[key][1]
                for k, a in enumerate(axes):
                    z[f"slidecal {a}"].append(float(d[k] / np.sqrt(C[k, k])))
        diff["slidecal deg"].append(rotation_angle_deg(A.hand_eye.R, B.hand_eye.R))
        if A.hand_eye.t_m is not None:
            diff["slidecal mm"].append(1000 * float(np.linalg.norm(A.hand_eye.t_m - T_b[:3, 3])))
        if all(cv) and "hand_eye" in cv[0] and "hand_eye" in cv[1]:
            X, Y = cv[0]["hand_eye"], cv[1]["hand_eye"]
            diff["OpenCV deg"].append(rotation_angle_deg(X[:3, :3], Y[:3, :3]))
            diff["OpenCV mm"].append(1000 * float(np.linalg.norm(X[:3, 3] - Y[:3, 3])))
    return {"z": z, "diff": diff, "failed": failed, "groups": len(set(groups.tolist())),
            "frames": len(problem.frames)}


def report(out: dict, source: str, seeds: int, by_group: bool) -> list[str]:
    """The markdown table of :func:`split_half`."""
    z, diff = out["z"], out["diff"]
    how = "whole orientation groups" if by_group else "within each orientation group"
    lines = [
        f"Session: {source}: {out['frames']} frames in {out['groups']} orientation group(s); "
        f"{seeds} random splits into halves ({how}); {out['failed']} split(s) where a half "
        "did not solve.",
        "",
        "| quantity | slidecal rms z | OpenCV rms z | splits |",
        "| --- | --- | --- | --- |",
    ]
    for p in INTRINSICS:
        lines.append(f"| {p} | {rms(z[f'slidecal {p}']):.2f} | {rms(z[f'OpenCV {p}']):.2f} | "
                     f"{len(z[f'slidecal {p}'])} |")
    for a in AXES:
        if z[f"slidecal {a}"]:
            lines.append(f"| hand-eye {a} | {rms(z[f'slidecal {a}']):.2f} | (no std) | "
                         f"{len(z[f'slidecal {a}'])} |")
    if diff["slidecal deg"]:
        lines += [
            "",
            "Hand-eye halves' difference, rms: slidecal "
            f"{rms(diff['slidecal deg']):.3f} deg, {rms(diff['slidecal mm']):.2f} mm; "
            f"OpenCV (Park) {rms(diff['OpenCV deg']):.3f} deg, {rms(diff['OpenCV mm']):.2f} mm.",
        ]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.bench split_half",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("source", type=Path, help="a session directory or a folder of images")
    ap.add_argument("--seeds", type=int, default=40, help="random splits (seeds 0..N-1)")
    ap.add_argument("--by-group", action="store_true", help="split by whole orientation groups")
    ap.add_argument("--chessboard", help="an image folder's board: COLSxROWS squares, e.g. 10x7")
    ap.add_argument("--square-m", type=float, default=0.025, help="an image folder's square side")
    ap.add_argument("--out", default=str(RESULTS / "SPLIT_HALF.md"), help="the report to write")
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    if (args.source / "session.yaml").is_file():
        problem = read_session(args.source)
    elif args.source.is_dir() and args.chessboard:
        problem = image_session(args.source, args.chessboard, args.square_m)
    else:
        raise InputError(f"{args.source} is neither a session directory (with session.yaml) nor "
                         "an image folder given with --chessboard COLSxROWS", where="SOURCE")
    out = split_half(problem, args.seeds, args.by_group)
    root = RESULTS.parent.parent  # a source inside the checkout as its path there, else its name
    here = args.source.resolve()
    shown = str(here.relative_to(root)) if here.is_relative_to(root) else args.source.name
    lines = report_header("Split-half honesty", "split_half",
                          [shown if a == str(args.source) else a for a in (argv or [])],
                          time.monotonic() - t0)
    return publish_report("\n".join(lines + report(out, shown, args.seeds, args.by_group)) + "\n",
                          args.out)
