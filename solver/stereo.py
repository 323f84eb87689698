"""Stereo heads: the infinite homography and the joint linear calibration of two cameras.

docs/METHOD.md Sec. 8 (Malm and Heyden 2006, Sec. IV). Two cameras ``a`` and ``b`` are rigidly
joined
with ``X_a = R_a_b X_b + t_a_b`` (camera-frame coordinates). For a board pose seen by both,
``H_a = lambda_a K_a [r1 r2 t]_a`` and ``H_b = lambda_b K_b [r1 r2 t]_b`` (plane to pixels), and the
infinite homography ``H_inf = K_a R_a_b K_b^-1`` maps camera b's image to camera a's
(``x_a ~ H_inf x_b`` for points at infinity).

Conventions used throughout: homographies are (3, 3) from board-plane coordinates ``(X, Y, 1)`` to
pixels; ``sizes`` are ``((width_a, height_a), (width_b, height_b))`` in pixels; every linear system
is solved in isotropically normalised image coordinates (``linear.image_normalisation``) with the
homography columns scaled to unit norm, unit-norm rows and unit-norm columns before the SVD
(docs/METHOD.md Sec. 3, "Numerical conditioning").
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.geometry import project_to_SO3
from slidecal.solver.linear import (
    K_from_w,
    LinearGroup,
    W_from_w,
    conic_row,
    image_normalisation,
    zhang_rows,
)

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


_TRANSLATION_KNOWLEDGE = ("robot", "board_translation", "board_direction", "lengths")


def _group_common_h12(H: np.ndarray) -> np.ndarray:
    """Rescale each ``H[k]`` (k >= 1) so its ``h1, h2`` match frame 0's (eq. 13 needs one scale)."""
    H = np.array(H, dtype=float)
    ref = H[0][:, :2].reshape(-1)
    for k in range(1, len(H)):
        v = H[k][:, :2].reshape(-1)
        H[k] *= (ref @ v) / (v @ v)
    return H


