"""The camera model: pinhole with skew and Brown-Conrady distortion (OpenCV's order and formula).

``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, ``dist = (k1, k2, p1, p2, k3)``. A point
``P_cam = (X, Y, Z)`` in the camera frame (metres) projects to pixels (pixel (0, 0) is the centre
of the top-left pixel):

    x, y = X / Z, Y / Z;  r2 = x^2 + y^2;  a = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    xd = a x + 2 p1 x y + p2 (r2 + 2 x^2);  yd = a y + p1 (r2 + 2 y^2) + 2 p2 x y
    u = fx xd + s yd + cx;  v = fy yd + cy

This is the model of ``cv2.projectPoints`` (which has no skew). Jacobians are analytic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "s")


def K_matrix(fx: float, fy: float, cx: float, cy: float, s: float = 0.0) -> np.ndarray:
    """The 3x3 intrinsic matrix in pixels."""
    return np.array([[fx, s, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _dist5(dist: np.ndarray | None) -> np.ndarray:
    d = np.zeros(5)
    if dist is not None:
        dd = np.asarray(dist, dtype=float).reshape(-1)
        d[: min(5, len(dd))] = dd[:5]
    return d


def project(K: np.ndarray, dist: np.ndarray | None, P_cam: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of points ``P_cam`` (N, 3) in the camera frame."""
    return project_with_jacobians(K, dist, P_cam, jacobians=False).px


@dataclass(frozen=True)
class Projection:
    """Projected pixels and, on request, their Jacobians.

    ``px`` (N, 2); ``d_P`` (N, 2, 3) with respect to the camera-frame point; ``d_K`` (N, 2, 5)
    with respect to (fx, fy, cx, cy, s); ``d_dist`` (N, 2, 5) with respect to (k1, k2, p1, p2, k3).
    """

    px: np.ndarray
    d_P: np.ndarray | None = None
    d_K: np.ndarray | None = None
    d_dist: np.ndarray | None = None


def _distort(
    k1: float,
    k2: float,
    p1: float,
    p2: float,
    k3: float,
    x: np.ndarray,
    y: np.ndarray,
    r2: np.ndarray,
    jacobian: bool = False,
) -> tuple[np.ndarray, ...]:
    """Distorted normalised coordinates ``xd, yd`` of ``x, y`` (``r2 = x^2 + y^2``) and, with
    ``jacobian``, their partial derivatives ``dxd_dx, dxd_dy, dyd_dx, dyd_dy``."""
    a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy = x * y
    xd = a * x + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x)
    yd = a * y + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy
    if not jacobian:
        return xd, yd
    da = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d a / d r2
    dxd_dx = a + 2.0 * x * x * da + 2.0 * p1 * y + 6.0 * p2 * x
    dxd_dy = 2.0 * x * y * da + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dx = 2.0 * x * y * da + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dy = a + 2.0 * y * y * da + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd, dxd_dx, dxd_dy, dyd_dx, dyd_dy


