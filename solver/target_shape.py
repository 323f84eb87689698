"""The board as it is: what its bow and print add to a solve (docs/ERROR_MODEL.md S8, by M4
and M5). The model takes the board as described, flat and printed at its nominal scale; the
estimate's response to each of five modes (scale, anisotropy, shear; a bow along x and along
y), the bow fitted under the board's flatness and the modes' second moment are the page's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slidecal.solver.problem import Target

#: Default one-sigma bow per metre of the pattern's diagonal: a real board's 0.2 mm over 0.65 m
FLATNESS_PER_DIAGONAL = 3e-4
#: Default one-sigma relative error of the print's scale, anisotropy and shear: a good plate
PRINT_TOLERANCE = 2e-4
#: Each of two readings the images cannot tell apart weighs alike (bow or lens; field or none)
READING_WEIGHT = 0.5
#: Difference step of the board-shape modes (metres of bow, relative strain)
_STEP = 1e-6


def default_flatness_m(points_m: np.ndarray) -> float:
    """A real board's one-sigma bow (metres) for a pattern of these points:
    :data:`FLATNESS_PER_DIAGONAL` times the pattern's diagonal."""
    xy = np.asarray(points_m, float)[:, :2]
    return FLATNESS_PER_DIAGONAL * float(np.hypot(*(xy.max(axis=0) - xy.min(axis=0))))


def tolerances(target: Target) -> np.ndarray:
    """The one-sigma (5,) of the board-shape modes of ``target``: scale, anisotropy and shear
    (relative), bow along x and along y (metres)."""
    tol, flat = float(target.print_tolerance), float(target.flatness_m)
    return np.array([tol, tol, tol, flat, flat], float)


def _pattern_frame(target: Target) -> tuple[np.ndarray, np.ndarray]:
    """(centre, half-extent) (2,) of the pattern's points in the board frame (metres)."""
    xy = np.asarray(target.points_m, float)[:, :2]
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    return (lo + hi) / 2.0, np.maximum((hi - lo) / 2.0, 1e-9)


def bow_height_m(target: Target, bow_m: np.ndarray, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
    """The height (+z into the board, metres) of a board bowed by ``bow_m`` (along x, along y:
    the two bow modes of :func:`shape_modes`) at board points ``(x_m, y_m)`` (any shape; the
    surface continues past the pattern's edges as the same quadratic)."""
    centre, half = _pattern_frame(target)
    u, v = (x_m - centre[0]) / half[0], (y_m - centre[1]) / half[1]
    return bow_m[0] * (1.0 - u * u) + bow_m[1] * (1.0 - v * v)


def shape_modes(target: Target, points_m: np.ndarray) -> list[np.ndarray]:
    """The displacement (n, 3) of each board point ``points_m`` (board frame) under a unit of
    each mode: isotropic scale, anisotropy (x stretched, y shrunk), shear, bow along x and
    along y (z = 1 - u^2 with u from -1 to 1 across the pattern; +z into the board)."""
    centre, half = _pattern_frame(target)
    x, y = points_m[:, 0] - centre[0], points_m[:, 1] - centre[1]
    u, v = x / half[0], y / half[1]
    z = np.zeros_like(x)
    return [
        np.column_stack([x, y, z]),
        np.column_stack([x / 2.0, -y / 2.0, z]),
        np.column_stack([y / 2.0, x / 2.0, z]),
        np.column_stack([z, z, 1.0 - u * u]),
        np.column_stack([z, z, 1.0 - v * v]),
    ]


@dataclass(frozen=True)
class BoardFit:
    """The board's shape as the solve sees it (:func:`fit_board`): ``bow_m`` (2,) the bow along
    x and y (metres at the centre line, +z into the board) and ``bow_cov`` its covariance;
    ``response`` (P, 5) the optimiser's coordinates per unit of each mode
    (:func:`shape_modes`); ``mode_cov`` (5, 5) the modes' second moment about the reported
    value: the print's tolerance, the bow's two readings ``w cov(bow) + w (1 - w) bow bow'``."""

    bow_m: np.ndarray
    bow_cov: np.ndarray
    response: np.ndarray
    mode_cov: np.ndarray


def fit_board(problem, out) -> BoardFit | None:  # noqa: ANN001 - CalibrationProblem, RefineOutput
    """The board's bow estimated with the parameters, to first order, and what the board's
    tolerance leaves uncertain; None without a covariance or with a tolerance of 0. With
    ``b = J' W J_n`` and ``G = -N^-1 b``: ``C = J_n' W J_n + b' G`` is the bow's information
    after the parameters', ``bow = -(C + L)^-1 (J_n' W r + G' g)`` (``L = s^2 / flatness^2``,
    ``g`` the solve's whole gradient), its covariance ``s^2 (C + L)^-1``."""
    m, state = out.model, out.state
    sig = tolerances(problem.target)
    if out.covariance_blocks is None or m.row_weights is None or not out.sigma_px > 0:
        return None
    if not np.any(sig > 0):
        return None
    w = m.row_weights
    n2 = 2 * m.n_obs
    r0 = m.evaluate(state, jacobian=False)[0][:n2]
    pts = m.o_pts
    Jn = []
    try:
        for D in shape_modes(problem.target, pts):
            m.o_pts = pts + _STEP * D
            Jn.append((m.evaluate(state, jacobian=False)[0][:n2] - r0) / _STEP)
    finally:
        m.o_pts = pts
    Jn = np.array(Jn).T  # (2 n, 5)
    b = np.array([m.pixel_gradient(state, w, Jn[:, k]) for k in range(Jn.shape[1])]).T  # (P, 5)
    Ni = out.covariance_blocks.scaled(1.0 / out.sigma_px**2)
    P0 = m.slices["E"].start if "E" in m.slices else len(m.names)
    G = np.array([-Ni.times(b[:P0, k], b[P0:, k].reshape(-1, 6)) for k in range(b.shape[1])]).T
    wp = w[:n2]
    bow, bow_cov = np.zeros(2), np.zeros((2, 2))
    if sig[3] > 0:
        B = slice(3, 5)
        C = Jn[:, B].T @ (wp[:, None] * Jn[:, B]) + b[:, B].T @ G[:, B]
        full = m.normal_blocks(state, w)  # the whole gradient (~0 at the minimum): the solve's
        g = Jn[:, B].T @ (wp * r0) + G[:, B].T @ np.concatenate([full.g_g, full.g_E.ravel()])
        post = np.linalg.inv(C + (out.sigma_px / sig[3]) ** 2 * np.eye(2))
        bow, bow_cov = -post @ g, out.sigma_px**2 * post
    mode_cov = np.diag(np.r_[sig[:3] ** 2, 0.0, 0.0])
    w = READING_WEIGHT
    mode_cov[3:, 3:] = w * bow_cov + w * (1.0 - w) * np.outer(bow, bow)
    return BoardFit(bow, 0.5 * (bow_cov + bow_cov.T), G, mode_cov)


def shape_excess(out, project) -> np.ndarray | None:  # noqa: ANN001 - RefineOutput
    """What the reported quantities' covariance (k, k) gains from the board (``out.board``):
    ``G S G'``, ``S`` the modes' second moment, through ``project`` (J (k, u), the u parameters
    it uses); None without a board fit."""
    fit = getattr(out, "board", None)
    if fit is None:
        return None
    J, used = project
    D = J @ fit.response[used]
    return D @ fit.mode_cov @ D.T
