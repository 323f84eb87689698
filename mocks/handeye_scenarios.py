"""Classic hand-eye sessions with ground truth: every frame at its own orientation.

The session every other hand-eye tool is built for: the robot carries the camera (eye-in-hand)
or the target (eye-to-hand) through poses that all differ in orientation, no two frames at the
same tilt. Optionally several translated frames per orientation (mixed sessions, and the
eye-to-hand AprilTag set-up: a single tag's 4 corners, a handful of orientations).

The cell is R1's (``slidecal.mocks.scenarios``): the same camera, board position, hand-eye and
fixed-camera transforms, so that the figures compare with the translation-group sessions.
"""

from __future__ import annotations

import numpy as np

from slidecal.mocks.scenarios import (
    R1_DIST,
    R1_K,
    R1_T_BASE_CAM,
    R1_T_TOOL_BOARD,
    R1_T_TOOL_CAM,
    Scenario,
    _detect,
    _perturb,
    r1_poses,
    r1_scenario,
)
from slidecal.solver.geometry import (
    R_from_rvec,
    T_from_Rt,
    inv_T,
    look_at_R_cam_world,
)
from slidecal.solver.problem import (
    Frame,
    ModelOptions,
    Target,
)

IMAGE_SIZE = (1280, 800)


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
    """``T_cam_board`` (n, 4, 4): views of the target, each at its own orientation.

    The camera looks at a point near the target centre (within ``aim_spread_m`` in the board
    plane, so the target lands on different parts of the image) from ``distance_m``, its axis
    tilted from the board normal by ``tilt_deg`` toward a random azimuth, rolled about the
    optical axis by up to ``roll_deg``.
    """
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
        R_cam_board = look_at_R_cam_world(p_cam, aim, up)
        R_cam_board = R_from_rvec([0.0, 0.0, np.radians(rng.uniform(-roll_deg, roll_deg))]) @ (
            R_cam_board
        )
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

    ``per_orientation`` > 1 adds translated frames at each orientation (a mixed session: then
    ``n_frames`` orientations of ``per_orientation`` frames). ``target``: R1's ChArUco board by
    default; ``distortion`` (5,): the lens (R1's by default). Robot poses are measured with
    ``robot_noise_m`` per axis and ``robot_noise_deg`` per rotation-vector component.
    ``T_cam_board`` (n, 4, 4): the views (:func:`camera_board_poses`) when the geometry must stay
    the same over Monte-Carlo trials; ``rng`` then draws only the noise (and the translations).
    """
    target = target or Target.charuco(11, 8, 0.030, 0.022)
    dist = R1_DIST.copy() if distortion is None else np.asarray(distortion, dtype=float)
    if T_cam_board is None:
        T_cam_board = camera_board_poses(rng, n_frames, target)
    T_cb = _translated(np.asarray(T_cam_board, dtype=float), rng, per_orientation)
    T_base_board = r1_poses()[0]
    frames = []
    for k, T_c_b in enumerate(T_cb):
        if eye_in_hand:
            T_base_tool = T_base_board @ inv_T(T_c_b) @ inv_T(R1_T_TOOL_CAM)
        else:
            T_base_tool = R1_T_BASE_CAM @ T_c_b @ inv_T(R1_T_TOOL_BOARD)
        det = _detect(R1_K, dist, T_c_b, target, IMAGE_SIZE, sigma_px, rng, 2.0)
        measured = _perturb(T_base_tool, rng, robot_noise_m, robot_noise_deg)
        frames.append(Frame(k, {"cam": det}, T_base_tool=measured))
    return r1_scenario(
        target, frames, eye_in_hand, options, sigma_px, T_base_board, dist, IMAGE_SIZE
    )


def board_in_view(s: Scenario) -> np.ndarray:
    """Per frame, the number of target points the camera saw (for checking a built scenario)."""
    return np.array([len(f.detections["cam"].ids) for f in s.problem.frames])
