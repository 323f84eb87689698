"""Synthetic scenes with ground truth: the one place every set-up of docs/SETUPS.md is built.

Homography-level scenes for the stereo method (:func:`s5_scene`), calibration
problems with their truth (:class:`Scenario`: S1-S4, R1 and its real-arm variants, rigs, classic
hand-eye sessions), and the scenes the studies and tests share. Board frame:
z = 0 plane; S1-S5 in the paper's length units ("l.u."), R1 in metres. No images here: the
rendered-image simulator is ``mocks/camera.py``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from slidecal.drivers import ur_kinematics as urk
from slidecal.drivers.ur_pose import rpy_deg
from slidecal.mocks import cell
from slidecal.mocks.camera import SimCamera, oak_d_like, oak_d_like_extrinsics, single_camera
from slidecal.mocks.render import render_target
from slidecal.mocks.robot import KinematicError
from slidecal.solver import robot_error
from slidecal.solver.camera import K_matrix, project
from slidecal.solver.detect import detect as detect_target
from slidecal.solver.errors import InputError
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
from slidecal.solver.model import ModelState
from slidecal.solver.problem import (
    CalibrationProblem,
    CameraSpec,
    Detection,
    Frame,
    ModelOptions,
    Target,
)
from slidecal.solver.target_shape import PRINT_TOLERANCE, default_flatness_m, shape_modes

#: An image model: what a camera finds of the board at ``T_cam_board`` (4, 4), drawing noise
#: from the generator, the board bowed by ``bow_m`` (2,) (metres, ``solver/target_shape.py``'s
#: bow modes; zeros: flat)
ImageModel = Callable[[np.ndarray, np.random.Generator, np.ndarray], Detection]

NO_DISTORTION = (False, False, False, False, False)
#: S1-S5's images (pixels).
PAPER_SIZE_PX = (300, 240)
K_S1 = K_matrix(400.0, 400.0, 150.0, 120.0)
K_S2 = K_matrix(400.0, 440.0, 150.0, 120.0)
D0 = np.diag([1.0, -1.0, -1.0])  # camera looking at the board along -z (docs/SETUPS.md)


@dataclass(frozen=True)
class Scenario:
    """A synthetic problem with its truth: ``truth`` in the solver's parametrisation, ``T_tool_cam``
    or ``T_base_cam`` and ``T_base_board`` (4, 4) where a robot is involved, and the detections'
    pixel noise ``sigma_px``."""

    problem: CalibrationProblem
    truth: ModelState
    sigma_px: float
    T_hand_eye: np.ndarray | None = None
    T_target: np.ndarray | None = None
    T_base_tool_true: np.ndarray | None = None  # (F, 4, 4) where the arm really was


@dataclass(frozen=True)
class RigScenario(Scenario):
    """A rig :class:`Scenario`; ``sigma_by_camera_px``: each camera's pixel noise (``sigma_px`` the
    reference camera's)."""

    sigma_by_camera_px: Mapping[str, float] = field(default_factory=dict)


# -- homography-level scenes (the linear method's tests) ---------------------------------------
def board_xy(nx: int = 9, ny: int = 7, pitch: float = 5.0) -> np.ndarray:
    """Grid points (nx * ny, 2), board frame, centred on the origin."""
    x = (np.arange(nx) - (nx - 1) / 2) * pitch
    y = (np.arange(ny) - (ny - 1) / 2) * pitch
    X, Y = np.meshgrid(x, y)
    return np.column_stack([X.ravel(), Y.ravel()])


def tilt_R(ax_deg: float = 0.0, ay_deg: float = 0.0, order: str = "xy") -> np.ndarray:
    """``R_cam_board = D0 (Rx Ry)^T`` (order "xy") or ``D0 (Ry Rx)^T`` (order "yx")."""
    a, b = Rx(np.radians(ax_deg)), Ry(np.radians(ay_deg))
    M = a @ b if order == "xy" else b @ a
    return D0 @ M.T


def centre_on_axis(R_cam_board: np.ndarray, distance: float = 100.0) -> np.ndarray:
    """Camera centre (3,) in the board frame, ``distance`` from the origin on the optical axis."""
    return -distance * (R_cam_board.T @ np.array([0.0, 0.0, 1.0]))


def plane_pixels(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Pixels (..., N, 2) of board points ``xy`` (N, 2) through homographies ``H`` (..., 3, 3)."""
    X = np.column_stack([xy, np.ones(len(xy))])
    u = np.einsum("...ij,nj->...ni", H, X)
    return u[..., :2] / u[..., 2:3]


def s1_geometry(theta_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """S1's ``R_cam_board`` (tilted ``theta`` about the board's y axis) and first centre, 100
    l.u. from the grid centre on the optical axis."""
    R = D0 @ Ry(np.radians(theta_deg)).T
    return R, centre_on_axis(R)


def s2_geometry() -> tuple[np.ndarray, np.ndarray]:
    """S2/S3's ``R_cam_board`` (30 deg about x then 30 about y) and first centre."""
    R = tilt_R(30.0, 30.0)
    return R, centre_on_axis(R)


# -- calibration problems: S1-S4 ----------------------------------------------------------------
def projected_detection(
    K: np.ndarray,
    dist: np.ndarray,
    T_cam_board: np.ndarray,
    target: Target,
    size: tuple[int, int],
    sigma_px: float,
    rng: np.random.Generator,
    margin_px: float = 0.0,
) -> Detection:
    """The target's points that project into the image (``margin_px`` inside its border) at
    their true pixels plus ``sigma_px`` Gaussian noise per coordinate."""
    P = transform_points(T_cam_board, target.points_m)
    ok = P[:, 2] > 0
    px = np.full((len(P), 2), np.nan)
    px[ok] = project(K, dist, P[ok])
    w, h = size
    ok &= (px[:, 0] >= margin_px - 0.5) & (px[:, 0] <= w - 0.5 - margin_px)
    ok &= (px[:, 1] >= margin_px - 0.5) & (px[:, 1] <= h - 0.5 - margin_px)
    ids = np.flatnonzero(ok)
    return Detection(ids, px[ids] + rng.normal(0.0, sigma_px, (len(ids), 2)))


