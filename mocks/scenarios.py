"""Synthetic detections with ground truth: the benchmark set-ups of docs/SETUPS.md (S1-S4, R1).

Each builder returns a :class:`Scenario`: the calibration problem (noisy detections and measured
motion), the true model state in the solver's parametrisation (``slidecal.solver.refine``) and
the noise it was built with, so that benchmarks and tests can compare an estimate with the truth
and with the Cramer-Rao bound. No images: the rendered-image simulator is ``mocks/camera.py``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from slidecal.drivers import ur_kinematics as urk
from slidecal.solver.camera import K_matrix, project
from slidecal.solver.geometry import (
    R_from_rvec,
    Rx,
    Ry,
    Rz,
    T_from_Rt,
    inv_T,
    look_at_R_cam_world,
    transform_points,
)
from slidecal.solver.problem import (
    CalibrationProblem,
    CameraSpec,
    Detection,
    Frame,
    ModelOptions,
    Target,
)
from slidecal.solver.refine import ModelState

NO_DISTORTION = (False, False, False, False, False)


@dataclass(frozen=True)
class Scenario:
    """A synthetic problem with its truth.

    ``truth``: the true state in the solver's parametrisation; ``T_tool_cam`` (eye-in-hand) or
    ``T_base_cam`` (eye-to-hand) and ``T_base_board`` as 4x4 transforms where a robot is
    involved; ``sigma_px``: the pixel noise the detections carry.
    """

    problem: CalibrationProblem
    truth: ModelState
    sigma_px: float
    T_hand_eye: np.ndarray | None = None
    T_target: np.ndarray | None = None
    T_base_tool_true: np.ndarray | None = None  # (F, 4, 4) where the arm really was


def paper_grid() -> Target:
    """S1-S4's target: 9 x 7 points, pitch 5 l.u., centred on the board origin."""
    x, y = np.meshgrid((np.arange(9) - 4) * 5.0, (np.arange(7) - 3) * 5.0)
    return Target.points(np.column_stack([x.ravel(), y.ravel()]))


def _detect(
    K: np.ndarray,
    dist: np.ndarray,
    T_cam_board: np.ndarray,
    target: Target,
    size: tuple[int, int],
    sigma_px: float,
    rng: np.random.Generator,
    margin_px: float = 0.0,
) -> Detection:
    P = transform_points(T_cam_board, target.points_m)
    ok = P[:, 2] > 0
    px = np.full((len(P), 2), np.nan)
    px[ok] = project(K, dist, P[ok])
    w, h = size
    ok &= (px[:, 0] >= margin_px - 0.5) & (px[:, 0] <= w - 0.5 - margin_px)
    ok &= (px[:, 1] >= margin_px - 0.5) & (px[:, 1] <= h - 0.5 - margin_px)
    ids = np.flatnonzero(ok)
    return Detection(ids, px[ids] + rng.normal(0.0, sigma_px, (len(ids), 2)))


def _board_frame_scenario(
    K: np.ndarray,
    R_cam_board: np.ndarray,
    centres: np.ndarray,
    knowledge: str,
    options: ModelOptions,
    sigma_px: float,
    rng: np.random.Generator,
    presumed: np.ndarray | None = None,
) -> Scenario:
    """One orientation group; camera centres (n, 3) in the board frame, frame 0 the reference.

    ``presumed`` (n, 3): the motion the solver is told (defaults to the true one): S4 uses it
    to inject robot motion errors.
    """
    target = paper_grid()
    dist = np.zeros(5)
    moves = centres - centres[0] if presumed is None else presumed - presumed[0]
    frames = []
    Ts = []
    for k, C in enumerate(centres):
        T = T_from_Rt(R_cam_board, -R_cam_board @ C)
        Ts.append(T)
        det = _detect(K, dist, T, target, (300, 240), sigma_px, rng)
        m = moves[k]
        if knowledge == "board_direction":
            m = m / np.linalg.norm(m) if np.linalg.norm(m) > 0 else np.zeros(3)
        frames.append(Frame(k, {"cam": det}, motion_board=m, group=0))
    problem = CalibrationProblem(
        target, (CameraSpec("cam", 300, 240),), tuple(frames), "none", knowledge, options
    )
    s = np.array([np.linalg.norm(c - centres[0]) for c in centres])
    truth = ModelState({"cam": K}, {"cam": dist}, {}, np.stack([Ts[0]]), np.eye(4), s)
    return Scenario(problem, truth, sigma_px)


