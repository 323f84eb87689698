"""Closed-form calibration from plane homographies (docs/METHOD.md Secs. 2-3; Malm and Heyden 2006).

The image of the absolute conic ``w = K^-T K^-1`` (symmetric, defined up to scale) is handled as
the vector ``w = (w11, w12, w22, w13, w23, w33)``; ``a' W b`` is linear in it with the
coefficient row :func:`conic_row` ``(a, b)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.geometry import right_singular
from slidecal.solver.numeric import distinct, median

W_NAMES = ("w11", "w12", "w22", "w13", "w23", "w33")


def conic_row(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Coefficients (6,) of the bilinear form ``a' W b`` on ``w = (w11, w12, w22, w13, w23, w33)``.

    ``a``, ``b``: (3,) homogeneous image vectors (pixels, or normalised pixels). Also accepts
    (m, 3) stacks and then returns (m, 6).
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.ndim == 1 and b.ndim == 1:  # one row: plain floats (faster than 0-d arrays)
        a0, a1, a2 = a.tolist()
        b0, b1, b2 = b.tolist()
        return np.array(
            [a0 * b0, a0 * b1 + a1 * b0, a1 * b1, a0 * b2 + a2 * b0, a1 * b2 + a2 * b1, a2 * b2]
        )
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
    """Zhang's two rows (2, 6) on ``w`` of one plane homography (docs/METHOD.md eqs. 10-11).

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
            "degenerate (docs/METHOD.md Sec. 7)"
        ) from None
    K = np.linalg.inv(L.T)
    return K / K[2, 2]


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


KNOWLEDGE = ("robot", "board_translation", "board_direction", "lengths", "none")


@dataclass(frozen=True)
class LinearGroup:
    """One orientation group for the linear method.

    ``H`` (n, 3, 3): jointly estimated homographies (board plane to pixels, identical ``h1, h2``;
    see ``slidecal.solver.homography.group_homographies``); frame 0 is the reference.
    ``motion`` (n, 3) or None; ``motion[0] = 0``; by knowledge: ``"robot"``: the camera's
    displacement since frame 0 in the robot frame (same length unit as the board; only inner
    products are used, pairs i, j of :func:`robot_pairs`); ``"board_translation"``: the
    displacement in the board frame (Case 3); ``"board_direction"``: its unit direction in the
    board frame, length unknown (Case 2); ``"lengths"``: only the norms are used (Case 1,
    eq. 27).
    """

    H: np.ndarray
    motion: np.ndarray | None = None


@dataclass(frozen=True)
class LinearSolution:
    """Result of :func:`linear_intrinsics`.

    ``K`` (3, 3) pixels, ``K[2, 2] = 1``. ``singular_values``: of the conditioned system
    (descending; the last is the residual of the null vector). ``unknowns``: names of the
    system's columns (``w``'s coefficients, then each group's ``c = lambda^2``).
    """

    K: np.ndarray
    singular_values: np.ndarray
    unknowns: tuple[str, ...]


@dataclass(frozen=True)
class LinearSystem:
    """The stacked, conditioned homogeneous system ``A x = 0`` of the linear method.

    ``A`` (rows, m + G): weighted rows, unit-norm columns; ``col_scale`` (m + G,):
    ``x = col_scale * y`` for a null vector ``y`` of ``A``; ``basis`` (6, m):
    ``w = basis @ x[:m]``; ``unknowns``: the columns' names; ``N`` (3, 3) the image
    normalisation; ``sigma``: the board-side scale (board units per normalised unit);
    ``h_scale`` (G,): each group's homographies were divided by it (so ``|h1|, |h2| ~ 1``).
    """

    A: np.ndarray
    col_scale: np.ndarray
    basis: np.ndarray
    unknowns: tuple[str, ...]
    N: np.ndarray
    sigma: float
    n_groups: int
    h_scale: np.ndarray


