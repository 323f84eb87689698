"""The one conversion between Universal Robots poses ``[x, y, z, rx, ry, rz]`` (metres, an
axis-angle vector in radians) and ``T_base_tool`` (docs/METHOD.md Sec. 1), and the pose as the
teach pendant shows it (:func:`pendant_text`; both: :func:`describe`)."""

from __future__ import annotations

import numpy as np

from slidecal.solver.geometry import R_from_rvec, T_from_Rt, rvec_from_R


def T_from_ur_pose(pose: list[float] | np.ndarray) -> np.ndarray:
    """``T_base_tool`` (4, 4) from a UR pose ``[x, y, z, rx, ry, rz]`` (metres, radians)."""
    try:
        p = np.asarray(pose, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        p = np.full(1, np.nan)
    if p.shape != (6,) or not np.all(np.isfinite(p)):
        raise ValueError(f"a UR pose is 6 finite numbers [x, y, z, rx, ry, rz], got {pose!r}")
    return T_from_Rt(R_from_rvec(p[3:]), p[:3])


def ur_pose_from_T(T_base_tool: np.ndarray) -> list[float]:
    """UR pose ``[x, y, z, rx, ry, rz]`` (metres, radians, angle in [0, pi]) of a 4x4 transform."""
    T = np.asarray(T_base_tool, dtype=float)
    return [float(v) for v in (*T[:3, 3], *rvec_from_R(T[:3, :3]))]


def rpy_deg(R: np.ndarray) -> list[float]:
    """The pendant's RPY (roll, pitch, yaw) in degrees of ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    pitch = np.arcsin(-np.clip(R[2, 0], -1.0, 1.0))
    roll = np.arctan2(R[2, 1], R[2, 2])
    yaw = np.arctan2(R[1, 0], R[0, 0])
    return [float(v) for v in np.degrees([roll, pitch, yaw])]


def pendant_text(T_base_tool: np.ndarray) -> str:
    """The pose as the teach pendant shows it: millimetres and RPY in degrees (X-Y-Z fixed axes)."""
    T = np.asarray(T_base_tool, dtype=float)
    x, y, z = T[:3, 3] * 1000.0
    r, p, w = rpy_deg(T[:3, :3])
    return f"X {x:.2f} Y {y:.2f} Z {z:.2f} mm, RPY {r:.3f} {p:.3f} {w:.3f} deg"


def describe(T_base_tool: np.ndarray) -> str:
    """The UR pose and, in brackets, the pendant's view of it (for messages)."""
    pose = ", ".join(f"{v:.4f}" for v in ur_pose_from_T(T_base_tool))
    return f"[{pose}] ({pendant_text(T_base_tool)})"
