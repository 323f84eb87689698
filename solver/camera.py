"""The camera model: pinhole with skew and one of three lens models (OpenCV's order and formulas).

``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]``; the distortion vector's length names the lens model
(:data:`DISTORTION_MODELS`): 5 ``opencv5`` (k1, k2, p1, p2, k3), 8 ``rational`` (k1, k2, p1, p2,
k3, k4, k5, k6), 4 ``fisheye`` (k1, k2, k3, k4). A point ``P_cam = (X, Y, Z)`` in the camera frame
(metres) projects to pixels (pixel (0, 0) is the centre of the top-left pixel):

    x, y = X / Z, Y / Z;  r2 = x^2 + y^2;  xd = a x + tx;  yd = a y + ty
    u = fx xd + s yd + cx;  v = fy yd + cy

with the radial factor ``a(r2)`` and the tangential terms ``tx, ty`` of the model:

    opencv5, rational:  a = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
                        tx = 2 p1 x y + p2 (r2 + 2 x^2);  ty = p1 (r2 + 2 y^2) + 2 p2 x y
    fisheye:            theta = atan(sqrt(r2));  a = theta (1 + k1 theta^2 + k2 theta^4
                        + k3 theta^6 + k4 theta^8) / sqrt(r2);  tx = ty = 0

These are the models of ``cv2.projectPoints`` and ``cv2.fisheye.projectPoints`` (whose skew is
``s / fx``); the fisheye model is Kannala-Brandt's, depthai's ``Fisheye`` and Kalibr's
``equidistant``. Jacobians are analytic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "s")
#: The lens models by name: their distortion coefficients, in order.
DISTORTION_MODELS = {
    "opencv5": ("k1", "k2", "p1", "p2", "k3"),
    "rational": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "fisheye": ("k1", "k2", "k3", "k4"),
}
_BY_LENGTH = {len(v): k for k, v in DISTORTION_MODELS.items()}
_SMALL_R2 = 1e-12  # below it the fisheye factor is its series 1 + (k1 - 1/3) r2 (exact to 1e-24)


def K_matrix(fx: float, fy: float, cx: float, cy: float, s: float = 0.0) -> np.ndarray:
    """The 3x3 intrinsic matrix in pixels."""
    return np.array([[fx, s, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def distortion_model(dist: np.ndarray | None) -> str:
    """The lens model a distortion vector describes: its length names it (None: opencv5)."""
    return _BY_LENGTH.get(0 if dist is None else np.size(dist), "opencv5")


def as_distortion(dist: np.ndarray | None) -> np.ndarray:
    """``dist`` as a float vector of its model's length (an opencv5 vector padded with zeros or
    cut to five values, as OpenCV reads a short one)."""
    dd = np.zeros(0) if dist is None else np.asarray(dist, dtype=float).reshape(-1)
    if len(dd) in (4, 8):
        return dd.copy()
    d = np.zeros(5)
    d[: min(5, len(dd))] = dd[:5]
    return d


def zero_distortion(model: str) -> np.ndarray:
    """The distortion vector of no distortion in lens model ``model``."""
    return np.zeros(len(DISTORTION_MODELS[model]))


def project(K: np.ndarray, dist: np.ndarray | None, P_cam: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of points ``P_cam`` (N, 3) in the camera frame."""
    return project_with_jacobians(K, dist, P_cam, jacobians=False).px


@dataclass(frozen=True)
class Projection:
    """Projected pixels and, on request, their Jacobians.

    ``px`` (N, 2); ``d_P`` (N, 2, 3) with respect to the camera-frame point; ``d_K`` (N, 2, 5)
    with respect to (fx, fy, cx, cy, s); ``d_dist`` (N, 2, len(dist)) with respect to the
    distortion coefficients in their model's order.
    """

    px: np.ndarray
    d_P: np.ndarray | None = None
    d_K: np.ndarray | None = None
    d_dist: np.ndarray | None = None


