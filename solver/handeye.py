"""Hand-eye orientation from pure translations (docs/METHOD.md Sec. 4) and classic AX = XB hand-eye.

Frames (docs/METHOD.md Sec. 1): ``base``, ``tool``, ``cam``, ``board``; ``T_a_b`` maps frame b
into a.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.geometry import (
    R_from_rvec,
    T_from_Rt,
    inv_T,
    project_to_SO3,
    quat_wxyz_from_R,
    rvec_from_R,
    skew,
)
from slidecal.solver.linear import LinearGroup

# Two directions count as distinct when the second singular value of the unit direction stack is
# at least this fraction of the first (about 0.6 deg between two directions).
_MIN_SPREAD = 1e-2
#: The third singular value of the moves' cross-covariance, against the first, above which a
#: reflection's better fit is taken as shown: the moves span three directions, and the camera's
#: own errors in them (about 1 % of their lengths) cannot turn a rotation into a reflection.
_MIRRORED = 0.1


def _group_scale(Kinv: np.ndarray, H0: np.ndarray) -> float:
    m1, m2 = Kinv @ H0[:, 0], Kinv @ H0[:, 1]
    return float(np.sqrt(0.5 * (m1 @ m1 + m2 @ m2)))


def camera_displacements(K: np.ndarray, group: LinearGroup) -> np.ndarray:
    """Camera displacements ``d`` (n, 3) since frame 0, camera axes, board length unit.

    ``d_k = K^-1 Delta_k / lambda`` with ``Delta_k = h3_0 - h3_k`` (docs/METHOD.md eqs. 12-13), so
    ``d_k = R_cam_board T_k`` for a camera displacement ``T_k`` in the board frame. ``K`` (3, 3)
    pixels; ``group.H`` (n, 3, 3) jointly estimated (common ``h1, h2``, ``h3[2] > 0``).
    ``d_0 = 0``.
    """
    H = np.asarray(group.H, dtype=float)
    Kinv = np.linalg.inv(np.asarray(K, dtype=float))
    lam = _group_scale(Kinv, H[0])
    if H[0][2, 2] < 0:
        lam = -lam
    return np.array([Kinv @ (H[0][:, 2] - Hk[:, 2]) / lam for Hk in H])


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
    if len(d) != len(t):
        raise InputError(f"d_cam has {len(d)} rows but t_robot has {len(t)}: pass matched pairs")
    w = np.ones(len(t)) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    keep = (np.linalg.norm(t, axis=1) > 0) & (w > 0)
    d, t, w = d[keep], t[keep], w[keep]
    if len(t) >= 2:
        u = t / np.linalg.norm(t, axis=1, keepdims=True)
        sv = np.linalg.svd(u, compute_uv=False)
    if len(t) < 2 or sv[1] < _MIN_SPREAD * sv[0]:
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


def hand_eye_rotation(
    K: np.ndarray,
    groups: Sequence[LinearGroup],
    T_base_tool_per_group: Sequence[np.ndarray],
    mount: str = "eye_in_hand",
) -> np.ndarray:
    """Hand-eye rotation from pure translations (docs/METHOD.md Sec. 4), all groups jointly.

    ``K`` (3, 3) pixels; ``groups``: orientation groups (homographies, board unit = robot unit);
    ``T_base_tool_per_group``: per group the measured poses (n, 4, 4), metres. Eye-in-hand: the
    camera displacement is the TCP displacement ``t_k`` (base), ``d_k = R_cam_tool
    R_base_tool' t_k``; returns ``R_tool_cam``. Eye-to-hand (board on the tool): the camera
    moves by ``-t_k`` relative to the board, ``d_k = -R_cam_base t_k``; returns ``R_base_cam``.
    """
    if mount not in ("eye_in_hand", "eye_to_hand"):
        raise InputError(f"mount must be 'eye_in_hand' or 'eye_to_hand', got {mount!r}")
    if len(groups) != len(T_base_tool_per_group):
        raise InputError("give one (n, 4, 4) array of T_base_tool per orientation group")
    ds, ts = [], []
    for g, (grp, T) in enumerate(zip(groups, T_base_tool_per_group, strict=True)):
        T = np.asarray(T, dtype=float)
        if T.shape != (len(grp.H), 4, 4):
            raise InputError(f"group {g}: T_base_tool must be ({len(grp.H)}, 4, 4)")
        t_base = T[:, :3, 3] - T[0, :3, 3]
        if mount == "eye_in_hand":
            ts.append(t_base @ T[0, :3, :3])  # R_base_tool' t_k: the displacement in tool axes
        else:
            ts.append(-t_base)
        ds.append(camera_displacements(K, grp))
    R_cam_x = rotation_from_directions(np.concatenate(ds), np.concatenate(ts))
    return R_cam_x.T


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


def _check_poses(T_base_tool: np.ndarray, T_cam_board: np.ndarray) -> tuple[np.ndarray, ...]:
    A = np.asarray(T_base_tool, dtype=float)
    B = np.asarray(T_cam_board, dtype=float)
    if A.ndim != 3 or A.shape[1:] != (4, 4) or A.shape != B.shape:
        raise InputError("T_base_tool and T_cam_board must both be (n, 4, 4) with the same n")
    if len(A) < 3:
        raise DegenerateError("hand-eye from general motions needs at least 3 poses")
    return A, B


def _motion_pairs(T_base_tool: np.ndarray, T_cam_board: np.ndarray) -> tuple[np.ndarray, ...]:
    """Eye-in-hand motions of all pairs ``i < j``: ``A = T_tool_base(i) T_base_tool(j)``,
    ``B = T_cam_board(i) T_board_cam(j)``, so that ``A X = X B`` with ``X = T_tool_cam``."""
    Tg, Tc = _check_poses(T_base_tool, T_cam_board)
    i, j = np.triu_indices(len(Tg), 1)
    Tg_inv = np.array([inv_T(T) for T in Tg])
    Tc_inv = np.array([inv_T(T) for T in Tc])
    return Tg_inv[i] @ Tg[j], Tc[i] @ Tc_inv[j]


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


def _qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    w1, v1, w2, v2 = p[0], p[1:], q[0], q[1:]
    return np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])


def _dual_quat(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Real and dual parts (4,), (4,) of the unit dual quaternion of ``T`` (4, 4)."""
    q = quat_wxyz_from_R(T[:3, :3])
    return q, 0.5 * _qmul(np.concatenate([[0.0], T[:3, 3]]), q)


