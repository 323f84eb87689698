"""The planner (``slidecal plan``): the shortest robot routine predicted to meet a goal.

From the cell description (robot model and workspace box, mount, camera resolution and nominal
intrinsics, target and its approximate pose) and a goal (one-sigma targets per parameter and a
time budget), choose orientation groups (tilts) and translations per group such that

- every pose is inside the workspace box, reachable within the joint limits and away from
  singularities, and every straight move between them is too (the UR kinematics of
  :mod:`slidecal.drivers.ur_kinematics`, sampled every 5 mm / 1 deg exactly as the simulated
  arm of :mod:`slidecal.mocks.robot` moves);
- every corner of the target is in the image with ``margin_px`` at every frame, and every
  corner's depth is within ``depth_m``;
- the plan is not degenerate: the linear step accepts it
  (:func:`slidecal.solver.degeneracy.check_configuration` on exact homographies) and its Fisher
  information (docs/METHOD.md Sec. 6) is of full rank, hand-eye translation included;
- the predicted standard deviations meet the goal with the least robot time (moves by a
  trapezoidal profile, plus settle and capture time per frame).

Method: candidate groups and frames (:func:`_candidates`, :data:`DIRECTIONS`), each frame's
information from the solver's prediction for the problem a run would give it
(:func:`nominal_problem`, :func:`_information`), a greedy choice per second of robot time
(:func:`_greedy`), checked by a dry run and predicted whole (:func:`_search`).

The ``plan:`` block of the cell file (every key optional) is described in docs/FORMATS.md.
Only the reference camera is planned for (its visibility and its information); the other
cameras of a rig are not checked.
"""

from __future__ import annotations

import argparse
import shlex
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from slidecal.drivers import ur_kinematics as urk
from slidecal.mocks.cell import simulated_arm_dict
from slidecal.mocks.robot import SimulatedUR, trapezoid_time_s
from slidecal.routines.config import (
    GOAL_KEYS,
    PLAN_ARM_NOISE,
    CellConfig,
    PlanGoal,
    PlanSettings,
    load_config,
)
from slidecal.routines.plan import Plan, tool_pose, write_plan
from slidecal.solver.camera import project
from slidecal.solver.degeneracy import check_configuration
from slidecal.solver.drift import T_cam_board
from slidecal.solver.errors import DegenerateError, HardwareFault, InputError
from slidecal.solver.geometry import (
    R_from_rvec,
    T_from_Rt,
    inv_T,
    rotation_angle_deg,
    rvec_from_R,
)
from slidecal.solver.linear import LinearGroup
from slidecal.solver.model import ModelState
from slidecal.solver.problem import (
    INTRINSIC_NAMES,
    CalibrationProblem,
    CameraSpec,
    Detection,
    Frame,
    mount_names,
)
from slidecal.solver.result import NamedCovariance
from slidecal.solver.uncertainty import FrameInformation, planned_covariance

help = "choose the shortest robot routine predicted to meet the accuracy goal (writes plan.yaml)"

#: Tool rotation speed / acceleration of a linear move (the simulated arm's defaults).
ANGULAR_SPEED_DEG_S = 60.0
ANGULAR_ACCEL_DEG_S2 = 80.0
#: Information below this fraction of the largest (after scaling) is a singular plan.
MIN_RCOND = 1e-10

#: Frame displacements within a group (camera axes: right, down, forward), unit vectors; every
#: one has a component along the viewing axis, none lies in the image plane.
_S2, _S3 = 1.0 / np.sqrt(2.0), 1.0 / np.sqrt(3.0)
DIRECTIONS = np.array(
    [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]
    + [[sx * _S2, 0.0, sz * _S2] for sx in (1, -1) for sz in (1, -1)]
    + [[0.0, sy * _S2, sz * _S2] for sy in (1, -1) for sz in (1, -1)]
    + [[sx * _S3, sy * _S3, sz * _S3] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)]
)


# -- geometry of candidates -------------------------------------------------------------------
def group_R_board_cam(tilt_deg: float, azimuth_deg: float) -> np.ndarray:
    """``R_board_cam`` (3, 3) of a group: looking along +z_board, tilted by ``tilt_deg`` about
    the in-plane axis at ``azimuth_deg``."""
    phi = np.radians(azimuth_deg)
    axis = np.array([np.cos(phi), np.sin(phi), 0.0])
    return R_from_rvec(axis * np.radians(tilt_deg))


def group_T_cam_board(
    centre_board: np.ndarray, standoff_m: float, R_board_cam: np.ndarray, offsets_cam_m: np.ndarray
) -> np.ndarray:
    """``T_cam_board`` (n, 4, 4) of a group's frames.

    ``centre_board`` (3,): the point looked at, board frame, metres; ``offsets_cam_m`` (n, 3):
    displacements of the camera from the group's pose, camera axes, metres.
    """
    c0 = centre_board - standoff_m * R_board_cam[:, 2]
    out = np.empty((len(offsets_cam_m), 4, 4))
    for k, o in enumerate(offsets_cam_m):
        out[k] = inv_T(T_from_Rt(R_board_cam, c0 + R_board_cam @ o))
    return out


