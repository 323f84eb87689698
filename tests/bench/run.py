"""End-to-end benchmark of ``slidecal run`` on a simulated cell over many seeds.

``python -m tests.bench run [--seeds 20] [--config cell.yaml] [--out docs/results/RUN.md]``
runs the whole routine (plan, simulated robot, rendered images, detection, solve) once per seed
and reports: wall and simulated robot time, the errors against the recorded truth (the hand-eye
against the truth the session can know, see ``results_io.errors_against_truth``), and whether
the reported standard deviations are honest: the share of parameters whose error lies inside
the reported 2-sigma interval (coverage; 95 % expected), the ratio of rms error to reported
std for the hand-eye rotation and translation (1 expected), and the worst |error| / std of
every seed, next to the worst intrinsic of a calibration of the same detections with a free
board pose per image (no robot poses): what the images alone leave, so a seed's miss can be
told apart as the robot's or the images'.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from slidecal.routines.results_io import hand_eye_transforms
from slidecal.routines.run import RunRequest, run_calibration
from slidecal.routines.session import load_session
from slidecal.solver.calibrate import calibrate
from slidecal.solver.errors import SlidecalError
from tests.bench.report import RESULTS, publish_report, report_header

SCALARS = ("fx", "fy", "cx", "cy")
#: the 95 % bound of a 3-vector's error norm in units of the root of its covariance's trace
#: (chi-square with 3 degrees of freedom, equal spread per axis): sqrt(7.815 / 3)
VECTOR_95 = float(np.sqrt(7.8147 / 3.0))


def worst_ratio(row: dict[str, float]) -> tuple[float, str]:
    """The largest |error| / reported std of a seed's row, and which quantity it is."""
    best = (0.0, "")
    for k, v in row.items():
        if not k.endswith("_err"):
            continue
        s = row.get(k[: -len("_err")] + "_std", np.nan)
        if np.isfinite(v) and np.isfinite(s) and s > 0 and abs(v) / s > best[0]:
            best = (abs(v) / s, k[: -len("_err")])
    return best


def free_pose_worst(out, row: dict[str, float]) -> tuple[float, str]:  # noqa: ANN001 - RunOutcome
    """The worst |error| / std of the intrinsics when the run's detections are solved with a
    free board pose per image (knowledge "none"): the images' own share of a seed's miss."""
    try:
        problem = load_session(out.session_dir, detect_images=False).problem
        free = calibrate(replace(problem, knowledge="none"))
    except SlidecalError:
        return float("nan"), ""
    best = (0.0, "")
    for cam_name, cam in free.cameras.items():
        K_run = out.result.cameras[cam_name].K
        for p, (a, b) in zip(SCALARS, ((0, 0), (1, 1), (0, 2), (1, 2)), strict=True):
            err = row.get(f"{cam_name}.{p}_err", np.nan) + cam.K[a, b] - K_run[a, b]
            z = abs(err) / cam.std.get(p, np.nan)
            if np.isfinite(z) and z > best[0]:
                best = (float(z), f"{cam_name}.{p}")
    return best


