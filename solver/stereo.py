"""Stereo heads: the infinite homography and the joint linear calibration of two cameras.

docs/METHOD.md Sec. 8 (Malm and Heyden 2006, Sec. IV). Two cameras ``a`` and ``b`` are rigidly
joined with ``X_a = R_a_b X_b + t_a_b`` (camera-frame coordinates); the infinite homography
``H_inf = K_a R_a_b K_b^-1`` maps camera b's image to camera a's. Homographies are (3, 3) from
board-plane ``(X, Y, 1)`` to pixels; ``sizes`` are ``((width_a, height_a), (width_b,
height_b))`` in pixels. The per-camera rows are ``slidecal.solver.linear.linear_system``'s; this
module adds what couples the cameras: the infinite homography (eqs. 58-61), its transfer of the
absolute conic (eq. 62) and the shared translations (eqs. 33-42).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np

from slidecal.solver.errors import DegenerateError
from slidecal.solver.linear import (
    K_from_normalised_w,
    LinearGroup,
    LinearSystem,
    W_from_w,
    conditioned_homographies,
    conic_row,
    image_normalisation,
    linear_system,
    solve_null,
    unit_columns,
    weighted_rows,
    zhang_intrinsics,
)
from slidecal.solver.numeric import median

# Third singular value of the views' stacked unit columns below which they are one orientation
# (H_inf undetermined: the head turned by less than about 0.1 deg).
_MIN_ORIENTATION_SPREAD = 2e-3


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


def _unit_rows(A: np.ndarray) -> np.ndarray:
    rn = np.linalg.norm(A, axis=1)
    return A[rn > 0] / rn[rn > 0, None]


def infinite_homography(
    H_a: np.ndarray,
    H_b: np.ndarray,
    *,
    sizes: Sequence[tuple[float, float]] | None = None,
    refine: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """``(H_inf, mu)``: the infinite homography (3, 3) from camera b's image to camera a's
    (``x_a ~ H_inf x_b`` in pixels, ``K_a R_a_b K_b^-1`` at ``det = 1``) and the per-view scales
    (n,) with ``h_a1 = mu_k H_inf h_b1``, ``h_a2 = mu_k H_inf h_b2`` (eqs. 58-61).

    ``H_a``, ``H_b`` (n, 3, 3): board plane to pixels, view k the same board pose in both
    cameras, n >= 2 orientations. ``sizes``: for the normalisation (else a data-based scale).
    ``refine``: after the linear solution, minimise ``sum_k ||A_k - mu_k H B_k||^2`` (``A_k``,
    ``B_k`` the normalised unit-norm columns ``[h1 h2]``) by alternating least squares.
    """
    H_a, H_b = np.asarray(H_a, dtype=float), np.asarray(H_b, dtype=float)
    n = len(H_a)
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
    A_sys, col_scale = unit_columns(_unit_rows(rows))
    x, _ = solve_null(
        A_sys,
        col_scale,
        [f"h{i}" for i in range(9)] + [f"nu{k}" for k in range(n)],
        remedy="too few or degenerate stereo views for the infinite homography; add stereo "
        "views with different board orientations",
    )
    x = x / np.linalg.norm(x)
    Hn = x[:9].reshape(3, 3)
    nu = x[9:]
    if np.any(np.abs(nu) < 1e-12):
        raise DegenerateError(
            "infinite homography: a view's scale came out zero, the views are inconsistent "
            "(check that H_a[k] and H_b[k] are the same board pose)"
        )
    mu_n = 1.0 / nu

    if refine:
        for _ in range(50):  # a bound: it stops at a step below 1e-13 long before
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


def conic_transfer_matrix(H: np.ndarray) -> np.ndarray:
    """The (6, 6) matrix mapping the conic vector ``w`` to that of ``H' W H`` (for eq. 62)."""
    M = np.zeros((6, 6))
    for j in range(6):
        e = np.zeros(6)
        e[j] = 1.0
        C = H.T @ W_from_w(e) @ H
        M[:, j] = [C[0, 0], C[0, 1], C[1, 1], C[0, 2], C[1, 2], C[2, 2]]
    return M


def _eq62_rows(H_n: np.ndarray, system: LinearSystem, scale: float) -> np.ndarray:
    """The six rows (6, 2m) of ``H_n' W_a H_n = W_b`` (eq. 62) on ``(w_a, w_b)``, ``H_n`` in the
    normalised images, each row scaled to the norm ``scale``."""
    B = system.basis
    rows = _unit_rows(np.hstack([conic_transfer_matrix(H_n) @ B, -B]))
    return scale * rows