def move_time_s(T0: np.ndarray, T1: np.ndarray, speed_mps: float, accel_mps2: float) -> float:
    """Duration of a linear move ``T0 -> T1`` ((4, 4) each, metres): the longer of the
    translation's and the rotation's trapezoidal profiles (as :class:`SimulatedUR` moves)."""
    length = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
    angle = float(np.linalg.norm(rvec_from_R(T0[:3, :3].T @ T1[:3, :3])))
    return max(
        trapezoid_time_s(length, speed_mps, accel_mps2),
        trapezoid_time_s(angle, np.radians(ANGULAR_SPEED_DEG_S), np.radians(ANGULAR_ACCEL_DEG_S2)),
    )


# -- the predicted model ----------------------------------------------------------------------
def nominal_T_cam_board(cfg: CellConfig, T_base_tool: np.ndarray) -> np.ndarray:
    """The nominal ``T_cam_board`` (4, 4) of the reference camera at a tool pose (4, 4)."""
    return T_cam_board(cfg.mount, cfg.approx_T_hand_eye, T_base_tool, cfg.approx_T_target)


def _spec(cfg: CellConfig) -> CameraSpec:
    return next(c for c in cfg.cameras if c.name == cfg.reference_camera)


def arm_noise(cfg: CellConfig, s: PlanSettings) -> tuple[float, float]:
    """The arm's accuracy (mm, deg per axis) the prediction assumes: what a run's extension
    learned (``s.robot_noise``), else the cell's ``options.robot_noise_*`` but at least what a
    solve learns of a real arm (:data:`~slidecal.routines.config.PLAN_ARM_NOISE`)."""
    if s.robot_noise is not None:
        return s.robot_noise
    o = cfg.options
    mm, deg = PLAN_ARM_NOISE
    return max(o.robot_noise_m * 1000.0, mm), max(o.robot_noise_deg, deg)


def _levels(s: PlanSettings) -> dict[str, tuple[float, float]] | None:
    """``s.robot_levels`` as ``planned_covariance`` takes them (rad, m), None when not set."""
    if s.robot_levels is None:
        return None
    return {k: (np.radians(deg), mm / 1000.0) for k, (mm, deg) in s.robot_levels.items()}


def nominal_problem(
    cfg: CellConfig, s: PlanSettings, T_base_tool: np.ndarray
) -> CalibrationProblem:
    """The problem a run of tool poses ``T_base_tool`` (F, 4, 4) would give the solver: the
    cell's target and reference camera, each frame's corners in the image (``margin`` 2 px)
    projected exactly through the nominal camera, the arm's accuracy at :func:`arm_noise`."""
    spec, pts = _spec(cfg), cfg.target.points_m
    w, h = spec.width, spec.height
    frames = []
    for k, T in enumerate(T_base_tool):
        T_cb = nominal_T_cam_board(cfg, T)
        P = pts @ T_cb[:3, :3].T + T_cb[:3, 3]
        ok = P[:, 2] > 1e-6
        px = np.full((len(P), 2), np.nan)
        px[ok] = project(s.K, s.dist, P[ok])
        ok &= (px[:, 0] >= 1.5) & (px[:, 0] <= w - 2.5) & (px[:, 1] >= 1.5) & (px[:, 1] <= h - 2.5)
        ids = np.flatnonzero(ok)
        frames.append(Frame(k, {spec.name: Detection(ids, px[ids])}, T_base_tool=T))
    mm, deg = arm_noise(cfg, s)
    options = replace(cfg.options, robot_noise_m=mm / 1000.0, robot_noise_deg=deg)
    cams = (CameraSpec(spec.name, w, h),)
    return CalibrationProblem(cfg.target, cams, tuple(frames), cfg.mount, "robot", options)


def nominal_state(cfg: CellConfig, s: PlanSettings, n_frames: int) -> ModelState:
    """The nominal cell in the solver's parametrisation (the truth the prediction is made at)."""
    cam, X = cfg.reference_camera, inv_T(cfg.approx_T_hand_eye)
    return ModelState(
        {cam: s.K}, {cam: s.dist}, {}, X[None], cfg.approx_T_target, np.zeros(n_frames)
    )


def _information(cfg: CellConfig, s: PlanSettings, T_base_tool: np.ndarray) -> FrameInformation:
    """Each frame's information on the shared parameters (the solver's, per frame: the frames
    of any plan add up); every frame must see the target."""
    problem = nominal_problem(cfg, s, T_base_tool)
    state = nominal_state(cfg, s, len(T_base_tool))
    info = planned_covariance(problem, state, s.corner_noise_px, levels=_levels(s), per_frame=True)
    assert isinstance(info, FrameInformation)
    return info


def _ratios(named: NamedCovariance, cfg: CellConfig, s: PlanSettings) -> np.ndarray:
    """Predicted std over target per goal that is set (:data:`GOAL_KEYS` order)."""
    cam, he = cfg.reference_camera, _hand_eye(cfg)
    std = {
        "fx_rel_std": _or_inf(named.std(f"{cam}.fx")) / float(s.K[0, 0]),
        "hand_eye_rot_std_deg": _or_inf(named.std_rot_deg(he)),
        "hand_eye_t_std_mm": _or_inf(named.std_t_mm(he)),
    }
    return np.array([std[k] / g for k in GOAL_KEYS if (g := getattr(s.goal, k)) is not None])