def rig_linear_intrinsics_translation(
    groups_a: Sequence[LinearGroup],
    groups_b: Sequence[LinearGroup],
    knowledge: str,
    *,
    skew: bool = False,
    unit_aspect: bool = False,
    sizes: Sequence[tuple[float, float]],
    use_eq62: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Joint linear intrinsics of a stereo head translated in front of a board (eqs. 33-42).

    Both cameras undergo the same translations ``T`` (board frame). Unknowns ``(w_a, w_b, c_1
    .. c_G)``: the scales of ``w_a`` and ``w_b`` are chosen so that both cameras share
    ``c_g = lambda_g^2`` of each orientation group. Rows: per camera and group Zhang's rows with
    ``c_g`` (eqs. 10-11) and the knowledge rows of docs/METHOD.md Sec. 3 (as
    ``slidecal.solver.linear.linear_system``); coupling rows for every translation k of a group,
    ``h_a1' W_a Delta_ak = h_b1' W_b Delta_bk`` (both ``T_x c``), the same with ``h2`` (``T_y c``)
    and ``Delta_ai' W_a Delta_ak = Delta_bi' W_b Delta_bk`` (``T_i . T_k c``) for ``i <= k``,
    which hold whatever the knowledge. With two or more groups, camera b's groups are first
    rescaled by the per-view scales ``mu_g`` of :func:`infinite_homography` (computed from the
    groups' reference frames) so that one ``c_g`` serves both cameras, and, with ``use_eq62``,
    the six rows of eq. 62 are added. Conditioning as in the module docstring, plus a common
    board-side scale (translations scaled with it).

    Parameters
    ----------
    groups_a, groups_b : sequences of ``slidecal.solver.linear.LinearGroup``
        Group g of camera a and of camera b hold the same frames: ``H`` (n_g, 3, 3) board plane
        to pixels. ``motion`` (n_g, 3) is read from ``groups_a`` (``groups_b``'s must be None or
        equal); its meaning follows ``knowledge`` (see ``LinearGroup``), in board units.
    knowledge : "robot", "board_translation", "board_direction" or "lengths"
    skew, unit_aspect : bool
        Estimate the skew (else zero); assume ``fx == fy``.
    sizes : ((width_a, height_a), (width_b, height_b)) in pixels.
    use_eq62 : bool
        Add eq. 62 when there are two or more groups (with one group ``H_inf`` is unknown).

    Returns
    -------
    K_a, K_b : (3, 3) intrinsics in pixels, ``K[2, 2] = 1``.
    """
    if knowledge not in _TRANSLATION_KNOWLEDGE:
        raise InputError(
            f"unknown motion knowledge {knowledge!r} for a translated stereo head; use one of "
            f"{_TRANSLATION_KNOWLEDGE} (general motion: rig_linear_intrinsics)"
        )
    G = len(groups_a)
    if G == 0 or len(groups_b) != G:
        raise InputError(
            f"groups_a has {G} groups and groups_b {len(groups_b)}: pass the same non-empty "
            "orientation groups for both cameras"
        )
    Ha, Hb, motions = [], [], []
    for g, (ga, gb) in enumerate(zip(groups_a, groups_b, strict=True)):
        A = _check_homographies(ga.H, f"groups_a[{g}].H")
        B = _check_homographies(gb.H, f"groups_b[{g}].H")
        if len(A) != len(B) or len(A) < 2:
            raise InputError(
                f"group {g}: camera a has {len(A)} frames, camera b {len(B)}; both need the same "
                "frames, at least two (one translation)"
            )
        mot = None if ga.motion is None else np.asarray(ga.motion, dtype=float)
        if mot is None or mot.shape != (len(A), 3):
            raise InputError(f"group {g}: groups_a[{g}].motion must be ({len(A)}, 3)")
        if gb.motion is not None and not np.allclose(np.asarray(gb.motion, float), mot):
            raise InputError(
                f"group {g}: the two cameras' motions differ; a rigid head has one translation "
                "per frame: pass it in groups_a and None (or the same) in groups_b"
            )
        Ha.append(_group_common_h12(A))
        Hb.append(_group_common_h12(B))
        motions.append(mot)
    H_inf = None
    if G >= 2:
        H_inf, mu = infinite_homography(
            np.array([H[0] for H in Ha]), np.array([H[0] for H in Hb]), sizes=sizes
        )
        Hb = [H * m for H, m in zip(Hb, mu, strict=True)]  # now h_a = H_inf h_b per group

    N_a = image_normalisation(*sizes[0])
    N_b = image_normalisation(*sizes[1])
    Ha = [np.einsum("ij,kjl->kil", N_a, H) for H in Ha]
    Hb = [np.einsum("ij,kjl->kil", N_b, H) for H in Hb]
    refs = [H[0] for H in Ha + Hb]
    sigma = float(
        np.median([np.linalg.norm(H[:, 2]) / np.linalg.norm(H[:, :2]) * np.sqrt(2) for H in refs])
    )
    f = 1.0 / np.linalg.norm(Ha[0][0][:, :2] * sigma)
    S = np.diag([sigma * f, sigma * f, f])  # board-side scale, then one common magnitude
    Ha = [H @ S for H in Ha]
    Hb = [H @ S for H in Hb]
    if G == 1:  # no relation between the cameras' homography scales: balance b on its own
        Hb = [Hb[0] / np.linalg.norm(Hb[0][0][:, :2])]
    motions = [m / sigma for m in motions]

    basis = w_basis(skew, unit_aspect)
    m = basis.shape[1]
    n_x = 2 * m + G
    rows: list[np.ndarray] = []

    def add(conic_a=None, conic_b=None, g: int | None = None, c_coef: float = 0.0) -> None:
        r = np.zeros(n_x)
        if conic_a is not None:
            r[:m] = conic_a @ basis
        if conic_b is not None:
            r[m : 2 * m] = conic_b @ basis
        if g is not None:
            r[2 * m + g] = c_coef
        rows.append(r)

    for g in range(G):
        T = motions[g]
        for cam, H in (("a", Ha[g]), ("b", Hb[g])):

            def put(conic, gg=None, cc=0.0, cam=cam):
                add(conic if cam == "a" else None, conic if cam == "b" else None, gg, cc)

            h1, h2 = H[0][:, 0], H[0][:, 1]
            put(conic_row(h1, h2))  # eq. 10
            put(conic_row(h1, h1), g, -1.0)  # eq. 11
            put(conic_row(h2, h2), g, -1.0)  # eq. 11
            D = [H[0][:, 2] - H[k][:, 2] for k in range(len(H))]  # eqs. 12-13
            for k in range(1, len(H)):
                if knowledge == "lengths":  # eq. 27
                    put(conic_row(D[k], D[k]), g, -(T[k] @ T[k]))
                elif knowledge == "board_translation":  # Case 3
                    put(conic_row(h1, D[k]), g, -T[k][0])
                    put(conic_row(h2, D[k]), g, -T[k][1])
                    put(conic_row(D[k], D[k]), g, -(T[k] @ T[k]))
                elif knowledge == "board_direction":  # eqs. 22-26, a = s c eliminated
                    n = T[k] / max(np.linalg.norm(T[k]), 1e-300)
                    if np.hypot(n[0], n[1]) < 1e-9:
                        put(conic_row(h1, D[k]))
                        put(conic_row(h2, D[k]))
                    else:
                        put(conic_row(n[1] * h1 - n[0] * h2, D[k]))
                else:  # "robot": all pairs, generalising eq. 27
                    for i in range(1, k + 1):
                        put(conic_row(D[i], D[k]), g, -(T[i] @ T[k]))
        # Coupling (eqs. 33-42): both cameras see the same T, so the same T_x c, T_y c, T_i.T_k c.
        A, B = Ha[g], Hb[g]
        Da = [A[0][:, 2] - A[k][:, 2] for k in range(len(A))]
        Db = [B[0][:, 2] - B[k][:, 2] for k in range(len(B))]
        for k in range(1, len(A)):
            for col in (0, 1):
                add(conic_row(A[0][:, col], Da[k]), -conic_row(B[0][:, col], Db[k]))
            for i in range(1, k + 1):
                add(conic_row(Da[i], Da[k]), -conic_row(Db[i], Db[k]))
    A_sys = np.array(rows)
    if H_inf is not None and use_eq62:
        Hn = N_a @ H_inf @ np.linalg.inv(N_b)  # exact scale: h_a = Hn h_b after the rescaling
        eq62 = np.hstack([conic_transfer_matrix(Hn) @ basis, -basis, np.zeros((6, G))])
        A_sys = np.vstack([A_sys, eq62])
    x = _null_vector(A_sys, "joint stereo calibration from translations (eqs. 33-42)")
    K_a = np.linalg.solve(N_a, K_from_w(basis @ x[:m]))
    K_b = np.linalg.solve(N_b, K_from_w(basis @ x[m : 2 * m]))
    return K_a / K_a[2, 2], K_b / K_b[2, 2]