def distortion_jacobian(
    K: np.ndarray, dist: np.ndarray | None, xy: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of normalised undistorted coordinates ``xy`` (N, 2) and the 2 x 2
    Jacobians (N, 2, 2) of the pixels with respect to them: ``project_with_jacobians`` at
    ``z = 1`` without the parameters' Jacobians (the same numbers, a fraction of the work)."""
    k1, k2, p1, p2, k3 = _dist5(dist)
    fx, s, cx = K[0]
    fy, cy = K[1, 1], K[1, 2]
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    x, y = xy[:, 0], xy[:, 1]
    xd, yd, dxd_dx, dxd_dy, dyd_dx, dyd_dy = _distort(k1, k2, p1, p2, k3, x, y, x * x + y * y, True)
    J = np.empty((len(xy), 2, 2))
    J[:, 0, 0] = fx * dxd_dx + s * dyd_dx
    J[:, 0, 1] = fx * dxd_dy + s * dyd_dy
    J[:, 1, 0] = fy * dyd_dx
    J[:, 1, 1] = fy * dyd_dy
    return np.stack([fx * xd + s * yd + cx, fy * yd + cy], axis=1), J


def project_with_jacobians(
    K: np.ndarray, dist: np.ndarray | None, P_cam: np.ndarray, jacobians: bool = True
) -> Projection:
    """Project ``P_cam`` (N, 3) and return the analytic Jacobians (see :class:`Projection`)."""
    P = np.asarray(P_cam, dtype=float).reshape(-1, 3)
    k1, k2, p1, p2, k3 = _dist5(dist)
    fx, s, cx = K[0]
    fy, cy = K[1, 1], K[1, 2]
    X, Y, Z = P[:, 0], P[:, 1], P[:, 2]
    iz = 1.0 / Z
    x, y = X * iz, Y * iz
    r2 = x * x + y * y
    if not jacobians:
        xd, yd = _distort(k1, k2, p1, p2, k3, x, y, r2)[:2]
        return Projection(np.stack([fx * xd + s * yd + cx, fy * yd + cy], axis=1))
    xd, yd, dxd_dx, dxd_dy, dyd_dx, dyd_dy = _distort(k1, k2, p1, p2, k3, x, y, r2, True)
    px = np.stack([fx * xd + s * yd + cx, fy * yd + cy], axis=1)
    n = len(P)
    # pixel w.r.t. normalised (x, y)
    du_dx = fx * dxd_dx + s * dyd_dx
    du_dy = fx * dxd_dy + s * dyd_dy
    dv_dx = fy * dyd_dx
    dv_dy = fy * dyd_dy
    d_P = np.empty((n, 2, 3))
    d_P[:, 0, 0] = du_dx * iz
    d_P[:, 0, 1] = du_dy * iz
    d_P[:, 0, 2] = -(du_dx * x + du_dy * y) * iz
    d_P[:, 1, 0] = dv_dx * iz
    d_P[:, 1, 1] = dv_dy * iz
    d_P[:, 1, 2] = -(dv_dx * x + dv_dy * y) * iz
    d_K = np.zeros((n, 2, 5))
    d_K[:, 0, 0] = xd
    d_K[:, 1, 1] = yd
    d_K[:, 0, 2] = 1.0
    d_K[:, 1, 3] = 1.0
    d_K[:, 0, 4] = yd
    r4 = r2 * r2
    xy = x * y
    # distorted normalised coordinates w.r.t. (k1, k2, p1, p2, k3)
    dxd = np.stack([x * r2, x * r4, 2.0 * xy, r2 + 2.0 * x * x, x * r4 * r2], axis=1)
    dyd = np.stack([y * r2, y * r4, r2 + 2.0 * y * y, 2.0 * xy, y * r4 * r2], axis=1)
    d_dist = np.empty((n, 2, 5))
    d_dist[:, 0, :] = fx * dxd + s * dyd
    d_dist[:, 1, :] = fy * dyd
    return Projection(px, d_P, d_K, d_dist)


def undistort_normalised(
    K: np.ndarray, dist: np.ndarray | None, px: np.ndarray, iterations: int = 20
) -> np.ndarray:
    """Normalised undistorted coordinates (N, 2) of pixels (N, 2): the inverse of the model.

    Fixed-point iteration as ``cv2.undistortPoints`` does, then Gauss-Newton polish; accurate to
    well below 1e-6 px inside the image for realistic lenses.
    """
    d = _dist5(dist)
    px = np.asarray(px, dtype=float).reshape(-1, 2)
    yd = (px[:, 1] - K[1, 2]) / K[1, 1]
    xd = (px[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    x, y = xd.copy(), yd.copy()
    k1, k2, p1, p2, k3 = d
    for _ in range(iterations):
        r2 = x * x + y * y
        a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x = (xd - dx) / a
        y = (yd - dy) / a
    if np.any(d != 0.0):
        for _ in range(3):
            pr, J = distortion_jacobian(np.eye(3), d, np.stack([x, y], axis=1))
            r = np.stack([xd, yd], axis=1) - pr
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            x = x + (J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1]) / det
            y = y + (-J[:, 1, 0] * r[:, 0] + J[:, 0, 0] * r[:, 1]) / det
    return np.stack([x, y], axis=1)