def _or_inf(v: float | None) -> float:
    return float("inf") if v is None else v


def _covariance(info: np.ndarray) -> np.ndarray | None:
    """Inverse of a Fisher matrix, None when singular (scaled reciprocal condition)."""
    d = np.sqrt(np.diag(info))
    if np.any(d <= 0):
        return None
    A = info / np.outer(d, d)
    ev = np.linalg.eigvalsh(A)
    if ev[0] <= MIN_RCOND * ev[-1]:
        return None
    return np.linalg.inv(A) / np.outer(d, d)


# -- candidates -------------------------------------------------------------------------------
@dataclass
class _Group:
    """A candidate group: its pose (index 0) and displaced frames; each frame's tool pose,
    whether it is usable and its information; the frames a failed dry run banned."""

    T_base_tool: np.ndarray  # (n, 4, 4)
    usable: np.ndarray  # (n,) bool
    info: np.ndarray  # (n, P, P)
    banned: set[int] = field(default_factory=set)


def _rejection(cfg: CellConfig, s: PlanSettings, T_base_tool: np.ndarray) -> str | None:
    """Why a tool pose cannot be a frame (workspace, reach, view), or None."""
    lo, hi = cfg.robot.workspace_min_m, cfg.robot.workspace_max_m
    p = T_base_tool[:3, 3]
    if lo is not None and hi is not None and (np.any(p < lo) or np.any(p > hi)):
        return "workspace"
    T_cb = nominal_T_cam_board(cfg, T_base_tool)
    P = cfg.target.points_m @ T_cb[:3, :3].T + T_cb[:3, 3]  # every corner in depth and image
    if np.any(P[:, 2] < s.depth_m[0]) or np.any(P[:, 2] > s.depth_m[1]):
        return "view"
    px, spec = project(s.K, s.dist, P), _spec(cfg)
    hi = np.array([spec.width, spec.height]) - 0.5 - s.margin_px
    if np.any(px < s.margin_px - 0.5) or np.any(px > hi):
        return "view"
    if not urk.reachable(T_base_tool, None, urk.model_by_name(cfg.robot.model), cfg.robot.tcp):
        return "reach"
    return None


def _via(cfg: CellConfig) -> np.ndarray:
    """The untilted view from ``standoff_m``, visited before each group (``Plan.via``)."""
    centre = cfg.target.points_m.mean(axis=0)
    T_cb = group_T_cam_board(centre, cfg.standoff_m, np.eye(3), np.zeros((1, 3)))[0]
    return tool_pose(cfg, T_cb)


def _candidates(
    cfg: CellConfig, s: PlanSettings
) -> tuple[list[_Group], dict[str, int], FrameInformation | None]:
    """Candidate groups with their usable frames' information; rejection counts by reason; the
    named layer's reading of the information (None without a candidate)."""
    centre = cfg.target.points_m.mean(axis=0)
    offsets = np.vstack([np.zeros((1, 3))] + [DIRECTIONS * (L / 1000.0) for L in s.step_mm])
    counts = {"workspace": 0, "view": 0, "reach": 0}
    groups: list[_Group] = []
    fim: FrameInformation | None = None
    via_why = _rejection(cfg, s, _via(cfg))
    if via_why is not None:
        counts[via_why] += 1
        return [], counts, fim
    for d in s.standoffs_m:
        for tilt in s.tilts_deg:
            for az in s.azimuths_deg:
                R = group_R_board_cam(tilt, az)
                T_cb = group_T_cam_board(centre, d, R, offsets)
                T_bt = np.stack([tool_pose(cfg, T) for T in T_cb])
                why = [_rejection(cfg, s, T) for T in T_bt]
                for w in why:
                    if w is not None:
                        counts[w] += 1
                usable = np.array([w is None for w in why])
                if not usable[0] or usable.sum() < s.min_frames_per_group:
                    continue
                idx = np.flatnonzero(usable)
                fim = _information(cfg, s, T_bt[idx])
                info = np.zeros((len(T_bt),) + fim.per_frame.shape[1:])
                info[idx] = fim.per_frame
                groups.append(_Group(T_bt, usable, info))
    return groups, counts, fim


# -- greedy search ----------------------------------------------------------------------------
@dataclass(frozen=True)
class _Prior:
    """Frames already recorded: their summed information (P, P), their number of orientation
    groups, and the candidate groups of the same orientation (not chosen again)."""

    info: np.ndarray
    n_groups: int
    groups: set[int]


@dataclass
class _Chosen:
    group: int  # index into the candidate list
    frames: list[int]  # offset indices, 0 (the group's pose) first


class _Timing:
    def __init__(self, cfg: CellConfig, s: PlanSettings, start: np.ndarray | None) -> None:
        self.v, self.a = cfg.robot.speed_mps, cfg.robot.accel_mps2
        self.per_frame = cfg.robot.settle_s + s.capture_s
        self.start = start

    def move(self, T0: np.ndarray | None, T1: np.ndarray) -> float:
        return 0.0 if T0 is None else move_time_s(T0, T1, self.v, self.a)


