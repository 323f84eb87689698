"""Synthetic ground truth for the linear-solver tests (docs/SETUPS.md S1-S3 and variants).

Board frame: z = 0 plane; a camera with ``R_cam_board`` and centre ``C`` (board frame) sees board
point ``X`` at ``K (R_cam_board (X - C))``. Lengths in the paper's units ("l.u.").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slidecal.solver.geometry import Rx, Ry

K_S1 = np.array([[400.0, 0.0, 150.0], [0.0, 400.0, 120.0], [0.0, 0.0, 1.0]])
K_S2 = np.array([[400.0, 0.0, 150.0], [0.0, 440.0, 120.0], [0.0, 0.0, 1.0]])
K_SKEW = np.array([[400.0, 3.0, 150.0], [0.0, 440.0, 120.0], [0.0, 0.0, 1.0]])
IMAGE_SIZE = (300, 240)
D0 = np.diag([1.0, -1.0, -1.0])  # camera looking at the board along -z (docs/SETUPS.md)


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


def H_true(K: np.ndarray, R_cam_board: np.ndarray, C: np.ndarray) -> np.ndarray:
    """``K [r1 r2 t]`` (3, 3) with ``t = -R C`` (lambda = 1)."""
    t = -R_cam_board @ C
    return K @ np.column_stack([R_cam_board[:, 0], R_cam_board[:, 1], t])


def project(K: np.ndarray, R: np.ndarray, C: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of board points ``xy`` (N, 2)."""
    P = np.column_stack([xy, np.zeros(len(xy))])
    u = (P - C) @ R.T @ K.T
    return u[:, :2] / u[:, 2:3]


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
    obs, Hs = [], []
    for T in T_board:
        px = project(K, R_cam_board, C0 + T, xy)
        obs.append((xy, px + sigma_px * rng.normal(size=px.shape)))
        Hs.append(H_true(K, R_cam_board, C0 + T))
    return Group(R_cam_board, C0, T_board, obs, np.array(Hs))


def line_steps(direction: np.ndarray, n: int, step: float = 5.0) -> np.ndarray:
    """Displacements (n, 3): 0, step, 2 step, ... along ``direction`` (normalised)."""
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    return np.arange(n)[:, None] * step * d


def s1_group(theta_deg: float, n: int, rng: np.random.Generator, sigma_px: float = 0.0) -> Group:
    """S1: rotated by theta about the board's y axis, translated toward the grid centre."""
    R = D0 @ Ry(np.radians(theta_deg)).T
    C0 = centre_on_axis(R)
    return make_group(K_S1, R, C0, line_steps(-C0, n), rng, sigma_px)


def s2_group(
    n: int, rng: np.random.Generator, sigma_px: float = 0.0, K: np.ndarray = K_S2
) -> Group:
    """S2/S3: 30 deg about x then 30 about y, translated along the board normal toward it."""
    R = tilt_R(30.0, 30.0)
    C0 = centre_on_axis(R)
    return make_group(K, R, C0, line_steps([0.0, 0.0, -1.0], n), rng, sigma_px)


def robot_poses(
    group: Group, T_base_fixed: np.ndarray, T_tool_x: np.ndarray, mount: str
) -> np.ndarray:
    """Measured ``T_base_tool`` (n, 4, 4) of a group's frames.

    Eye-in-hand: ``T_base_fixed = T_base_board`` (board fixed), ``T_tool_x = T_tool_cam``.
    Eye-to-hand: ``T_base_fixed = T_base_cam`` (camera fixed), ``T_tool_x = T_tool_board``; the
    camera displacement ``T`` relative to the board is then a board motion.
    """
    out = []
    for T in group.T_board:
        T_board_cam = np.eye(4)
        T_board_cam[:3, :3] = group.R_cam_board.T
        T_board_cam[:3, 3] = group.C0 + T
        if mount == "eye_in_hand":
            out.append(T_base_fixed @ T_board_cam @ np.linalg.inv(T_tool_x))
        else:
            T_base_board = T_base_fixed @ np.linalg.inv(T_board_cam)
            out.append(T_base_board @ np.linalg.inv(T_tool_x))
    return np.array(out)