def w_basis(skew: bool, unit_aspect: bool) -> tuple[np.ndarray, tuple[str, ...]]:
    """Linear basis (6, m) of ``w`` for the camera model, and the coefficient names.

    Zero skew: ``w12 = 0``; unit aspect (with zero skew): also ``w11 = w22``. Unit aspect with
    skew is not linear in ``w``: the full basis is used and the refinement enforces it.
    """
    I6 = np.eye(6)
    if skew:
        return I6, W_NAMES
    if unit_aspect:
        basis = np.column_stack([I6[0] + I6[2], I6[3], I6[4], I6[5]])
        return basis, ("w11=w22", "w13", "w23", "w33")
    return I6[:, [0, 2, 3, 4, 5]], ("w11", "w22", "w13", "w23", "w33")


def _common_h12(H: np.ndarray) -> np.ndarray:
    """Rescale each H[k] (k >= 1) so its h1, h2 match frame 0's (no-op for joint estimates)."""
    H = np.asarray(H, dtype=float)
    v = np.concatenate([H[:, :, 0], H[:, :, 1]], axis=1)[:, None]  # (n, 1, 6)
    scale = (v @ v[0, 0]) / (v @ v.transpose(0, 2, 1))[:, 0]
    scale[0] = 1.0
    return H * scale[:, :, None]


def _board_scale(Hs: list[np.ndarray]) -> float:
    r = [
        np.linalg.norm(H[:, 2]) / np.sqrt(0.5 * (H[:, 0] @ H[:, 0] + H[:, 1] @ H[:, 1])) for H in Hs
    ]
    return float(median(r))


def _check_groups(groups: Sequence[LinearGroup], knowledge: str) -> None:
    if knowledge not in KNOWLEDGE:
        raise InputError(f"unknown motion knowledge {knowledge!r}; use one of {KNOWLEDGE}")
    if len(groups) == 0:
        raise InputError("the linear method needs at least one orientation group")


#: Partners of each translation in a large orientation group (the robot knowledge): every pair
#: of a group's n translations gives a row, n^2 / 2 rows, while the information grows like n.
#: Beyond ``ROBOT_PARTNERS + 1`` translations, each pairs with itself and with
#: ``ROBOT_PARTNERS`` translations spread evenly over the group (as accurate, far fewer rows).
ROBOT_PARTNERS = 20


