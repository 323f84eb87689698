"""``slidecal check --config CELL --installed STORE``: does the installed calibration still hold?
A few frames at poses the installed session recorded, compared pair by pair with its corners, or
the calibration re-estimated from them (:func:`refit`); ``ok`` or ``drifted``: docs/UNATTENDED.md.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from slidecal.mocks.cell import SimulatedCell
from slidecal.routines.acquire import cell_key, clock, new_session_dir, record_session
from slidecal.routines.config import CellConfig, load_config
from slidecal.routines.ops.install import (
    check_same_cell,
    current_dir,
    installed_info,
    installed_session,
)
from slidecal.routines.ops.verdict import (
    Check,
    Verdict,
    check_residuals,
    compare,
    paired_compare,
    uncertainty_map,
    write_verdict,
)
from slidecal.routines.plan import Plan, read_plan
from slidecal.routines.planner import dry_run, make_plan
from slidecal.routines.progress import Progress
from slidecal.routines.results_io import read_result
from slidecal.routines.session import load_session
from slidecal.solver.camera import project
from slidecal.solver.drift import T_cam_board as _T_cam_board
from slidecal.solver.drift import fit_target, hand_eye_T, match_poses
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import R_from_rvec, T_from_Rt, inv_T
from slidecal.solver.numeric import least_squares
from slidecal.solver.problem import CalibrationProblem
from slidecal.solver.result import CalibrationResult, TransformEstimate

MAX_ROBOT_TIME_S = 15.0
DEFAULT_FRAMES = 6
help = "verify the installed calibration at a few known robot poses (ok or drifted)"


def check_plan_from(plan: Plan, cfg: CellConfig, frames: int = DEFAULT_FRAMES) -> Plan:
    """A short plan: the first two poses of as many of ``plan``'s groups as ``frames`` allows
    (two tilts at least), shortened until the predicted robot time is at most
    :data:`MAX_ROBOT_TIME_S`."""
    per = 2 if frames >= 4 else 1
    n_groups = max(1, min(len(plan.groups), frames // per))
    while True:
        groups = tuple(tuple(g[:per]) for g in plan.groups[:n_groups])
        short = Plan.build(
            groups,
            plan,
            via=plan.via,
            notes=(f"check: {sum(len(g) for g in groups)} frames of the installed plan",),
        )
        robot_s, bad, why = dry_run(short, cfg)
        if bad is not None:
            raise InputError(f"the check's poses fail the motion check ({why})", cfg.source)
        total = robot_s + short.n_poses * 0.1
        if total <= MAX_ROBOT_TIME_S or (n_groups == 1 and per == 1):
            return short
        if n_groups > 2 or per == 1:
            n_groups -= 1
        else:
            per = 1


def recorded_plan(plan: Plan, recorded: CalibrationProblem) -> Plan:
    """``plan`` with only the poses the installed session recorded a frame at (its measured
    robot pose within :data:`slidecal.solver.drift.MATCH_M` / ``MATCH_DEG`` of the commanded
    one) and groups left empty dropped; ``plan`` itself when none matches."""
    seen = [
        f.T_base_tool for f in recorded.frames if any(len(d.ids) for d in f.detections.values())
    ]
    groups = tuple(
        kept
        for kept in (tuple(T for T in g if match_poses([T], seen)) for g in plan.groups)
        if kept
    )
    return dataclasses.replace(plan, groups=groups) if groups else plan


def expected_rms_px(
    installed: CalibrationResult, info: dict[str, Any], cfg: CellConfig
) -> dict[str, float]:
    """What the installed calibration explains per camera (docs/UNATTENDED.md)."""
    rec = info.get("chain_rms_px") or {}
    out = {}
    for n, c in installed.cameras.items():
        if rec.get(n) is not None:
            out[n] = float(rec[n])
            continue
        f = float(np.asarray(c.K)[0, 0])
        d = cfg.standoff_m
        robot_px = (
            f / d * np.hypot(cfg.options.robot_noise_m, d * np.radians(cfg.options.robot_noise_deg))
        )
        out[n] = float(np.hypot(c.reproj_rms_px, np.sqrt(2) * robot_px))
    return out


def refit(
    problem: CalibrationProblem,
    installed: CalibrationResult,
    robot_noise_m: float = 5e-5,
    robot_noise_deg: float = 0.005,
) -> CalibrationResult:
    """The installed calibration re-estimated from the check's frames: fx, fy, cx, cy, the
    reference camera's hand-eye and the target pose free, distortion and rig as installed; each
    measured robot pose corrected under the robot's noise prior (``robot_noise_m``/``_deg``), the
    residuals whitened by the installed pixel noise, the one-sigmas scaled up by a reduced
    chi-square above 1."""
    mount = installed.mount
    ref = installed.reference_camera or next(iter(installed.cameras))
    cams = [c.name for c in problem.cameras if c.name in installed.cameras]
    X0 = hand_eye_T(installed, ref)
    # T_<camera>_<reference> (hand_eye_T refuses an incomplete rig)
    T_c_ref = {c: np.eye(4) if c == ref else inv_T(hand_eye_T(installed, c)) @ X0 for c in cams}
    Y0, _ = fit_target(problem, installed)
    pts = problem.target.points_m
    frames = [fr for fr in problem.frames if fr.T_base_tool is not None]
    obs = [
        (k, c, fr.T_base_tool, pts[fr.detections[c].ids], np.asarray(fr.detections[c].px, float))
        for k, fr in enumerate(frames)
        for c in cams
        if c in fr.detections and len(fr.detections[c].ids) >= 4
    ]
    sigma_px = max(float(installed.sigma_px), 0.02) if np.isfinite(installed.sigma_px) else 0.1
    s_rot = max(np.radians(robot_noise_deg), 1e-7)
    s_t = max(robot_noise_m, 1e-7)
    K0 = {c: np.asarray(installed.cameras[c].K, float) for c in cams}
    dist = {c: np.asarray(installed.cameras[c].distortion, float) for c in cams}
    nk = 4 * len(cams)

    def unpack(theta: np.ndarray):  # noqa: ANN202
        K = {}
        for j, c in enumerate(cams):
            fx, fy, cx, cy = theta[4 * j : 4 * j + 4]
            K[c] = np.array([[fx, K0[c][0, 1], cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        X = T_from_Rt(
            R_from_rvec(theta[nk : nk + 3]) @ X0[:3, :3], X0[:3, 3] + theta[nk + 3 : nk + 6]
        )
        Y = T_from_Rt(
            R_from_rvec(theta[nk + 6 : nk + 9]) @ Y0[:3, :3], Y0[:3, 3] + theta[nk + 9 : nk + 12]
        )
        return K, X, Y

    n_glob = nk + 12

    def residuals(theta: np.ndarray) -> np.ndarray:
        K, X, Y = unpack(theta)
        d = theta[n_glob:].reshape(-1, 6)
        out = []
        for k, c, T, P, px in obs:
            Tk = T @ T_from_Rt(R_from_rvec(d[k, :3]), d[k, 3:])  # the true pose, corrected
            Tcb = T_c_ref[c] @ _T_cam_board(mount, X, Tk, Y)
            Pc = P @ Tcb[:3, :3].T + Tcb[:3, 3]
            out.append((project(K[c], dist[c], Pc) - px).ravel() / sigma_px)
        out.append((d[:, :3] / s_rot).ravel())
        out.append((d[:, 3:] / s_t).ravel())
        return np.concatenate(out)

    theta0 = np.concatenate(
        [[K0[c][0, 0], K0[c][1, 1], K0[c][0, 2], K0[c][1, 2]] for c in cams]
        + [np.zeros(12 + 6 * len(frames))]
    )
    sol = least_squares(residuals, theta0)
    r = sol.fun
    dof = max(len(r) - len(theta0), 1)
    JtJ = sol.jac.T @ sol.jac
    try:
        cov = np.linalg.inv(JtJ)[:n_glob, :n_glob] * max(1.0, float(r @ r) / dof)
    except np.linalg.LinAlgError:
        raise InputError(
            "the check's frames cannot determine the calibration (singular); take more frames "
            "(--frames) or check that the plan has tilted groups"
        ) from None
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    K, X, Y = unpack(sol.x)
    cameras = {}
    for j, c in enumerate(cams):
        std = dict(
            zip(("fx", "fy", "cx", "cy"), (float(v) for v in sd[4 * j : 4 * j + 4]), strict=True)
        )
        cameras[c] = dataclasses.replace(installed.cameras[c], K=K[c], std=std)
    rot_deg = float(np.degrees(np.sqrt(np.trace(cov[nk : nk + 3, nk : nk + 3]))))
    t_mm = float(np.sqrt(np.trace(cov[nk + 3 : nk + 6, nk + 3 : nk + 6])) * 1000.0)
    he = TransformEstimate(installed.hand_eye.name, X[:3, :3], X[:3, 3], rot_deg, t_mm)
    return dataclasses.replace(
        installed,
        cameras=cameras,
        hand_eye=he,
        T_target=TransformEstimate("target", Y[:3, :3], Y[:3, 3]),
        covariance=None,
        parameter_names=(),
    )


def judge_problem(
    problem: CalibrationProblem,
    installed: CalibrationResult,
    expected: dict[str, float],
    cfg: CellConfig,
    installed_problem: CalibrationProblem | None = None,
) -> Verdict:
    """The check's verdict of recorded check frames against the installed calibration: paired with
    ``installed_problem`` when the check's poses are among its poses, else (said in the notes)
    the re-estimate and the fixed-calibration residuals."""
    Y, res = fit_target(problem, installed)
    rms = {n: float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) for n, r in res.items() if len(r)}
    drift = {n: float(np.sqrt(max(rms[n] ** 2 - expected[n] ** 2, 0.0))) for n in rms}
    sig = {}
    for n in rms:  # the drift in the rms over the image of the installed projection one-sigma
        m = uncertainty_map(installed, n, (16, 10))
        s = None if m is None else float(np.sqrt(np.mean(m**2)))
        sig[n] = None if not s else drift[n] / s
    extra = {
        "check": {
            "frames": len(problem.frames),
            "residual_rms_px": rms,
            "expected_rms_px": {n: expected[n] for n in rms},
            "drift_px": drift,
            "drift_sigma": sig,
            "target_pose_t_m": [float(v) for v in Y[:3, 3]],
        }
    }
    notes = [
        f"camera {n}: drift {drift[n]:.2f} px"
        + (f" = {sig[n]:.1f} times the installed projection one-sigma" if sig[n] else "")
        for n in rms
    ]
    lim = cfg.limits
    paired: list = []
    if installed_problem is None:
        why = "the install keeps no session (installed before sessions were kept)"
    else:
        paired, pinfo = paired_compare(
            problem, installed_problem, installed, lim.check_max_px, lim.change_region
        )
        extra["check"]["paired"] = pinfo
        why = pinfo.get("why", "")
    own = check_residuals(rms, expected, drift, lim, len(problem.frames))
    again = refit(problem, installed, cfg.options.robot_noise_m, cfg.options.robot_noise_deg)
    change, info = compare(
        again, installed, dataclasses.replace(lim, max_change_px=lim.check_change_px)
    )
    extra["check"]["change"] = info
    if paired:
        # the paired comparison decides; the re-estimate's figures stay in the verdict file
        checks = tuple(paired)
        shared = extra["check"]["paired"]["shared_poses"]
        notes = [f"paired comparison at {shared} of the installed session's robot poses"] + [
            f"not deciding: {n} (the installed calibration fixed, the board re-fitted)"
            for n in notes
        ]
    else:
        fallback = (
            f"no paired comparison ({why}); fell back to re-estimating the calibration from "
            "the check's frames"
        )
        checks = (Check("paired", True, None, None, fallback), *own, *change)
        notes = [fallback] + notes
    verdict = "ok" if all(c.passed for c in checks) else "drifted"
    return Verdict(verdict, "check", checks, info, tuple(notes), extra)


def run_check(
    config: str | Path | CellConfig | None,
    installed: str | Path,
    out_dir: str | Path | None = None,
    frames: int = DEFAULT_FRAMES,
    progress: bool | Progress | None = None,
    seed: int | None = None,
    cell: Any = None,
) -> tuple[Verdict, Path]:
    """Record a short check session and judge it against the installed calibration; write
    ``verdict.yaml`` into the session; return the verdict and the session directory."""
    cfg = config if isinstance(config, CellConfig) else load_config(config)
    store = Path(installed)
    cur = current_dir(store) if store.is_dir() else None
    if cur is None:
        raise InputError(
            "holds no installed calibration (no current/); install one with slidecal run --install",
            where=str(store),
        )
    inst = read_result(cur / "result.yaml")
    info = installed_info(cur)
    check_same_cell(inst, str(cur), cfg.cameras, cfg.source)
    if (cur / "plan.yaml").is_file():
        base = read_plan(cur / "plan.yaml")
    else:
        base = make_plan(cfg)
    recorded = installed_session(cur)
    if recorded is not None:
        base = recorded_plan(base, recorded)
    plan = check_plan_from(base, cfg, frames)
    if seed is not None and seed < 0:
        raise InputError(f"--seed must be 0 or a positive integer, got {seed}")
    out = new_session_dir(out_dir, "check_", resume="")
    prog = Progress.from_option(progress, plan.n_poses)
    if cfg.simulated and cell is None:
        cell = SimulatedCell.from_config(cfg, seed)
    robot, _ = record_session(
        cfg,
        plan,
        out,
        prog,
        lock_key=cell_key(config, cfg),
        cell=cell,
        extra={"purpose": "check", "installed": str(cur)},
    )
    problem = load_session(out).problem
    verdict = judge_problem(
        problem, inst, expected_rms_px(inst, info, cfg), cfg, installed_problem=recorded
    )
    verdict.extra["check"]["robot_time_s"] = clock(robot)
    write_verdict(verdict, out)
    for line in verdict.lines():
        prog.event(line)
    return verdict, out


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``slidecal check --config CELL --installed STORE [--out DIR] [--frames N]``."""
    p.add_argument("--config", help="cell description (default: the simulated default cell)")
    p.add_argument("--installed", required=True, metavar="STORE", help="the install store")
    p.add_argument("--out", help="check session directory (default: sessions/check_<time>)")
    p.add_argument("--frames", type=int, default=DEFAULT_FRAMES, help="frames to take (2-12)")
    p.add_argument("--seed", type=int, help="simulated cells: the random seed")
    p.add_argument("--quiet", action="store_true", help="print only the verdict")


def main(args: argparse.Namespace) -> int:
    """Check, print the verdict, exit 0 (ok) or 5 (drifted)."""
    if not 2 <= args.frames <= 12:
        raise InputError(f"--frames must be 2 to 12, got {args.frames}")
    verdict, out = run_check(
        args.config,
        args.installed,
        args.out,
        frames=args.frames,
        progress=False if args.quiet else None,
        seed=args.seed,
    )
    print("\n".join(verdict.lines()) if not args.quiet else f"verdict: {verdict.verdict}")
    print(f"check session: {out}")
    return verdict.exit_code
