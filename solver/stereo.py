"""Stereo heads: the infinite homography and the joint linear calibration of two cameras.

MATH.md Sec. 8 (Malm and Heyden 2006, Sec. IV). Two cameras ``a`` and ``b`` are rigidly joined
with ``X_a = R_a_b X_b + t_a_b`` (camera-frame coordinates). For a board pose seen by both,
``H_a = lambda_a K_a [r1 r2 t]_a`` and ``H_b = lambda_b K_b [r1 r2 t]_b`` (plane to pixels), and the
infinite homography ``H_inf = K_a R_a_b K_b^-1`` maps camera b's image to camera a's
(``x_a ~ H_inf x_b`` for points at infinity).

Conventions used throughout: homographies are (3, 3) from board-plane coordinates ``(X, Y, 1)`` to
pixels; ``sizes`` are ``((width_a, height_a), (width_b, height_b))`` in pixels; every linear system
is solved in isotropically normalised image coordinates (``linear.image_normalisation``) with the
homography columns scaled to unit norm, unit-norm rows and unit-norm columns before the SVD
(MATH.md Sec. 3, "Numerical conditioning").
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.geometry import project_to_SO3
from slidecal.solver.linear import K_from_w, W_from_w, image_normalisation, zhang_rows

# Relative size of the third singular value of the stacked (unit) columns h_b1, h_b2 of all views
# below which the views are taken as one orientation (pure translation): H_inf is then not
# determined (a rotation of the head by less than about 0.1 deg between views).
_MIN_ORIENTATION_SPREAD = 2e-3
# Relative gap between the two smallest singular values of a homogeneous system below which its
# null space is taken as more than one-dimensional.
_MIN_NULL_GAP = 1e-9


def _check_homographies(H: np.ndarray, name: str) -> np.ndarray:
    H = np.asarray(H, dtype=float)
    if H.ndim == 2:
        H = H[None]
    if H.ndim != 3 or H.shape[1:] != (3, 3):
        raise InputError(f"{name} must be an (n, 3, 3) stack of homographies, got {H.shape}")
    if not np.all(np.isfinite(H)):
        raise InputError(f"{name} contains NaN or infinite entries: re-estimate the homographies")
    return H


def _normaliser(H: np.ndarray, size: tuple[float, float] | None) -> np.ndarray:
    """Image normalisation (3, 3) from the image size, or, without it, from the data.

    Without a size: centre on the mean image of the board origin and scale isotropically by its
    mean distance from the image origin (a stand-in for the image size).
    """
    if size is not None:
        return image_normalisation(float(size[0]), float(size[1]))
    o = H[:, :2, 2] / H[:, 2:3, 2]
    s = 1.0 / max(float(np.mean(np.linalg.norm(o, axis=1))), 1.0)
    return np.array([[s, 0.0, 0.0], [0.0, s, 0.0], [0.0, 0.0, 1.0]])


def _unit_columns12(Hn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scale each (3, 3) so that ``[h1 h2]`` has unit Frobenius norm; returns (scaled, scales)."""
    s = np.linalg.norm(Hn[:, :, :2], axis=(1, 2))
    return Hn / s[:, None, None], s


def _null_vector(A: np.ndarray, what: str) -> np.ndarray:
    """Unit null vector of ``A`` after unit-norm rows and columns (equilibration), unscaled."""
    rn = np.linalg.norm(A, axis=1)
    A = A[rn > 0] / rn[rn > 0, None]
    cn = np.linalg.norm(A, axis=0)
    if np.any(cn == 0):
        raise DegenerateError(f"{what}: an unknown appears in no equation; add views")
    A = A / cn
    _, sv, Vt = np.linalg.svd(A, full_matrices=False)
    if len(sv) < A.shape[1] or sv[-2] < _MIN_NULL_GAP * sv[0]:
        raise DegenerateError(
            f"{what}: the linear system has more than one solution (too few or degenerate "
            "views); add stereo views with different board orientations"
        )
    x = Vt[-1] / cn
    return x / np.linalg.norm(x)


