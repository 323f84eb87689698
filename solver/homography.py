"""Plane homographies: normalised DLT, reprojection refinement and joint group estimates.

``H`` (3, 3) maps board points ``(X, Y, 1)`` (board frame, any length unit) to image points
(pixels): ``x ~ H (X, Y, 1)``, ``H = lambda K [r1 r2 t]`` (docs/METHOD.md Sec. 2).

Every returned ``H`` has unit Frobenius norm and ``H[2, 2] = lambda t_z > 0`` (``lambda > 0``
for a board in front of the camera). A joint group estimate (:func:`group_homographies`) scales
all its frames alike, frame 0 to unit norm: ``h1, h2`` are identical in all frames.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.geometry import right_singular
from slidecal.solver.numeric import median

Observation = tuple[np.ndarray, np.ndarray]  # (board_xy (N, 2), px (N, 2))


def _check_pairs(board_xy: np.ndarray, px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    b = np.asarray(board_xy, dtype=float)[:, :2]
    p = np.asarray(px, dtype=float).reshape(-1, 2)
    if len(b) != len(p):
        raise InputError(f"board_xy has {len(b)} points but px has {len(p)}: pass matched pairs")
    if len(b) < 4:
        raise InputError(f"a homography needs at least 4 point pairs, got {len(b)}")
    return b, p


def _similarity(xy: np.ndarray) -> np.ndarray:
    """Hartley normalisation (3, 3): centroid to origin, mean distance sqrt(2)."""
    c = xy.mean(axis=0)
    d = np.mean(np.linalg.norm(xy - c, axis=1))
    if d <= 0.0:
        raise DegenerateError(
            "all points coincide: a homography needs points spread over the board"
        )
    s = np.sqrt(2.0) / d
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def _apply(T: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return xy @ T[:2, :2].T + T[:2, 2]


def _sign_scale(H: np.ndarray) -> np.ndarray:
    H = H / np.linalg.norm(H)
    return -H if H[2, 2] < 0 else H


def _dlt_normalised(b: np.ndarray, p: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The DLTs (F, 3, 3) of F point sets at once: ``b``, ``p`` (F, n, 2), ``w`` (F, n) 1 for a
    point and 0 for padding (a padded point's rows are zero: no change to the null vector)."""
    F, n = w.shape
    X = np.concatenate([b, np.ones((F, n, 1))], axis=2) * w[:, :, None]
    A = np.zeros((F, max(2 * n, 9), 9))  # with 4 points (8 rows) the 9th right singular vector
    A[:, 0 : 2 * n : 2, 0:3] = X
    A[:, 0 : 2 * n : 2, 6:9] = -p[:, :, :1] * X
    A[:, 1 : 2 * n : 2, 3:6] = X
    A[:, 1 : 2 * n : 2, 6:9] = -p[:, :, 1:2] * X
    _, sv, Vt = np.linalg.svd(np.linalg.qr(A, mode="r"))  # a QR first: LAPACK's SVD of 16+ rows
    for k in np.flatnonzero(np.sum(w, axis=1) < 8):  # takes one; fewer rows: alone, unpadded
        sv[k], Vt[k] = right_singular(A[k, : 2 * int(np.sum(w[k]))])
    if np.any(sv[:, -2] <= 1e-12 * sv[:, 0]):
        raise DegenerateError(
            "the board points are (nearly) colinear: a homography needs points spread in 2D"
        )
    return Vt[:, -1].reshape(F, 3, 3)


