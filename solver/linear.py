"""Closed-form calibration from plane homographies (MATH.md Secs. 2-3; Malm and Heyden 2006).

The image of the absolute conic ``w = K^-T K^-1`` (symmetric, defined up to scale) is handled as
the vector ``w = (w11, w12, w22, w13, w23, w33)``; ``a' W b`` is linear in it with the
coefficient row :func:`conic_row` ``(a, b)``.
"""

from __future__ import annotations

import numpy as np

from slidecal.solver.errors import DegenerateError

W_NAMES = ("w11", "w12", "w22", "w13", "w23", "w33")


def conic_row(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Coefficients (6,) of the bilinear form ``a' W b`` on ``w = (w11, w12, w22, w13, w23, w33)``.

    ``a``, ``b``: (3,) homogeneous image vectors (pixels, or normalised pixels). Also accepts
    (m, 3) stacks and then returns (m, 6).
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    return np.stack(
        [
            a[..., 0] * b[..., 0],
            a[..., 0] * b[..., 1] + a[..., 1] * b[..., 0],
            a[..., 1] * b[..., 1],
            a[..., 0] * b[..., 2] + a[..., 2] * b[..., 0],
            a[..., 1] * b[..., 2] + a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 2],
        ],
        axis=-1,
    )


def W_from_w(w: np.ndarray) -> np.ndarray:
    """Symmetric matrix (3, 3) of the conic vector ``w`` (6,)."""
    w11, w12, w22, w13, w23, w33 = np.asarray(w, dtype=float)
    return np.array([[w11, w12, w13], [w12, w22, w23], [w13, w23, w33]])


def zhang_rows(H: np.ndarray) -> np.ndarray:
    """Zhang's two rows (2, 6) on ``w`` of one plane homography (MATH.md eqs. 10-11).

    ``H`` (3, 3): board plane (X, Y, 1) to image (pixels or normalised pixels). Rows:
    ``h1' W h2 = 0`` (eq. 10) and ``h1' W h1 - h2' W h2 = 0`` (eq. 11).
    """
    H = np.asarray(H, dtype=float)
    h1, h2 = H[:, 0], H[:, 1]
    return np.stack([conic_row(h1, h2), conic_row(h1, h1) - conic_row(h2, h2)])


def K_from_w(w: np.ndarray) -> np.ndarray:
    """Intrinsic matrix (3, 3), ``K[2, 2] = 1``, from the conic vector ``w`` (6,) (any scale).

    ``w = K^-T K^-1`` up to scale; the sign is flipped when ``w11 < 0``, then the Cholesky factor
    ``W = L L'`` gives ``K = inv(L')``. Raises ``DegenerateError`` when ``W`` is not positive
    definite.
    """
    W = W_from_w(w)
    if not np.all(np.isfinite(W)) or np.linalg.norm(W) == 0.0:
        raise DegenerateError(
            "the image of the absolute conic is zero or not finite: the linear system has no "
            "unique solution; add frames, orientations or motion knowledge"
        )
    if W[0, 0] < 0:
        W = -W
    W = W / np.linalg.norm(W)
    try:
        L = np.linalg.cholesky(W)
    except np.linalg.LinAlgError:
        raise DegenerateError(
            "the estimated image of the absolute conic is not positive definite, which means "
            "degenerate or inconsistent data: check the motion knowledge (step lengths, "
            "directions, board square size), the detections, and that the configuration is not "
            "degenerate (MATH.md Sec. 7)"
        ) from None
    K = np.linalg.inv(L.T)
    return K / K[2, 2]


def w_from_K(K: np.ndarray) -> np.ndarray:
    """Conic vector ``w`` (6,) of ``W = K^-T K^-1``, normalised to unit norm, ``w11 > 0``.

    ``K`` (3, 3) upper triangular intrinsics (pixels).
    """
    Ki = np.linalg.inv(np.asarray(K, dtype=float))
    W = Ki.T @ Ki
    w = np.array([W[0, 0], W[0, 1], W[1, 1], W[0, 2], W[1, 2], W[2, 2]])
    return w / np.linalg.norm(w)


def image_normalisation(width: float, height: float) -> np.ndarray:
    """Isotropic image normalisation ``N`` (3, 3): pixels to centred, unit-scale coordinates.

    ``x_n = N x_px`` moves the image centre to the origin and divides both axes by the same
    scale ``(width + height) / 2`` (the same scale on both axes keeps the unit-aspect basis of
    ``w`` valid). Intrinsics transform as ``K_n = N K``.
    """
    s = 2.0 / (float(width) + float(height))
    cx = (float(width) - 1.0) / 2.0
    cy = (float(height) - 1.0) / 2.0
    return np.array([[s, 0.0, -s * cx], [0.0, s, -s * cy], [0.0, 0.0, 1.0]])