def ax_xb_daniilidis(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``X`` (4, 4) solving ``A_k X = X B_k`` (n, 4, 4), Daniilidis 1999 (dual quaternions).

    Per motion, the vector parts of ``a q = q b`` and of its dual part give six rows on the dual
    quaternion ``(q, q')`` of ``X`` (paper eq. 31); rotation and translation come together from
    the two-dimensional null space of the stacked system and the unit and orthogonality
    constraints (eqs. 34-35). Motions without rotation carry no information and are dropped.
    """
    A, B = np.asarray(A, dtype=float), np.asarray(B, dtype=float)
    rows, alphas = [], []
    for Ak, Bk in zip(A, B, strict=True):
        a, a_d = _dual_quat(Ak)
        b, b_d = _dual_quat(Bk)
        if np.linalg.norm(a[1:]) < 1e-9 or np.linalg.norm(b[1:]) < 1e-9:
            continue
        if a[0] * b[0] < 0:  # the same screw angle needs the same sign of the scalar parts
            b, b_d = -b, -b_d
        alphas.append(a[1:])
        top = np.hstack([(a[1:] - b[1:])[:, None], skew(a[1:] + b[1:]), np.zeros((3, 4))])
        bottom = np.hstack(
            [
                (a_d[1:] - b_d[1:])[:, None],
                skew(a_d[1:] + b_d[1:]),
                (a[1:] - b[1:])[:, None],
                skew(a[1:] + b[1:]),
            ]
        )
        rows += [top, bottom]
    if not alphas or _single_axis(np.array(alphas)):
        raise DegenerateError(_SINGLE_AXIS)
    _, _, Vt = np.linalg.svd(np.vstack(rows))
    u1, v1, u2, v2 = Vt[-2, :4], Vt[-2, 4:], Vt[-1, :4], Vt[-1, 4:]
    # lambda1 v7 + lambda2 v8 with |q| = 1 and q . q' = 0: s = lambda1 / lambda2 solves
    # s^2 u1.v1 + s (u1.v2 + u2.v1) + u2.v2 = 0; pick the root giving the larger |q|^2.
    roots = np.roots([u1 @ v1, u1 @ v2 + u2 @ v1, u2 @ v2])
    roots = roots[np.isreal(roots)].real if len(roots) else np.zeros(0)
    if len(roots) == 0:
        raise DegenerateError(
            "the dual-quaternion hand-eye system has no real solution: the motions are "
            "inconsistent; check the robot poses and the detections"
        )
    norms = [s * s * (u1 @ u1) + 2 * s * (u1 @ u2) + u2 @ u2 for s in roots]
    s = roots[int(np.argmax(norms))]
    lam2 = 1.0 / np.sqrt(max(max(norms), 1e-300))
    q, q_d = lam2 * (s * u1 + u2), lam2 * (s * v1 + v2)
    t = 2.0 * _qmul(q_d, q * np.array([1.0, -1.0, -1.0, -1.0]))[1:]
    angle = 2.0 * np.arctan2(np.linalg.norm(q[1:]), q[0])
    n = np.linalg.norm(q[1:])
    R_X = R_from_rvec(angle * q[1:] / n) if n > 0 else np.eye(3)
    return T_from_Rt(R_X, t)


def park_martin(T_base_tool: np.ndarray, T_cam_board: np.ndarray) -> np.ndarray:
    """Eye-in-hand ``T_tool_cam`` (4, 4) from general motions, Park and Martin 1994 (AX = XB).

    ``T_base_tool`` (n, 4, 4): robot poses (metres); ``T_cam_board`` (n, 4, 4): board poses seen
    by the camera, same length unit. Uses all pairs ``i < j``:
    ``A = T_tool_base(i) T_base_tool(j)``,
    ``B = T_cam_board(i) T_board_cam(j)``. Needs rotations about two non-parallel axes.
    """
    return ax_xb_park_martin(*_motion_pairs(T_base_tool, T_cam_board))


def daniilidis(T_base_tool: np.ndarray, T_cam_board: np.ndarray) -> np.ndarray:
    """Eye-in-hand ``T_tool_cam`` (4, 4), Daniilidis 1999 (dual quaternions); inputs as for
    :func:`park_martin`, all pairs ``i < j``."""
    return ax_xb_daniilidis(*_motion_pairs(T_base_tool, T_cam_board))


def tsai_lenz(T_base_tool: np.ndarray, T_cam_board: np.ndarray) -> np.ndarray:
    """Eye-in-hand ``T_tool_cam`` (4, 4), Tsai and Lenz 1989 (modified Rodrigues parameters).

    Same inputs as :func:`park_martin`; consecutive motion pairs.
    """
    Tg, Tc = _check_poses(T_base_tool, T_cam_board)
    rows, rhs, As, Bs = [], [], [], []
    for i in range(len(Tg) - 1):
        A = inv_T(Tg[i]) @ Tg[i + 1]
        B = Tc[i] @ inv_T(Tc[i + 1])
        ra, rb = rvec_from_R(A[:3, :3]), rvec_from_R(B[:3, :3])
        pa = 2.0 * np.sin(np.linalg.norm(ra) / 2) * ra / max(np.linalg.norm(ra), 1e-300)
        pb = 2.0 * np.sin(np.linalg.norm(rb) / 2) * rb / max(np.linalg.norm(rb), 1e-300)
        s = pa + pb
        rows.append(np.array([[0, -s[2], s[1]], [s[2], 0, -s[0]], [-s[1], s[0], 0]]))
        rhs.append(pb - pa)
        As.append(A)
        Bs.append(B)
    M = np.concatenate(rows)
    sv = np.linalg.svd(M, compute_uv=False)
    if sv[2] < 1e-3 * sv[0]:  # each skew block has rank 2: one axis leaves sv[2] = 0
        raise DegenerateError(_SINGLE_AXIS)
    # skew(pa + pb) p' = pb - pa  (with the sign convention A X = X B, rotations of A).
    pp, *_ = np.linalg.lstsq(M, np.concatenate(rhs), rcond=None)
    p = 2.0 * pp / np.sqrt(1.0 + pp @ pp)
    n = np.linalg.norm(p)
    angle = 2.0 * np.arcsin(min(n / 2.0, 1.0))
    R_X = R_from_rvec(angle * p / n) if n > 0 else np.eye(3)
    return T_from_Rt(R_X, _translation_ax_xb(np.array(As), np.array(Bs), R_X))