def _sequence(cands: list[_Group], chosen: list[_Chosen], via: np.ndarray):
    """The plan's pose sequence: (kind, T) with kind 'via' or 'frame'."""
    seq = []
    for c in chosen:
        g = cands[c.group]
        seq.append(("via", via))
        seq.extend(("frame", g.T_base_tool[k]) for k in c.frames)
    return seq


def _greedy(
    cands: list[_Group],
    fim: FrameInformation,
    cfg: CellConfig,
    s: PlanSettings,
    timing: _Timing,
    via: np.ndarray,
    prior: _Prior | None = None,
) -> tuple[list[_Chosen], float, np.ndarray | None, str]:
    """Add the frame (or new group of two frames) with the largest drop of the goal's predicted
    variance per second until the goal and the minimum structure are met or time runs out.
    ``prior``: frames already recorded (an extension, :func:`extend_plan`): their information
    counts, their groups count towards ``min_groups``, and new groups are chosen after them.

    Returns the choice, its predicted duration, its goal ratios (None: still singular) and why
    the search stopped: "met", "time" (over the budget) or "exhausted" (no candidate left)."""

    def goal_ratios_of(cov: np.ndarray) -> np.ndarray:  # cov: an inverse of summed information
        return _ratios(fim.named(cov), cfg, s)

    P = len(fim.kinds)
    ridge = _ridge(fim, s)
    chosen: list[_Chosen] = []
    info = np.zeros((P, P)) if prior is None else prior.info.copy()
    n_prior = 0 if prior is None else prior.n_groups
    t_now = 0.0

    def objective(A: np.ndarray) -> float:
        c = np.linalg.inv(A + ridge)
        return float(np.sum(goal_ratios_of(c) ** 2))

    f_now = objective(info)
    while True:
        cov = _covariance(info) if chosen or n_prior else None
        ratios = goal_ratios_of(cov) if cov is not None else None
        structure_ok = len(chosen) + n_prior >= s.min_groups and all(
            len(c.frames) >= s.min_frames_per_group for c in chosen
        )
        met = ratios is not None and bool(np.all(ratios <= 1.0))
        if met and structure_ok and (n_prior or _linear_ok(cands, chosen, cfg, s)):
            return chosen, t_now, ratios, "met"
        only_fix = met and not structure_ok
        # the minimum structure first: min_groups groups of min_frames_per_group frames (fewer
        # groups cannot make the hand-eye translation observable, docs/METHOD.md Sec. 4)
        building = len(chosen) + n_prior < s.min_groups
        short = any(len(c.frames) < s.min_frames_per_group for c in chosen)
        seq = _sequence(cands, chosen, via)
        last = seq[-1][1] if seq else timing.start
        best = None  # (score, dt, new info, action)
        used = {c.group for c in chosen} | (prior.groups if prior is not None else set())
        # append a frame to an existing group
        for ci, c in enumerate(chosen):
            if len(c.frames) >= s.max_frames_per_group:
                continue
            if (only_fix or building) and len(c.frames) >= s.min_frames_per_group:
                continue
            g = cands[c.group]
            T_last = g.T_base_tool[c.frames[-1]]
            nxt = via if ci + 1 < len(chosen) else None  # the via pose after the group
            base_dt = timing.move(T_last, nxt) if nxt is not None else 0.0
            for k in np.flatnonzero(g.usable):
                if k in c.frames or k in g.banned:
                    continue
                Tk = g.T_base_tool[k]
                dt = timing.move(T_last, Tk) + timing.per_frame
                if nxt is not None:
                    dt += timing.move(Tk, nxt) - base_dt
                A = info + g.info[k]
                best = _better(best, f_now, objective(A), dt, A, ("add", ci, int(k)))
        # open a new group with its pose and one displaced frame
        if (
            len(chosen) < s.max_groups
            and not (only_fix and len(chosen) + n_prior >= s.min_groups)
            and not (building and short)
        ):
            for gi, g in enumerate(cands):
                if gi in used or 0 in g.banned:
                    continue
                dt0 = timing.move(last, via) + timing.move(via, g.T_base_tool[0]) + timing.per_frame
                A0 = info + g.info[0]
                for k in np.flatnonzero(g.usable)[1:]:
                    if k in g.banned:
                        continue
                    dt = dt0 + timing.move(g.T_base_tool[0], g.T_base_tool[k]) + timing.per_frame
                    A = A0 + g.info[k]
                    best = _better(best, f_now, objective(A), dt, A, ("new", gi, int(k)))
        if best is None:
            return chosen, t_now, ratios, "exhausted"
        _, dt, A, (kind, i, k) = best
        if kind == "add":
            chosen[i].frames.append(k)
        else:
            chosen.append(_Chosen(i, [0, k]))
        info, f_now = A, objective(A)
        t_now, prev = 0.0, timing.start
        for kind, T in _sequence(cands, chosen, via):
            t_now += timing.move(prev, T) + (timing.per_frame if kind == "frame" else 0.0)
            prev = T
        if t_now > s.goal.max_duration_s:
            cov = _covariance(info)
            return chosen, t_now, goal_ratios_of(cov) if cov is not None else None, "time"


