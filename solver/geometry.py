"""Rigid transforms and rotations (docs/METHOD.md Sec. 1 conventions).

``T_a_b`` is a 4x4 homogeneous transform mapping coordinates in frame ``b`` to frame ``a``
(``p_a = T_a_b @ p_b``, ``T_a_c = T_a_b @ T_b_c``). ``R_a_b`` and ``t_a_b`` are its rotation and
translation (metres). Rotation vectors (``rvec``) are axis-angle in radians.
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-12


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]x`` of a (3,) vector, so that ``skew(a) @ b == cross(a, b)``."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def R_from_rvec(rvec: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a rotation vector (3,) in radians (Rodrigues' formula)."""
    rvec = np.asarray(rvec, dtype=float)
    theta = float(np.linalg.norm(rvec))
    K = skew(rvec)
    if theta < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    a = np.sin(theta) / theta
    b = (1.0 - np.cos(theta)) / theta**2
    return np.eye(3) + a * K + b * K @ K


def R_from_rvecs(v: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of rotation vectors (n, 3): :func:`R_from_rvec` for a stack."""
    th = np.linalg.norm(v, axis=1)
    small = th < 1e-8
    ts = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ts) / ts)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    S = _skew_batch(v)
    return np.eye(3) + a[:, None, None] * S + b[:, None, None] * (S @ S)


def _skew_batch(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (n, 3, 3) of vectors (n, 3)."""
    S = np.zeros((len(v), 3, 3))
    S[:, 0, 1], S[:, 0, 2] = -v[:, 2], v[:, 1]
    S[:, 1, 0], S[:, 1, 2] = v[:, 2], -v[:, 0]
    S[:, 2, 0], S[:, 2, 1] = -v[:, 1], v[:, 0]
    return S


def rvec_from_R(R: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) in radians, angle in [0, pi], of a rotation matrix (3, 3).

    Accurate to ~1e-12 everywhere, including near pi (UR poses with the tool pointing down):
    the angle from ``atan2`` of the skew and symmetric parts, and near pi the axis from
    ``a a' = (sym(R) - cos(theta) I) / (1 - cos(theta))``.
    """
    R = np.asarray(R, dtype=float)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = 0.5 * float(np.linalg.norm(w))
    c = 0.5 * (float(np.trace(R)) - 1.0)
    theta = float(np.arctan2(s, c))
    if theta < 1e-6:
        return 0.5 * w
    if c > -0.5:
        return theta / (2.0 * s) * w
    A = (0.5 * (R + R.T) - c * np.eye(3)) / (1.0 - c)
    i = int(np.argmax(np.diag(A)))
    axis = A[i] / np.sqrt(max(A[i, i], _EPS))
    axis /= np.linalg.norm(axis)
    if axis @ w < 0:
        axis = -axis
    return theta * axis


def R_from_quat_wxyz(q: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion ``(w, x, y, z)`` (4,) (scalar first, as ABB
    controllers and Eigen's constructor order it; ROS orders ``(x, y, z, w)``). The quaternion
    is normalised; ``q`` and ``-q`` give the same rotation."""
    w, x, y, z = np.asarray(q, dtype=float) / float(np.linalg.norm(q))
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_wxyz_from_R(R: np.ndarray) -> np.ndarray:
    """The unit quaternion ``(w, x, y, z)`` (4,), ``w >= 0``, of ``R`` (3, 3) (the inverse of
    :func:`R_from_quat_wxyz`)."""
    v = rvec_from_R(R)
    angle = float(np.linalg.norm(v))
    axis = v / angle if angle > 0 else np.zeros(3)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def project_to_SO3(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to a 3x3 matrix in the Frobenius norm (SVD, det = +1)."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def T_from_Rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 transform from a rotation (3, 3) and a translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform: ``inv_T(T_a_b) == T_b_a``."""
    R = T[:3, :3]
    return T_from_Rt(R.T, -R.T @ T[:3, 3])


def transform_points(T_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Points (N, 3) in frame b mapped to frame a."""
    p_b = np.asarray(p_b, dtype=float)
    return p_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray | None = None) -> float:
    """Angle in degrees of ``R_a`` (or of ``R_a R_b'`` when ``R_b`` is given), by
    :func:`rvec_from_R` (exact also for tiny angles, where ``arccos`` of the trace is not)."""
    R = np.asarray(R_a, float) if R_b is None else np.asarray(R_a, float) @ np.asarray(R_b).T
    return float(np.degrees(np.linalg.norm(rvec_from_R(R))))


def Rx(angle_rad: float) -> np.ndarray:
    """Rotation about x by an angle in radians."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def Ry(angle_rad: float) -> np.ndarray:
    """Rotation about y by an angle in radians."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def Rz(angle_rad: float) -> np.ndarray:
    """Rotation about z by an angle in radians."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def look_at_R_cam_world(
    p_cam_world: np.ndarray, p_target_world: np.ndarray, up_world: np.ndarray
) -> np.ndarray:
    """``R_cam_world`` of a camera at ``p_cam_world`` looking at ``p_target_world``.

    Camera axes (docs/METHOD.md Sec. 1): +z along the optical axis, +x right, +y down;
    ``up_world`` is the world direction that should appear as up (-y) in the image.
    """
    z = np.asarray(p_target_world, float) - np.asarray(p_cam_world, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up_world, float))  # then y = z x x = -(up without its z part)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at_R_cam_world: the up direction is parallel to the viewing ray")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def right_singular(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Singular values ``sv`` (n,) and right singular vectors ``Vt`` (n, n) of ``A`` (m, n),
    any m: a system with fewer rows than unknowns is padded with zero rows (its null space is
    then the last rows of ``Vt``). Thin SVD: the cost stays linear in m."""
    A = np.asarray(A, dtype=float)
    m, n = A.shape
    if m < n:
        A = np.vstack([A, np.zeros((n - m, n))])
    _, sv, Vt = np.linalg.svd(A, full_matrices=False)
    return sv, Vt
