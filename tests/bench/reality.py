"""Honesty on a real arm: coverage of the reported uncertainty under a simulated arm's accuracy.

One study, four tables: ``python -m tests.bench reality --table
reality|arm_2mm|arm_05mm|render`` writes docs/results/REALITY.md, REALITY_ARM_2MM.md,
REALITY_ARM_05MM.md, REALITY_RENDER.md (or give ``--trials``, ``--images points|render``,
``--arm-mm``, ``--arm-deg``, ``--out``). Each trial draws a new UR5e whose kinematics err like
an uncalibrated real arm (``slidecal.mocks.robot.KinematicError``: 0.5-2 mm, 0.05-0.2 deg,
smooth over the workspace, plus repeatability) and a new image noise; the controller reports the
nominal poses, the camera sees the true ones, and ``calibrate`` runs with default settings (the
robot's accuracy learned from the data). Per parameter: the fraction of trials whose error is
within 2 reported standard deviations (the target is >= 90 %), the largest and the rms of
|error| / std. The hand-eye is compared with the effective truth (what the session can know: the
physical hand-eye moved by the arm's constant error, ``effective_truth``), rotation and
translation as 3-vectors (Mahalanobis distance against the reported covariance; 2-sigma coverage
is a chi-square(3) below 8.03) and per axis, in the result's own parametrisation of the reported
transform (``T_tool_cam.rx`` .. ``.tz``, docs/FORMATS.md). Beside every figure, what a
calibrated Gaussian estimator gives over as many trials (:func:`calibration`: binomial ranges of
the coverage and of the count beyond 3 sigma, chi-square for the rms) and a verdict, so a row
that is off tells itself from sampling noise.

Image models: ``points``: the true corners with Gaussian noise (0.15 px, what a good corner
detector leaves on a sharp image); ``render``: images from ``slidecal.mocks.render`` and the
project's detector (slower; the photograph-like renderer is meant to replace it). Then the
clean scenarios' efficiency (ML std over the Cramer-Rao bound; docs/results/BENCHMARKS.md) and the
speed of the solve against ``cv2.calibrateCamera``.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from slidecal.mocks import scenarios as sc
from slidecal.mocks.scenarios import drifting_arm, render_detector
from slidecal.mocks.truth import (
    CHI2_3_2SIGMA,
    CHI2_3_3SIGMA,
    INTRINSICS,
    P_2SIGMA,
    P_3SIGMA,
    VERDICT_P,
    calibration,
    hand_eye_errors,
)
from slidecal.solver.calibrate import calibrate
from slidecal.solver.errors import SlidecalError
from slidecal.solver.geometry import rvec_from_R
from slidecal.solver.robot_error import TOOL_OFFSET_SIGMA_M
from tests.bench import solver as bench
from tests.bench.report import RESULTS, publish_report, shown_out

#: The long-armed classic row: the arm's positions this much further from its base than
#: reported (the linear field a public classic session learns is of this size)
LONG_ARM = 0.005
@dataclass
class RealityRow:
    """Normalised errors of one scenario over the trials."""

    name: str
    z: dict[str, list[float]] = field(default_factory=dict)  # error / std per parameter
    maha: dict[str, list[float]] = field(default_factory=dict)  # hand-eye Mahalanobis^2
    physical_deg: list[float] = field(default_factory=list)  # hand-eye rot. error, physical
    effective_deg: list[float] = field(default_factory=list)
    std_rot_deg: list[float] = field(default_factory=list)
    robot: list[tuple[float, float]] = field(default_factory=list)
    adequate: int = 0
    failures: list[str] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)


def run_reality_row(
    name: str, make: Callable[[np.random.Generator], sc.Scenario], trials: int
) -> RealityRow:
    """Monte-Carlo of one real-arm scenario (seeds 2000..)."""
    row = RealityRow(name, {p: [] for p in INTRINSICS})
    for t in range(trials):
        rng = np.random.default_rng(2000 + t)
        s = make(rng)
        t0 = time.perf_counter()
        try:
            res = calibrate(s.problem)
        except SlidecalError as e:
            row.failures.append(f"seed {2000 + t}: {e}")
            continue
        row.seconds.append(time.perf_counter() - t0)
        cam = res.cameras["cam"]
        for p, (a, b) in INTRINSICS.items():
            row.z[p].append(float((cam.K[a, b] - s.truth.K["cam"][a, b]) / cam.std[p]))
        ra = res.robot_accuracy
        row.robot.append((ra.translation_mm, ra.rotation_deg))
        row.adequate += bool(res.adequacy.adequate)
        gone = {f for f, _, _ in ra.left_out}  # the truth of the frames the solve used
        used = [i for i, f in enumerate(s.problem.frames) if f.id not in gone]
        T_eff, _ = sc.effective_truth(
            s, max(ra.rotation_deg, 1e-4), max(ra.translation_mm, 1e-3), used
        )
        for key, (d, C) in hand_eye_errors(res, T_eff).items():
            row.maha.setdefault(key, []).append(float(d @ np.linalg.solve(C, d)))
            for i, ax in enumerate("xyz"):
                row.z.setdefault(f"hand-eye {key} {ax}", []).append(float(d[i] / np.sqrt(C[i, i])))
        row.physical_deg.append(
            float(np.degrees(np.linalg.norm(rvec_from_R(res.hand_eye.R @ s.T_hand_eye[:3, :3].T))))
        )
        row.effective_deg.append(
            float(np.degrees(np.linalg.norm(rvec_from_R(res.hand_eye.R @ T_eff[:3, :3].T))))
        )
        row.std_rot_deg.append(float(res.hand_eye.std_rot_deg or np.nan))
    return row


def reality_table(rows: list[RealityRow]) -> list[str]:
    """The coverage table (one line per scenario and parameter), each figure beside what a
    calibrated Gaussian estimator gives over as many trials (:func:`calibration`)."""
    level = f"{100.0 * (1.0 - VERDICT_P):.0f} %"
    out = [
        f"| scenario | parameter | trials | 2-sigma coverage (calibrated: {level} range) "
        f"| beyond 3 sigma (calibrated: {level} range) | max abs(error)/std "
        f"| rms error/std ({level} interval) | verdict |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    for r in rows:
        items = [(p, z, 1) for p, z in r.z.items() if z]
        items += [(f"hand-eye {k} (3-vector, Mahalanobis)", m, 3) for k, m in r.maha.items() if m]
        for p, v, dof in items:
            c = calibration(v, dof)
            lo2, hi2 = (100.0 * x / c.trials for x in c.inside_2_range)
            worst = float(np.sqrt(np.max(v))) if dof == 3 else float(np.max(np.abs(v)))
            as_scalar = f" ({c.worst_z:.2f} as a scalar)" if dof == 3 else ""
            out.append(
                f"| {r.name} | {p} | {c.trials} | {100.0 * c.inside_2 / c.trials:.1f} % "
                f"({lo2:.1f}-{hi2:.1f} %) | {c.beyond_3} ({c.beyond_3_range[0]}-"
                f"{c.beyond_3_range[1]}) | {worst:.2f}{as_scalar} | {c.scale:.2f} "
                f"({c.scale_range[0]:.2f}-{c.scale_range[1]:.2f}) | {c.verdict} |"
            )
    return out


def reality_notes(rows: list[RealityRow]) -> list[str]:
    """Per scenario: the robot accuracy learned, adequacy, hand-eye against both truths."""
    out = []
    for r in rows:
        if not r.robot:
            out.append(f"- {r.name}: every trial failed ({'; '.join(r.failures[:3])})")
            continue
        t_mm = np.array([x[0] for x in r.robot])
        r_deg = np.array([x[1] for x in r.robot])
        out.append(
            f"- {r.name}: robot accuracy learned {np.median(t_mm):.3f} mm "
            f"({t_mm.min():.3f}-{t_mm.max():.3f}), {np.median(r_deg):.4f} deg "
            f"({r_deg.min():.4f}-{r_deg.max():.4f}) rms per axis (median, range); marked "
            f"adequate in {r.adequate} of {len(r.robot)}; hand-eye rotation error "
            f"{np.sqrt(np.mean(np.square(r.effective_deg))):.4f} deg rms against the "
            f"effective truth, {np.sqrt(np.mean(np.square(r.physical_deg))):.4f} deg against "
            f"the physical one, reported std {np.nanmedian(r.std_rot_deg):.4f} deg (median); "
            f"solve {1000 * statistics.median(r.seconds):.0f} ms (median)"
            + (f"; {len(r.failures)} failed: {r.failures[0]}" if r.failures else "")
        )
    return out


def clean_rows(trials: int) -> tuple[list[bench.Row], list[str]]:
    """The clean scenarios whose efficiency must not move (docs/results/BENCHMARKS.md): the robot
    rows S1 and R1 (board-frame S2, S3 do not estimate a robot's accuracy)."""
    rows = [
        bench.run_row("S1", "theta 30 deg", lambda rng: sc.s1(30, 0.5, rng), trials, ("fx",)),
        bench.run_row(
            "S2", "5 images, sigma 0.5", lambda rng: sc.s2(5, 0.5, rng), trials, tuple(bench.PARAMS)
        ),
    ]
    r1 = bench.r1_hand_eye_row(trials, False, False)
    rows.append(r1)
    return rows, [f"R1 ({r1.setting}): {r1.extra}"]


def speed(repeats: int = 15) -> dict[str, float]:
    """Median wall time of the R1 solve against cv2.calibrateCamera: exact poses (robot noise
    0: the F test keeps them exact) and R1's default 0.05 mm / 0.005 deg noise (learned)."""
    out = {}
    for label, s in (
        ("clean", sc.r1(np.random.default_rng(7), 0.15, 0.0, 0.0)),
        ("noisy", sc.r1(np.random.default_rng(7))),
    ):
        t = bench.time_against_opencv(s, repeats)
        out[f"{label}_slidecal_s"], out[f"{label}_opencv_s"] = t["slidecal_s"], t["opencv_s"]
    return out


#: The study's tables: ``--table NAME`` sets these options (any given explicitly wins) and writes
#: the page; without it, the options as given and REALITY.md
TABLES = {
    "reality": ({"trials": 200, "clean_trials": 100}, "REALITY.md"),
    "arm_2mm": ({"trials": 100, "clean_trials": 0, "arm_mm": 2.0, "arm_deg": 0.2},
                "REALITY_ARM_2MM.md"),
    "arm_05mm": ({"trials": 100, "clean_trials": 0, "arm_mm": 0.5, "arm_deg": 0.05},
                 "REALITY_ARM_05MM.md"),
    "render": ({"trials": 20, "clean_trials": 0, "images": "render"}, "REALITY_RENDER.md"),
}


def main(argv: list[str] | None = None) -> int:
    """Entry point (``python -m tests.bench reality``)."""
    ap = argparse.ArgumentParser(
        prog="python -m tests.bench reality", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--table", choices=sorted(TABLES), help="one of the study's tables and page")
    ap.add_argument("--trials", type=int, default=30, help="Monte-Carlo trials per scenario")
    ap.add_argument("--images", choices=("points", "render"), default="points")
    ap.add_argument("--sigma-px", type=float, default=0.15, help="corner noise of 'points'")
    ap.add_argument("--arm-mm", type=float, default=1.0)
    ap.add_argument("--arm-deg", type=float, default=0.1)
    ap.add_argument(
        "--clean-trials",
        dest="clean_trials",
        type=int,
        default=100,
        help="trials of the clean efficiency rows (0: skip them)",
    )
    ap.add_argument("--out", default=str(RESULTS / "REALITY.md"), help="the report to write")
    base = {k: ap.get_default(k) for k in ("sigma_px", "arm_mm", "arm_deg")}
    table = ap.parse_args(argv).table
    if table:
        ap.set_defaults(**TABLES[table][0], out=str(RESULTS / TABLES[table][1]))
    args = ap.parse_args(argv)
    t0 = time.time()
    det = render_detector() if args.images == "render" else None
    kw = {"sigma_px": args.sigma_px, "arm_mm": args.arm_mm, "arm_deg": args.arm_deg, "detect": det}
    scenarios = [
        ("R1 eye-in-hand", lambda rng: sc.r1_real_arm(rng, **kw)),
        (
            "R1 eye-in-hand, a real board (bowed; its tolerance as a file gives it)",
            lambda rng: sc.r1_real_arm(rng, real_board=True, **kw),
        ),
        ("R1 eye-to-hand", lambda rng: sc.r1_real_arm(rng, eye_in_hand=False, **kw)),
        (
            "13 frames, one orientation",
            lambda rng: sc.r1_real_arm(rng, translations_only=True, **kw),
        ),
        (
            "13 frames, one orientation, drift 0.06 deg / 60 mm",
            lambda rng: drifting_arm(rng, args.sigma_px, detect=det)[0],
        ),
        ("classic eye-in-hand, 28 orientations", lambda rng: sc.classic_real_arm(rng, **kw)),
        (
            "classic eye-to-hand, 28 orientations",
            lambda rng: sc.classic_real_arm(rng, eye_in_hand=False, **kw),
        ),
    ]
    if det is None:  # the model's question, not the detector's: points only
        scenarios.append(
            (
                f"classic eye-in-hand, the arm's moves {100 * LONG_ARM:.1f} % long",
                lambda rng: sc.classic_real_arm(rng, arm_scale=LONG_ARM, **kw),
            )
        )
    tag_kw = {**kw, "detect": render_detector(0.10) if det is not None else None}
    scenarios.append(
        (
            "eye-to-hand, one tag, 205 frames in 7 orientations",
            lambda rng: sc.tag_real_arm(rng, **tag_kw),
        )
    )
    rows = [run_reality_row(n, m, args.trials) for n, m in scenarios]
    clean, clean_notes = clean_rows(args.clean_trials) if args.clean_trials > 0 else ([], [])
    sp = speed() if args.clean_trials > 0 else None
    cmd = (
        f"python -m tests.bench reality --trials {args.trials} --clean-trials "
        f"{args.clean_trials} --images {args.images}"
    )
    for flag, value in (
        ("--sigma-px", "sigma_px"),
        ("--arm-mm", "arm_mm"),
        ("--arm-deg", "arm_deg"),
    ):
        if getattr(args, value) != base[value]:  # what the report needs to be rerun
            cmd += f" {flag} {getattr(args, value):g}"
    lines = [
        "# The solver on a real arm: coverage of its reported uncertainty",
        "",
        f"Regenerate with `{cmd} --out {shown_out(args.out)}` "
        f"({platform.machine()}, "
        f"{platform.python_version()}, numpy {np.__version__}, OpenCV {cv2.__version__}; this "
        f"run took {time.time() - t0:.0f} s).",
        "",
        f"Every trial (seeds 2000..) draws a UR5e whose kinematics err by about {args.arm_mm} mm "
        f"and {args.arm_deg} deg (perturbed DH parameters, joint sag, transmission errors; "
        "0.03 mm / 0.005 deg repeatability) and "
        + (
            f"point detections with {args.sigma_px} px Gaussian noise"
            if args.images == "points"
            else "images rendered by mocks/render.py, detected by solver/detect.py"
        )
        + ". The controller reports the nominal poses; `calibrate` runs with default options "
        "(the robot's accuracy learned from the data). Coverage: trials whose error is within "
        "2 reported standard deviations (target >= 90 %, and abs(error)/std <= 3 on every "
        "seed). The hand-eye is judged against the effective truth (the physical one moved by "
        "the arm's constant error, which no camera can separate from it: docs/ROBOT_ACCURACY.md)"
        "; its 3-vectors by their Mahalanobis distance (2-sigma: chi-square(3) <= "
        f"{CHI2_3_2SIGMA:.2f}; the max column shows the distance in sigmas); its axes are those "
        "of the reported transform (`T_tool_cam.rx` .. `.tz`: rotation vector on the left, "
        "translation, docs/FORMATS.md).",
        "",
        "Each figure stands beside what a calibrated Gaussian estimator (errors exactly as "
        "large as the reported standard deviations say) gives over as many trials, at the "
        f"{100 * (1 - VERDICT_P):.0f} % level: the range of its 2-sigma coverage "
        f"(binomial, p = {P_2SIGMA:.4f}; for the 3-vectors chi-square(3) <= {CHI2_3_2SIGMA:.2f}), "
        f"of its count beyond 3 sigma (p = {1 - P_3SIGMA:.4f}; chi-square(3) > "
        f"{CHI2_3_3SIGMA:.2f}), and the interval of the rms error/std that the data imply "
        "(the sum of squares is chi-square with one degree of freedom per trial and axis). The "
        "verdict says 'consistent' unless the sum of squares, the coverage or the tail is "
        f"beyond what the calibrated estimator gives with probability {VERDICT_P} (then how much "
        "the std is too small or too large, or which test failed); three tests on some 40 rows "
        "give about one such row per report by chance. A 3-vector's largest distance is also "
        "given as the scalar error of the same tail probability. With honest standard "
        f"deviations, {args.trials} trials put {args.trials * (1 - P_3SIGMA):.2f} errors per "
        f"row beyond 3 sigma on average and leave a row without any with probability "
        f"{100 * P_3SIGMA**args.trials:.0f} %: abs(error)/std <= 3 on every seed is a statement "
        "about the tail that a calibrated estimator meets only by luck at this many trials.",
        "",
        "The covariance covers the arm's smooth error (docs/ERROR_MODEL.md): where an "
        "orientation group has too few frames to tell a linear trend of the pose error along its "
        "moves from the frames' scatter (R1's groups of five), the reported covariance is the "
        "larger of the estimator's spread under both readings (`smooth_field_excess`, way "
        "`groups`); a "
        "one-orientation session (the two 13-frame rows) does not learn its translation trend, "
        "which is a scale of the moves and so the focal length's, and always carries that "
        "reading on the translation axes, at no less than 0.1 % of the moves. Where one "
        "orientation leaves the camera's offset from the flange unobserved (the two 13-frame "
        f"rows), it carries the estimator's response to that offset at {TOOL_OFFSET_SIGMA_M} m "
        "per axis "
        "(`tool_offset_excess`).",
        "",
        "The drifting-arm row takes the one-orientation session's commanded poses on an arm "
        "whose orientation drifts linearly along the moves (0.06 deg per 60 mm in a random "
        "direction per trial, plus 0.003 deg / 0.02 mm per stop: `drifting_arm`), the physics "
        "of docs/ROBOT_ACCURACY.md in its pure form; the session's linear trend of the pose "
        "correction is built for it.",
        "",
        "The classic rows are hand-eye sessions of 28 frames, each at its own orientation "
        "(`classic_real_arm`: tilts of 15-35 deg, rolls up to 30 deg, 0.45-0.6 m from the "
        "board), on the same arm. No orientation group has a trend of its own; eye-in-hand, "
        "the session gets one linear trend of the pose corrections over the tool's positions "
        "(`SESSION_TREND_MIN_FRAMES`), whose translation the covariance carries at no less "
        "than 0.1 % of the moves (`smooth_field_excess`, way `field`); eye-to-hand, the "
        "corrections stay "
        "independent and the covariance carries a linear field of the translations over the "
        "positions at that level (`smooth_field_excess`, way `field`). Eye-in-hand, the result "
        "is reported "
        "halfway between the readings with and without that trend, their spread in its "
        "covariance (`session_field_step`); the long-armed row (points only) puts the arm's "
        f"positions {100 * LONG_ARM:.1f} % further from its base than reported "
        "(`classic_real_arm(arm_scale=...)`), an arm whose link lengths err alike, as a "
        "public classic session's learned field suggests (docs/results/PUBLIC_DATA.md).",
        "",
        "The tag row is a fixed camera watching one AprilTag's 4 corners on the tool "
        "(rendered: a 100 mm tag on a white margin of one cell, `render_detector(0.10)`): 205 "
        "frames in 7 orientations, each at a random place in R1's image 0.45-0.85 m "
        "away (`tag_real_arm`): many frames spread over a large part of the workspace, where "
        "the arm's error is correlated from frame to frame and the images pin each pose "
        "loosely. Besides each group's offset and trend, the groups share a trend of the "
        "rotation and a quadratic field of the translation (`common_trend`), and the covariance "
        "covers the reading where their translation trends are one field "
        "(`smooth_field_excess`, way `field`).",
        "",
        *reality_table(rows),
        "",
        *reality_notes(rows),
    ]
    if sp is not None:
        lines += _clean_section(args.clean_trials, clean, clean_notes, sp)
    text = "\n".join(lines) + "\n"
    return publish_report(text, args.out)


def _clean_section(
    trials: int, clean: list[bench.Row], clean_notes: list[str], sp: dict[str, float]
) -> list[str]:
    return [
        "",
        "## Clean scenarios: efficiency unchanged",
        "",
        f"The rows of docs/results/BENCHMARKS.md that a robot's learned accuracy could touch, "
        f"{trials} trials (same seeds as there). With exact poses the F test keeps "
        "them exact, so the solve is the one of BENCHMARKS.md.",
        "",
        bench.table(clean),
        "",
        *[f"- {n}" for n in clean_notes],
        "",
        "## Speed (R1: 20 frames x 70 corners, distortion, hand-eye, covariance)",
        "",
        f"- exact poses recognised: slidecal {1000 * sp['clean_slidecal_s']:.1f} ms, "
        f"cv2.calibrateCamera {1000 * sp['clean_opencv_s']:.1f} ms, ratio "
        f"{sp['clean_slidecal_s'] / sp['clean_opencv_s']:.2f}",
        f"- robot noise 0.05 mm / 0.005 deg learned: slidecal {1000 * sp['noisy_slidecal_s']:.1f} "
        f"ms, cv2.calibrateCamera {1000 * sp['noisy_opencv_s']:.1f} ms, ratio "
        f"{sp['noisy_slidecal_s'] / sp['noisy_opencv_s']:.2f}",
    ]


if __name__ == "__main__":
    sys.exit(main())
