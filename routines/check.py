"""``slidecal check --config CELL --installed STORE``: does the installed calibration still hold?

A short verification, not a calibration: a handful of frames (at most
:data:`MAX_ROBOT_TIME_S` of robot time) at known robot poses, taken from the plan of the
installed calibration (or the planner's plan for the cell), first frames of its groups. The
installed intrinsics, distortion, hand-eye and rig are held fixed; only the target's pose is
fitted (the board may have been put back slightly differently). What the fixed calibration
cannot explain is the drift:

- ``residual_rms_px``: rms of the reprojection residuals per camera;
- ``expected_rms_px``: what the installed calibration explains at those poses (the rms of the
  same residuals on the installed calibration's own session, recorded at install time in
  ``installed.yaml``; else its reprojection rms and the robot's noise at the standoff);
- ``drift_px = sqrt(residual^2 - expected^2)`` and ``drift_sigma``: the drift in units of the
  installed calibration's projection uncertainty at the observed corners (from its covariance).

Verdict ``ok`` or ``drifted`` (:func:`slidecal.routines.verdict.judge_check`): drifted when the
rms exceeds ``limits.check_max_rms_ratio`` times the expected rms and the drift exceeds
``limits.check_max_px``. Written to the check's session as ``verdict.yaml``; exit 0 / 5.
"""

from __future__ import annotations

import argparse
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from slidecal.routines.config import CellConfig, load_config
from slidecal.routines.plan import Plan, read_plan
from slidecal.routines.progress import Progress
from slidecal.routines.verdict import Verdict, judge_check, write_verdict
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import inv_T
from slidecal.solver.problem import CalibrationProblem
from slidecal.solver.result import CalibrationResult

MAX_ROBOT_TIME_S = 15.0
DEFAULT_FRAMES = 6
help = "verify the installed calibration at a few known robot poses (ok or drifted)"