def robot_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(k, j)``, ``j <= k``, of the ``n`` translations of one group whose rows
    ``Delta_j' W Delta_k = (T_j . T_k) c`` the robot knowledge stacks: every pair up to
    ``ROBOT_PARTNERS + 1`` translations, beyond that each translation with itself and with the
    evenly spread partners (O(n) rows, see ``ROBOT_PARTNERS``)."""
    if n <= ROBOT_PARTNERS + 1:
        return np.tril_indices(n)
    partners = distinct(np.linspace(0, n - 1, ROBOT_PARTNERS).round().astype(int))
    k = np.repeat(np.arange(n), len(partners) + 1)
    j = np.column_stack([np.arange(n), np.tile(partners, (n, 1))]).reshape(-1)
    pairs = distinct(np.maximum(k, j) * n + np.minimum(k, j))  # in the order of (k, j)
    return pairs // n, pairs % n


def linear_system(
    groups: Sequence[LinearGroup],
    knowledge: str,
    *,
    skew: bool = False,
    unit_aspect: bool = False,
    image_size: tuple[float, float],
    condition: bool = True,
    row_weighting: Literal["noise", "unit"] = "noise",
) -> LinearSystem:
    """Stack and condition every constraint of docs/METHOD.md Sec. 3 (table) on ``(w, c_1 .. c_G)``.

    Per group: ``h1' W h2 = 0``, ``h1' W h1 = c``, ``h2' W h2 = c`` (eqs. 10-11), then per
    translation, by ``knowledge`` (see :class:`LinearGroup`): ``"lengths"``: ``Delta' W Delta =
    L^2 c`` (eq. 27); ``"board_translation"``: ``h1' W Delta = T_x c``, ``h2' W Delta = T_y c``,
    ``Delta' W Delta = |T|^2 c``; ``"board_direction"`` (eqs. 22-26): ``h1' W Delta = n_x a``,
    ``h2' W Delta = n_y a`` with ``a`` eliminated (``q`` only fixes the length afterwards);
    ``"robot"``: ``Delta_i' W Delta_j = (T_i . T_j) c`` for the pairs ``1 <= i <= j`` of
    :func:`robot_pairs` (all of them in groups of up to 21 translations);
    ``"none"``: Zhang's two rows of every frame (each frame its own pose), no ``c``.
    Conditioning: docs/METHOD.md, "Numerical conditioning" (``row_weighting="noise"``: each row
    over its noise scale ``|a| + |b|``; ``"unit"``: unit-norm rows; ``condition=False``: none).
    """
    _check_groups(groups, knowledge)
    N = image_normalisation(*image_size) if condition else np.eye(3)
    B, wnames = w_basis(skew, unit_aspect)
    m = B.shape[1]
    Hn = [np.einsum("ij,kjl->kil", N, _common_h12(np.asarray(g.H, dtype=float))) for g in groups]
    sigma = _board_scale([H[0] for H in Hn]) if condition else 1.0
    S = np.diag([sigma, sigma, 1.0])
    Hn = [H @ S for H in Hn]
    # Each group's scale so that |h1|, |h2| ~ 1: c = lambda^2 is then O(1) like w.
    h_scale = np.array([np.sqrt(0.5 * np.sum(H[0][:, :2] ** 2)) if condition else 1.0 for H in Hn])
    Hn = [H / s for H, s in zip(Hn, h_scale, strict=True)]
    G = 0 if knowledge == "none" else len(groups)
    # rows are built in blocks, vectorised over the frames of a group: the coefficients on w
    # (k, 6), each row's noise scale (k,), and its coefficient on the group's c (k,)
    conics: list[np.ndarray] = []
    noises: list[np.ndarray] = []
    c_cols: list[np.ndarray] = []

    def add(conic: np.ndarray, noise: np.ndarray, g: int | None = None, c_coef=0.0) -> None:
        conic = np.asarray(conic, dtype=float).reshape(-1, 6)
        k = len(conic)
        conics.append(conic)
        noises.append(np.broadcast_to(np.asarray(noise, dtype=float), (k,)))
        c = np.zeros((k, G))
        if g is not None:
            c[:, g] = c_coef
        c_cols.append(c)

    def nrm(v: np.ndarray) -> np.ndarray:
        return np.linalg.norm(v, axis=-1)

    for g, (grp, H) in enumerate(zip(groups, Hn, strict=True)):
        if knowledge == "none":  # Zhang's two rows of every frame, frame by frame
            a, b = H[:, :, 0], H[:, :, 1]
            z = np.stack([conic_row(a, b), conic_row(a, a) - conic_row(b, b)], axis=1)
            add(z, np.repeat(nrm(a) + nrm(b), 2))
            continue
        h1, h2 = H[0][:, 0], H[0][:, 1]
        add(conic_row(h1, h2), nrm(h1) + nrm(h2))  # eq. 10
        add(conic_row(h1, h1), 2 * nrm(h1), g, -1.0)  # eq. 11
        add(conic_row(h2, h2), 2 * nrm(h2), g, -1.0)  # eq. 11
        if len(H) < 2:
            continue
        motion = np.asarray(grp.motion, dtype=float) / sigma
        D = H[0][:, 2] - H[1:, :, 2]  # (n - 1, 3) eqs. 12-13, frame k >= 1 against frame 0
        T = motion[1:]
        nD = nrm(D)
        if knowledge == "lengths":  # eq. 27
            add(conic_row(D, D), 2 * nD, g, -np.sum(T * T, axis=1))
        elif knowledge == "board_translation":  # Case 3, three rows per translation
            rows3 = np.stack([conic_row(h1, D), conic_row(h2, D), conic_row(D, D)], axis=1)
            noise3 = np.stack([nrm(h1) + nD, nrm(h2) + nD, 2 * nD], axis=1)
            coef3 = np.stack([-T[:, 0], -T[:, 1], -np.sum(T * T, axis=1)], axis=1)
            add(rows3, noise3.reshape(-1), g, coef3.reshape(-1))
        elif knowledge == "board_direction":  # eqs. 22-26, a = s c eliminated
            n = T / np.maximum(nrm(T), 1e-300)[:, None]
            mxy = np.hypot(n[:, 0], n[:, 1])
            along = mxy < 1e-9  # along the board normal: both in-plane rows vanish
            if np.any(along):
                Da = D[along]
                rows2 = np.stack([conic_row(h1, Da), conic_row(h2, Da)], axis=1)
                add(rows2, np.stack([nrm(h1) + nrm(Da), nrm(h2) + nrm(Da)], axis=1).ravel())
            if not np.all(along):
                keep = ~along
                hn = (n[keep, 1, None] * h1 - n[keep, 0, None] * h2) / mxy[keep, None]
                add(conic_row(hn, D[keep]), nrm(hn) + nD[keep])
        elif knowledge == "robot":  # pairs of translations, generalising eq. 27
            k, j = robot_pairs(len(D))
            coef = -np.sum(motion[1:][j] * T[k], axis=1)
            add(conic_row(D[j], D[k]), nD[j] + nD[k], g, coef)
    A = (
        np.concatenate([np.concatenate(conics) @ B, np.concatenate(c_cols)], axis=1)
        if conics
        else np.zeros((0, m + G))
    )
    noise_all = np.concatenate(noises) if noises else np.zeros(0)
    rn = np.linalg.norm(A, axis=1)
    keep = rn > 1e-300
    A = A[keep]
    col_scale = np.ones(A.shape[1])
    if condition:
        A = A / (rn if row_weighting == "unit" else noise_all)[keep, None]  # the rows' weights
        A, col_scale = unit_columns(A)
    names = wnames + tuple(f"c{g}" for g in range(G))
    return LinearSystem(A, col_scale, B, names, N, sigma, G, h_scale)


#: second-smallest over largest singular value below which the conditioned system is singular:
#: exactly degenerate data sits at rounding, accepted configurations far above it.
NULL_SPACE_TOL = 1e-10


_SINGULAR_REMEDY = (
    "the data cannot determine the intrinsics with this knowledge; add translation directions "
    "or tilts (docs/METHOD.md Sec. 7)"
)


def solve_null(
    A: np.ndarray,
    col_scale: np.ndarray,
    unknowns: Sequence[str],
    remedy: str = _SINGULAR_REMEDY,
) -> tuple[np.ndarray, np.ndarray]:
    """Null vector ``x`` (n,) of a conditioned homogeneous system and its singular values.

    ``A`` (rows, n): weighted rows, columns already scaled by ``col_scale`` (n,);
    ``x = col_scale * y`` for the unit null vector ``y`` of ``A``. ``unknowns``: the column
    names (for the message). ``remedy``: what to do when the null space is not one-dimensional.
    Raises ``DegenerateError`` with too few rows or a null space of more than one dimension.
    """
    n_unknowns = A.shape[1]
    if A.shape[0] < n_unknowns - 1:
        raise DegenerateError(
            f"too few constraints ({A.shape[0]}) for {n_unknowns - 1} unknowns "
            f"({', '.join(unknowns)} up to scale): add frames, translations in other "
            "directions, or orientation groups, or assume zero skew / unit aspect"
        )
    sv, Vt = right_singular(A)
    if sv[-2] <= NULL_SPACE_TOL * sv[0]:
        raise DegenerateError(
            f"the linear system is singular (its null space is not one-dimensional): {remedy}"
        )
    return Vt[-1] * col_scale, sv


def unit_columns(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(A * col_scale, col_scale)``: the columns of ``A`` (rows, n) scaled to unit norm (an
    all-zero column is left as it is)."""
    cn = np.linalg.norm(A, axis=0)
    col_scale = 1.0 / np.where(cn > 0, cn, 1.0)
    return A * col_scale, col_scale


