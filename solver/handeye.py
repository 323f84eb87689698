"""Hand-eye orientation from pure translations (docs/METHOD.md Sec. 4) and classic AX = XB hand-eye.

Frames (docs/METHOD.md Sec. 1): ``base``, ``tool``, ``cam``, ``board``; ``T_a_b`` maps frame b
into a.
"""

from __future__ import annotations

import numpy as np

from slidecal.solver.errors import DegenerateError
from slidecal.solver.geometry import (
    T_from_Rt,
    project_to_SO3,
    rvec_from_R,
)
from slidecal.solver.linear import LinearGroup

# Two directions count as distinct when the second singular value of the unit direction stack is
# at least this fraction of the first (about 0.6 deg between two directions).
_MIN_SPREAD = 1e-2
#: The third singular value of the moves' cross-covariance, against the first, above which a
#: reflection's better fit is taken as shown: the moves span three directions, and the camera's
#: own errors in them (about 1 % of their lengths) cannot turn a rotation into a reflection.
_MIRRORED = 0.1


def camera_displacements(K: np.ndarray, group: LinearGroup) -> np.ndarray:
    """Camera displacements ``d`` (n, 3) since frame 0, camera axes, board length unit.

    ``d_k = K^-1 Delta_k / lambda`` with ``Delta_k = h3_0 - h3_k`` (docs/METHOD.md eqs. 12-13), so
    ``d_k = R_cam_board T_k`` for a camera displacement ``T_k`` in the board frame. ``K`` (3, 3)
    pixels; ``group.H`` (n, 3, 3) jointly estimated (common ``h1, h2``, ``h3[2] > 0``).
    ``d_0 = 0``.
    """
    H = np.asarray(group.H, dtype=float)
    Kinv = np.linalg.inv(np.asarray(K, dtype=float))
    m1, m2 = Kinv @ H[0][:, 0], Kinv @ H[0][:, 1]
    lam = float(np.sqrt(0.5 * (m1 @ m1 + m2 @ m2)))
    if H[0][2, 2] < 0:
        lam = -lam
    return np.array([Kinv @ (H[0][:, 2] - Hk[:, 2]) / lam for Hk in H])


def n_directions(v: np.ndarray) -> int:
    """How many independent directions (0 to 3) the non-zero rows of ``v`` (n, 3) span."""
    n = np.linalg.norm(v, axis=1)
    u = v[n > 0] / n[n > 0, None]
    ev = np.linalg.eigvalsh(u.T @ u)  # the unit rows' squared singular values, ascending
    return int(np.sum(ev >= _MIN_SPREAD**2 * ev[-1])) if len(u) else 0


def rotation_from_directions(
    d_cam: np.ndarray, t_robot: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """``R_cam_robot`` (3, 3) minimising ``sum w_k |d_k - R t_k|^2`` (weighted Kabsch, det +1).

    ``d_cam`` (n, 3): displacements in camera axes; ``t_robot`` (n, 3): the same displacements
    in the robot frame (any common unit; zero rows are ignored); ``weights`` (n,) or None.
    Raises ``DegenerateError`` unless ``t_robot`` spans at least two directions.
    """
    d = np.asarray(d_cam, dtype=float).reshape(-1, 3)
    t = np.asarray(t_robot, dtype=float).reshape(-1, 3)
    w = np.ones(len(t)) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    keep = (np.linalg.norm(t, axis=1) > 0) & (w > 0)
    d, t, w = d[keep], t[keep], w[keep]
    if n_directions(t) < 2:
        raise DegenerateError(
            "the robot translations are all parallel: the rotation about their direction is "
            "undetermined; translate along at least two non-parallel directions"
        )
    M = (d * w[:, None]).T @ t  # sum w d t'
    U, sv_m, Vt = np.linalg.svd(M)
    if np.linalg.det(U @ Vt) < 0 and sv_m[2] > _MIRRORED * sv_m[0]:
        # the moves span three directions and a reflection maps them far better than any
        # rotation: the camera sees the robot's moves mirrored, which no hand-eye explains
        raise DegenerateError(
            "the camera sees the robot's moves mirrored (a reflection, not a rotation, maps the "
            "robot's translations onto the camera's): the poses are T_tool_base (the inverse of "
            "T_base_tool), the session's mount is the other one, one axis of the robot's frame "
            "is flipped, or the images are paired with other frames' poses; check the pose "
            "records, how they are paired with the images, and the mount"
        )
    return project_to_SO3(M)


def board_pose_from_homography(K: np.ndarray, H: np.ndarray) -> np.ndarray:
    """``T_cam_board`` (4, 4) from ``H`` (3, 3) (board plane to pixels) and ``K`` (3, 3).

    ``K^-1 H = lambda [r1 r2 t]``; ``lambda`` from the mean norm of the first two columns, its
    sign so that the board is in front (``t_z > 0``); ``R`` projected onto SO(3). The
    translation is in the board's length unit.
    """
    M = np.linalg.inv(np.asarray(K, dtype=float)) @ np.asarray(H, dtype=float)
    lam = np.sqrt(0.5 * (M[:, 0] @ M[:, 0] + M[:, 1] @ M[:, 1]))
    if M[2, 2] < 0:
        lam = -lam
    r1, r2, t = M[:, 0] / lam, M[:, 1] / lam, M[:, 2] / lam
    R = project_to_SO3(np.column_stack([r1, r2, np.cross(r1, r2)]))
    return T_from_Rt(R, t)


def _single_axis(alphas: np.ndarray) -> bool:
    """True when the rotation vectors (n, 3) of the motions share one axis (or are absent)."""
    sv = np.linalg.svd(np.asarray(alphas).reshape(-1, 3), compute_uv=False)
    return len(sv) < 2 or sv[0] == 0.0 or sv[1] < 1e-3 * sv[0]


_SINGLE_AXIS = (
    "the robot rotations are all about one axis (or absent): the hand-eye transform is "
    "undetermined; rotate about at least two non-parallel axes"
)


def _translation_ax_xb(A: np.ndarray, B: np.ndarray, R_X: np.ndarray) -> np.ndarray:
    """``t_X`` (3,) of ``A X = X B`` for a known ``R_X``: ``(R_A - I) t_X = R_X t_B - t_A``."""
    C = (A[:, :3, :3] - np.eye(3)).reshape(-1, 3)
    d = (np.einsum("ij,nj->ni", R_X, B[:, :3, 3]) - A[:, :3, 3]).reshape(-1)
    t_X, *_ = np.linalg.lstsq(C, d, rcond=None)
    return t_X


def ax_xb_park_martin(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``X`` (4, 4) solving ``A_k X = X B_k`` for motions ``A``, ``B`` (n, 4, 4), Park and Martin
    1994: the rotation axes satisfy ``alpha_k = R_X beta_k`` (orthogonal Procrustes over all
    motions), then ``t_X`` by linear least squares. Needs rotations about two non-parallel axes.
    """
    A, B = np.asarray(A, dtype=float), np.asarray(B, dtype=float)
    al = np.array([rvec_from_R(R) for R in A[:, :3, :3]])
    be = np.array([rvec_from_R(R) for R in B[:, :3, :3]])
    if _single_axis(al):
        raise DegenerateError(_SINGLE_AXIS)
    R_X = project_to_SO3(al.T @ be)
    return T_from_Rt(R_X, _translation_ax_xb(A, B, R_X))