def check_plan_from(plan: Plan, cfg: CellConfig, frames: int = DEFAULT_FRAMES) -> Plan:
    """A short plan: the first two poses of as many of ``plan``'s groups as ``frames`` allows
    (two tilts at least), shortened until the predicted robot time is at most
    :data:`MAX_ROBOT_TIME_S`."""
    from slidecal.routines.planner import dry_run

    per = 2 if frames >= 4 else 1
    n_groups = max(1, min(len(plan.groups), frames // per))
    while True:
        groups = tuple(tuple(g[:per]) for g in plan.groups[:n_groups])
        short = Plan(
            groups=groups,
            via=plan.via,
            speed_mps=plan.speed_mps,
            accel_mps2=plan.accel_mps2,
            settle_s=plan.settle_s,
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


def _hand_eye_T(installed: CalibrationResult, camera: str) -> np.ndarray:
    from slidecal.routines.results_io import hand_eye_names, hand_eye_transforms

    key = hand_eye_names(installed).get(camera)
    t = hand_eye_transforms(installed).get(key) if key else None
    if t is None or t.T is None:
        raise InputError(
            f"the installed calibration has no complete hand-eye for camera {camera!r}; "
            "check needs the hand-eye rotation and translation"
        )
    return t.T


def _T_cam_board(mount: str, X: np.ndarray, T_base_tool: np.ndarray, Y: np.ndarray):
    """``T_cam_board`` from the hand-eye ``X`` (T_tool_cam or T_base_cam), the robot pose and
    the target pose ``Y`` (T_base_board or T_tool_board)."""
    if mount == "eye_in_hand":
        return inv_T(X) @ inv_T(T_base_tool) @ Y
    return inv_T(X) @ T_base_tool @ Y


def fit_target(
    problem: CalibrationProblem, installed: CalibrationResult
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The target pose (4, 4) that best explains the images with the installed calibration
    held fixed, and the residual vectors (N, 2) px per camera."""
    from scipy.optimize import least_squares

    from slidecal.solver.camera import project
    from slidecal.solver.geometry import R_from_rvec, T_from_Rt, rvec_from_R

    mount = installed.mount
    cams = [c.name for c in problem.cameras if c.name in installed.cameras]
    X = {c: _hand_eye_T(installed, c) for c in cams}
    pts = problem.target.points_m
    obs = []
    for fr in problem.frames:
        if fr.T_base_tool is None:
            continue
        for c in cams:
            det = fr.detections.get(c)
            if det is not None and len(det.ids) >= 4:
                obs.append((c, fr.T_base_tool, pts[det.ids], np.asarray(det.px, float)))
    if not obs:
        raise InputError("no frame of the check saw the target; check the cell and the board")
    Y0 = installed.T_target.T if installed.T_target is not None else None
    if Y0 is None:
        import cv2

        c, T, P, px = obs[0]
        cam = installed.cameras[c]
        ok, rv, tv = cv2.solvePnP(
            P.astype(np.float64), px, np.asarray(cam.K, float), np.asarray(cam.distortion, float)
        )
        T_cb = T_from_Rt(cv2.Rodrigues(rv)[0], tv.ravel())
        Y0 = T @ X[c] @ T_cb if mount == "eye_in_hand" else inv_T(T) @ X[c] @ T_cb

    def residuals(theta: np.ndarray) -> np.ndarray:
        Y = T_from_Rt(R_from_rvec(theta[:3]), theta[3:])
        out = []
        for c, T, P, px in obs:
            cam = installed.cameras[c]
            Tcb = _T_cam_board(mount, X[c], T, Y)
            Pc = P @ Tcb[:3, :3].T + Tcb[:3, 3]
            out.append((project(np.asarray(cam.K), np.asarray(cam.distortion), Pc) - px).ravel())
        return np.concatenate(out)

    theta0 = np.concatenate([rvec_from_R(Y0[:3, :3]), Y0[:3, 3]])
    sol = least_squares(residuals, theta0, x_scale="jac")
    Y = T_from_Rt(R_from_rvec(sol.x[:3]), sol.x[3:])
    r = residuals(sol.x).reshape(-1, 2)
    per: dict[str, list[np.ndarray]] = {c: [] for c in cams}
    k = 0
    for c, _T, P, _px in obs:
        per[c].append(r[k : k + len(P)])
        k += len(P)
    return Y, {c: np.vstack(v) if v else np.zeros((0, 2)) for c, v in per.items()}


def expected_rms_px(
    installed: CalibrationResult, info: dict[str, Any], cfg: CellConfig
) -> dict[str, float]:
    """What the installed calibration explains per camera (see the module docstring)."""
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


def chain_rms_px(result: CalibrationResult, problem: CalibrationProblem) -> dict[str, float]:
    """Per camera, the rms (norm) of the residuals of ``result`` on its own session with the
    robot poses as measured (what :func:`fit_target` sees on an unchanged cell)."""
    out = {}
    try:
        _, res = fit_target(problem, result)
    except InputError:
        return out
    for n, r in res.items():
        if len(r):
            out[n] = float(np.sqrt(np.mean(np.sum(r**2, axis=1))))
    return out


def projection_sigma_px(installed: CalibrationResult, camera: str) -> float | None:
    """The rms over the image of the installed calibration's projection one-sigma (px)."""
    from slidecal.routines.report import uncertainty_map

    m = uncertainty_map(installed, camera, (16, 10))
    return None if m is None else float(np.sqrt(np.mean(m**2)))


def judge_problem(
    problem: CalibrationProblem,
    installed: CalibrationResult,
    expected: dict[str, float],
    cfg: CellConfig,
) -> Verdict:
    """The check's verdict of recorded check frames against the installed calibration."""
    from slidecal.routines.run import cell_limits

    Y, res = fit_target(problem, installed)
    rms = {n: float(np.sqrt(np.mean(np.sum(r**2, axis=1)))) for n, r in res.items() if len(r)}
    drift = {n: float(np.sqrt(max(rms[n] ** 2 - expected[n] ** 2, 0.0))) for n in rms}
    sig = {}
    for n in rms:
        s = projection_sigma_px(installed, n)
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
    return judge_check(rms, expected, drift, cell_limits(cfg), len(problem.frames), extra, notes)


def run_check(
    config: str | Path | CellConfig | None,
    installed: str | Path,
    out_dir: str | Path | None = None,
    frames: int = DEFAULT_FRAMES,
    progress: bool | Progress | None = None,
    seed: int | None = None,
    cell: Any = None,
    retries: int = 2,
) -> tuple[Verdict, Path]:
    """Record a short check session and judge it against the installed calibration; write
    ``verdict.yaml`` into the session; return the verdict and the session directory."""
    from slidecal.routines.install import INSTALLED_FILE, current_dir
    from slidecal.routines.results_io import read_result
    from slidecal.routines.run import _lock_key, check_out_dir, record_session
    from slidecal.routines.session import load_session, load_yaml

    cfg = config if isinstance(config, CellConfig) else load_config(config)
    store = Path(installed)
    cur = current_dir(store) if store.is_dir() else None
    if cur is None:
        raise InputError(
            "holds no installed calibration (no current/); install one with slidecal run --install",
            where=str(store),
        )
    inst = read_result(cur / "result.yaml")
    info = (
        load_yaml(cur / INSTALLED_FILE, "installed.yaml")
        if (cur / INSTALLED_FILE).is_file()
        else {}
    )
    if (cur / "plan.yaml").is_file():
        base = read_plan(cur / "plan.yaml")
    else:
        from slidecal.routines.planner import make_plan

        base = make_plan(cfg).plan
    plan = check_plan_from(base, cfg, frames)
    if seed is not None and seed < 0:
        raise InputError(f"--seed must be 0 or a positive integer, got {seed}")
    out = (
        Path(out_dir)
        if out_dir is not None
        else Path("sessions") / datetime.now().strftime("check_%Y%m%d_%H%M%S")
    )
    check_out_dir(out)
    if (out / "session.yaml").exists():
        raise InputError("already holds a session; choose a new --out directory", str(out))
    prog = (
        progress
        if isinstance(progress, Progress)
        else Progress(plan.n_poses, quiet=False if progress is None else not progress)
    )
    rec = record_session(
        cfg,
        plan,
        out,
        prog,
        lock_key=_lock_key(config, cfg),
        seed=seed,
        cell=cell,
        retries=retries,
        extra={"purpose": "check", "installed": str(cur)},
    )
    problem = load_session(out).problem
    verdict = judge_problem(problem, inst, expected_rms_px(inst, info or {}, cfg), cfg)
    t = getattr(rec.robot, "robot_time_s", None)
    verdict.extra["check"]["robot_time_s"] = None if t is None else float(t)
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