def _paper_scenario(
    K: np.ndarray,
    R_cam_board: np.ndarray,
    centres: np.ndarray,
    knowledge: str,
    options: ModelOptions,
    sigma_px: float,
    rng: np.random.Generator,
    presumed: np.ndarray | None = None,
) -> Scenario:
    """One orientation group; camera centres (n, 3) in the board frame, frame 0 the reference;
    ``presumed`` (n, 3): the centres the solver is told (default: the true ones). ``knowledge``
    "robot": known translations in an unknown robot frame (Case 1 and its generalisation), the
    base the board frame turned arbitrarily, the tool the camera; else motions in the board
    frame."""
    target = Target.points(board_xy())  # 9 x 7 points, pitch 5 l.u., centred on the origin
    dist = np.zeros(5)
    told = centres if presumed is None else presumed
    robot = knowledge == "robot"
    T_base_board = T_from_Rt(R_from_rvec(np.array([0.3, -0.2, 0.5])), np.array([10.0, -20.0, 5.0]))
    views = [T_from_Rt(R_cam_board, -R_cam_board @ C) for C in centres]
    poses = [T_base_board @ inv_T(T_from_Rt(R_cam_board, -R_cam_board @ C)) for C in told]
    cams = [SimCamera("cam", *PAPER_SIZE_PX, K, dist)]
    frames = _frames(views, poses, target, sigma_px, rng, cams=cams, margin_px=0.0)
    for k, C in enumerate(() if robot else told):  # motions in the board frame, no robot poses
        m = C - told[0]
        if knowledge == "board_direction":
            m = m / np.linalg.norm(m) if np.linalg.norm(m) > 0 else np.zeros(3)
        frames[k] = Frame(k, frames[k].detections, motion_board=m, group=0)
    problem = CalibrationProblem(
        target,
        (CameraSpec("cam", *PAPER_SIZE_PX),),
        tuple(frames),
        "eye_in_hand" if robot else "none",
        knowledge,
        options,
    )
    cam = ({"cam": K}, {"cam": dist}, {})
    if robot:
        truth = ModelState(*cam, np.eye(4)[None], T_base_board, np.zeros(len(centres)))
        return Scenario(problem, truth, sigma_px, np.eye(4), T_base_board)
    s = np.array([np.linalg.norm(c - centres[0]) for c in centres])
    return Scenario(problem, ModelState(*cam, views[0][None], np.eye(4), s), sigma_px)


def s1(
    theta_deg: float,
    sigma_px: float,
    rng: np.random.Generator,
    n_images: int = 5,
    step_error: float = 0.0,
) -> Scenario:
    """S1 (paper Table I): tilt ``theta`` about the board y axis, steps of known length 5 toward
    the grid centre; unit aspect, zero skew. ``step_error``: real steps are 5 (1 + e) (S4)."""
    R, C0 = s1_geometry(theta_deg)
    axis = R.T @ np.array([0.0, 0.0, 1.0])  # optical axis in the board frame
    steps = np.arange(n_images)[:, None] * 5.0
    centres = C0 + steps * (1.0 + step_error) * axis
    presumed = C0 + steps * axis
    opts = ModelOptions(unit_aspect=True, distortion=NO_DISTORTION)
    return _paper_scenario(K_S1, R, centres, "robot", opts, sigma_px, rng, presumed)


def s2(
    n_images: int,
    sigma_px: float,
    rng: np.random.Generator,
    phi_deg: float = 0.0,
    knowledge: str = "board_direction",
    options: ModelOptions | None = None,
) -> Scenario:
    """S2 (Tables II, III): tilted 30 deg about x then 30 about y, translated along the board
    normal toward the plane by steps of 5; direction known, lengths unknown; zero skew.
    ``phi_deg``: the real direction is rotated by phi about the board x axis (S4). ``knowledge``,
    ``options``: what the solver is told and solves for (default S2's; :func:`s3`)."""
    R, C0 = s2_geometry()
    normal = np.array([0.0, 0.0, 1.0]) * np.sign(-C0[2])  # toward the plane
    real = Rx(np.radians(phi_deg)) @ normal
    steps = np.arange(n_images)[:, None] * 5.0
    opts = options or ModelOptions(distortion=NO_DISTORTION)
    centres, presumed = C0 + steps * real, C0 + steps * normal
    return _paper_scenario(K_S2, R, centres, knowledge, opts, sigma_px, rng, presumed)


def s3(n_images: int, sigma_px: float, rng: np.random.Generator) -> Scenario:
    """S3 (Case 3): the S2 set-up with the full translation known; all five intrinsics."""
    opts = ModelOptions(skew=True, distortion=NO_DISTORTION)
    return s2(n_images, sigma_px, rng, 0.0, "board_translation", opts)


# -- S5: a stereo head (paper Figs. 7-9) --------------------------------------------------------
S5_K_LEFT = K_matrix(420.0, 410.0, 152.0, 118.0)
S5_K_RIGHT = K_matrix(400.0, 400.0, 150.0, 120.0)
# X_left = R X_right + t (docs/SETUPS.md S5): T_left_right, l.u.
S5_T_LEFT_RIGHT = T_from_Rt(R_from_rvec(np.radians([0.0, 5.0, 0.0])), np.array([-20.0, 0.0, 0.0]))
S5_VIEWS_DEG = ((20, 0, 0), (0, 20, 0), (-20, -20, 0), (15, -15, 10), (-10, 25, -5), (25, 10, 5))


def s5_T_right_board() -> np.ndarray:
    """The right camera's six view poses ``T_right_board`` (6, 4, 4), l.u. (docs/SETUPS.md S5)."""
    flip = np.diag([1.0, -1.0, -1.0])
    out = []
    for rv in S5_VIEWS_DEG:
        R = R_from_rvec(np.radians(rv)) @ flip
        centre_board = -130.0 * R[2]
        out.append(T_from_Rt(R, -R @ centre_board))
    return np.stack(out)