def _solve_rig(
    A: np.ndarray,
    sys_a: LinearSystem,
    sys_b: LinearSystem,
    row_weighting: str,
    what: str,
) -> tuple[np.ndarray, np.ndarray]:
    """``(K_a, K_b)`` from the stacked rig system ``A`` on ``(w_a, w_b, ...)``: rows weighted
    (unit norm with ``row_weighting="unit"``), columns scaled to unit norm, null vector."""
    if row_weighting == "unit":
        A = _unit_rows(A)
    m = sys_a.basis.shape[1]
    A, col_scale = unit_columns(A)
    names = [f"{n}_a" for n in sys_a.unknowns[:m]] + [f"{n}_b" for n in sys_b.unknowns[:m]]
    names += list(sys_a.unknowns[m:])
    x, _ = solve_null(
        A, col_scale, names, remedy=f"{what}: add views with different board orientations"
    )
    return (
        K_from_normalised_w(sys_a.basis @ x[:m], sys_a.N),
        K_from_normalised_w(sys_b.basis @ x[m : 2 * m], sys_b.N),
    )


def rig_linear_intrinsics(
    Hs_a: np.ndarray,
    Hs_b: np.ndarray,
    H_inf: np.ndarray | None,
    *,
    sizes: Sequence[tuple[float, float]],
    row_weighting: Literal["noise", "unit"] = "unit",
    **options,
) -> tuple[np.ndarray, np.ndarray]:
    """Joint linear intrinsics of both cameras of a stereo head (eqs. 10-11 with eq. 62;
    docs/METHOD.md Sec. 8): each camera's ``linear_system`` rows of knowledge ``"none"`` and
    the six rows of eq. 62 (at the median norm of the cameras' rows) in ``(w_a, s w_b)``.

    ``Hs_a``, ``Hs_b`` (n_a, 3, 3), (n_b, 3, 3): each camera's homographies (views not
    necessarily paired). ``H_inf``: :func:`infinite_homography`'s, or None to solve each camera
    alone with the same rows (``slidecal.solver.linear.zhang_intrinsics``). ``row_weighting`` and
    ``options`` (``skew``, ``unit_aspect``): as for ``linear_system`` (``"unit"``:
    docs/results/S5.md).
    Returns ``K_a``, ``K_b`` (3, 3) in pixels.
    """
    Hs = (np.asarray(Hs_a, dtype=float), np.asarray(Hs_b, dtype=float))
    options = {**options, "row_weighting": row_weighting}
    if H_inf is None:
        K_a, K_b = (
            zhang_intrinsics(H, image_size=size, **options)
            for H, size in zip(Hs, sizes, strict=True)
        )
        return K_a, K_b
    sys_a, sys_b = (
        linear_system([LinearGroup(Hk[None]) for Hk in H], "none", image_size=size, **options)
        for H, size in zip(Hs, sizes, strict=True)
    )
    A_a, A_b = weighted_rows(sys_a), weighted_rows(sys_b)
    H_n = sys_a.N @ np.asarray(H_inf, dtype=float) @ np.linalg.inv(sys_b.N)
    d = np.linalg.det(H_n)
    H_n = H_n / (np.sign(d) * abs(d) ** (1.0 / 3.0))
    scale = median(np.linalg.norm(np.vstack([A_a, A_b]), axis=1))
    A = np.vstack(
        [
            np.hstack([A_a, np.zeros_like(A_a)]),
            np.hstack([np.zeros_like(A_b), A_b]),
            _eq62_rows(H_n, sys_a, scale),
        ]
    )
    return _solve_rig(A, sys_a, sys_b, row_weighting, "joint stereo calibration (eqs. 10-11, 62)")


#: Orientation groups from which a translated rig adds eq. 62 (``H_inf`` from fewer is too rough).
_EQ62_MIN_GROUPS = 3


def _shared_translation_rows(
    Ha: np.ndarray, Hb: np.ndarray, f1: float, f2: float
) -> tuple[np.ndarray, np.ndarray]:
    """Rows (r, 12) on the conic vectors ``(w_a, w_b)`` equating what both cameras see of one
    group's translations (eqs. 33-42), and their noise scales (r,): ``h1' W Delta_k``
    (``T_x c``), ``h2' W Delta_k`` (``T_y c``) and ``Delta_i' W Delta_k`` (``T_i . T_k c``),
    ``i <= k``. ``Ha``, ``Hb`` (n, 3, 3): the group's conditioned homographies
    (``linear.conditioned_homographies``); camera b's side is multiplied by ``f1`` on the first
    two (camera a's translation scale over camera b's and c over camera b's ``c``) and by ``f2``
    on the ``Delta' W Delta`` rows (the same with the translation scales squared)."""
    Da, Db = Ha[0][:, 2] - Ha[:, :, 2], Hb[0][:, 2] - Hb[:, :, 2]  # (n, 3): Delta_k
    # every row's four vectors, in the order (k, then h1, h2, Delta_1 .. Delta_k), vectorised
    # (a group of n frames has n^2 / 2 rows)
    k_of, i_of = [], []
    for k in range(1, len(Ha)):
        k_of += [k] * (k + 2)
        i_of += [-2, -1, *range(1, k + 1)]  # -2, -1: the first homography's columns 0 and 1
    k_of, i_of = np.array(k_of, dtype=int), np.array(i_of, dtype=int)
    col = np.where(i_of < 0, i_of + 2, 0)
    h = i_of < 0
    a1 = np.where(h[:, None], Ha[0][:, col].T, Da[np.maximum(i_of, 0)])
    a2 = np.where(h[:, None], Hb[0][:, col].T, Db[np.maximum(i_of, 0)])
    b1, b2 = Da[k_of], Db[k_of]
    fb = np.where(h, f1, f2)
    rows = np.hstack([conic_row(a1, b1), -fb[:, None] * conic_row(a2, b2)])
    nrm = np.linalg.norm
    noises = nrm(a1, axis=1) + nrm(b1, axis=1) + fb * (nrm(a2, axis=1) + nrm(b2, axis=1))
    return rows.reshape(-1, 12), noises