def _better(best, f_now, f_new, dt, A, action):  # noqa: ANN001, ANN202 - internal helper
    score = (np.log(f_now) - np.log(f_new)) / max(dt, 1e-3)
    if best is None or score > best[0]:
        return (score, dt, A, action)
    return best


def _ridge(info: FrameInformation, s: PlanSettings) -> np.ndarray:
    """A weak prior (P, P) that keeps the greedy's first steps finite: 30 % of f on the
    intrinsics, 1 on distortion, 0.5 rad / 0.5 m on the poses."""
    sd = {"intrinsics": 0.3 * s.K[0, 0], "distortion": 1.0}
    d = np.array([sd.get(k, 0.5) for k in info.kinds])
    return np.diag(1.0 / d**2)


def _linear_ok(
    cands: list[_Group], chosen: list[_Chosen], cfg: CellConfig, s: PlanSettings
) -> bool:
    """Whether the linear step accepts the plan: the exact homographies ``K [r1 r2 t]`` (eq. 10)
    of the nominal model and the robot's moves, per group."""
    groups = []
    for c in chosen:
        T = cands[c.group].T_base_tool[c.frames]
        H = [s.K @ nominal_T_cam_board(cfg, Tk)[:3, [0, 1, 3]] for Tk in T]
        H = [h / np.linalg.norm(h[:, :2]) for h in H]
        groups.append(LinearGroup(np.array(H), T[:, :3, 3] - T[0, :3, 3]))
    o, spec = cfg.options, _spec(cfg)
    try:
        check_configuration(
            groups,
            "robot",
            skew=o.skew,
            unit_aspect=o.unit_aspect,
            image_size=(spec.width, spec.height),
            K_guess=s.K,
            hand_eye=True,
            robot_translations=[g.motion for g in groups],
        )
    except DegenerateError:
        return False
    return True


# -- prediction of a whole plan ---------------------------------------------------------------
def predict_std(
    plan: Plan, cfg: CellConfig, settings: PlanSettings | None = None
) -> dict[str, float]:
    """Predicted one-sigma of a plan's estimates: the solver's prediction
    (:func:`slidecal.solver.uncertainty.planned_covariance`) of the :func:`nominal_problem`.

    Keys as :func:`slidecal.routines.results_io.errors_against_truth`: ``<cam>.fx_px`` ..
    ``<cam>.cy_px``, ``<cam>.fx_rel``, distortion ``<cam>.k1`` ..., ``<hand-eye>.rot_deg`` /
    ``.t_mm`` and ``<target>.rot_deg`` / ``.t_mm``. Raises ``DegenerateError`` when the plan's
    Fisher information is singular or a parameter is unobservable.
    """
    s = settings or cfg.plan
    T = np.array([T for _, T in plan.poses])
    problem = nominal_problem(cfg, s, T)
    if any(len(f.detections[problem.reference].ids) < 4 for f in problem.frames):
        raise DegenerateError(
            "a planned frame does not see the target; move the frame or the target into view"
        )
    state = nominal_state(cfg, s, len(T))
    named = planned_covariance(problem, state, s.corner_noise_px, levels=_levels(s))
    assert isinstance(named, NamedCovariance)
    d = np.diag(named.matrix)
    if not np.all(np.isfinite(named.matrix)) or np.any(d <= 0):
        raise DegenerateError(
            "the plan's Fisher information is singular: add orientation groups tilted about "
            "different axes and translations out of the board plane"
        )
    out: dict[str, float] = {}
    cam = cfg.reference_camera
    for n, var in zip(named.names, d, strict=True):
        if n.startswith(f"{cam}."):
            key = n.split(".", 1)[1]
            unit = "_px" if key in INTRINSIC_NAMES else ""
            out[f"{cam}.{key}{unit}"] = float(np.sqrt(var))
    out[f"{cam}.fx_rel"] = out[f"{cam}.fx_px"] / float(s.K[0, 0])
    frames = mount_names(cfg.mount)
    assert frames is not None  # the planner plans robot sessions only
    for tf in (frames.hand_eye, frames.target):
        out[f"{tf}.rot_deg"] = _or_inf(named.std_rot_deg(tf))
        out[f"{tf}.t_mm"] = _or_inf(named.std_t_mm(tf))
    return out


def _hand_eye(cfg: CellConfig) -> str:
    """The name of the planned hand-eye transform (the planner plans robot sessions only)."""
    frames = mount_names(cfg.mount)
    assert frames is not None
    return frames.hand_eye


def goal_ratios(pred: dict[str, float], cfg: CellConfig, goal: PlanGoal) -> dict[str, float]:
    """Predicted std over the goal's target, per goal that is set (<= 1: met)."""
    cam, he = cfg.reference_camera, _hand_eye(cfg)
    keys = dict(zip(GOAL_KEYS, (f"{cam}.fx_rel", f"{he}.rot_deg", f"{he}.t_mm"), strict=True))
    return {k: pred[keys[k]] / g for k in GOAL_KEYS if (g := getattr(goal, k)) is not None}


# -- dry run ----------------------------------------------------------------------------------
def _start_q(T_base_tool: np.ndarray, cfg: CellConfig) -> np.ndarray | None:
    """Joints (6,) rad of a non-singular solution of a pose nearest the home configuration."""
    model = urk.model_by_name(cfg.robot.model)
    sols = [
        q
        for q in urk.ik(T_base_tool, urk.Q_HOME, model, cfg.robot.tcp)
        if urk.singularity(q, model) is None
    ]
    return sols[0] if sols else None


