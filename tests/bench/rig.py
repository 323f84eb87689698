"""Benchmark of rig calibration (issue 5): maximum likelihood against the Cramer-Rao bound.

(i) S5 (docs/SETUPS.md, paper Figs. 7-9) as a general-motion two-camera problem through
``calibrate``: equal noise, then the left camera at twice the right's (the solver estimates
and weighs each camera's noise), and that again with the left camera's pixels scaled to the
right's noise (:func:`scale_pixels`, a cross-check of the weighting). (ii) The OAK-D-like head
eye-in-hand on R1's poses (``mocks/scenarios.oak_rig``), with exact and with noisy, modelled
robot poses. Per camera and parameter: bias and std over the trials, the bound and the
efficiency ratio std / bound; the relative rotation's rms error against its bound (root of the
trace of the rig rotation block), and the rms error of the linear eq. 63 rotation. (iii) End to
end on the simulated OAK cell (rendered images, detection, solve) over a few seeds: baseline
and relative rotation errors against the recorded truth, with the reported one-sigma.

The bound with unequal camera noise weighs every residual row by its camera's noise:
``(J_w' J_w)^-1`` with ``J_w = diag(1 / sigma_row) J`` (:func:`rig_bounds`, through the named
model's ``predicted_covariance`` with ``camera_sigma_px``). ``refine`` estimates each camera's
noise and weighs its rows by it; the row with the left camera's pixels scaled by
``sigma_right / sigma_left`` (:func:`scale_pixels`) cross-checks that weighting, and the
column "equal weights" gives the best an estimator weighing all rows alike could do (the
sandwich ``(J' W J)^-1 J' W Sigma W J (J' W J)^-1``, the named model's
``equal_weight_covariance``), i.e. what the per-camera weighting buys.

Regenerate ``docs/results/RIG.md``::

    python -m tests.bench rig --out docs/results/RIG.md
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import slidecal.mocks as mocks
from slidecal.mocks import scenarios as rs
from slidecal.mocks.truth import rig_bounds
from slidecal.routines.results_io import truth_transform
from slidecal.routines.run import RunRequest, run_calibration
from slidecal.routines.session import load_session
from slidecal.solver.calibrate import calibrate
from slidecal.solver.errors import SlidecalError
from slidecal.solver.geometry import rotation_angle_deg
from slidecal.solver.homography import homography_dlt, refine_homography
from slidecal.solver.model import build_structure
from slidecal.solver.problem import ModelOptions
from slidecal.solver.stereo import infinite_homography, rig_linear_intrinsics
from tests.bench.report import RESULTS, publish_report, report_header
from tests.helpers import relative_rotation
from tests.session_io import scale_pixels

PARAMS = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}
ROBOT_NOISE = (5e-5, 0.005)  # metres, degrees: R1's robot pose noise


@dataclass
class RigRow:
    """One Monte-Carlo row: per camera and parameter the ML errors, bounds and rotation errors."""

    name: str
    setting: str
    cameras: tuple[str, ...]
    rig_key: str
    errors: dict[str, list[float]] = field(default_factory=dict)
    bound: dict[str, float] = field(default_factory=dict)
    unit_weight: dict[str, float] = field(default_factory=dict)
    rot_err_deg: list[float] = field(default_factory=list)
    rot_eq63_err_deg: list[float] = field(default_factory=list)
    rot_std_reported_deg: list[float] = field(default_factory=list)
    baseline_err_mm: list[float] = field(default_factory=list)
    failures: int = 0
    time_s: float = 0.0


def _eq63_rotation(s: rs.RigScenario, a: str, b: str) -> np.ndarray | None:
    """``R_a_b`` from the linear pipeline: per-view homographies, ``H_inf`` (eqs. 58-61), joint
    linear intrinsics (eq. 62) and eq. 63; None when fewer than two common views exist."""
    p = s.problem
    pts = p.target.points_m[:, :2]
    H = {a: [], b: []}
    for f in p.frames:
        if a in f.detections and b in f.detections:
            da, db = f.detections[a], f.detections[b]
            if min(len(da.ids), len(db.ids)) < 8:
                continue
            for c, d in ((a, da), (b, db)):
                H[c].append(refine_homography(homography_dlt(pts[d.ids], d.px), pts[d.ids], d.px))
    if len(H[a]) < 2:
        return None
    Ha, Hb = np.array(H[a]), np.array(H[b])
    sizes = [(p.camera(c).width, p.camera(c).height) for c in (a, b)]
    H_inf, _ = infinite_homography(Ha, Hb, sizes=sizes)
    Ka, Kb = rig_linear_intrinsics(Ha, Hb, H_inf, sizes=sizes)
    return relative_rotation(Ka, Kb, H_inf)


def run_rig_row(
    name: str,
    setting: str,
    make: Callable[[np.random.Generator], rs.RigScenario],
    trials: int,
    seed: int,
    weigh_by_camera: bool = False,
) -> RigRow:
    """Monte-Carlo of ``calibrate`` over ``trials`` problems of ``make`` (seeds ``[seed, t]``).

    ``weigh_by_camera``: weigh each camera's rows by its known noise, emulated with
    :func:`scale_pixels` (a cross-check of the solver's own per-camera weighting).
    """
    s0 = make(np.random.default_rng([seed, 0]))
    p0, ref = s0.problem, s0.problem.reference
    other = next(c.name for c in p0.cameras if c.name != ref)
    cams = tuple(c.name for c in p0.cameras)
    row = RigRow(name, setting, cams, f"T_{other}_{ref}")
    st = build_structure(p0, s0.truth.X[0][:3, :3])
    crb, uw = rig_bounds(p0, st, s0.truth, s0.sigma_by_camera_px)
    for c in cams:
        for p in PARAMS:
            row.bound[f"{c}.{p}"] = crb.std(f"{c}.{p}")
            row.unit_weight[f"{c}.{p}"] = uw.std(f"{c}.{p}")
            row.errors[f"{c}.{p}"] = []
    row.bound["rot"] = crb.std_rot_deg(row.rig_key)
    row.unit_weight["rot"] = uw.std_rot_deg(row.rig_key)
    T_true = s0.truth.T_cam_ref[other]
    t0 = time.perf_counter()
    for t in range(trials):
        s = s0 if t == 0 else make(np.random.default_rng([seed, t]))
        factor = {c: s.sigma_px / s.sigma_by_camera_px[c] for c in cams}
        try:
            res = calibrate(scale_pixels(s.problem, factor) if weigh_by_camera else s.problem)
        except SlidecalError:
            row.failures += 1
            continue
        for c in cams:
            K = res.cameras[c].K
            if weigh_by_camera:
                K = np.diag([1 / factor[c], 1 / factor[c], 1.0]) @ K
            for p, (i, j) in PARAMS.items():
                row.errors[f"{c}.{p}"].append(float(K[i, j] - s.truth.K[c][i, j]))
        est = res.rig[row.rig_key]
        row.rot_err_deg.append(rotation_angle_deg(est.R, T_true[:3, :3]))
        row.rot_std_reported_deg.append(float(est.std_rot_deg or np.nan))
        row.baseline_err_mm.append(
            1000.0 * float(np.linalg.norm(est.t_m) - np.linalg.norm(T_true[:3, 3]))
        )
        try:
            R63 = _eq63_rotation(s, other, ref)
        except SlidecalError:
            R63 = None
        if R63 is not None:
            row.rot_eq63_err_deg.append(rotation_angle_deg(R63, T_true[:3, :3]))
    row.time_s = time.perf_counter() - t0
    return row


def _rms(v: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(v)))) if v else float("nan")


def row_lines(row: RigRow) -> list[str]:
    """Markdown lines of one row: per-parameter table and the rotation summary."""
    n = len(row.rot_err_deg)
    out = [
        f"### {row.name}: {row.setting}",
        "",
        f"{n} trials ({row.failures} failed), {row.time_s:.0f} s.",
        "",
        "| camera | parameter | bias (px) | std (px) | bound (px) | std / bound | "
        "equal weights, best possible (px) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for c in row.cameras:
        for p in PARAMS:
            k = f"{c}.{p}"
            e = np.array(row.errors[k])
            sd = float(np.std(e, ddof=1)) if len(e) > 1 else float("nan")
            out.append(
                f"| {c} | {p} | {np.mean(e):+.3f} | {sd:.3f} | {row.bound[k]:.3f} | "
                f"{sd / row.bound[k]:.2f} | {row.unit_weight[k]:.3f} |"
            )
    rms = _rms(row.rot_err_deg)
    out += [
        "",
        f"Relative rotation `{row.rig_key}`: ML rms error {rms:.4f} deg, bound "
        f"{row.bound['rot']:.4f} deg (ratio {rms / row.bound['rot']:.2f}; equal row weights "
        f"at best {row.unit_weight['rot']:.4f} deg); mean reported one-sigma "
        f"{np.nanmean(row.rot_std_reported_deg):.4f} deg; linear eq. 63 rms error "
        f"{_rms(row.rot_eq63_err_deg):.4f} deg over {len(row.rot_eq63_err_deg)} trials. "
        f"Baseline length error: bias {np.mean(row.baseline_err_mm):+.4f}, std "
        f"{np.std(row.baseline_err_mm, ddof=1):.4f} (scene units / 1000).",
        "",
    ]
    return out


def efficiency_summary(rows: list[RigRow]) -> list[str]:
    """One line per row: the worst K efficiency and the rotation ratio."""
    out = [
        "| row | worst std / bound on fx, fy, cx, cy (parameter) | rotation rms / bound |",
        "| --- | --- | --- |",
    ]
    for r in rows:
        ratios = {
            k: float(np.std(v, ddof=1)) / r.bound[k] for k, v in r.errors.items() if len(v) > 1
        }
        worst = max(ratios, key=ratios.get)
        rot = _rms(r.rot_err_deg) / r.bound["rot"]
        out.append(f"| {r.name}: {r.setting} | {ratios[worst]:.2f} ({worst}) | {rot:.2f} |")
    return out


def oak_cell_end_to_end(seeds: list[int]) -> list[dict[str, float]]:
    """Run the simulated OAK cell (rendered images, detection, solve) once per seed.

    Returns per seed: for every non-reference camera ``c``, ``c.baseline_mm`` (|t| error),
    ``c.t_mm``, ``c.rot_deg`` against the recorded truth and the reported ``c.std_rot_deg``,
    ``c.std_t_mm``; ``time_s``.
    """
    cfg = Path(mocks.__file__).parent / "oak_cell.yaml"
    out = []
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            o = run_calibration(RunRequest(
                cfg, out_dir=Path(tmp) / "s", progress=False, recording=False, seed=seed
            ))
            d: dict[str, float] = {"seed": seed, "time_s": time.perf_counter() - t0}
            truth = load_session(o.session_dir, detect_images=False).simulation
            for key, est in o.result.rig.items():
                T = truth_transform(truth, key)
                c = key.split("_")[1]
                d[f"{c}.baseline_mm"] = 1000.0 * float(
                    np.linalg.norm(est.t_m) - np.linalg.norm(T[:3, 3])
                )
                d[f"{c}.t_mm"] = o.errors[f"{key}.t_mm"]
                d[f"{c}.rot_deg"] = o.errors[f"{key}.rot_deg"]
                d[f"{c}.std_rot_deg"] = float(est.std_rot_deg)
                d[f"{c}.std_t_mm"] = float(est.std_t_mm)
            d["sigma_px"] = o.result.sigma_px
            out.append(d)
    return out


def oak_cell_lines(runs: list[dict[str, float]]) -> list[str]:
    """Markdown table of the end-to-end OAK cell runs."""
    cams = sorted({k.split(".")[0] for r in runs for k in r if k.endswith(".rot_deg")})
    out = [
        "| seed | camera | baseline error (mm) | t error (mm) | reported std t (mm) | "
        "rotation error (deg) | reported std rotation (deg) | sigma (px) | time (s) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in runs:
        for c in cams:
            out.append(
                f"| {int(r['seed'])} | {c} | {r[f'{c}.baseline_mm']:+.4f} | {r[f'{c}.t_mm']:.4f} "
                f"| {r[f'{c}.std_t_mm']:.4f} | {r[f'{c}.rot_deg']:.4f} | "
                f"{r[f'{c}.std_rot_deg']:.4f} | {r['sigma_px']:.3f} | {r['time_s']:.0f} |"
            )
    for c in cams:
        b = max(abs(r[f"{c}.baseline_mm"]) for r in runs)
        rot = max(r[f"{c}.rot_deg"] for r in runs)
        z = np.sqrt(np.mean([(r[f"{c}.rot_deg"] / r[f"{c}.std_rot_deg"]) ** 2 for r in runs]))
        out.append(
            f"\n- `{c}`: worst |baseline error| {b:.4f} mm (target < 0.2), worst rotation error "
            f"{rot:.4f} deg (target < 0.02); rms of error / reported std {z:.2f}"
        )
    return out


def rows_for(trials: int, seed: int) -> list[RigRow]:
    """The Monte-Carlo rows (i) and (ii) of the benchmark."""
    opts = ModelOptions(robot_noise_m=ROBOT_NOISE[0], robot_noise_deg=ROBOT_NOISE[1])
    return [
        run_rig_row(
            "S5", "sigma 0.5 px on both cameras", lambda r: rs.s5_rig(r, 0.5), trials, seed
        ),
        run_rig_row(
            "S5",
            "right 0.5 px, left 1.0 px",
            lambda r: rs.s5_rig(r, 0.5, left_factor=2.0),
            trials,
            seed + 1,
        ),
        run_rig_row(
            "S5",
            "right 0.5 px, left 1.0 px, left pixels scaled by 1/2 (weighting cross-check)",
            lambda r: rs.s5_rig(r, 0.5, left_factor=2.0),
            trials,
            seed + 1,
            weigh_by_camera=True,
        ),
        run_rig_row(
            "OAK rig on R1",
            "0.15 px, exact robot poses",
            lambda r: rs.oak_rig(r),
            trials,
            seed + 2,
        ),
        run_rig_row(
            "OAK rig on R1",
            "0.15 px, robot noise 0.05 mm / 0.005 deg, modelled",
            lambda r: rs.oak_rig(r, 0.15, ("left", "right"), *ROBOT_NOISE, options=opts),
            trials,
            seed + 3,
        ),
    ]


def main(argv: list[str] | None = None) -> int:
    """Run the rig benchmark and write the markdown report to ``--out``."""
    ap = argparse.ArgumentParser(
        prog="python -m tests.bench rig", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--out", default=str(RESULTS / "RIG.md"), help="the report to write")
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--seeds", type=int, default=5, help="OAK cell end-to-end runs")
    ap.add_argument("--seed", type=int, default=20060402)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = rows_for(args.trials, args.seed)
    runs = oak_cell_end_to_end(list(range(1, args.seeds + 1))) if args.seeds else []
    elapsed_s = time.perf_counter() - t0
    lines = [
        *report_header(
            "Rig calibration: maximum likelihood against the Cramer-Rao bound", "rig", argv,
            elapsed_s,
        ),
        f"{args.trials} trials per row, seed {args.seed}, {args.seeds} OAK cell seeds.",
        "",
        "Targets: std / bound <= 1.15 on fx, fy, cx, cy of each camera; relative rotation rms "
        "error within 1.5x its bound; on the simulated OAK cell baseline error < 0.2 mm and "
        "relative rotation error < 0.02 deg.",
        "",
        "## Summary",
        "",
        *efficiency_summary(rows),
        "",
        "## Monte-Carlo rows",
        "",
    ]
    for r in rows:
        lines += row_lines(r)
    if runs:
        lines += [
            "## Simulated OAK cell end to end (rendered images, ChArUco detection, solve)",
            "",
            "Every seed runs `slidecal run` on the cell: the planner's poses, new image noise, "
            "new robot measurement noise and the target set up anew (the cell's "
            "`simulation.target_jitter`, so that the renderer's per-corner artefacts do not "
            "repeat from seed to seed).",
            "",
            *oak_cell_lines(runs),
            "",
        ]
    text = "\n".join(lines)
    return publish_report(text, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