def weighted_rows(system: LinearSystem) -> np.ndarray:
    """The rows of ``system`` with their weights but the columns as the unknowns are (the column
    scaling undone): the block a larger system (a rig's) stacks and conditions again."""
    return system.A / system.col_scale


def conditioned_homographies(
    groups: Sequence[LinearGroup], system: LinearSystem
) -> list[np.ndarray]:
    """Each group's homographies (n, 3, 3) as the rows of ``system`` (:func:`linear_system` of
    ``groups``) use them: common ``h1, h2`` per group, then ``N H diag(sigma, sigma, 1) /
    h_scale``. Translations pair with them divided by ``system.sigma``."""
    S = np.diag([system.sigma, system.sigma, 1.0])
    return [
        np.einsum("ij,kjl->kil", system.N, _common_h12(np.asarray(g.H, dtype=float))) @ S / s
        for g, s in zip(groups, system.h_scale, strict=True)
    ]


def K_from_normalised_w(w: np.ndarray, N: np.ndarray) -> np.ndarray:
    """Intrinsics (3, 3) in pixels, ``K[2, 2] = 1``, from the conic vector ``w`` (6,) of the
    normalised image ``x_n = N x_px`` (:func:`image_normalisation`)."""
    K = np.linalg.solve(N, K_from_w(w))
    return K / K[2, 2]