def _start_pose(cfg: CellConfig) -> np.ndarray | None:
    """Where the simulated arm starts (``T_base_tool``), None for real cells (unknown)."""
    if not cfg.simulated:
        return None
    if cfg.robot.start_q is not None:
        q = cfg.robot.start_q
    elif cfg.robot.start_pose is not None:
        return cfg.robot.start_pose
    else:
        q = urk.Q_HOME
    return urk.fk(q, urk.model_by_name(cfg.robot.model), cfg.robot.tcp)


def dry_run(plan: Plan, cfg: CellConfig) -> tuple[float, int | None, str]:
    """Execute ``plan`` on a noise-free simulated arm of the cell's model and limits.

    Simulated cells start where their arm starts (``start_pose``, ``start_q`` or home); real
    cells at the via pose (or the first pose), their start being unknown. Returns (robot time
    in seconds for moves and settling, index of the first failing move in execution order or
    None, the failure message).
    """
    r = simulated_arm_dict(cfg)
    if not cfg.simulated:
        first = plan.via if plan.via is not None else plan.groups[0][0]
        q = _start_q(first, cfg)
        if q is None:
            return 0.0, 0, "the first pose of the plan is out of reach or singular"
        r["start_q"] = q.tolist()
        r.pop("start_pose", None)
    try:
        robot = SimulatedUR.from_dict(r)
    except InputError as e:
        return 0.0, 0, str(e)
    robot.connect()
    i = 0
    for group in plan.groups:
        seq = ([("via", plan.via)] if plan.via is not None else []) + [("frame", T) for T in group]
        for kind, T in seq:
            try:
                robot.move_linear(T, plan.speed_mps, plan.accel_mps2)
            except (HardwareFault, InputError) as e:
                return robot.robot_time_s, i, str(e)
            if kind == "frame":
                robot.wait_settled(plan.settle_s)
            i += 1
    return robot.robot_time_s, None, ""


# -- the planner ------------------------------------------------------------------------------
def make_plan(cfg: CellConfig, settings: PlanSettings | None = None) -> Plan:
    """The plan that meets the cell's goal with the least robot time (module docstring), with
    its ``predicted_std`` and ``duration_s``.

    Raises ``InputError`` with the reason and what to change when no plan can: no reachable
    view of the target, the target does not fit in the image, or the goal needs more time than
    ``plan.max_duration_s``.
    """
    s = settings or cfg.plan
    where = f"{cfg.source}: plan"
    cands, rejected, fim = _candidates(cfg, s)
    if len(cands) < s.min_groups:
        raise InputError(_no_candidates_message(cfg, s, rejected, len(cands)), where=where)
    via = _via(cfg)
    assert fim is not None  # there are candidates
    plan, robot_s, pred = _search(cfg, cands, fim, s, _Timing(cfg, s, _start_pose(cfg)), via, where)
    n = plan.n_poses
    duration = robot_s + n * s.capture_s
    ratios_d = goal_ratios(pred, cfg, s.goal)
    notes = (
        f"planned: {len(plan.groups)} groups, {n} frames, predicted {duration:.1f} s of robot time "
        f"(moves and settling {robot_s:.1f} s, capture {n * s.capture_s:.1f} s); goal ratios "
        + ", ".join(f"{k} {v:.2f}" for k, v in ratios_d.items()),
        "prediction for corner noise {:g} px and the arm's accuracy {:g} mm / {:g} deg".format(
            s.corner_noise_px, *arm_noise(cfg, s)
        ),
    )
    return replace(plan, predicted_std=pred, duration_s=float(duration), notes=notes)


def _search(
    cfg: CellConfig,
    cands: list[_Group],
    fim: FrameInformation,
    s: PlanSettings,
    timing: _Timing,
    via: np.ndarray,
    where: str,
    before: Plan | None = None,
    prior: _Prior | None = None,
) -> tuple[Plan, float, dict[str, float]]:
    """The greedy choice that passes the dry run (a failing move bans its pose and the search
    runs again) and whose prediction (:func:`predict_std`) meets the goal (where the frames'
    summed information promised more, the search runs again for the goal tightened by that
    factor), as a plan after ``before`` (an extension: ``before``'s groups first); its robot
    time (moves and settling) in seconds and its prediction. Raises ``InputError`` when none
    does."""
    last_failure = ""
    skip = 0 if before is None else sum(len(g) + (before.via is not None) for g in before.groups)
    n_goals = sum(getattr(s.goal, k) is not None for k in GOAL_KEYS)
    factor = np.ones(n_goals)  # goal / the search's target, per goal set
    for _attempt in range(12):
        tight = replace(s, goal=_scaled(s.goal, 1.0 / factor))
        chosen, t_pred, ratios, stop = _greedy(cands, fim, cfg, tight, timing, via, prior)
        if stop != "met":
            raise InputError(_goal_message(s, t_pred, ratios, stop), where=where)
        groups = tuple(tuple(cands[c.group].T_base_tool[k] for k in c.frames) for c in chosen)
        plan = Plan.build(groups, cfg.robot, via=via)
        if before is not None:
            plan = Plan.build(before.groups + plan.groups, before, via=before.via)
        robot_s, bad, why = dry_run(plan, cfg)
        if bad is None:
            try:
                pred = predict_std(plan, cfg, s)
            except DegenerateError as e:
                raise InputError(f"the chosen plan is degenerate ({e})", where=where) from None
            got = np.array(list(goal_ratios(pred, cfg, s.goal).values()))
            if np.all(got <= 1.0):
                return plan, robot_s, pred
            factor = np.maximum(factor, 1.02 * got * factor / np.maximum(ratios, 1e-12))
            continue
        last_failure = why
        if bad < skip:  # the recorded part itself fails: nothing to ban in the new part
            break
        _ban(cands, chosen, bad - skip)
    raise InputError(
        f"no plan passed the robot's motion check (last: {last_failure}); move the target "
        "closer to the robot's usual workspace or widen robot.workspace",
        where=where,
    )