@dataclass(frozen=True)
class StereoScene:
    """Noise-free S5 set-up at the level of homographies, l.u. and pixels: ``board_xy`` (N, 2),
    ``K_left``, ``K_right``, ``X_left = R_left_right X_right + t_left_right``, and the right
    camera's view poses ``R_right_board`` (n, 3, 3), ``t_right_board`` (n, 3)."""

    board_xy: np.ndarray
    K_left: np.ndarray
    K_right: np.ndarray
    R_left_right: np.ndarray
    t_left_right: np.ndarray
    R_right_board: np.ndarray
    t_right_board: np.ndarray

    def _pair(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Left and right homographies (3, 3) of the right camera at ``(R, t)``."""
        Rl, tl = self.R_left_right @ R, self.R_left_right @ t + self.t_left_right
        return (
            self.K_left @ np.column_stack([Rl[:, 0], Rl[:, 1], tl]),
            self.K_right @ np.column_stack([R[:, 0], R[:, 1], t]),
        )

    def homographies(self) -> tuple[np.ndarray, np.ndarray]:
        """True plane-to-pixel homographies (n, 3, 3) of the left and the right camera."""
        views = zip(self.R_right_board, self.t_right_board, strict=True)
        left, right = zip(*(self._pair(R, t) for R, t in views), strict=True)
        return np.array(left), np.array(right)

    def translated(
        self, views: Sequence[int], steps_board: np.ndarray
    ) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The head translated by ``steps_board`` (n, 3) (board frame, l.u.) at each of the
        ``views``: per view, the left and the right camera's homographies (n, 3, 3)."""
        left, right = [], []
        for v in views:
            R = self.R_right_board[v]
            # the camera centre moves by T (eqs. 12-13)
            pairs = [self._pair(R, self.t_right_board[v] - R @ T) for T in steps_board]
            left.append(np.array([p[0] for p in pairs]))
            right.append(np.array([p[1] for p in pairs]))
        return left, right

    def pixels(self) -> tuple[np.ndarray, np.ndarray]:
        """True image points (n, N, 2) of the grid in the left and the right camera."""
        H_l, H_r = self.homographies()
        return plane_pixels(H_l, self.board_xy), plane_pixels(H_r, self.board_xy)


def s5_scene() -> StereoScene:
    """The S5 set-up of docs/SETUPS.md (14 x 10 grid, pitch 5 l.u., six stereo views)."""
    Ts = s5_T_right_board()
    return StereoScene(
        board_xy=board_xy(14, 10),
        K_left=S5_K_LEFT,
        K_right=S5_K_RIGHT,
        R_left_right=S5_T_LEFT_RIGHT[:3, :3],
        t_left_right=S5_T_LEFT_RIGHT[:3, 3],
        R_right_board=Ts[:, :3, :3],
        t_right_board=Ts[:, :3, 3],
    )


def s5_rig(
    rng: np.random.Generator,
    sigma_px: float = 0.5,
    left_factor: float = 1.0,
    options: ModelOptions | None = None,
) -> RigScenario:
    """S5 as a general-motion rig problem (knowledge and mount "none", reference "right"):
    ``sigma_px`` the right camera's noise, ``left_factor`` times it the left's; zero skew, no
    distortion; points outside the 300 x 240 images not detected."""
    target = Target.points(board_xy(14, 10))
    Ts = s5_T_right_board()
    sig = {"left": left_factor * sigma_px, "right": sigma_px}
    K = {"left": S5_K_LEFT, "right": S5_K_RIGHT}
    cams = [SimCamera(c, *PAPER_SIZE_PX, K[c], np.zeros(5)) for c in K]
    T_cam_right = {"left": S5_T_LEFT_RIGHT}
    frames = _frames(Ts, [None] * len(Ts), target, sig, rng, cams=cams, T_cam_ref=T_cam_right)
    problem = CalibrationProblem(
        target,
        (CameraSpec("left", *PAPER_SIZE_PX), CameraSpec("right", *PAPER_SIZE_PX)),
        tuple(frames),
        "none",
        "none",
        options or ModelOptions(distortion=NO_DISTORTION),
        reference_camera="right",
    )
    truth = ModelState(
        {c: K[c].copy() for c in K},
        {c: np.zeros(5) for c in K},
        {"left": S5_T_LEFT_RIGHT.copy()},
        Ts,
        np.eye(4),
        np.zeros(len(Ts)),
    )
    return RigScenario(problem, truth, sigma_px, sigma_by_camera_px=sig)


# -- R1: a UR5e-class cell, eye-in-hand or eye-to-hand ------------------------------------------
R1_CAM = single_camera()
R1_SIZE_PX, R1_K, R1_DIST = (R1_CAM.width, R1_CAM.height), R1_CAM.K, R1_CAM.dist
R1_T_TOOL_CAM = T_from_Rt(
    R_from_rvec(np.radians([1.5, -2.0, 90.0])), np.array([0.035, -0.06, 0.09])
)


def r1_target() -> Target:
    """R1's ChArUco board: 11 x 8 squares of 30 mm, 22 mm markers."""
    return Target.charuco(11, 8, 0.030, 0.022)


def r1_poses() -> tuple[np.ndarray, np.ndarray]:
    """The R1 cell: ``T_base_board`` and the planned ``T_base_tool`` (20, 4, 4): 4 tilt groups of 25
    deg looking at the board centre from 0.5 m, each its pose and 4 non-coplanar translations of
    40-80 mm."""
    target = r1_target()
    centre_board = target.points_m.mean(axis=0)
    # board frame: +z into the table (down), so a camera above reads the print (R_cam_board ~ I)
    R_base_board = np.diag([1.0, -1.0, -1.0])
    T_base_board = T_from_Rt(R_base_board, np.array([0.55, -0.10, 0.02]))
    centre = transform_points(T_base_board, centre_board[None])[0]
    up = np.array([1.0, 0.0, 0.0])  # image up away from the robot base
    tilts = [(25.0, 0.0), (0.0, 25.0), (-20.0, -18.0), (18.0, -20.0)]
    moves_mm = np.array(
        [[60.0, 0.0, -40.0], [0.0, 50.0, 45.0], [-35.0, -30.0, 55.0], [30.0, -40.0, -50.0]]
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
    cam: SimCamera = R1_CAM,
    T_base_tool_true: np.ndarray | None = None,
    T_tool_board: np.ndarray = R1_T_TOOL_BOARD,
) -> Scenario:
    """The scenario of R1's camera (or ``cam``) with these ``frames``: the problem, the truth in
    the solver's parametrisation and the hand-eye and target poses of the mount (the target on
    the tool at ``T_tool_board`` eye-to-hand)."""
    problem = CalibrationProblem(
        target,
        (CameraSpec("cam", *R1_SIZE_PX),),
        tuple(frames),
        "eye_in_hand" if eye_in_hand else "eye_to_hand",
        "robot",
        options or ModelOptions(),
    )
    T_hand_eye = R1_T_TOOL_CAM if eye_in_hand else R1_T_BASE_CAM
    T_target = T_base_board if eye_in_hand else T_tool_board
    truth = ModelState(
        {"cam": cam.K},
        {"cam": cam.dist},
        {},
        inv_T(T_hand_eye)[None],
        T_target,
        np.zeros(len(frames)),
    )
    return Scenario(problem, truth, sigma_px, T_hand_eye, T_target, T_base_tool_true)


def _tool_pose(
    T_cam_board: np.ndarray,
    T_base_board: np.ndarray,
    eye_in_hand: bool,
    T_tool_board: np.ndarray = R1_T_TOOL_BOARD,
) -> np.ndarray:
    """The ``T_base_tool`` putting R1's camera at ``T_cam_board``: on the tool, the board at
    ``T_base_board``; or fixed at ``R1_T_BASE_CAM``, the board on the tool at ``T_tool_board``."""
    if eye_in_hand:
        return T_base_board @ inv_T(T_cam_board) @ inv_T(R1_T_TOOL_CAM)
    return R1_T_BASE_CAM @ T_cam_board @ inv_T(T_tool_board)


def _view(
    T_base_tool: np.ndarray,
    T_base_board: np.ndarray,
    eye_in_hand: bool = True,
    T_tool_board: np.ndarray = R1_T_TOOL_BOARD,
) -> np.ndarray:
    """R1's camera's ``T_cam_board`` with the tool at ``T_base_tool``: :func:`_tool_pose`'s
    inverse."""
    if eye_in_hand:
        return inv_T(T_base_tool @ R1_T_TOOL_CAM) @ T_base_board
    return inv_T(R1_T_BASE_CAM) @ T_base_tool @ T_tool_board


def _frames(
    views: Sequence[np.ndarray],
    told: Sequence[np.ndarray | None],
    target: Target,
    sigma_px: float | Mapping[str, float],
    rng: np.random.Generator,
    noise: tuple[float, float] = (0.0, 0.0),
    detect: ImageModel | None = None,
    bow_m: np.ndarray | None = None,
    cams: Sequence[SimCamera] = (R1_CAM,),
    T_cam_ref: Mapping[str, np.ndarray] | None = None,
    margin_px: float = 2.0,
) -> list[Frame]:
    """Per pose ``views[k]`` (``T_cam_board`` of the first camera; camera ``c``'s is
    ``T_cam_ref[c]`` times it), what each of ``cams`` (default R1's) finds of ``target``
    (``detect``'s image model, the board bowed by ``bow_m``; or the projected points
    ``margin_px`` inside the image with ``sigma_px`` noise, one or per camera), then the robot
    pose ``told[k]`` with ``noise`` (metres, degrees) as the arm measures it."""
    sig = sigma_px if isinstance(sigma_px, Mapping) else {c.name: sigma_px for c in cams}
    frames = []
    for k, (T_cam_board, T_base_tool) in enumerate(zip(views, told, strict=True)):
        dets = {}
        for c in cams:
            T = (T_cam_ref or {}).get(c.name, np.eye(4)) @ T_cam_board
            if detect is not None:
                dets[c.name] = detect(T, rng, np.zeros(2) if bow_m is None else bow_m)
            else:
                size, sigma = (c.width, c.height), sig[c.name]
                dets[c.name] = projected_detection(
                    c.K, c.dist, T, target, size, sigma, rng, margin_px
                )
        frames.append(Frame(k, dets, T_base_tool=_perturb(T_base_tool, rng, *noise)))
    return frames


def r1(
    rng: np.random.Generator,
    sigma_px: float = 0.15,
    robot_noise_m: float = 5e-5,
    robot_noise_deg: float = 0.005,
    options: ModelOptions | None = None,
    eye_in_hand: bool = True,
    dist: np.ndarray = R1_DIST,
) -> Scenario:
    """R1 (docs/SETUPS.md): eye-in-hand UR5e-class cell, ChArUco 11 x 8 x 30 mm, 1280 x 800
    camera with distortion, 4 tilt groups of 5 frames, robot poses measured with noise.
    ``eye_in_hand`` False: R1 mirrored, the camera fixed in the cell and the board on the tool;
    the camera-board poses are R1's, so the tilt groups and translations carry over. ``dist``:
    the lens (its length names the model, ``solver/camera.py``)."""
    target = r1_target()
    T_base_board, poses = r1_poses()
    views = [_view(T, T_base_board) for T in poses]
    told = poses if eye_in_hand else [_tool_pose(T, T_base_board, False) for T in views]
    noise = (robot_noise_m, robot_noise_deg)
    cam = replace(R1_CAM, dist=dist)
    frames = _frames(views, told, target, sigma_px, rng, noise, cams=[cam])
    return r1_scenario(target, frames, eye_in_hand, options, sigma_px, T_base_board, cam)


#: A wide M12 lens on R1's sensor (about 100 deg across, 120 deg diagonal): OpenCV's rational model
#: fitted to an equidistant lens of 720 px per radian out to 62 deg off the axis (within 0.8 px).
WIDE_K = K_matrix(720.0, 720.0, 640.0, 400.0)
WIDE_RATIONAL = np.array([0.956, 0.185, 5e-4, -3e-4, 0.004, 1.289, 0.414, 0.027])


def wide_r1(
    rng: np.random.Generator,
    sigma_px: float = 0.15,
    options: ModelOptions | None = None,
    dist: np.ndarray = WIDE_RATIONAL,
) -> Scenario:
    """R1's cell with a wide lens (``WIDE_K``, ``dist``) and exact robot poses: 4 orientations
    20-40 deg off the board normal from 0.15-0.25 m, aimed within 0.12 m of the board's centre so
    that it reaches the image's edges, each with 4 translations of 30-60 mm (20 frames, a fixed
    plan as R1's; ``rng`` draws the pixel noise)."""
    target = r1_target()
    T_base_board, _ = r1_poses()
    plan = np.random.default_rng(38)
    views = _translated(
        camera_board_poses(plan, 4, target, (0.15, 0.25), (20.0, 40.0), aim_spread_m=0.12), plan, 5
    )
    told = [_tool_pose(T, T_base_board, True) for T in views]
    cam = replace(R1_CAM, K=WIDE_K, dist=dist)
    frames = _frames(views, told, target, sigma_px, rng, cams=[cam])
    return r1_scenario(target, frames, True, options, sigma_px, T_base_board, cam)


# -- a real arm: systematic kinematic error (REALITY: accuracy is not repeatability) ------------
#: R1's cell placed in front of a UR5e so that every pose is reachable: turned 180 deg about
#: the base z axis, the board's origin at (0.5, 0, 0) m.
R1_IN_REACH = T_from_Rt(Rz(np.pi), np.zeros(3))


def _in_reach() -> tuple[np.ndarray, np.ndarray]:
    """:func:`r1_poses` moved by ``R1_IN_REACH``."""
    T_base_board, poses = r1_poses()
    S = R1_IN_REACH.copy()
    S[:3, 3] = np.array([0.5, 0.0, 0.0]) - S[:3, :3] @ T_base_board[:3, 3]
    return S @ T_base_board, np.stack([S @ T for T in poses])


def real_arm_poses(
    planned: np.ndarray,
    rng: np.random.Generator,
    arm_mm: float = 1.0,
    arm_deg: float = 0.1,
    repeatability_mm: float = 0.03,
    repeatability_deg: float = 0.005,
) -> np.ndarray:
    """Where a UR5e with a random kinematic error (``KinematicError.random`` of these sizes) really
    puts the tool for ``planned`` ``T_base_tool`` (F, 4, 4), plus each stop's repeatability error.
    Each pose's joints are the solution nearest the previous pose's, from the configuration a walk
    from ``Q_HOME`` ends in, so every frame stands on one configuration."""
    ke = KinematicError.random(rng, arm_mm, arm_deg, repeatability_mm, repeatability_deg)
    q_prev = urk.Q_HOME
    for _ in range(2):  # the first walk finds the configuration, the second starts in it
        joints = []
        for k, T in enumerate(planned):
            sols = [q for q in urk.ik(T, q_prev, urk.UR5E) if urk.singularity(q, urk.UR5E) is None]
            if not sols:
                raise ValueError(f"planned pose {k} is out of the UR5e's reach")
            q_prev = sols[0]
            joints.append(q_prev)
    return np.stack([ke.fk(q, urk.UR5E) @ ke.stop_error(rng) for q in joints])


def r1_real_arm(
    rng: np.random.Generator,
    sigma_px: float = 0.15,
    arm_mm: float = 1.0,
    arm_deg: float = 0.1,
    *,
    eye_in_hand: bool = True,
    translations_only: bool = False,
    options: ModelOptions | None = None,
    detect: ImageModel | None = None,
    real_board: bool = False,
) -> Scenario:
    """R1 on a UR5e whose kinematics err by about ``arm_mm`` and ``arm_deg`` (drawn from ``rng``):
    the measured poses are the planned ones, the camera sees the true ones.

    ``translations_only``: one orientation, 12 non-coplanar translations of 40-80 mm. ``detect``:
    the image model (default: projected corners with ``sigma_px`` noise). ``real_board``: a bowed
    board described with a real board's tolerance (:func:`real_board_of`). What the data can
    determine of the truth: :func:`effective_truth`.
    """
    target = seen = r1_target()
    bow = np.zeros(2)
    if real_board:
        target, seen, bow = real_board_of(target, rng)
    T_base_board, poses = _in_reach()
    if translations_only:
        poses = np.stack([poses[0], *_r1_translations(poses[0])])
    planned = poses
    if not eye_in_hand:  # the same camera-board poses, the board on the tool, the camera fixed
        planned = np.stack([_tool_pose(_view(T, T_base_board), T_base_board, False) for T in poses])
    true = real_arm_poses(planned, rng, arm_mm, arm_deg)
    views = [_view(T, T_base_board, eye_in_hand) for T in true]
    frames = _frames(views, planned, seen, sigma_px, rng, detect=detect, bow_m=bow)
    return r1_scenario(
        target, frames, eye_in_hand, options, sigma_px, T_base_board, T_base_tool_true=true
    )


def _r1_translations(T_base_tool: np.ndarray) -> list[np.ndarray]:
    """12 pure translations of ``T_base_tool`` by 50 and -70 mm in 6 non-coplanar directions of
    R1's camera axes."""
    R_base_cam = (T_base_tool @ R1_T_TOOL_CAM)[:3, :3]
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
    moves = [R_base_cam @ (d / np.linalg.norm(d)) * s for d in dirs for s in (0.05, -0.07)]
    return [T_from_Rt(T_base_tool[:3, :3], T_base_tool[:3, 3] + m) for m in moves]


def symmetric_board_r1(
    rng: np.random.Generator,
    sigma_px: float = 0.15,
    robot_noise_m: float = 5e-5,
    robot_noise_deg: float = 0.005,
    rolled: Sequence[int] = (),
) -> Scenario:
    """R1 mirrored (:func:`r1` with ``eye_in_hand`` False) with an 8 x 6-square chessboard of 30 mm
    on the tool, a board that looks the same after a half turn: R1's 20 frames and 13 more at its
    first orientation (its pure translations, :func:`_r1_translations`), 33 frames. The frames
    ``rolled`` have the tool turned so that the board turns 150 deg about its centre in view."""
    target = Target.chessboard(8, 6, 0.030)
    c = target.points_m.mean(axis=0)
    roll = T_from_Rt(Rz(np.radians(150.0)), c - Rz(np.radians(150.0)) @ c)
    T_base_board, poses = r1_poses()
    tools = [*poses, *_r1_translations(poses[0]), poses[0]]
    views = [
        _view(T, T_base_board) @ (roll if k in rolled else np.eye(4)) for k, T in enumerate(tools)
    ]
    told = [_tool_pose(T, T_base_board, False) for T in views]
    frames = _frames(views, told, target, sigma_px, rng, (robot_noise_m, robot_noise_deg))
    return r1_scenario(target, frames, False, None, sigma_px, T_base_board)


def real_board_of(target: Target, rng: np.random.Generator) -> tuple[Target, Target, np.ndarray]:
    """A real board of ``target``'s description: (the target as a session describes it, with a real
    board's tolerance; the bowed board the camera sees; the bow (2,), metres)."""
    flat = default_flatness_m(target.points_m)
    described = replace(target, flatness_m=flat, print_tolerance=PRINT_TOLERANCE)
    bow = rng.normal(0.0, flat, 2)
    modes = shape_modes(target, target.points_m)
    seen = replace(target, points_m=target.points_m + bow[0] * modes[3] + bow[1] * modes[4])
    return described, seen, bow


def effective_truth(
    s: Scenario,
    sigma_rot_deg: float = 0.1,
    sigma_mm: float = 1.0,
    frames: Sequence[int] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The hand-eye and target pose ``(T_hand_eye, T_target)`` as the session can know them (over
    ``frames``, default all): :func:`slidecal.solver.robot_error.effective_truth`."""
    used = list(range(len(s.problem.frames)) if frames is None else frames)
    true = s.T_base_tool_true
    return robot_error.effective_truth(
        s.problem.mount,
        true if true is None else true[used],
        [s.problem.frames[i].T_base_tool for i in used],
        inv_T(s.truth.X[0]),  # X = T_cam_tool / T_cam_base
        s.truth.Y,
        sigma_rot_deg,
        sigma_mm,
    )


# -- rigs on R1: the OAK-D-like head --------------------------------------------------------------
def oak_rig(
    rng: np.random.Generator,
    sigma_px: float | Mapping[str, float] = 0.15,
    cameras: Sequence[str] = ("left", "right"),
    robot_noise_m: float = 0.0,
    robot_noise_deg: float = 0.0,
    options: ModelOptions | None = None,
    view_offset_deg: float = 20.0,
) -> RigScenario:
    """The OAK-D-like head eye-in-hand on the R1 cell; reference camera "left".

    ``sigma_px``: corner noise, one or per camera. ``cameras``: of "left", "right", "rgb" (with
    "left"). ``robot_noise_m``, ``robot_noise_deg``: one-sigma noise of the measured poses.
    ``view_offset_deg``: the left camera turned about its y axis by this, the board off-centre.
    Corners outside an image (2 px margin) are not detected.
    """
    sims = {c.name: c for c in oak_d_like()}
    cameras = tuple(cameras)
    if "left" not in cameras or any(c not in sims for c in cameras):
        raise InputError(f"cameras must include 'left' and be among {list(sims)}, got {cameras}")
    sig = {c: float(sigma_px[c] if isinstance(sigma_px, Mapping) else sigma_px) for c in cameras}
    extr = oak_d_like_extrinsics()
    T_tool_left = R1_T_TOOL_CAM @ T_from_Rt(Ry(np.radians(view_offset_deg)), np.zeros(3))
    target = r1_target()
    T_base_board, poses = r1_poses()
    views = [inv_T(T @ T_tool_left) @ T_base_board for T in poses]
    noise = (robot_noise_m, robot_noise_deg)
    cams = [sims[c] for c in cameras]
    frames = _frames(views, poses, target, sig, rng, noise, cams=cams, T_cam_ref=extr)
    problem = CalibrationProblem(
        target,
        tuple(sims[c].spec for c in cameras),
        tuple(frames),
        "eye_in_hand",
        "robot",
        options or ModelOptions(),
        reference_camera="left",
    )
    truth = ModelState(
        {c: sims[c].K.copy() for c in cameras},
        {c: sims[c].dist.copy() for c in cameras},
        {c: extr[c].copy() for c in cameras if c != "left"},
        inv_T(T_tool_left)[None],
        T_base_board,
        np.zeros(len(poses)),
    )
    return RigScenario(
        problem, truth, sig["left"], T_tool_left, T_base_board, sigma_by_camera_px=sig
    )


# -- classic hand-eye sessions: every frame at its own orientation (R1's cell) -----------------
def square_tag(side_m: float = 0.08) -> Target:
    """A single square tag's 4 corners (an AprilTag's outer corners), centred on the origin."""
    h = side_m / 2.0
    return Target.points(np.array([[-h, -h], [h, -h], [h, h], [-h, h]]))


def camera_board_poses(
    rng: np.random.Generator,
    n_orientations: int,
    target: Target,
    distance_m: tuple[float, float] = (0.45, 0.6),
    tilt_deg: tuple[float, float] = (15.0, 35.0),
    roll_deg: float = 30.0,
    aim_spread_m: float = 0.06,
) -> np.ndarray:
    """``T_cam_board`` (n, 4, 4), each at its own orientation: the camera looks from ``distance_m``
    at a point within ``aim_spread_m`` of the target centre, tilted ``tilt_deg`` from the board
    normal toward a random azimuth and rolled by up to ``roll_deg``."""
    centre = target.points_m.mean(axis=0)
    out = []
    for _ in range(n_orientations):
        az = rng.uniform(0.0, 2.0 * np.pi)
        tilt = np.radians(rng.uniform(*tilt_deg))
        # board frame: +z into the board, so a camera in front sits at negative z
        view = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
        aim = centre + np.array([*rng.uniform(-aim_spread_m, aim_spread_m, 2), 0.0])
        p_cam = aim + rng.uniform(*distance_m) * view
        up = np.array([0.0, -1.0, 0.0])  # board -y appears up in the image
        roll = R_from_rvec([0.0, 0.0, np.radians(rng.uniform(-roll_deg, roll_deg))])
        R_cam_board = roll @ look_at_R_cam_world(p_cam, aim, up)
        out.append(T_from_Rt(R_cam_board, -R_cam_board @ p_cam))
    return np.array(out)


def _translated(
    T_cam_board: np.ndarray, rng: np.random.Generator, per_orientation: int
) -> np.ndarray:
    """Each pose followed by ``per_orientation - 1`` translated copies (30-60 mm moves of the
    camera in non-coplanar directions, each with a component along the optical axis)."""
    out = []
    for T in T_cam_board:
        out.append(T)
        dirs = np.array([[1.0, 0.2, 0.6], [-0.3, 1.0, 0.5], [0.4, -0.6, -0.8], [-0.8, -0.4, 0.7]])
        for k in range(per_orientation - 1):
            d = dirs[k % len(dirs)] / np.linalg.norm(dirs[k % len(dirs)])
            move_cam = rng.uniform(0.03, 0.06) * d  # camera displacement, camera axes
            Tk = T.copy()
            Tk[:3, 3] -= move_cam  # p_cam' = p_cam - move: the camera moved by +move
            out.append(Tk)
    return np.array(out)


def classic_real_arm(
    rng: np.random.Generator,
    n_frames: int = 28,
    sigma_px: float = 0.15,
    arm_mm: float = 1.0,
    arm_deg: float = 0.1,
    eye_in_hand: bool = True,
    detect: ImageModel | None = None,
    arm_scale: float = 0.0,
) -> Scenario:
    """A classic hand-eye session (:func:`camera_board_poses`) on a UR5e whose kinematics err by
    about ``arm_mm`` and ``arm_deg``; views out of reach are drawn again. ``detect``: as
    :func:`r1_real_arm`'s. ``arm_scale``: the true positions are ``1 + arm_scale`` times as far from
    the base as the reported ones."""
    target = r1_target()
    T_base_board = _in_reach()[0]
    views: list[np.ndarray] = []
    while len(views) < n_frames:
        for T in camera_board_poses(rng, 2 * n_frames, target):
            if urk.reachable(_tool_pose(T, T_base_board, eye_in_hand), None, urk.UR5E):
                views.append(T)
                if len(views) == n_frames:
                    break
    planned = np.stack([_tool_pose(T, T_base_board, eye_in_hand) for T in views])
    true = real_arm_poses(planned, rng, arm_mm, arm_deg)
    true[:, :3, 3] *= 1.0 + arm_scale
    views = [_view(T, T_base_board, eye_in_hand) for T in true]
    frames = _frames(views, planned, target, sigma_px, rng, detect=detect)
    return r1_scenario(
        target, frames, eye_in_hand, None, sigma_px, T_base_board, T_base_tool_true=true
    )


#: The tag session's 7 orientations of the tag seen by the camera: (tilt about x, tilt about y,
#: roll) deg
TAG_TILTS_DEG = (
    (0, 0, 0),
    (30, 0, 10),
    (-30, 0, -10),
    (0, 30, 20),
    (0, -30, -20),
    (22, 22, 30),
    (-22, -22, -30),
)
#: The tag on the tool, facing away from the flange a few centimetres off its axis
TAG_T_TOOL_TAG = T_from_Rt(
    R_from_rvec(np.radians([180.0, 0.0, 0.0])), np.array([0.03, -0.02, 0.02])
)


def tag_real_arm(
    rng: np.random.Generator,
    n_frames: int = 205,
    sigma_px: float = 0.1,
    arm_mm: float = 0.8,
    arm_deg: float = 0.08,
    side_m: float = 0.10,
    detect: ImageModel | None = None,
) -> Scenario:
    """Eye-to-hand with one AprilTag (``side_m``) on the tool and R1's fixed camera: ``n_frames`` in
    the orientations of ``TAG_TILTS_DEG`` at random places 0.45-0.85 m away, on a UR5e erring by
    about ``arm_mm`` and ``arm_deg``; a tag reaching the border keeps the corners inside."""
    target = square_tag(side_m)
    w, h = R1_SIZE_PX
    planned: list[np.ndarray] = []
    per = [n_frames // 7 + (o < n_frames % 7) for o in range(7)]
    for (ax, ay, rz), n in zip(TAG_TILTS_DEG, per, strict=True):
        R = Rz(np.radians(rz)) @ Rx(np.radians(ax)) @ Ry(np.radians(ay))
        group: list[np.ndarray] = []
        for _ in range(200 * n):
            if len(group) == n:
                break
            z = rng.uniform(0.45, 0.85)
            u, v = rng.uniform(0.12 * w, 0.88 * w), rng.uniform(0.15 * h, 0.85 * h)
            ray = np.array([(u - R1_K[0, 2]) / R1_K[0, 0], (v - R1_K[1, 2]) / R1_K[1, 1], 1.0])
            T = R1_T_BASE_CAM @ T_from_Rt(R, z * ray) @ inv_T(TAG_T_TOOL_TAG)
            if urk.reachable(T, None, urk.UR5E):
                group.append(T)
        if len(group) < n:
            raise ValueError("the tag session's views are out of the UR5e's reach")
        planned += group
    planned_a = np.stack(planned)
    true = real_arm_poses(planned_a, rng, arm_mm, arm_deg)
    views = [_view(T, np.eye(4), False, TAG_T_TOOL_TAG) for T in true]
    frames = _frames(views, planned_a, target, sigma_px, rng, detect=detect)
    return r1_scenario(
        target,
        frames,
        False,
        None,
        sigma_px,
        np.eye(4),
        T_base_tool_true=true,
        T_tool_board=TAG_T_TOOL_TAG,
    )


def classic(
    rng: np.random.Generator,
    n_frames: int = 20,
    sigma_px: float = 0.15,
    robot_noise_m: float = 5e-5,
    robot_noise_deg: float = 0.005,
    eye_in_hand: bool = True,
    options: ModelOptions | None = None,
    target: Target | None = None,
    per_orientation: int = 1,
    distortion: np.ndarray | None = None,
    T_cam_board: np.ndarray | None = None,
) -> Scenario:
    """A classic hand-eye session in the R1 cell: ``n_frames`` orientations, all different.

    ``per_orientation``: translated frames per orientation (a mixed session). ``target``,
    ``distortion`` (5,): R1's by default. ``robot_noise_m``, ``robot_noise_deg``: one-sigma noise of
    the measured poses. ``T_cam_board`` (n, 4, 4): fixed views, ``rng`` then drawing only the noise.
    """
    target = target or r1_target()
    cam = R1_CAM if distortion is None else replace(R1_CAM, dist=distortion)
    if T_cam_board is None:
        T_cam_board = camera_board_poses(rng, n_frames, target)
    T_cb = _translated(np.asarray(T_cam_board, dtype=float), rng, per_orientation)
    T_base_board = r1_poses()[0]
    told = [_tool_pose(T, T_base_board, eye_in_hand) for T in T_cb]
    noise = (robot_noise_m, robot_noise_deg)
    frames = _frames(T_cb, told, target, sigma_px, rng, noise, cams=[cam])
    return r1_scenario(target, frames, eye_in_hand, options, sigma_px, T_base_board, cam)


#: The single-camera cells without any noise (pixels, robot poses), by name: a solve of each
#: must return its truth to round-off (the pipeline's and the refinement's tests).
NOISE_FREE: dict[str, Callable[[np.random.Generator], Scenario]] = {
    "R1": lambda rng: r1(rng, 0.0, 0.0, 0.0),
    "R1-eye-to-hand": lambda rng: r1(rng, 0.0, 0.0, 0.0, eye_in_hand=False),
    "S1": lambda rng: s1(30.0, 0.0, rng),
    "S2": lambda rng: s2(5, 0.0, rng),
    "S3": lambda rng: s3(5, 0.0, rng),
}


# --------------------------------------------- scenes of the studies and the tests built on them
def render_detector(tag_m: float | None = None) -> ImageModel:
    """The ``render`` image model: R1's camera renders the board (bowed as the trial's board is),
    the detector finds it; with ``tag_m``: one flat AprilTag of that side (36h11, id 0, a white
    margin of one cell on the tool's darker surround) and its 4 corners (ids 0-3 in the centred
    frame of :func:`square_tag`)."""
    cam = single_camera()
    target = r1_target() if tag_m is None else Target.apriltag(tag_m)
    T_board_seen = np.eye(4)  # square_tag's centred frame <- the tag's (origin at a corner)
    if tag_m is not None:
        T_board_seen = T_from_Rt(np.eye(3), np.array([-tag_m / 2, -tag_m / 2, 0.0]))

    def run(T_cam_board: np.ndarray, rng: np.random.Generator, bow_m: np.ndarray) -> Detection:
        bow = (bow_m[0], bow_m[1]) if tag_m is None else (0.0, 0.0)
        image = render_target(target, cam, T_cam_board @ T_board_seen, rng, bow_m=bow)
        return detect_target(image, target).detection

    return run


def drifting_arm(
    rng: np.random.Generator,
    sigma_px: float = 0.15,
    drift_deg: float = 0.06,
    over_m: float = 0.06,
    detect: ImageModel | None = None,
) -> tuple[Scenario, np.ndarray]:
    """The one-orientation session of ``r1_real_arm`` on an arm whose orientation drifts linearly
    along the moves: a random ``D`` (rad/m, largest gain ``drift_deg`` per ``over_m``) turns the
    tool by ``D (t - mean t)``, plus repeatability per stop. Returns the scenario and ``D``."""
    base = r1_real_arm(rng, sigma_px, translations_only=True)
    T_meas = np.stack([f.T_base_tool for f in base.problem.frames])
    D = rng.normal(size=(3, 3))
    D *= np.radians(drift_deg) / over_m / np.linalg.norm(D, 2)
    t0 = T_meas[:, :3, 3].mean(axis=0)
    target, frames, true = base.problem.target, [], []
    for T in T_meas:
        e = D @ (T[:3, 3] - t0) + rng.normal(0.0, np.radians(0.003), 3)
        T_true = T_from_Rt(R_from_rvec(e) @ T[:3, :3], T[:3, 3] + rng.normal(0.0, 2e-5, 3))
        true.append(T_true)
        view = [_view(T_true, base.T_target)]
        frames += _frames(view, [T], target, sigma_px, rng, detect=detect)
    frames = [replace(f, id=k) for k, f in enumerate(frames)]
    scenario = r1_scenario(
        target, frames, True, None, sigma_px, base.T_target, T_base_tool_true=np.stack(true)
    )
    return scenario, D


#: the one-tag session's corner noise (px) and robot pose noise (metres per axis, degrees per
#: rotation-vector component): the classic hand-eye study's levels
ONE_TAG_SIGMA_PX = 0.15
ONE_TAG_ROBOT_NOISE = (5e-5, 0.005)


def one_tag_geometry() -> np.ndarray:
    """The one-tag row's camera-board poses: 7 orientations of an 8 cm tag (seed 7)."""
    return camera_board_poses(np.random.default_rng(7), 7, square_tag(0.08), aim_spread_m=0.15)


