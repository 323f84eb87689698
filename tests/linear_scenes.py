"""Homography-level scenes of the paper's set-ups S1-S3 (docs/SETUPS.md) for the linear method's
tests: noisy plane-to-image observations of one orientation group, without a calibration problem."""

from dataclasses import dataclass

import numpy as np

from slidecal.mocks.scenarios import K_S1, K_S2, board_xy, plane_pixels, s1_geometry, s2_geometry
from slidecal.solver.homography import homography_dlt, refine_homography

K_SKEW = np.array([[400.0, 3.0, 150.0], [0.0, 440.0, 120.0], [0.0, 0.0, 1.0]])


def H_true(K: np.ndarray, R_cam_board: np.ndarray, C: np.ndarray) -> np.ndarray:
    """``K [r1 r2 t]`` (3, 3) with ``t = -R C`` (lambda = 1)."""
    t = -R_cam_board @ C
    return K @ np.column_stack([R_cam_board[:, 0], R_cam_board[:, 1], t])


@dataclass
class Group:
    """One orientation group: true pose, displacements (board frame) and noisy observations."""

    R_cam_board: np.ndarray
    C0: np.ndarray
    T_board: np.ndarray  # (n, 3) camera displacement since frame 0, board frame
    observations: list
    H: np.ndarray  # (n, 3, 3) true homographies, common scale


def make_group(
    K: np.ndarray,
    R_cam_board: np.ndarray,
    C0: np.ndarray,
    T_board: np.ndarray,
    rng: np.random.Generator,
    sigma_px: float = 0.0,
    xy: np.ndarray | None = None,
) -> Group:
    """Observations of the board from ``C0 + T_board[k]`` with i.i.d. pixel noise ``sigma_px``."""
    xy = board_xy() if xy is None else xy
    T_board = np.asarray(T_board, dtype=float)
    Hs = np.array([H_true(K, R_cam_board, C0 + T) for T in T_board])
    obs = [(xy, px + sigma_px * rng.normal(size=px.shape)) for px in plane_pixels(Hs, xy)]
    return Group(R_cam_board, C0, T_board, obs, Hs)


def line_steps(direction: np.ndarray, n: int, step: float = 5.0) -> np.ndarray:
    """Displacements (n, 3): 0, step, 2 step, ... along ``direction`` (normalised)."""
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    return np.arange(n)[:, None] * step * d


def s1_group(theta_deg: float, n: int, rng: np.random.Generator, sigma_px: float = 0.0) -> Group:
    """S1: rotated by theta about the board's y axis, translated toward the grid centre."""
    R, C0 = s1_geometry(theta_deg)
    return make_group(K_S1, R, C0, line_steps(-C0, n), rng, sigma_px)


def s2_group(
    n: int, rng: np.random.Generator, sigma_px: float = 0.0, K: np.ndarray = K_S2
) -> Group:
    """S2/S3: 30 deg about x then 30 about y, translated along the board normal toward it."""
    R, C0 = s2_geometry()
    return make_group(K, R, C0, line_steps([0.0, 0.0, -1.0], n), rng, sigma_px)


def estimate_homographies(board_xy: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Homographies (n, 3, 3) per view of ``board_xy`` (N, 2) l.u. seen at ``px`` (n, N, 2):
    normalised DLT, then reprojection-error refinement."""
    return np.array([refine_homography(homography_dlt(board_xy, p), board_xy, p) for p in px])


def params_of(K: np.ndarray) -> np.ndarray:
    """(fx, fy, cx, cy) of an intrinsic matrix (3, 3), pixels."""
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