def _robot_translation_scenario(
    K: np.ndarray,
    R_cam_board: np.ndarray,
    centres: np.ndarray,
    options: ModelOptions,
    sigma_px: float,
    rng: np.random.Generator,
    presumed: np.ndarray | None = None,
) -> Scenario:
    """Known translations in an unknown robot frame (Case 1 and its generalisation).

    The robot base is the board frame rotated by an arbitrary rotation, the tool is the camera;
    only the displacements (their lengths and mutual angles) carry information.
    """
    target = paper_grid()
    dist = np.zeros(5)
    R_base_board = R_from_rvec(np.array([0.3, -0.2, 0.5]))
    T_base_board = T_from_Rt(R_base_board, np.array([10.0, -20.0, 5.0]))
    told = centres if presumed is None else presumed
    frames = []
    for k, C in enumerate(centres):
        T_cam_board = T_from_Rt(R_cam_board, -R_cam_board @ C)
        det = _detect(K, dist, T_cam_board, target, (300, 240), sigma_px, rng)
        T_base_cam_told = T_base_board @ inv_T(T_from_Rt(R_cam_board, -R_cam_board @ told[k]))
        frames.append(Frame(k, {"cam": det}, T_base_tool=T_base_cam_told))
    problem = CalibrationProblem(
        target, (CameraSpec("cam", 300, 240),), tuple(frames), "eye_in_hand", "robot", options
    )
    truth = ModelState(
        {"cam": K}, {"cam": dist}, {}, np.eye(4)[None], T_base_board, np.zeros(len(centres))
    )
    return Scenario(problem, truth, sigma_px, np.eye(4), T_base_board)


def s1(
    theta_deg: float,
    sigma_px: float,
    rng: np.random.Generator,
    n_images: int = 5,
    step_error: float = 0.0,
) -> Scenario:
    """S1 (paper Table I): tilt ``theta`` about the board y axis, steps of known length 5 toward
    the grid centre; unit aspect, zero skew. ``step_error``: real steps are 5 (1 + e) (S4)."""
    K = K_matrix(400.0, 400.0, 150.0, 120.0)
    R = np.diag([1.0, -1.0, -1.0]) @ Ry(np.radians(theta_deg)).T
    axis = R.T @ np.array([0.0, 0.0, 1.0])  # optical axis in the board frame
    C0 = -100.0 * axis
    steps = np.arange(n_images)[:, None] * 5.0
    centres = C0 + steps * (1.0 + step_error) * axis
    presumed = C0 + steps * axis
    opts = ModelOptions(unit_aspect=True, distortion=NO_DISTORTION)
    return _robot_translation_scenario(K, R, centres, opts, sigma_px, rng, presumed)


def _s2_geometry() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    K = K_matrix(400.0, 440.0, 150.0, 120.0)
    R = np.diag([1.0, -1.0, -1.0]) @ (Rx(np.radians(30.0)) @ Ry(np.radians(30.0))).T
    axis = R.T @ np.array([0.0, 0.0, 1.0])
    return K, R, -100.0 * axis


def s2(n_images: int, sigma_px: float, rng: np.random.Generator, phi_deg: float = 0.0) -> Scenario:
    """S2 (Tables II, III): tilted 30 deg about x then 30 about y, translated along the board
    normal toward the plane by steps of 5; direction known, lengths unknown; zero skew.
    ``phi_deg``: the real direction is rotated by phi about the board x axis (S4)."""
    K, R, C0 = _s2_geometry()
    normal = np.array([0.0, 0.0, 1.0]) * np.sign(-C0[2])  # toward the plane
    real = Rx(np.radians(phi_deg)) @ normal
    steps = np.arange(n_images)[:, None] * 5.0
    opts = ModelOptions(distortion=NO_DISTORTION)
    return _board_frame_scenario(
        K,
        R,
        C0 + steps * real,
        "board_direction",
        opts,
        sigma_px,
        rng,
        presumed=C0 + steps * normal,
    )


def s3(n_images: int, sigma_px: float, rng: np.random.Generator) -> Scenario:
    """S3 (Case 3): the S2 set-up with the full translation known; all five intrinsics."""
    K, R, C0 = _s2_geometry()
    normal = np.array([0.0, 0.0, 1.0]) * np.sign(-C0[2])
    centres = C0 + np.arange(n_images)[:, None] * 5.0 * normal
    opts = ModelOptions(skew=True, distortion=NO_DISTORTION)
    return _board_frame_scenario(K, R, centres, "board_translation", opts, sigma_px, rng)


