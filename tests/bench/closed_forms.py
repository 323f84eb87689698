"""The closed-form AX = XB hand-eye methods the hand-eye benchmark sets beside the solver's ML
estimate: Park and Martin 1994 (the solver's start, ``ax_xb_park_martin``), Daniilidis 1999 and
Tsai and Lenz 1989, on eye-in-hand robot and board poses."""

from __future__ import annotations

import numpy as np

from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.geometry import (
    R_from_rvec,
    T_from_Rt,
    inv_T,
    quat_wxyz_from_R,
    rvec_from_R,
    skew,
)
from slidecal.solver.handeye import (
    _SINGLE_AXIS,
    _single_axis,
    _translation_ax_xb,
    ax_xb_park_martin,
)


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
