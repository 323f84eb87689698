"""Hand-eye rotation from translations (docs/METHOD.md Sec. 4) and the AX = XB cross-checks."""

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from slidecal.mocks import scenarios as sl
from slidecal.solver.errors import DegenerateError
from slidecal.solver.geometry import (
    Rz,
    T_from_Rt,
    inv_T,
    rvec_from_R,
)
from slidecal.solver.handeye import (
    ax_xb_park_martin,
    board_pose_from_homography,
    camera_displacements,
    rotation_from_directions,
)
from slidecal.solver.homography import group_homographies
from slidecal.solver.linear import LinearGroup
from tests.helpers import random_rotation

sys.path.insert(0, str(Path(__file__).parent))
import linear_scenes as lg  # noqa: E402


def robot_poses(
    group: lg.Group, T_base_fixed: np.ndarray, T_tool_x: np.ndarray, mount: str
) -> np.ndarray:
    """Measured ``T_base_tool`` (n, 4, 4) of a group's frames: eye-in-hand with ``T_base_fixed =
    T_base_board`` and ``T_tool_x = T_tool_cam``, eye-to-hand with ``T_base_cam`` and
    ``T_tool_board`` (the displacement is then a board motion)."""
    out = []
    for T in group.T_board:
        T_board_cam = T_from_Rt(group.R_cam_board.T, group.C0 + T)
        if mount == "eye_in_hand":
            out.append(T_base_fixed @ T_board_cam @ np.linalg.inv(T_tool_x))
        else:
            T_base_board = T_base_fixed @ np.linalg.inv(T_board_cam)
            out.append(T_base_board @ np.linalg.inv(T_tool_x))
    return np.array(out)


def hand_eye_rotation(K, groups, T_base_tool_per_group, mount):
    """Hand-eye rotation from pure translations (docs/METHOD.md Sec. 4), all groups jointly,
    from their homographies: ``R_tool_cam`` (eye-in-hand) or ``R_base_cam``."""
    ds, ts = [], []
    for grp, T in zip(groups, T_base_tool_per_group, strict=True):
        t_base = T[:, :3, 3] - T[0, :3, 3]
        ts.append(t_base @ T[0, :3, :3] if mount == "eye_in_hand" else -t_base)
        ds.append(camera_displacements(K, grp))
    return rotation_from_directions(np.concatenate(ds), np.concatenate(ts)).T


def park_martin(T_base_tool, T_cam_board):
    """Eye-in-hand ``T_tool_cam`` by the solver's Park-Martin over all pairs of poses."""
    i, j = np.triu_indices(len(T_base_tool), 1)
    Tg_inv = np.array([inv_T(T) for T in T_base_tool])
    Tc_inv = np.array([inv_T(T) for T in T_cam_board])
    return ax_xb_park_martin(Tg_inv[i] @ T_base_tool[j], T_cam_board[i] @ Tc_inv[j])


def angle_deg(R_a, R_b):
    """Angle of ``R_a R_b'`` in degrees, accurate near zero (rotation vector norm)."""
    return float(np.degrees(np.linalg.norm(rvec_from_R(R_a @ R_b.T))))


def _groups(rng, sigma=0.0, tilts=((30, 30), (-25, 10), (10, -30))):
    T = np.array([[0, 0, 0], [0, 0, -10], [8, 0, -6], [0, 8, -6.0]])
    out = []
    for ax, ay in tilts:
        R = sl.tilt_R(ax, ay)
        out.append(lg.make_group(sl.K_S2, R, sl.centre_on_axis(R), T, rng, sigma))
    return out


def test_camera_displacements_and_board_pose_noise_free():
    rng = np.random.default_rng(1)
    g = _groups(rng)[0]
    grp = LinearGroup(group_homographies(g.observations))
    d = camera_displacements(sl.K_S2, grp)
    assert np.abs(d - g.T_board @ g.R_cam_board.T).max() < 1e-9
    T_cam_board = board_pose_from_homography(sl.K_S2, grp.H[2])
    assert angle_deg(T_cam_board[:3, :3], g.R_cam_board) < 1e-6
    assert np.abs(T_cam_board[:3, 3] + g.R_cam_board @ (g.C0 + g.T_board[2])).max() < 1e-9


def test_rotation_from_directions():
    rng = np.random.default_rng(2)
    R = random_rotation(rng)
    t = rng.normal(size=(6, 3))
    assert angle_deg(rotation_from_directions(t @ R.T, t), R) < 1e-6
    w = rng.uniform(0.5, 2.0, size=6)
    assert angle_deg(rotation_from_directions(t @ R.T, t, w), R) < 1e-6
    line = np.outer(np.arange(1.0, 5.0), [1.0, 2.0, 0.5])
    with pytest.raises(DegenerateError, match="non-parallel"):
        rotation_from_directions(line @ R.T, line)