def one_tag_session(rng: np.random.Generator, geometry: np.ndarray) -> Scenario:
    """The one-tag row's session: eye-to-hand, 5 frames at each of ``geometry``'s 7
    orientations, the tag's 4 corners, no distortion."""
    return classic(
        rng,
        7,
        ONE_TAG_SIGMA_PX,
        *ONE_TAG_ROBOT_NOISE,
        eye_in_hand=False,
        options=ModelOptions(
            distortion=NO_DISTORTION,
            robot_noise_m=ONE_TAG_ROBOT_NOISE[0],
            robot_noise_deg=ONE_TAG_ROBOT_NOISE[1],
        ),
        target=square_tag(0.08),
        per_orientation=5,
        distortion=np.zeros(5),
        T_cam_board=geometry,
    )


#: the cameras of a 1, 2 or 3-camera session of :func:`scale_session`
CAMERA_SETS = {1: ("left",), 2: ("left", "right"), 3: ("left", "right", "rgb")}


#: :func:`scale_session`'s erring arm: one-sigma pose error per axis (metres, degrees).
ARM_ERROR = (2e-4, 0.02)


def scale_session(
    n_frames: int, n_cameras: int, seed: int = 7, arm_error: bool = False
) -> CalibrationProblem:
    """A simulated session of ``n_frames`` frames (R1's 20 poses repeated, new noise each time);
    ``arm_error``: the robot poses err by ``ARM_ERROR``."""
    rng = np.random.default_rng(seed)
    frames: list[Frame] = []
    noise_m, noise_deg = ARM_ERROR if arm_error else (0.0, 0.0)
    while len(frames) < n_frames:
        base = oak_rig(
            rng, cameras=CAMERA_SETS[n_cameras], robot_noise_m=noise_m, robot_noise_deg=noise_deg
        ).problem
        frames += base.frames
    return replace(base, frames=tuple(replace(f, id=k) for k, f in enumerate(frames[:n_frames])))