def _radial(d: np.ndarray, r2: np.ndarray, jacobian: bool) -> tuple[np.ndarray, ...]:
    """The radial factor ``a`` of the model of ``d`` at ``r2`` and, with ``jacobian``,
    ``da / dr2`` and ``da / dk``, one (N,) array per radial coefficient."""
    if len(d) == 4:  # fisheye
        r2s = np.maximum(r2, _SMALL_R2)
        r = np.sqrt(r2s)
        th = np.arctan(r)
        t2 = th * th
        powers = np.stack([t2, t2 * t2, t2**3, t2**4], axis=1)  # theta^2 .. theta^8
        poly = 1.0 + powers @ d
        small = r2 < _SMALL_R2
        a = np.where(small, 1.0 + (d[0] - 1.0 / 3.0) * r2, th * poly / r)
        if not jacobian:
            return (a,)
        dthd_dth = 1.0 + powers @ (d * np.array([3.0, 5.0, 7.0, 9.0]))
        dthd_dr = dthd_dth / (1.0 + r2s)
        da_dr2 = np.where(small, d[0] - 1.0 / 3.0, (dthd_dr * r - th * poly) / (2.0 * r2s * r))
        return a, da_dr2, list((powers * (th / r)[:, None]).T)
    k1, k2, k3 = d[0], d[1], d[4]
    a = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    da_dr2 = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2) if jacobian else None
    r4 = r2 * r2
    powers = [r2, r4, r4 * r2]  # da / d(k1, k2, k3) of opencv5
    if len(d) == 8:  # a = numerator / denominator
        k4, k5, k6 = d[5], d[6], d[7]
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        a = a / den
        if jacobian:
            da_dr2 = (da_dr2 - a * (k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2))) / den
            powers = [q / den for q in powers]
            powers += [-a * q for q in powers]
    return (a, da_dr2, powers) if jacobian else (a,)


def _distort(
    d: np.ndarray, x: np.ndarray, y: np.ndarray, jacobian: bool = False, params: bool = True
) -> tuple:
    """Distorted normalised coordinates ``xd, yd`` of ``x, y`` and, with ``jacobian``, their
    (N, 2, 2) derivatives with respect to ``(x, y)`` and (with ``params``) the (N, 2, len(d))
    ones with respect to ``d``."""
    r2 = x * x + y * y
    rad = _radial(d, r2, jacobian)
    a = rad[0]
    xy = x * y
    p1, p2 = (0.0, 0.0) if len(d) == 4 else (d[2], d[3])
    xd = a * x + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x)
    yd = a * y + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy
    if not jacobian:
        return xd, yd
    da, da_dk = rad[1], rad[2]
    J = np.empty((len(x), 2, 2))
    J[:, 0, 0] = a + 2.0 * x * x * da + 2.0 * p1 * y + 6.0 * p2 * x
    J[:, 0, 1] = J[:, 1, 0] = 2.0 * xy * da + 2.0 * p1 * x + 2.0 * p2 * y
    J[:, 1, 1] = a + 2.0 * y * y * da + 6.0 * p1 * y + 2.0 * p2 * x
    if not params:
        return xd, yd, J
    gx, gy = [x * g for g in da_dk], [y * g for g in da_dk]
    if len(d) != 4:  # OpenCV's order: k1 k2 p1 p2 k3 (k4 k5 k6)
        gx = [gx[0], gx[1], 2.0 * xy, r2 + 2.0 * x * x, *gx[2:]]
        gy = [gy[0], gy[1], r2 + 2.0 * y * y, 2.0 * xy, *gy[2:]]
    return xd, yd, J, np.stack(gx + gy, axis=1).reshape(len(x), 2, len(gx))


def _pixels(K: np.ndarray, xd: np.ndarray, yd: np.ndarray, *d_dist: np.ndarray) -> tuple:
    """Pixels (N, 2) of distorted normalised ``xd, yd`` and, for each (N, 2, k) derivative of
    ``(xd, yd)`` given, the pixels' (N, 2, k)."""
    fx, s, cx = K[0]
    fy, cy = K[1, 1], K[1, 2]
    out = [np.stack([fx * xd + s * yd + cx, fy * yd + cy], axis=1)]
    for D in d_dist:
        J = D * np.array([[fx], [fy]])
        if s:
            J[:, 0] += s * D[:, 1]
        out.append(J)
    return tuple(out)