R1_K = K_matrix(880.0, 880.0, 640.0, 400.0)
R1_DIST = np.array([-0.12, 0.05, 5e-4, -3e-4, 0.0])
R1_T_TOOL_CAM = T_from_Rt(
    R_from_rvec(np.radians([1.5, -2.0, 90.0])), np.array([0.035, -0.06, 0.09])
)


def r1_poses(rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The R1 cell: ``T_base_board`` and the planned ``T_base_tool`` poses (20, 4, 4).

    Board flat on the table 0.5 m below the camera's first pose; 4 tilt groups (25 deg about
    different axes, looking at the board centre from 0.5 m) of 5 frames: the group's pose and
    4 translations of 40-80 mm in non-coplanar directions (each with a component along the
    viewing axis: translations parallel to the board are degenerate, docs/METHOD.md Sec. 7).
    """
    target = Target.charuco(11, 8, 0.030, 0.022)
    centre_board = target.points_m.mean(axis=0)
    # board frame: +z into the table (down), so a camera above reads the print (R_cam_board ~ I)
    R_base_board = np.diag([1.0, -1.0, -1.0])
    T_base_board = T_from_Rt(R_base_board, np.array([0.55, -0.10, 0.02]))
    centre = transform_points(T_base_board, centre_board[None])[0]
    up = np.array([1.0, 0.0, 0.0])  # image up away from the robot base
    tilts = [(25.0, 0.0), (0.0, 25.0), (-20.0, -18.0), (18.0, -20.0)]
    moves_mm = np.array(
        [
            [60.0, 0.0, -40.0],
            [0.0, 50.0, 45.0],
            [-35.0, -30.0, 55.0],
            [30.0, -40.0, -50.0],
        ]
    )
    poses = []
    for gi, (ax_deg, ay_deg) in enumerate(tilts):
        view = Rx(np.radians(ax_deg)) @ Ry(np.radians(ay_deg)) @ np.array([0.0, 0.0, 1.0])
        p_cam = centre + 0.5 * view
        R_base_cam = look_at_R_cam_world(p_cam, centre, up).T
        T_base_cam = T_from_Rt(R_base_cam, p_cam)
        T_base_tool = T_base_cam @ inv_T(R1_T_TOOL_CAM)
        poses.append(T_base_tool)
        order = np.roll(np.arange(4), gi)
        for j in order:
            m = moves_mm[j] / 1000.0
            m = R_base_cam @ m  # camera axes: (right, down, forward)
            T = T_base_tool.copy()
            T[:3, 3] += m
            poses.append(T)
    return T_base_board, np.stack(poses)


def _perturb(
    T: np.ndarray, rng: np.random.Generator, noise_m: float, noise_deg: float
) -> np.ndarray:
    if noise_m == 0 and noise_deg == 0:
        return T
    dR = R_from_rvec(rng.normal(0.0, np.radians(noise_deg), 3))
    return T_from_Rt(dR @ T[:3, :3], T[:3, 3] + rng.normal(0.0, noise_m, 3))


R1_T_BASE_CAM = T_from_Rt(
    look_at_R_cam_world(
        np.array([0.9, 0.4, 0.6]), np.array([0.5, 0.0, 0.3]), np.array([0.0, 0.0, -1.0])
    ).T,
    np.array([0.9, 0.4, 0.6]),
)
R1_T_TOOL_BOARD = T_from_Rt(
    R_from_rvec(np.radians([180.0, 0.0, 0.0])), np.array([-0.165, -0.12, 0.02])
)


def r1_scenario(
    target: Target,
    frames: list[Frame],
    eye_in_hand: bool,
    options: ModelOptions | None,
    sigma_px: float,
    T_base_board: np.ndarray,
    dist: np.ndarray = R1_DIST,
    size: tuple[int, int] = (1280, 800),
    T_base_tool_true: np.ndarray | None = None,
) -> Scenario:
    """The scenario of R1's camera (``R1_K``, ``dist``) with these ``frames``: the problem, the
    truth in the solver's parametrisation and the hand-eye and target poses of the mount."""
    problem = CalibrationProblem(
        target,
        (CameraSpec("cam", *size),),
        tuple(frames),
        "eye_in_hand" if eye_in_hand else "eye_to_hand",
        "robot",
        options or ModelOptions(),
    )
    T_hand_eye = R1_T_TOOL_CAM if eye_in_hand else R1_T_BASE_CAM
    T_target = T_base_board if eye_in_hand else R1_T_TOOL_BOARD
    truth = ModelState(
        {"cam": R1_K},
        {"cam": np.array(dist, dtype=float)},
        {},
        inv_T(T_hand_eye)[None],
        T_target,
        np.zeros(len(frames)),
    )
    return Scenario(problem, truth, sigma_px, T_hand_eye, T_target, T_base_tool_true)