def extend_plan(
    cfg: CellConfig, plan: Plan, s: PlanSettings, achieved: Mapping[str, float]
) -> Plan:
    """``plan`` with more orientation groups after it, for a run whose recorded frames missed
    the accuracy its gate asks for (docs/UNATTENDED.md, "A run that extends its plan"): the
    search of :func:`make_plan` with ``plan``'s frames counted, under settings ``s`` that hold
    the noise the data showed (``corner_noise_px``, ``robot_noise``, ``robot_levels``) and the
    goal, tightened by how far ``achieved`` (the recorded frames' one-sigma per goal key)
    exceeds their prediction. ``InputError`` (with the reason) when no extension meets it."""
    where = f"{cfg.source}: plan (extension)"
    try:
        before = goal_ratios(predict_std(plan, cfg, s), cfg, PlanGoal(1.0, 1.0, 1.0))
    except DegenerateError:
        before = {}
    tight: dict[str, float | None] = dict.fromkeys(GOAL_KEYS)
    for k in GOAL_KEYS:
        target = getattr(s.goal, k)
        if target is not None:
            pred, got = before.get(k), achieved.get(k)
            factor = got / pred if pred and got and np.isfinite(got / pred) else 1.0
            tight[k] = target / max(1.0, factor)
    goal = PlanGoal(**tight, max_duration_s=s.goal.max_duration_s)
    s = replace(s, goal=goal)
    cands, _, fim = _candidates(cfg, s)
    if fim is None:
        raise InputError("no candidate view of the target is left to extend the plan", where=where)
    T_old = np.array([T for _, T in plan.poses])
    old = nominal_problem(cfg, s, T_old)
    sees = [len(f.detections[old.reference].ids) >= 4 for f in old.frames]
    info = _information(cfg, s, T_old[sees]).per_frame.sum(axis=0)
    R_first = [g[0][:3, :3] for g in plan.groups]
    same = {
        i
        for i, g in enumerate(cands)
        if any(rotation_angle_deg(R.T @ g.T_base_tool[0][:3, :3]) < 1.0 for R in R_first)
    }
    prior = _Prior(info, len(plan.groups), same)
    via = plan.via if plan.via is not None else _via(cfg)
    timing = _Timing(cfg, s, T_old[-1])
    ext, robot_s, pred = _search(cfg, cands, fim, s, timing, via, where, plan, prior)
    n_new = ext.n_poses - plan.n_poses
    ratios = goal_ratios(pred, cfg, goal)
    mm, deg = arm_noise(cfg, s)  # the accuracy the first run's data showed
    notes = plan.notes + (
        f"extended by {len(ext.groups) - len(plan.groups)} groups, {n_new} frames (the first "
        f"run's data: corner noise {s.corner_noise_px:.3g} px, robot accuracy "
        f"{mm:.3g} mm / {deg:.3g} deg); predicted goal ratios "
        + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items()),
    )
    duration = robot_s + ext.n_poses * s.capture_s
    return replace(ext, predicted_std=pred, notes=notes, duration_s=float(duration))


def _scaled(goal: PlanGoal, mult: np.ndarray) -> PlanGoal:
    """``goal`` with each target that is set (in :data:`GOAL_KEYS` order) times ``mult``."""
    it = iter(mult)
    vals = {k: None if (v := getattr(goal, k)) is None else v * next(it) for k in GOAL_KEYS}
    return replace(goal, **vals)


def _ban(cands: list[_Group], chosen: list[_Chosen], bad: int) -> None:
    """Ban what the failing move (index in execution order) went to."""
    i = 0
    for c in chosen:
        if bad == i or bad == i + 1:  # the via move or the move to the group's pose
            cands[c.group].banned.add(0)
            return
        i += 1
        for k in c.frames:
            if bad == i:
                cands[c.group].banned.add(k)
                return
            i += 1