def test_moves_seen_mirrored_are_named_not_fitted():
    # a tool's moves read through inverted poses (-R' t) or the wrong mount reach the camera
    # mirrored: when they span three directions no rotation fits, and the solve is refused
    rng = np.random.default_rng(3)
    R = random_rotation(rng)
    t = rng.normal(size=(8, 3)) * [0.2, 0.1, 0.05]
    d = (t @ R.T) * (1.0 + 0.01 * rng.normal(size=(8, 3)))  # the camera's own 1 % errors
    assert angle_deg(rotation_from_directions(d, t), R) < 2.0
    with pytest.raises(DegenerateError, match="mirrored.*T_tool_base"):
        rotation_from_directions(-d, t)
    # moves in one plane: a mirror of the plane is a half-turn about its normal, a rotation
    flat = t * [1.0, 1.0, 0.0]
    assert rotation_from_directions(-(flat @ R.T), flat) is not None


@pytest.mark.parametrize("mount", ["eye_in_hand", "eye_to_hand"])
def test_hand_eye_rotation_from_translations_noise_free(mount):
    rng = np.random.default_rng(3)
    T_tool_x = T_from_Rt(random_rotation(rng), rng.normal(size=3) * 20)
    T_base_fixed = T_from_Rt(random_rotation(rng), rng.normal(size=3) * 500)
    groups, poses = [], []
    for g in _groups(rng):
        groups.append(LinearGroup(group_homographies(g.observations)))
        poses.append(robot_poses(g, T_base_fixed, T_tool_x, mount))
    R = hand_eye_rotation(sl.K_S2, groups, poses, mount)
    if mount == "eye_in_hand":
        truth = T_tool_x[:3, :3]  # R_tool_cam
    else:
        truth = T_base_fixed[:3, :3]  # R_base_cam
    assert angle_deg(R, truth) < 1e-6
    # A single group works too (two non-parallel translations suffice).
    R1 = hand_eye_rotation(sl.K_S2, groups[:1], poses[:1], mount)
    assert angle_deg(R1, truth) < 1e-6


def test_hand_eye_rotation_noisy_agrees_with_park_martin():
    # Three tilt groups: the translations give R_tool_cam; the board poses of all frames give
    # general motions for Park-Martin. Both must agree with the truth within the noise.
    rng = np.random.default_rng(4)
    T_tool_cam = T_from_Rt(random_rotation(rng), rng.normal(size=3) * 20)
    T_base_board = T_from_Rt(random_rotation(rng), rng.normal(size=3) * 500)
    groups, poses, T_cam_board = [], [], []
    for g in _groups(rng, sigma=0.2):
        grp = LinearGroup(group_homographies(g.observations))
        groups.append(grp)
        poses.append(robot_poses(g, T_base_board, T_tool_cam, "eye_in_hand"))
        T_cam_board += [board_pose_from_homography(sl.K_S2, H) for H in grp.H]
    R = hand_eye_rotation(sl.K_S2, groups, poses, "eye_in_hand")
    X = park_martin(np.concatenate(poses), np.array(T_cam_board))
    err_t, err_pm = angle_deg(R, T_tool_cam[:3, :3]), angle_deg(X[:3, :3], T_tool_cam[:3, :3])
    assert err_t < 1.0 and err_pm < 1.0
    assert angle_deg(R, X[:3, :3]) < 1.5


def _general_motions(rng, n, noise_deg=0.0):
    X = T_from_Rt(random_rotation(rng), rng.normal(size=3) * 0.1)
    T_base_board = T_from_Rt(random_rotation(rng), rng.normal(size=3))
    Tg, Tc = [], []
    for _ in range(n):
        T = T_from_Rt(random_rotation(rng, 0.7), rng.normal(size=3) * 0.2)
        Tg.append(T)
        Tcb = inv_T(X) @ inv_T(T) @ T_base_board
        if noise_deg:
            Tcb = T_from_Rt(random_rotation(rng, np.radians(noise_deg)), np.zeros(3)) @ Tcb
            Tcb[:3, 3] += rng.normal(size=3) * 1e-3
        Tc.append(Tcb)
    return X, np.array(Tg), np.array(Tc)


def test_classic_hand_eye_noise_free_and_against_opencv():
    method = park_martin
    rng = np.random.default_rng(5)
    X, Tg, Tc = _general_motions(rng, 8)
    Y = method(Tg, Tc)
    assert angle_deg(Y[:3, :3], X[:3, :3]) < 1e-6
    assert np.abs(Y[:3, 3] - X[:3, 3]).max() < 1e-9
    X, Tg, Tc = _general_motions(rng, 10, noise_deg=0.05)
    R_cv, t_cv = cv2.calibrateHandEye(
        Tg[:, :3, :3], Tg[:, :3, 3], Tc[:, :3, :3], Tc[:, :3, 3], method=cv2.CALIB_HAND_EYE_PARK
    )
    Y = method(Tg, Tc)
    assert angle_deg(Y[:3, :3], X[:3, :3]) < 0.2  # 10 poses at 0.05 deg noise each
    assert angle_deg(Y[:3, :3], R_cv) < 0.05
    assert np.linalg.norm(Y[:3, 3] - t_cv.ravel()) < 5e-3


def test_classic_hand_eye_refuses_single_axis():
    rng = np.random.default_rng(6)
    X = T_from_Rt(random_rotation(rng), np.zeros(3))
    Tg = np.array([T_from_Rt(Rz(a), rng.normal(size=3)) for a in (0.0, 0.3, 0.6, 0.9)])
    Tc = np.array([inv_T(X) @ inv_T(T) for T in Tg])
    with pytest.raises(DegenerateError, match="two non-parallel axes"):
        park_martin(Tg, Tc)