def _r1_cell(
    rng: np.random.Generator,
    sigma_px: float,
    robot_noise_m: float,
    robot_noise_deg: float,
    options: ModelOptions | None,
    eye_in_hand: bool,
) -> Scenario:
    """R1's camera-board poses, with the camera on the tool or fixed in the cell."""
    target = Target.charuco(11, 8, 0.030, 0.022)
    T_base_board, poses = r1_poses()
    frames = []
    for k, T_bt in enumerate(poses):
        T_cam_board = inv_T(T_bt @ R1_T_TOOL_CAM) @ T_base_board
        # eye-to-hand: the same camera-board poses, the board moving with the tool
        T_base_tool = (
            T_bt if eye_in_hand else (R1_T_BASE_CAM @ T_cam_board @ inv_T(R1_T_TOOL_BOARD))
        )
        det = _detect(R1_K, R1_DIST, T_cam_board, target, (1280, 800), sigma_px, rng, 2.0)
        measured = _perturb(T_base_tool, rng, robot_noise_m, robot_noise_deg)
        frames.append(Frame(k, {"cam": det}, T_base_tool=measured))
    return r1_scenario(target, frames, eye_in_hand, options, sigma_px, T_base_board)


def r1(
    rng: np.random.Generator,
    sigma_px: float = 0.15,
    robot_noise_m: float = 5e-5,
    robot_noise_deg: float = 0.005,
    options: ModelOptions | None = None,
) -> Scenario:
    """R1 (docs/SETUPS.md): eye-in-hand UR5e-class cell, ChArUco 11 x 8 x 30 mm, 1280 x 800
    camera with distortion, 4 tilt groups of 5 frames, robot poses measured with noise."""
    return _r1_cell(rng, sigma_px, robot_noise_m, robot_noise_deg, options, True)


def r1_eye_to_hand(
    rng: np.random.Generator,
    sigma_px: float = 0.15,
    robot_noise_m: float = 5e-5,
    robot_noise_deg: float = 0.005,
    options: ModelOptions | None = None,
) -> Scenario:
    """R1 mirrored: the camera fixed in the cell, the board on the tool. The camera-board poses
    are R1's, so the tilt groups and translations carry over (the board moves, not the camera).
    """
    return _r1_cell(rng, sigma_px, robot_noise_m, robot_noise_deg, options, False)


# -- a real arm: systematic kinematic error (REALITY: accuracy is not repeatability) ------------
#: R1's cell placed in front of a UR5e so that every pose is reachable: turned 180 deg about
#: the base z axis, the board's origin at (0.5, 0, 0) m.
R1_IN_REACH = T_from_Rt(Rz(np.pi), np.zeros(3))


def _in_reach() -> np.ndarray:
    T_base_board, _ = r1_poses()
    S = R1_IN_REACH.copy()
    S[:3, 3] = np.array([0.5, 0.0, 0.0]) - S[:3, :3] @ T_base_board[:3, 3]
    return S


def real_arm_poses(
    planned: np.ndarray,
    rng: np.random.Generator,
    arm_mm: float = 1.0,
    arm_deg: float = 0.1,
    repeatability_mm: float = 0.03,
    repeatability_deg: float = 0.005,
) -> np.ndarray:
    """Where a UR5e with a random kinematic error really puts the tool for ``planned``
    ``T_base_tool`` poses (F, 4, 4): the controller's inverse kinematics (nominal model) gives
    the joints, the perturbed arm (``KinematicError.random`` with these sizes) the pose, plus
    the stop's repeatability error. The controller reports the planned poses."""
    from slidecal.mocks.robot import KinematicError

    ke = KinematicError.random(rng, arm_mm, arm_deg, repeatability_mm, repeatability_deg)
    out = np.empty_like(planned)
    q_prev = urk.Q_HOME
    for k, T in enumerate(planned):
        sols = [q for q in urk.ik(T, q_prev, urk.UR5E) if urk.singularity(q, urk.UR5E) is None]
        if not sols:
            raise ValueError(f"planned pose {k} is out of the UR5e's reach")
        q_prev = sols[0]
        dR = R_from_rvec(rng.normal(0.0, np.radians(repeatability_deg), 3))
        stop = T_from_Rt(dR, rng.normal(0.0, repeatability_mm / 1000.0, 3))
        out[k] = ke.fk(q_prev, urk.UR5E) @ stop
    return out