def homography_dlt(board_xy: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Normalised DLT homography (3, 3) (Hartley normalisation on both sides).

    ``board_xy`` (N, 2): board frame, any length unit. ``px`` (N, 2): pixels. N >= 4.
    Returned with unit Frobenius norm and ``H[2, 2] > 0`` (module docstring).
    """
    b, p = _check_pairs(board_xy, px)
    Tb, Ti = _similarity(b), _similarity(p)
    Hn = _dlt_normalised(_apply(Tb, b)[None], _apply(Ti, p)[None], np.ones((1, len(b))))[0]
    return _sign_scale(np.linalg.inv(Ti) @ Hn @ Tb)


def _project(H: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    u = b @ H[:, :2].T + H[:, 2]
    return u[:, :2] / u[:, 2:3], u


def _residual_and_jac(H: np.ndarray, b: np.ndarray, p: np.ndarray):
    """Residuals (2N,) x0 y0 x1 ... and their Jacobian (2N, 9) w.r.t. H's columns h1, h2, h3."""
    xy, u = _project(H, b)
    r = (xy - p).reshape(-1)
    n = len(b)
    iw = 1.0 / u[:, 2]
    J = np.zeros((2 * n, 9))
    X = np.column_stack([b, np.ones(n)])  # coefficient of column j is X[:, j]
    J[0::2, 0::3] = J[1::2, 1::3] = X * iw[:, None]
    J[0::2, 2::3] = -X * iw[:, None] * xy[:, :1]
    J[1::2, 2::3] = -X * iw[:, None] * xy[:, 1:]
    return r, J


def _levenberg_marquardt(fun, x0: np.ndarray, max_iter: int = 30) -> np.ndarray:  # noqa: ANN001
    """Minimise ``|r(x)|^2`` from ``x0``, ``fun(x) = (r, dr/dx)`` (small dense problems; tolerates
    the homographies' scale gauge through the damping). Stops when the cost no longer falls by
    1e-12 relative."""
    x = np.asarray(x0, dtype=float)
    if max_iter <= 0:  # the start itself (no residuals to evaluate)
        return x
    r, J = fun(x)
    cost = float(r @ r)
    lam = 1e-4
    for _ in range(max_iter):
        A = J.T @ J
        g = J.T @ r
        d = np.diag(A).copy()
        d[d <= 0] = 1.0
        while True:
            step = np.linalg.solve(A + lam * np.diag(d), -g)
            x_new = x + step
            r_new, J_new = fun(x_new)
            cost_new = float(r_new @ r_new)
            if np.isfinite(cost_new) and cost_new <= cost:
                break
            lam *= 10.0
            if lam > 1e10:
                return x
        done = cost - cost_new <= 1e-12 * cost + 1e-30
        x, r, J, cost = x_new, r_new, J_new, cost_new
        lam = max(lam * 0.1, 1e-12)
        if done:
            break
    return x


def _H(x: np.ndarray) -> np.ndarray:
    return x.reshape(3, 3).T


def refine_homography(H: np.ndarray, board_xy: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Homography (3, 3) minimising the image reprojection error (Levenberg-Marquardt).

    ``H`` (3, 3): initial estimate. ``board_xy`` (N, 2): board frame, any unit. ``px`` (N, 2):
    pixels. Returned with unit Frobenius norm and ``H[2, 2] > 0``.
    """
    b, p = _check_pairs(board_xy, px)
    Tb, Ti = _similarity(b), _similarity(p)
    bn, pn = _apply(Tb, b), _apply(Ti, p)
    Hn = Ti @ np.asarray(H, dtype=float) @ np.linalg.inv(Tb)
    Hn /= np.linalg.norm(Hn)

    def fun(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _residual_and_jac(_H(x), bn, pn)

    x = _levenberg_marquardt(fun, Hn.T.reshape(-1))  # columns h1, h2, h3 stacked
    return _sign_scale(np.linalg.inv(Ti) @ _H(x) @ Tb)


def homography_rms_px(H: np.ndarray, board_xy: np.ndarray, px: np.ndarray) -> float:
    """Root mean square point distance (pixels) between ``H`` applied to ``board_xy`` (N, 2)
    and ``px`` (N, 2): ``sqrt(mean(dx^2 + dy^2))``."""
    b, p = _check_pairs(board_xy, px)
    xy, _ = _project(np.asarray(H, dtype=float), b)
    return float(np.sqrt(np.mean(np.sum((xy - p) ** 2, axis=1))))


def group_homographies(observations: Sequence[Observation], max_iter: int = 30) -> np.ndarray:
    """Joint homographies (n, 3, 3) of one orientation group (docs/METHOD.md Sec. 3).

    ``observations``: per frame ``(board_xy (N_k, 2) board frame, px (N_k, 2) pixels)``; one
    shared ``h1, h2`` and one ``h3`` per frame. Scale: ``Hs[0]`` has unit Frobenius norm and
    ``h3[2] > 0``. ``max_iter``: Levenberg-Marquardt iterations from the rescaled per-frame
    DLTs (0 returns those).
    """
    obs = [_check_pairs(b, p) for b, p in observations]
    B, P = (np.concatenate(a) for a in zip(*obs, strict=True))  # every frame's points
    Tb, Ti = _similarity(B), _similarity(P)
    counts = np.array([len(b) for b, _ in obs])
    w = np.arange(counts.max()) < counts[:, None]  # (frames, points): the padded stacks' points
    bn, pn = np.zeros((2, *w.shape, 2))
    bn[w], pn[w] = _apply(Tb, B), _apply(Ti, P)
    obs_n = [(bk[:c], pk[:c]) for bk, pk, c in zip(bn, pn, counts, strict=True)]
    Hs = _dlt_normalised(bn, pn, w)  # per frame, then scaled to frame 0's h1, h2 (any sign)
    v = np.concatenate([Hs[:, :, 0], Hs[:, :, 1]], axis=1)[:, None]  # (n, 1, 6)
    alpha = (v @ (v[0, 0] / np.linalg.norm(v[0, 0]))) / (v @ v.transpose(0, 2, 1))[:, 0]
    h12, h3 = np.mean(alpha * v[:, 0], axis=0), alpha * Hs[:, :, 2]
    n = len(obs_n)

    def unpack(x: np.ndarray) -> np.ndarray:
        H = np.empty((n, 3, 3))
        H[:, :, 0], H[:, :, 1], H[:, :, 2] = x[0:3], x[3:6], x[6:].reshape(n, 3)
        return H

    def place(k: int, Jk: np.ndarray) -> np.ndarray:
        B = np.zeros((len(Jk), 6 + 3 * n))
        B[:, 0:6] = Jk[:, 0:6]
        B[:, 6 + 3 * k : 9 + 3 * k] = Jk[:, 6:9]
        return B

    def fun(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        rj = [_residual_and_jac(H, b, p) for H, (b, p) in zip(unpack(x), obs_n, strict=True)]
        return np.concatenate([r for r, _ in rj]), np.vstack(
            [place(k, J) for k, (_, J) in enumerate(rj)]
        )

    x = _levenberg_marquardt(fun, np.concatenate([h12, h3.reshape(-1)]), max_iter)
    Tii = np.linalg.inv(Ti)
    Hs = Tii @ unpack(x) @ Tb
    s = np.linalg.norm(Hs[0])
    if median(Hs[:, 2, 2]) < 0:  # board in front of the camera
        s = -s
    return Hs / s
