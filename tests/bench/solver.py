"""Monte-Carlo benchmark of the solver against the Cramer-Rao bound (docs/SETUPS.md S1-S4, R1).

Run ``python -m tests.bench solver`` (or ``python -m tests.bench.solver``); ``--trials`` sets the
Monte-Carlo size (100 by default), ``--out`` writes the markdown table
committed as docs/results/BENCHMARKS.md. Per row and parameter: bias and standard deviation over the
trials of the paper's linear method and of the maximum-likelihood estimator, the Cramer-Rao
bound computed by the project for the same scenario and knowledge, and the efficiency ratio
(ML std / bound). Then the R1 solve time next to ``cv2.calibrateCamera`` on the same detections,
measured in the same run.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from slidecal.mocks import scenarios as sc
from slidecal.mocks.camera import LENSES
from slidecal.solver.calibrate import calibrate
from slidecal.solver.errors import SlidecalError
from slidecal.solver.geometry import rotation_angle_deg
from slidecal.solver.homography import homography_dlt, refine_homography
from slidecal.solver.linear import LinearGroup, linear_intrinsics
from slidecal.solver.problem import ModelOptions
from slidecal.solver.uncertainty import predicted_covariance
from tests.bench.report import RESULTS, publish_report, report_header
from tests.helpers import linearised_estimator

PARAMS = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}


@dataclass
class Row:
    """One scenario row: per parameter the linear and ML errors over the trials."""

    scenario: str
    setting: str
    params: tuple[str, ...]
    lin: dict[str, list[float]]
    ml: dict[str, list[float]]
    bound: dict[str, float]
    failures: int = 0
    extra: str = ""
    ref: dict[str, list[float]] | None = None


def _crb(s: sc.Scenario, sigma: float) -> dict[str, float]:
    bound = predicted_covariance(s.problem, s.truth, sigma)
    return {p: bound.std(f"cam.{p}") for p in PARAMS}


def run_row(
    scenario: str,
    setting: str,
    make: Callable[[np.random.Generator], sc.Scenario],
    trials: int,
    params: tuple[str, ...],
    bound: bool = True,
    bound_scenario: sc.Scenario | None = None,
    reference: bool = True,
    hand_eye_errors_deg: list[float] | None = None,
) -> Row:
    """Monte-Carlo over ``trials`` seeds of ``make``; errors of K against the truth.

    The bound (and the linearised sampling reference, with ``reference``) come from
    ``bound_scenario`` or the first trial; ``hand_eye_errors_deg`` collects the hand-eye
    rotation error of every trial when given.
    """
    row = Row(scenario, setting, params, {p: [] for p in params}, {p: [] for p in params}, {})
    lin_ref = None
    for t in range(trials):
        s = make(np.random.default_rng(1000 + t))
        if t == 0 and bound:
            sb = bound_scenario or s
            row.bound = _crb(sb, sb.sigma_px)
            if reference:
                lin_ref = linearised_estimator(sb.problem, sb.truth)
                row.ref = {p: [] for p in params}
        if lin_ref is not None:
            errors = lin_ref.errors(s.problem)
            for p in params:
                row.ref[p].append(float(errors[f"cam.{p}"]))
        try:
            res = calibrate(s.problem, joint_homographies=True)
        except SlidecalError:
            row.failures += 1
            continue
        Kt = s.truth.K["cam"]
        for p in params:
            a, b = PARAMS[p]
            row.lin[p].append(float(res.linear["cam"][a, b] - Kt[a, b]))
            row.ml[p].append(float(res.cameras["cam"].K[a, b] - Kt[a, b]))
        if hand_eye_errors_deg is not None:
            hand_eye_errors_deg.append(rotation_angle_deg(res.hand_eye.R, s.T_hand_eye[:3, :3]))
    return row


def _stats(v: list[float]) -> tuple[float, float]:
    if len(v) < 2:
        return float("nan"), float("nan")
    return float(np.mean(v)), float(np.std(v, ddof=1))


def r1_hand_eye_row(
    trials: int, robot_noise: bool, model_noise: bool, learn: bool = False
) -> Row:
    """R1 with distortion: K errors and the hand-eye rotation error against its bound.

    ``robot_noise``: the measured poses carry 0.05 mm / 0.005 deg noise; ``model_noise``: the
    solver is told that level (errors in variables, ``ModelOptions.robot_noise_*``) and the bound
    is that of the same model; ``learn``: the solver's default, the level learned from the data
    (``ModelOptions.estimate_robot_noise``), against the bound of the model with the true level.
    Without ``learn`` the level is taken as given (0: poses exact).
    """
    noise = (5e-5, 0.005) if robot_noise else (0.0, 0.0)
    told = {"robot_noise_m": 5e-5, "robot_noise_deg": 0.005} if model_noise else {}
    opts = ModelOptions(**told, estimate_robot_noise=learn)
    bound_opts = ModelOptions(robot_noise_m=5e-5, robot_noise_deg=0.005) if learn else opts
    setting = "no robot noise"
    if robot_noise:
        setting = "robot noise 0.05 mm, 0.005 deg, " + (
            "learned from the data (default)"
            if learn
            else "modelled" if model_noise else "poses taken as exact"
        )
    s0 = sc.r1(np.random.default_rng(1000), 0.15, 0.0, 0.0, options=bound_opts)
    rot_bound = predicted_covariance(s0.problem, s0.truth, 0.15).std_rot_deg("T_tool_cam")
    errs: list[float] = []
    row = run_row(
        "R1",
        setting,
        lambda rng: sc.r1(rng, 0.15, *noise, options=opts),
        trials,
        tuple(PARAMS),
        bound_scenario=s0,
        reference=not robot_noise,  # the truth of a noisy pose is not at hand for it
        hand_eye_errors_deg=errs,
    )
    rms = float(np.sqrt(np.mean(np.square(errs)))) if errs else float("nan")
    row.extra = (
        f"hand-eye rotation rms error {rms:.4f} deg, bound {rot_bound:.4f} deg "
        f"(ratio {rms / rot_bound:.2f})"
    )
    if robot_noise and not model_noise and not learn:
        row.extra += "; the bound is that of exact poses, so the ratio is what the noise costs"
    return row


def lens_model_rows(trials: int) -> list[Row]:
    """R1 without robot noise, one row per lens model (``mocks/camera.py``'s LENSES): the solver
    told the model, against the bound of the same model; then the rational model on a wide lens
    whose field the board covers (``mocks/scenarios.py``'s ``wide_r1``), at R1's noise and at a
    tenth of it (the bound is linear in the noise, the estimator is not)."""
    rows = []
    for model, dist in LENSES.items():
        opts = ModelOptions(distortion_model=model)
        make = lambda rng, o=opts, d=dist: sc.r1(rng, 0.15, 0.0, 0.0, options=o, dist=d)  # noqa: E731
        rows.append(run_row("R1", f"lens model {model}", make, trials, tuple(PARAMS)))
    opts = ModelOptions(distortion_model="rational")
    for sigma in (0.15, 0.015):
        make = lambda rng, s=sigma: sc.wide_r1(rng, s, opts)  # noqa: E731
        setting = f"lens model rational, sigma {sigma} px"
        rows.append(run_row("wide R1", setting, make, trials, tuple(PARAMS)))
    return rows


def linear_per_frame(s: sc.Scenario) -> np.ndarray:
    """The linear method with per-frame homographies (each refined alone, then rescaled to the
    first frame's h1, h2 as docs/METHOD.md Sec. 3 allows) instead of the joint group estimate."""
    p = s.problem
    pts = p.target.points_m[:, :2]
    Hs = []
    for f in p.frames:
        d = f.detections["cam"]
        Hs.append(refine_homography(homography_dlt(pts[d.ids], d.px), pts[d.ids], d.px))
    ref = np.concatenate([Hs[0][:, 0], Hs[0][:, 1]])
    H = np.array([H * (ref @ np.r_[H[:, 0], H[:, 1]]) / np.sum(H[:, :2] ** 2) for H in Hs])
    if p.knowledge == "robot":
        m = np.array([f.T_base_tool[:3, 3] for f in p.frames])
        m = m - m[0]
    else:
        m = np.array([f.motion_board for f in p.frames])
    o = p.options
    return linear_intrinsics(
        [LinearGroup(H, m)],
        p.knowledge,
        skew=o.skew,
        unit_aspect=o.unit_aspect,
        image_size=(300, 240),
    ).K


def per_frame_rows(trials: int) -> list[str]:
    """The paper's linear method with per-frame homographies against the reference figures."""
    cases = [
        ("S1, theta = 30", lambda rng: sc.s1(30, 0.5, rng), "+0.4 / 4.5"),
        ("S1, theta = 60", lambda rng: sc.s1(60, 0.5, rng), "+0.5 / 5.5"),
        ("S2, 3 images", lambda rng: sc.s2(3, 0.5, rng), "+2.7 / 7.2"),
        ("S2, 5 images", lambda rng: sc.s2(5, 0.5, rng), "+3.5 / 5.6"),
        ("S2, 10 images", lambda rng: sc.s2(10, 0.5, rng), "+4.9 / 5.4"),
        ("S2, 5 images, sigma 0.1", lambda rng: sc.s2(5, 0.1, rng), "+0.2 / 0.8"),
        ("S2, 5 images, sigma 1.0", lambda rng: sc.s2(5, 1.0, rng), "+11.5 / 13.0"),
    ]
    out = [
        "| scenario | reference linear bias / std | joint homographies (ours) | "
        "per-frame homographies |",
        "| --- | --- | --- | --- |",
    ]
    for name, make, ref in cases:
        joint, single = [], []
        for t in range(trials):
            s = make(np.random.default_rng(1000 + t))
            fx = s.truth.K["cam"][0, 0]
            try:
                single.append(linear_per_frame(s)[0, 0] - fx)
                joint.append(calibrate(s.problem, joint_homographies=True).linear["cam"][0, 0] - fx)
            except SlidecalError:
                continue
        (jb, js), (pb, ps) = _stats(joint), _stats(single)
        out.append(f"| {name} | {ref} | {jb:+.1f} / {js:.1f} | {pb:+.1f} / {ps:.1f} |")
    return out


def time_against_opencv(s: sc.Scenario, repeats: int = 15) -> dict[str, float]:
    """Median wall time of our solve of a one-camera scenario (linear start, refinement,
    covariance) and of cv2.calibrateCamera on the same detections, in the same run."""
    obj = [
        s.problem.target.points_m[f.detections["cam"].ids].astype(np.float32)
        for f in s.problem.frames
    ]
    img = [f.detections["cam"].px.astype(np.float32) for f in s.problem.frames]
    size = (s.problem.cameras[0].width, s.problem.cameras[0].height)
    ours, theirs = [], []
    calibrate(s.problem)
    for _ in range(repeats):
        t = time.perf_counter()
        calibrate(s.problem)
        ours.append(time.perf_counter() - t)
        t = time.perf_counter()
        cv2.calibrateCamera(obj, img, size, None, None)
        theirs.append(time.perf_counter() - t)
    return {"slidecal_s": statistics.median(ours), "opencv_s": statistics.median(theirs)}


def speed(repeats: int = 15) -> dict[str, float]:
    """Median wall time of our R1 solve (with covariance) and of cv2.calibrateCamera."""
    return time_against_opencv(sc.r1(np.random.default_rng(7)), repeats)


def all_rows(trials: int) -> tuple[list[Row], list[str]]:
    """Every row of the benchmark (S1-S4, R1) and the notes that go under the table."""
    rows: list[Row] = []
    notes: list[str] = []
    f_only = ("fx",)
    four = tuple(PARAMS)
    for th in (10, 20, 30, 45, 60):
        rows.append(
            run_row("S1", f"theta {th} deg", lambda rng, th=th: sc.s1(th, 0.5, rng), trials, f_only)
        )
    for name, fn in (("S2", sc.s2), ("S3", sc.s3)):
        for n in (2, 3, 5, 10):
            rows.append(
                run_row(
                    name,
                    f"{n} images, sigma 0.5",
                    lambda rng, n=n, fn=fn: fn(n, 0.5, rng),
                    trials,
                    four,
                )
            )
        for sig in (0.1, 0.25, 1.0):
            rows.append(
                run_row(
                    name,
                    f"5 images, sigma {sig}",
                    lambda rng, sig=sig, fn=fn: fn(5, sig, rng),
                    trials,
                    four,
                )
            )
    for e in (0.0, 0.01, 0.02, 0.05):
        rows.append(
            run_row(
                "S4 (S1 theta 30)",
                f"step error {100 * e:.0f} %",
                lambda rng, e=e: sc.s1(30, 0.5, rng, step_error=e),
                trials,
                f_only,
                bound=e == 0,
            )
        )
    for phi in (0.0, 1.0, 2.0, 5.0):
        rows.append(
            run_row(
                "S4 (S2 5 images)",
                f"direction error {phi:.0f} deg",
                lambda rng, phi=phi: sc.s2(5, 0.5, rng, phi_deg=phi),
                trials,
                four,
                bound=phi == 0,
            )
        )
    for robot_noise, model_noise, learn in (
        (False, False, False),
        (True, False, False),
        (True, True, False),
        (True, False, True),
    ):
        row = r1_hand_eye_row(trials, robot_noise, model_noise, learn)
        rows.append(row)
        notes.append(f"R1 ({row.setting}): {row.extra}")
    return rows, notes


def table(rows: list[Row]) -> str:
    """The markdown table of all rows."""
    out = [
        "| scenario | setting | param | linear bias | linear std | ML bias | ML std | "
        "bound | efficiency | sampling reference | ML abs(bias)/std | failed |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        for p in r.params:
            lb, ls = _stats(r.lin[p])
            mb, ms = _stats(r.ml[p])
            bd = r.bound.get(p, float("nan"))
            eff = ms / bd if bd == bd else float("nan")
            ref = _stats(r.ref[p])[1] / bd if r.ref and bd == bd else float("nan")
            label = "f" if r.params == ("fx",) else p
            out.append(
                f"| {r.scenario} | {r.setting} | {label} | {lb:+.3f} | {ls:.3f} | {mb:+.3f} | "
                f"{ms:.3f} | {'' if bd != bd else f'{bd:.3f}'} | "
                f"{'' if eff != eff else f'{eff:.2f}'} | {'' if ref != ref else f'{ref:.2f}'} | "
                f"{abs(mb) / ms:.2f} | {r.failures} |"
            )
    return "\n".join(out)


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The options of ``python -m tests.bench``."""
    ap.add_argument("--trials", type=int, default=100, help="Monte-Carlo trials per row")
    ap.add_argument("--out", default=str(RESULTS / "BENCHMARKS.md"), help="the report to write")
    ap.add_argument(
        "--lens-models", action="store_true", help="only the lens models' rows (printed)"
    )


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m tests.bench solver`` (and ``python -m``)."""
    ap = argparse.ArgumentParser(
        prog="python -m tests.bench solver", description=__doc__.splitlines()[0]
    )
    add_arguments(ap)
    args = ap.parse_args(argv)
    if args.lens_models:
        print(table(lens_model_rows(args.trials)))
        return 0
    t0 = time.time()
    rows, notes = all_rows(args.trials)
    rows += lens_model_rows(args.trials)
    sp = speed()
    ratio = sp["slidecal_s"] / sp["opencv_s"]
    lines = [
        *report_header("Benchmarks", "solver", argv, time.time() - t0),
        f"Monte-Carlo over {args.trials} trials per row (seeds 1000..). Errors in pixels of the "
        "estimate minus the truth; 'bound' is the Cramer-Rao bound (docs/METHOD.md Sec. 6) for the "
        "same "
        "scenario, knowledge and noise; efficiency = ML std / bound (1.0 is perfect). 'sampling "
        "reference' is the same ratio for the linearised ML estimator at the truth on the same "
        "noise draws: exactly efficient by construction, it shows how far from 1.0 a perfect "
        "estimator lands with this many trials. S4 rows with motion errors have no bound (the "
        "model is then wrong on purpose).",
        "",
        table(rows),
        "",
        *[f"- {n}" for n in notes],
        "",
        "## The linear method against the reference figures (fx, pixels)",
        "",
        "The reference figures for the paper's linear method (docs/SETUPS.md) were measured by an",
        "independent implementation. Ours estimates each orientation group's homographies",
        "jointly (shared h1, h2; docs/METHOD.md Sec. 3) and weighs the rows by their noise scale:",
        "its spread is 1.4 to 3.6 times smaller than the reference's, and it has no bias. With",
        "per-frame homographies (each fitted alone, then rescaled) the spread is of the",
        "reference's order (within 10-40 % on S2, twice it on S1); the reference's bias, growing",
        "with the number of images and the noise, is not reproduced by either variant.",
        "",
        *per_frame_rows(args.trials),
        "",
        "## Speed (R1: 20 frames x 70 corners, distortion, hand-eye, covariance)",
        "",
        f"- slidecal calibrate (linear start, refinement, covariance): "
        f"{1000 * sp['slidecal_s']:.1f} ms (median of 15)",
        f"- cv2.calibrateCamera on the same detections (intrinsics and per-frame poses only): "
        f"{1000 * sp['opencv_s']:.1f} ms",
        f"- ratio: {ratio:.2f}",
    ]
    text = "\n".join(lines) + "\n"
    return publish_report(text, args.out)


if __name__ == "__main__":
    sys.exit(main())