def run_seeds(config: str | None, seeds: list[int]) -> list[dict[str, float]]:
    """One row per seed: errors, reported std, times."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            t0 = time.perf_counter()
            out = run_calibration(RunRequest(
                config, out_dir=Path(tmp) / f"s{seed}", progress=False, recording=False, seed=seed
            ))
            row = {
                "seed": seed,
                "wall_s": time.perf_counter() - t0,
                "robot_s": out.robot_time_s or float("nan"),
            }
            res = out.result
            ra = res.robot_accuracy
            row["robot_mm"] = ra.translation_mm if ra is not None else np.nan
            row["robot_deg"] = ra.rotation_deg if ra is not None else np.nan
            row["adequate"] = bool(res.adequacy is None or res.adequacy.adequate)
            for cam_name, cam in res.cameras.items():
                for p in SCALARS:
                    row[f"{cam_name}.{p}_err"] = out.errors.get(f"{cam_name}.{p}_px", np.nan)
                    row[f"{cam_name}.{p}_std"] = cam.std.get(p, np.nan)
                row[f"{cam_name}.fx_rel"] = out.errors.get(f"{cam_name}.fx_rel", np.nan)
            for name, T in hand_eye_transforms(res).items():
                row[f"{name}.rot_err"] = out.errors.get(f"{name}.rot_deg", np.nan)
                row[f"{name}.rot_std"] = T.std_rot_deg if T.std_rot_deg is not None else np.nan
                row[f"{name}.t_err"] = out.errors.get(f"{name}.t_mm", np.nan)
                row[f"{name}.t_std"] = T.std_t_mm if T.std_t_mm is not None else np.nan
            row["free_worst"], row["free_of"] = free_pose_worst(out, row)
            rows.append(row)
            print(f"seed {seed}: {row['wall_s']:.1f} s", file=sys.stderr)
    return rows


def report(rows: list[dict[str, float]], argv: list[str] | None, elapsed_s: float) -> str:
    """The markdown report of :func:`run_seeds` (``argv``: the benchmark's options)."""
    keys = rows[0].keys()
    n = len(rows)
    lines = [
        *report_header("`slidecal run` on the simulated cell", "run", argv, elapsed_s),
        f"{n} seeds; each run plans, moves the simulated UR5e, "
        "renders and detects every image, solves and writes the session.",
        "",
        f"- wall time per run: median {np.median([r['wall_s'] for r in rows]):.1f} s, "
        f"max {np.max([r['wall_s'] for r in rows]):.1f} s (2-core machine)",
        f"- simulated robot time per run: {np.median([r['robot_s'] for r in rows]):.1f} s",
        "",
        "| quantity | max abs error | rms error | mean reported std | rms error / std | "
        "inside 2 sigma |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    inside_all = []
    for k in keys:
        if not k.endswith("_err"):
            continue
        base = k[: -len("_err")]
        e = np.array([r[k] for r in rows], float)
        s = np.array([r.get(base + "_std", np.nan) for r in rows], float)
        ok = np.isfinite(e) & np.isfinite(s)
        if not ok.any():
            continue
        e, s = e[ok], s[ok]
        rms = float(np.sqrt(np.mean(e**2)))
        unit = "deg" if base.endswith(".rot") else "mm" if base.endswith(".t") else "px"
        if base.endswith((".rot", ".t")):  # a 3-vector: the error norm against sqrt(trace)
            inside = e < VECTOR_95 * s
        else:
            inside = np.abs(e) < 2.0 * s
        inside_all.extend(inside)
        cover = f"{100 * inside.mean():.0f} %"
        lines.append(
            f"| {base} ({unit}) | {np.max(np.abs(e)):.4f} | {rms:.4f} | "
            f"{np.mean(s):.4f} | {rms / np.mean(s):.2f} | {cover} |"
        )
    worst = [worst_ratio(r) for r in rows]
    lines += [
        "",
        "Worst |error| / reported std per seed (scalars: |error| / std; rotations and "
        "translations: error norm / root of the covariance's trace):",
        "",
        "| seed | worst | of | free poses, images alone: worst intrinsic | robot accuracy "
        "estimated (mm, deg) | adequate |",
        "| ---: | ---: | --- | --- | --- | --- |",
    ]
    for r, (w, which) in zip(rows, worst, strict=True):
        lines.append(
            f"| {r['seed']} | {w:.2f} | {which} | {r['free_worst']:.2f} {r['free_of']} | "
            f"{r['robot_mm']:.3f}, {r['robot_deg']:.4f} | {'yes' if r['adequate'] else 'NO'} |"
        )
    n_over = sum(w > 3.0 for w, _ in worst)
    lines += [
        "",
        f"- seeds with a worst |error| / std above 3: {n_over} of {n}; of them, also above 3 "
        "with free poses (the images' own error, not the robot's): "
        f"{sum(w > 3.0 and r['free_worst'] > 3.0 for r, (w, _) in zip(rows, worst, strict=True))}",
    ]
    rel = [r[k] for r in rows for k in keys if k.endswith(".fx_rel")]
    lines += [
        "",
        f"- fx relative error: max {100 * np.max(rel):.4f} %, rms "
        f"{100 * np.sqrt(np.mean(np.square(rel))):.4f} %",
        f"- coverage of the reported 2-sigma (95 %) intervals over all parameters: "
        f"{100 * np.mean(inside_all):.0f} % ({int(np.sum(inside_all))} of {len(inside_all)}; "
        "95 % expected)",
        "- rotations and translations: the error is the angle (norm) of a 3-vector whose "
        "reported std is the root of the covariance's trace, so rms error / std near 1 is "
        f"honest; its 95 % interval is norm < {VECTOR_95:.2f} std (chi-square, 3 degrees of "
        "freedom, equal spread per axis).",
        "- the hand-eye and the target pose are judged against the effective truth (the "
        "physical one moved by the arm's constant error, which no camera can tell from it); "
        "the intrinsics against the physical truth.",
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Command line of the benchmark."""
    ap = argparse.ArgumentParser(
        prog="python -m tests.bench run", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--config", default=None, help="cell file (default: the default cell)")
    ap.add_argument("--out", default=str(RESULTS / "RUN.md"), help="the report to write")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = run_seeds(args.config, list(range(1, args.seeds + 1)))
    text = report(rows, argv, time.perf_counter() - t0)
    return publish_report(text, args.out)


if __name__ == "__main__":
    sys.exit(main())