def infinite_homography(
    H_a: np.ndarray,
    H_b: np.ndarray,
    *,
    sizes: Sequence[tuple[float, float]] | None = None,
    refine: bool = True,
    max_iterations: int = 50,
) -> tuple[np.ndarray, np.ndarray]:
    """The infinite homography from camera b's image to camera a's, from stereo views.

    Parameters
    ----------
    H_a, H_b : (n, 3, 3)
        Board plane to pixel homographies of camera a and camera b; view k is the same board
        pose seen by both cameras. n >= 2 with different board orientations.
    sizes : ((width_a, height_a), (width_b, height_b)) in pixels, optional
        Image sizes for the normalisation; without them a data-based scale is used.
    refine : bool
        After the linear solution (eqs. 58-61), minimise ``sum_k ||A_k - mu_k H B_k||^2`` over
        ``H`` and ``mu_k`` by alternating least squares, where ``A_k``, ``B_k`` are the
        normalised, unit-norm columns ``[h1 h2]`` of view k (errors in camera a's columns).

    Returns
    -------
    H_inf : (3, 3)
        ``x_a ~ H_inf x_b`` in pixels, ``H_inf = K_a R_a_b K_b^-1`` up to scale, normalised to
        ``det(H_inf) = 1``.
    mu : (n,)
        Per-view scales with ``h_a1 = mu_k H_inf h_b1`` and ``h_a2 = mu_k H_inf h_b2`` for the
        homographies as given (eqs. 58-59).
    """
    H_a = _check_homographies(H_a, "H_a")
    H_b = _check_homographies(H_b, "H_b")
    n = len(H_a)
    if len(H_b) != n:
        raise InputError(f"H_a has {n} views but H_b has {len(H_b)}: pass the same stereo views")
    if n < 2:
        raise DegenerateError(
            "the infinite homography needs at least two stereo views with different board "
            f"orientations (eqs. 58-61), got {n}; add views"
        )
    N_a = _normaliser(H_a, None if sizes is None else sizes[0])
    N_b = _normaliser(H_b, None if sizes is None else sizes[1])
    A, alpha = _unit_columns12(N_a @ H_a)
    B, beta = _unit_columns12(N_b @ H_b)
    A, B = A[:, :, :2], B[:, :, :2]  # (n, 3, 2): only h1, h2 enter (eqs. 58-59)

    Bcols = np.concatenate(list(B), axis=1)  # (3, 2n)
    sB = np.linalg.svd(Bcols, compute_uv=False)
    if sB[2] < _MIN_ORIENTATION_SPREAD * sB[0]:
        raise DegenerateError(
            "all stereo views have the same board orientation (pure translations or parallel "
            "views): the infinite homography is not determined; add views with the head rotated "
            "by several degrees about at least one more axis"
        )

    # Eqs. 58-59 as nu_k a_ki - H b_ki = 0 (nu_k = 1 / mu_k): unknowns vec(H) (row-major), nu.
    rows = np.zeros((6 * n, 9 + n))
    for k in range(n):
        for i in range(2):
            for r in range(3):
                row = rows[6 * k + 3 * i + r]
                row[3 * r : 3 * r + 3] = -B[k, :, i]
                row[9 + k] = A[k, r, i]
    x = _null_vector(rows, "infinite homography")
    Hn = x[:9].reshape(3, 3)
    nu = x[9:]
    if np.any(np.abs(nu) < 1e-12):
        raise DegenerateError(
            "infinite homography: a view's scale came out zero, the views are inconsistent "
            "(check that H_a[k] and H_b[k] are the same board pose)"
        )
    mu_n = 1.0 / nu

    if refine:
        for _ in range(max_iterations):
            lhs = np.einsum("k,kri,kci->rc", mu_n, A, B)
            rhs = np.einsum("k,kri,kci->rc", mu_n**2, B, B)
            H_new = np.linalg.solve(rhs.T, lhs.T).T
            H_new /= np.linalg.norm(H_new)
            HB = np.einsum("rc,kci->kri", H_new, B)
            mu_n = np.einsum("kri,kri->k", A, HB) / np.einsum("kri,kri->k", HB, HB)
            step = min(np.linalg.norm(H_new - Hn), np.linalg.norm(H_new + Hn))
            Hn = H_new
            if step < 1e-13:
                break

    H_inf = np.linalg.solve(N_a, Hn @ N_b)
    d = np.linalg.det(H_inf)
    if not np.isfinite(d) or abs(d) < 1e-300:
        raise DegenerateError("infinite homography: the estimate is singular; add views")
    c = np.sign(d) * abs(d) ** (1.0 / 3.0)
    H_inf = H_inf / c
    # h_a = (alpha / beta) mu_n N_a^-1 Hn N_b h_b = (alpha / beta) mu_n c H_inf h_b
    mu = alpha / beta * mu_n * c
    return H_inf, mu


def w_basis(skew: bool, unit_aspect: bool) -> np.ndarray:
    """Basis (6, m) of the conic vectors ``w = (w11, w12, w22, w13, w23, w33)`` allowed.

    ``skew``: skew estimated (else ``w12 = 0``). ``unit_aspect``: ``fx == fy`` (then also
    ``w11 = w22``; needs ``skew=False``). Valid in isotropically normalised coordinates too.
    """
    if unit_aspect and skew:
        raise InputError(
            "unit_aspect with an estimated skew is not linear in w; use skew=False with "
            "unit_aspect=True"
        )
    B = np.eye(6)
    if not skew:
        B = B[:, [0, 2, 3, 4, 5]]
    if unit_aspect:
        B = np.column_stack([B[:, 0] + B[:, 1], B[:, 2:]])
    return B