def rig_linear_intrinsics_translation(
    groups_a: Sequence[LinearGroup],
    groups_b: Sequence[LinearGroup],
    knowledge: str,
    *,
    sizes: Sequence[tuple[float, float]],
    row_weighting: Literal["noise", "unit"] = "noise",
    **options,
) -> tuple[np.ndarray, np.ndarray]:
    """Joint linear intrinsics of a stereo head translated in front of a board (eqs. 33-42;
    docs/METHOD.md Sec. 8): unknowns ``(w_a, w_b, c_1 .. c_G)``, one ``c_g`` for both cameras
    (camera b's column rescaled through :func:`infinite_homography`'s ``mu_g``), coupling rows
    per translation (:func:`_shared_translation_rows`) and, from ``_EQ62_MIN_GROUPS`` groups on,
    eq. 62.

    ``groups_a``, ``groups_b``: ``LinearGroup`` per orientation group, the same frames in both
    (``motion`` read from ``groups_a``, board units, by ``knowledge``: "robot",
    "board_translation", "board_direction" or "lengths"). ``row_weighting`` and ``options``
    (``skew``, ``unit_aspect``): as for ``linear_system``; coupling rows get the noise scale of
    their two sides. Returns ``K_a``, ``K_b`` (3, 3) in pixels.
    """
    ga = list(groups_a)  # camera b's groups take the head's one motion, camera a's
    gb = [LinearGroup(np.asarray(b.H, float), a.motion) for a, b in zip(ga, groups_b, strict=True)]
    G = len(ga)
    H_inf, mu = None, np.ones(G)
    if G >= 2:
        H_inf, mu = infinite_homography(
            np.array([g.H[0] for g in ga]), np.array([g.H[0] for g in gb]), sizes=sizes
        )
    options = {**options, "row_weighting": row_weighting}
    sys_a, sys_b = (
        linear_system(g, knowledge, image_size=size, **options)
        for g, size in zip((ga, gb), sizes, strict=True)
    )
    B = sys_a.basis
    m = B.shape[1]
    # c_b = r c_a per group: c = (lambda sigma / h_scale)^2 and lambda_b = lambda_a / mu
    # (up to one factor common to all groups, which w_b's scale absorbs).
    r = (sys_b.sigma * sys_a.h_scale / (sys_a.sigma * sys_b.h_scale * mu)) ** 2
    A_a, A_b = weighted_rows(sys_a), weighted_rows(sys_b)
    blocks = [
        np.hstack([A_a[:, :m], np.zeros((len(A_a), m)), A_a[:, m:]]),
        np.hstack([np.zeros((len(A_b), m)), A_b[:, :m], A_b[:, m:] * r]),
    ]
    # translations divided by sigma in each camera's rows, camera b's c_g is r c_g
    s_ba = sys_b.sigma / sys_a.sigma
    cond_a, cond_b = conditioned_homographies(ga, sys_a), conditioned_homographies(gb, sys_b)
    for Ha, Hb, r_g in zip(cond_a, cond_b, r, strict=True):
        rows, noises = _shared_translation_rows(Ha, Hb, s_ba / r_g, s_ba**2 / r_g)
        rows = np.hstack([rows[:, :6] @ B, rows[:, 6:] @ B, np.zeros((len(rows), G))])
        blocks.append(rows / noises[:, None])
    if H_inf is not None and G >= _EQ62_MIN_GROUPS:
        # exact scale: W_b = H_n' W_a H_n for the w_b the rescaled c_g columns imply
        H_n = sys_a.N @ H_inf @ np.linalg.inv(sys_b.N)
        scale = median(np.linalg.norm(np.vstack(blocks[:2]), axis=1))
        blocks.append(np.hstack([_eq62_rows(H_n, sys_a, scale), np.zeros((6, G))]))
    return _solve_rig(
        np.vstack(blocks),
        sys_a,
        sys_b,
        row_weighting,
        "joint stereo calibration from translations (eqs. 33-42)",
    )