def r1_real_arm(
    rng: np.random.Generator,
    sigma_px: float = 0.15,
    arm_mm: float = 1.0,
    arm_deg: float = 0.1,
    *,
    eye_in_hand: bool = True,
    translations_only: bool = False,
    options: ModelOptions | None = None,
    detect: Callable[[np.ndarray, np.random.Generator], Detection] | None = None,
) -> Scenario:
    """R1 on a real arm: a UR5e (R1's cell within its reach) whose kinematics err by about
    ``arm_mm`` and ``arm_deg`` (:class:`slidecal.mocks.robot.KinematicError`, drawn anew from
    ``rng``); the measured poses are the planned ones, the camera sees the true ones.

    ``translations_only``: one orientation (R1's first tilt) and 12 translations of 40-80 mm in
    non-coplanar directions, the session of the issue's real data. ``detect``: the image model,
    ``T_cam_board -> Detection`` (default: R1's projected corners with ``sigma_px`` Gaussian
    noise). ``T_hand_eye`` and ``T_target`` are the physical truth; see
    :func:`effective_truth` for what the data can determine.
    """
    target = Target.charuco(11, 8, 0.030, 0.022)
    S = _in_reach()
    T_base_board, poses = r1_poses()
    T_base_board = S @ T_base_board
    poses = np.stack([S @ T for T in poses])
    if translations_only:
        base = poses[0]
        R_base_cam = (base @ R1_T_TOOL_CAM)[:3, :3]
        dirs = np.array(
            [
                [1.0, 0.0, -0.6],
                [0.0, 1.0, 0.7],
                [-0.7, -0.6, 1.0],
                [0.6, -0.8, -0.9],
                [0.9, 0.5, 0.4],
                [-0.5, 0.9, -0.5],
            ]
        )
        moves = [
            R_base_cam @ (d / np.linalg.norm(d)) * length for d in dirs for length in (0.05, -0.07)
        ]
        poses = np.stack([base] + [T_from_Rt(base[:3, :3], base[:3, 3] + m) for m in moves])
    if eye_in_hand:
        planned = poses
    else:  # the same camera-board poses, the board on the tool, the camera fixed
        planned = np.stack(
            [
                R1_T_BASE_CAM @ inv_T(T @ R1_T_TOOL_CAM) @ T_base_board @ inv_T(R1_T_TOOL_BOARD)
                for T in poses
            ]
        )
    true = real_arm_poses(planned, rng, arm_mm, arm_deg)
    if detect is None:

        def detect(T_cam_board: np.ndarray, g: np.random.Generator) -> Detection:
            return _detect(R1_K, R1_DIST, T_cam_board, target, (1280, 800), sigma_px, g, 2.0)

    frames = []
    for k, (T_true, T_meas) in enumerate(zip(true, planned, strict=True)):
        if eye_in_hand:
            T_cam_board = inv_T(T_true @ R1_T_TOOL_CAM) @ T_base_board
        else:
            T_cam_board = inv_T(R1_T_BASE_CAM) @ T_true @ R1_T_TOOL_BOARD
        frames.append(Frame(k, {"cam": detect(T_cam_board, rng)}, T_base_tool=T_meas))
    return r1_scenario(
        target, frames, eye_in_hand, options, sigma_px, T_base_board, T_base_tool_true=true
    )


def effective_truth(
    s: Scenario, sigma_rot_deg: float = 0.1, sigma_mm: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """The hand-eye and target pose ``(T_hand_eye, T_target)`` as the session can know them.

    A constant part of the arm's error is indistinguishable from a change of the hand-eye (in
    the tool frame) or of the target (in the base frame): no camera can tell them apart. The
    solver's per-frame pose corrections have a zero-mean prior, so it converges to the pair
    that leaves the smallest corrections (:func:`slidecal.mocks.cell.effective_truth`, which
    the session judge uses too). Physical truth and effective truth differ by the arm's
    constant error (about ``sigma_*``).
    """
    from slidecal.mocks.cell import effective_truth as _effective

    T_he, T_tg = _effective(
        s.problem.mount,
        s.T_base_tool_true,
        [f.T_base_tool for f in s.problem.frames],
        inv_T(s.truth.X[0]),  # X = T_cam_tool / T_cam_base
        s.truth.Y,
        sigma_rot_deg,
        sigma_mm,
    )
    return T_he, T_tg