def conic_transfer_matrix(H: np.ndarray) -> np.ndarray:
    """The (6, 6) matrix mapping the conic vector ``w`` to that of ``H' W H`` (for eq. 62)."""
    M = np.zeros((6, 6))
    for j in range(6):
        e = np.zeros(6)
        e[j] = 1.0
        C = H.T @ W_from_w(e) @ H
        M[:, j] = [C[0, 0], C[0, 1], C[1, 1], C[0, 2], C[1, 2], C[2, 2]]
    return M


def _zhang_block(Hn: np.ndarray, basis: np.ndarray) -> np.ndarray:
    return np.concatenate([zhang_rows(H) for H in Hn]) @ basis


def rig_linear_intrinsics(
    Hs_a: np.ndarray,
    Hs_b: np.ndarray,
    H_inf: np.ndarray | None,
    *,
    skew: bool = False,
    unit_aspect: bool = False,
    sizes: Sequence[tuple[float, float]],
) -> tuple[np.ndarray, np.ndarray]:
    """Joint linear intrinsics of both cameras of a stereo head (eqs. 10-11 with eq. 62).

    One homogeneous system in ``(w_a, s w_b)``: Zhang's two rows per homography of each camera
    and the six rows of ``H_inf' W_a H_inf = s W_b`` (eq. 62); the unknown scale ``s`` of eq. 62
    is carried by ``w_b``, whose own rows are homogeneous. Solved in normalised image
    coordinates, with ``H_inf`` there scaled to ``det = 1``, unit-norm rows and columns.

    Parameters
    ----------
    Hs_a, Hs_b : (n_a, 3, 3), (n_b, 3, 3)
        Board plane to pixel homographies of each camera (any views, not necessarily paired).
    H_inf : (3, 3) or None
        Camera b's image to camera a's, in pixels (:func:`infinite_homography`); None solves
        each camera alone with the same conditioning (the separate calibration).
    skew, unit_aspect : bool
        Estimate the skew (else zero); assume ``fx == fy``.
    sizes : ((width_a, height_a), (width_b, height_b)) in pixels.

    Returns
    -------
    K_a, K_b : (3, 3) intrinsics in pixels, ``K[2, 2] = 1``.
    """
    Hs_a = _check_homographies(Hs_a, "Hs_a")
    Hs_b = _check_homographies(Hs_b, "Hs_b")
    basis = w_basis(skew, unit_aspect)
    m = basis.shape[1]
    N_a = image_normalisation(*sizes[0])
    N_b = image_normalisation(*sizes[1])
    Za = _zhang_block(_unit_columns12(N_a @ Hs_a)[0], basis)
    Zb = _zhang_block(_unit_columns12(N_b @ Hs_b)[0], basis)
    if H_inf is None:
        w_a = basis @ _null_vector(Za, "camera a alone (eqs. 10-11)")
        w_b = basis @ _null_vector(Zb, "camera b alone (eqs. 10-11)")
    else:
        Hn = N_a @ np.asarray(H_inf, dtype=float) @ np.linalg.inv(N_b)
        d = np.linalg.det(Hn)
        Hn = Hn / (np.sign(d) * abs(d) ** (1.0 / 3.0))
        coupling = np.hstack([conic_transfer_matrix(Hn) @ basis, -basis])  # eq. 62
        A = np.vstack(
            [
                np.hstack([Za, np.zeros((len(Za), m))]),
                np.hstack([np.zeros((len(Zb), m)), Zb]),
                coupling,
            ]
        )
        x = _null_vector(A, "joint stereo calibration (eqs. 10-11, 62)")
        w_a, w_b = basis @ x[:m], basis @ x[m:]
    K_a = np.linalg.solve(N_a, K_from_w(w_a))
    K_b = np.linalg.solve(N_b, K_from_w(w_b))
    return K_a / K_a[2, 2], K_b / K_b[2, 2]


def relative_rotation(K_a: np.ndarray, K_b: np.ndarray, H_inf: np.ndarray) -> np.ndarray:
    """``R_a_b`` (3, 3) from ``H_inf = K_a R_a_b K_b^-1`` (eq. 63), projected onto SO(3).

    ``K_a``, ``K_b``: (3, 3) intrinsics in pixels; ``H_inf``: (3, 3), any scale, camera b's image
    to camera a's. ``X_a = R_a_b X_b + t_a_b`` for camera-frame coordinates.
    """
    M = np.linalg.solve(np.asarray(K_a, float), np.asarray(H_inf, float) @ np.asarray(K_b, float))
    d = np.linalg.det(M)
    if not np.isfinite(d) or abs(d) < 1e-300:
        raise DegenerateError("relative_rotation: K_a^-1 H_inf K_b is singular; check H_inf")
    return project_to_SO3(M / (np.sign(d) * abs(d) ** (1.0 / 3.0)))