def linear_intrinsics(
    groups: Sequence[LinearGroup],
    knowledge: str,
    *,
    system: LinearSystem | None = None,
    **options,
) -> LinearSolution:
    """Closed-form intrinsics from translation groups (docs/METHOD.md Sec. 3, every row of its
    table). ``groups``: orientation groups (:class:`LinearGroup`, homographies in pixels and
    board units); ``options``: the keywords of :func:`linear_system`; ``system``: that system
    when already built (``check_configuration`` returns it). Raises ``DegenerateError`` when it
    has no unique, positive definite solution.
    """
    if system is None:
        system = linear_system(groups, knowledge, **options)
    x, sv = solve_null(system.A, system.col_scale, system.unknowns)
    K = K_from_normalised_w(system.basis @ x[: system.basis.shape[1]], system.N)
    return LinearSolution(K, sv, system.unknowns)


def zhang_intrinsics(Hs: np.ndarray, **options) -> np.ndarray:
    """Zhang's general-motion intrinsics ``K`` (3, 3) from homographies ``Hs`` (n, 3, 3).

    Each homography (board plane to pixels, any scale) is its own pose (eqs. 10-11). Needs at
    least 3 orientations with skew, 2 with zero skew (4 unknowns), fewer with unit aspect.
    ``options``: the keywords of :func:`linear_system` (``image_size`` (width, height) pixels,
    ``skew``, ``unit_aspect``, ``row_weighting``).
    """
    Hs = np.asarray(Hs, dtype=float).reshape(-1, 3, 3)
    system = linear_system([LinearGroup(H[None]) for H in Hs], "none", **options)
    x, _ = solve_null(system.A, system.col_scale, system.unknowns)
    return K_from_normalised_w(system.basis @ x[: system.basis.shape[1]], system.N)


def focal_from_homographies(Hs: np.ndarray, *, image_size: tuple[float, float]) -> np.ndarray:
    """The one-parameter start ``K`` (3, 3): square pixels, no skew, the principal point at the
    image centre, and the focal length that best satisfies Zhang's rows (eqs. 10-11) of the
    homographies ``Hs`` (n, 3, 3): with ``w = (1, 0, 1, 0, 0, f^2)`` in centred, normalised
    coordinates each row gives ``r_11 + r_22 + r_33 f^2 = 0``. ``f`` = image width when ``f^2``
    comes out negative. ``image_size``: (width, height) pixels.
    """
    Hs = np.asarray(Hs, dtype=float).reshape(-1, 3, 3)
    N = image_normalisation(*image_size)
    rows = []
    for H in Hs:
        Hn = N @ H
        Hn = Hn / np.sqrt(0.5 * np.sum(Hn[:, :2] ** 2))  # |h1|, |h2| ~ 1
        for r in zhang_rows(Hn):
            rows.append(r / max(np.linalg.norm(r), 1e-300))
    R = np.array(rows)
    a, b = R[:, 0] + R[:, 2], R[:, 5]
    f2 = -(a @ b) / (b @ b) if b @ b > 0 else -1.0
    s = N[0, 0]
    f_px = np.sqrt(f2) / s if f2 > 0 else float(image_size[0])
    w, h = float(image_size[0]), float(image_size[1])
    return np.array([[f_px, 0.0, (w - 1) / 2], [0.0, f_px, (h - 1) / 2], [0.0, 0.0, 1.0]])