def _board_too_big(cfg: CellConfig, s: PlanSettings) -> str | None:
    """Why the target cannot fit the image at any planned standoff (head-on view), or None."""
    pts = cfg.target.points_m
    ext = pts.max(axis=0)[:2] - pts.min(axis=0)[:2]
    d = max(s.standoffs_m)
    spec = _spec(cfg)
    w = spec.width - 2 * s.margin_px
    h = spec.height - 2 * s.margin_px
    fx, fy = float(s.K[0, 0]), float(s.K[1, 1])
    need = (fx * ext[0] / d, fy * ext[1] / d)
    if (need[0] <= w and need[1] <= h) or (fx * ext[1] / d <= w and fy * ext[0] / d <= h):
        return None
    d_min = min(max(fx * ext[0] / w, fy * ext[1] / h), max(fx * ext[1] / w, fy * ext[0] / h))
    return (
        f"the target leaves the view: it ({ext[0] * 1000:.0f} x {ext[1] * 1000:.0f} mm) spans "
        f"{need[0]:.0f} x {need[1]:.0f} px at {d:.2f} m, more than the {spec.width} x "
        f"{spec.height} px image holds (margins {s.margin_px:g} px); increase "
        f"approximate.standoff_m to at least {d_min:.2f} m or use a smaller target"
    )


def _no_candidates_message(cfg: CellConfig, s: PlanSettings, rejected: dict, n_ok: int) -> str:
    if s.fx_px is None and cfg.simulation is None:  # a real camera's lens guessed: say that first
        hfov = np.degrees(2.0 * np.arctan((_spec(cfg).width / 2.0) / s.K[0, 0]))
        return (
            f"no plan possible for a {hfov:.0f}-degree lens, which the planner assumed: the "
            f"cell does not give camera {cfg.reference_camera}'s field of view; set plan.hfov_deg "
            "(the data sheet's horizontal field of view) or plan.fx_px"
        )
    too_big = _board_too_big(cfg, s)
    if too_big is not None:
        return f"no plan possible: {too_big}"
    worst = max(rejected, key=lambda k: rejected[k]) if any(rejected.values()) else "view"
    fix = {
        "workspace": "the candidate poses leave the workspace box (robot.workspace); widen it "
        "or move the target so that views from approximate.standoff_m fit inside",
        "reach": "the candidate poses are unreachable or singular for the "
        f"{cfg.robot.model}; move the target closer to the robot or change "
        "approximate.standoff_m",
        "view": "the target leaves the view (or the usable depth) at the candidate poses; "
        "increase approximate.standoff_m, reduce plan.tilts_deg or plan.margin_px, or use a "
        "smaller target",
    }[worst]
    return (
        f"no plan possible: only {n_ok} usable tilt groups (need {s.min_groups}); "
        f"rejected frames: {rejected}; {fix}"
    )


def _goal_message(s: PlanSettings, t: float, ratios: np.ndarray | None, stop: str) -> str:
    names = [k for k in GOAL_KEYS if getattr(s.goal, k) is not None]
    if ratios is None:
        state = "no non-degenerate plan was found"
        worst = names[0]
    else:
        worst = names[int(np.argmax(ratios))]
        state = f"the predicted {worst} is {float(np.max(ratios)):.2f} times the goal"
    if stop == "time":
        return (
            f"the goal needs more time than allowed: after {t:.1f} s {state} "
            f"(plan.max_duration_s = {s.goal.max_duration_s:g} s); allow more time, relax "
            f"plan.goal.{worst}, or reduce the noise (robot_noise_*, corner noise)"
        )
    return (
        f"the candidates ran out after {t:.1f} s of robot time and {state}; allow more groups "
        "or frames (plan.max_groups, plan.max_frames_per_group), more plan.tilts_deg / "
        f"azimuths_deg / step_mm, or relax plan.goal.{worst}"
    )


# -- command line -----------------------------------------------------------------------------
def add_arguments(p: argparse.ArgumentParser) -> None:
    """``slidecal plan [--config cell.yaml] --out plan.yaml``."""
    p.add_argument("--config", help="cell description (default: the simulated default cell)")
    p.add_argument("--out", default="plan.yaml", help="plan file to write (default plan.yaml)")
    p.add_argument("--quiet", action="store_true", help="print nothing but errors")


def main(args: argparse.Namespace) -> int:
    """Plan, write ``plan.yaml``, print the prediction."""
    out = Path(args.out)
    if str(out) in ("", "."):
        raise InputError("--out is empty; name the plan file to write (e.g. plan.yaml)")
    if out.is_dir():
        raise InputError("is a directory; --out must name a plan file", where=str(out))
    if out.parent.exists() and not out.parent.is_dir():
        raise InputError(f"{out.parent} is a file; --out must lie in a directory", str(out))
    cfg = load_config(args.config)
    plan = make_plan(cfg)
    path = write_plan(plan, out)
    if not args.quiet:
        for n in plan.notes:
            print(n)
        pred = plan.predicted_std or {}
        cam = cfg.reference_camera
        he = _hand_eye(cfg)
        print(
            f"predicted std: fx {pred[f'{cam}.fx_px']:.3f} px "
            f"({pred[f'{cam}.fx_rel'] * 100:.4f} %), "
            f"{he} {pred[f'{he}.rot_deg']:.4f} deg / {pred[f'{he}.t_mm']:.3f} mm"
        )
        config = f" --config {shlex.quote(str(args.config))}" if args.config else ""
        print(f"plan: {path}  (run it with: slidecal run{config} --plan {shlex.quote(str(path))})")
    return 0