def cell_overrides(fx_rel: float = 0.0, cx_px: float = 0.0, he_deg: float = 0.0) -> dict:
    """Overrides of the default cell's truth for the same changes (a changed cell)."""
    f = 880.0 * (1 + fx_rel)
    sim: dict = {"cameras": {"cam": {"K": [[f, 0.0, 640.0 + cx_px], [0.0, f, 400.0], [0, 0, 1]]}}}
    if he_deg:
        r, p, y = np.radians([0.8, -1.2, 90.5])  # the default cell's true T_tool_cam
        R = R_from_rvec(np.radians(he_deg) * np.array([0.6, 0.0, 0.8])) @ Rz(y) @ Ry(p) @ Rx(r)
        sim["T_tool_cam"] = {"rpy_deg": rpy_deg(R), "t_m": [0.032, -0.061, 0.045]}
    return {"simulation": sim}


def same_cell(cfg, cell_seed: int, run_seed: int) -> cell.SimulatedCell:  # noqa: ANN001
    """The simulated cell of ``cfg`` built with ``cell_seed`` (its arm's error and board pose), run
    with fresh noise from ``run_seed``: two runs of one cell."""
    sim = cell.SimulatedCell.from_config(cfg, cell_seed)
    robot_rng, camera_rng = np.random.SeedSequence([cell_seed, run_seed]).spawn(2)
    sim.robot.rng = np.random.default_rng(robot_rng)
    sim.rig.rng = np.random.default_rng(camera_rng)
    return sim