def distortion_jacobian(
    K: np.ndarray, dist: np.ndarray | None, xy: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of normalised undistorted coordinates ``xy`` (N, 2) and the 2 x 2
    Jacobians (N, 2, 2) of the pixels with respect to them: ``project_with_jacobians`` at
    ``z = 1`` without the parameters' Jacobians (the same numbers, a fraction of the work)."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    return _pixels(K, *_distort(as_distortion(dist), xy[:, 0], xy[:, 1], True, params=False))


def project_with_jacobians(
    K: np.ndarray,
    dist: np.ndarray | None,
    P_cam: np.ndarray,
    jacobians: bool = True,
    params: bool = True,
) -> Projection:
    """Project ``P_cam`` (N, 3) and return the analytic Jacobians (see :class:`Projection`);
    ``params`` False: the point's alone (``d_K``, ``d_dist`` None: a pose fit's)."""
    P = np.asarray(P_cam, dtype=float).reshape(-1, 3)
    d = as_distortion(dist)
    iz = 1.0 / P[:, 2]
    x, y = P[:, 0] * iz, P[:, 1] * iz
    if not jacobians:
        return Projection(_pixels(K, *_distort(d, x, y))[0])
    xd, yd, *d_xy = _distort(d, x, y, True, params)
    px, J, *d_dist = _pixels(K, xd, yd, *d_xy)
    d_P = np.empty((len(P), 2, 3))
    d_P[:, :, :2] = J * iz[:, None, None]
    d_P[:, :, 2] = -(J[:, :, 0] * x[:, None] + J[:, :, 1] * y[:, None]) * iz[:, None]
    if not params:
        return Projection(px, d_P)
    d_K = np.zeros((len(P), 2, 5))
    d_K[:, 0, 0], d_K[:, 1, 1], d_K[:, 0, 4] = xd, yd, yd  # fx, fy, s
    d_K[:, 0, 2] = d_K[:, 1, 3] = 1.0
    return Projection(px, d_P, d_K, d_dist[0])


def undistort_normalised(
    K: np.ndarray, dist: np.ndarray | None, px: np.ndarray, iterations: int = 20
) -> np.ndarray:
    """Normalised undistorted coordinates (N, 2) of pixels (N, 2): the inverse of the model.

    Fixed-point iteration as ``cv2.undistortPoints`` does (a fisheye starts from the equidistant
    inverse instead), then Gauss-Newton polish; accurate to well below 1e-6 px inside the image
    for realistic lenses.
    """
    d = as_distortion(dist)
    px = np.asarray(px, dtype=float).reshape(-1, 2)
    yd = (px[:, 1] - K[1, 2]) / K[1, 1]
    xd = (px[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    polish = 3
    if len(d) == 4:  # theta ~ r_d: the equidistant lens; Newton does the rest
        rd = np.maximum(np.hypot(xd, yd), 1e-12)
        scale = np.tan(np.minimum(rd, 1.4)) / rd  # below 80 degrees off the axis
        x, y = xd * scale, yd * scale
        polish = 10
    else:
        x, y = xd.copy(), yd.copy()
        p1, p2 = d[2], d[3]
        for _ in range(iterations):
            r2 = x * x + y * y
            a = _radial(d, r2, False)[0]
            dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            x = (xd - dx) / a
            y = (yd - dy) / a
    if np.any(d != 0.0) or len(d) == 4:
        for _ in range(polish):
            pr, J = distortion_jacobian(np.eye(3), d, np.stack([x, y], axis=1))
            r = np.stack([xd, yd], axis=1) - pr
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            x = x + (J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1]) / det
            y = y + (-J[:, 1, 0] * r[:, 0] + J[:, 0, 0] * r[:, 1]) / det
    return np.stack([x, y], axis=1)


def opencv_view(
    K: np.ndarray, dist: np.ndarray | None, px: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """``K``, distortion and pixels ``px`` (N, 2) for OpenCV's pinhole functions (``solvePnP``):
    as given for the models they know; for a fisheye the pixels where the undistorted pinhole
    camera ``K`` sees the same rays, and no distortion."""
    d = as_distortion(dist)
    if len(d) != 4:
        return K, d, px
    xy = undistort_normalised(K, d, px)
    return K, None, np.ascontiguousarray(xy @ K[:2, :2].T + K[:2, 2])
