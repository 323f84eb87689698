"""The error model's terms (docs/ERROR_MODEL.md Sec. 3, M2-M6): what a finished solve's
covariance gains beyond the model's own; :func:`covariance_terms` lists them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from slidecal.solver.errors import InputError
from slidecal.solver.geometry import R_from_rvec, T_from_Rt, inv_T, rvec_from_R
from slidecal.solver.model import LEVELS, BundleModel
from slidecal.solver.numeric import chi2_tail, distinct, least_squares, median
from slidecal.solver.problem import CalibrationProblem
from slidecal.solver.refine import SIGMA_FLOOR, RefineOutput
from slidecal.solver.target_shape import READING_WEIGHT, shape_excess


@dataclass(frozen=True)
class ImageErrors:
    """How a solve's image errors read: ``correlated``, ``misfit`` (:func:`images_err_together`),
    ``grouped`` (:func:`grouped_detection_errors`); each None when not read."""

    correlated: tuple[float, int] | None = None
    misfit: tuple[int, float, float] | None = None
    grouped: tuple[float, int, float] | None = None


def image_errors(problem: CalibrationProblem, out: RefineOutput, groups: np.ndarray) -> ImageErrors:
    """Whether a finished solve's image errors go together, image by image or over the frames
    of an orientation group (``groups`` (F,))."""
    correlated = misfit = None
    if len(out.model.frame_rows) >= MIN_CLUSTER_FRAMES:  # (with fewer frames they cannot be)
        correlated, misfit = images_err_together(out)
    grouped = grouped_detection_errors(out, groups) if problem.knowledge == "robot" else None
    return ImageErrors(correlated, misfit, grouped)


def covariance_terms(
    problem: CalibrationProblem,
    out: RefineOutput,
    project: tuple[np.ndarray, np.ndarray],
    images: ImageErrors,
    groups: np.ndarray,
) -> list[np.ndarray]:
    """Every term the error model adds to the model's covariance of a finished solve's reported
    quantities, each (k, k) symmetric and positive semi-definite, in the order they are added
    (docs/ERROR_MODEL.md Sec. 3). ``project``: the reported quantities' Jacobian (k, u) and the
    u optimiser coordinates it uses; ``images``: how the images' errors read; ``groups`` (F,):
    the frames' orientation groups. A term comparing two readings adds its positive part."""
    frames = np.arange(len(problem.frames))
    by_frame = images.correlated is not None or images.misfit is not None
    terms = (
        smooth_field_excess(out, project),  # the arm's smooth error no image places
        session_field_excess(out, project),  # a classic session's two readings
        level_excess(out, project),  # the arm's levels are estimates
        tool_offset_excess(problem, out, project),  # an unobserved hand-eye offset
        shape_excess(out, project),  # the real board is not quite the one described
    )
    clusters = (  # the detections' errors go together within an image, or an orientation group
        cluster_excess(out, project, frames) if by_frame else None,
        cluster_excess(out, project, groups) if images.grouped else None,
    )
    return [0.5 * (x + x.T) for x in terms if x is not None] + [
        _positive_part(x) for x in clusters if x is not None
    ]


def _columns(
    out: RefineOutput, project: tuple[np.ndarray, np.ndarray] | None, cols: np.ndarray
) -> np.ndarray:
    """``cov[:, cols]`` of the optimiser's covariance, or ``J cov[used, cols]`` with ``project``."""
    cols = np.asarray(cols, int)
    if project is None:
        return np.asarray(out.covariance, float)[:, cols]
    J, used = project
    return J @ out.covariance_blocks.submatrix(used, cols)


#: Fewest dof behind a level for its uncertainty to be carried (below, ``nu / (nu - 2)`` > 3)
MIN_LEVEL_DOF = 3.0
#: A shared level counts from this share of a frame's own: below, it adds under 1 % to its variance
SHARED_LEVEL_SHARE = 0.1


def level_excess(
    out: RefineOutput, project: tuple[np.ndarray, np.ndarray] | None = None
) -> np.ndarray | None:
    """M2 (PSD); ``project`` as :func:`smooth_field_excess`. None when nothing is added."""
    m = out.model
    red = getattr(m, "level_redundancy", None)
    if out.covariance_blocks is None or not red or m.pose_sigma is None:
        return None
    sig = np.asarray(m.pose_sigma, float)
    k = len(out.names) if project is None else len(project[0])
    excess = np.zeros((k, k))
    for key in (key for key in LEVELS if key in m.slices and key in red):
        sl, rot, per_frame = m.slices[key], m.rotation_rows(key), m.level_share(key)
        C = _columns(out, project, np.arange(sl.start, sl.stop))
        for i, rows in enumerate((rot, ~rot)):
            nu, level = float(red[key][i]), float(getattr(m, LEVELS[key])[i])
            if nu < MIN_LEVEL_DOF or not rows.any() or level <= 2.0 * SIGMA_FLOOR[i]:
                continue
            share = per_frame if np.isscalar(per_frame) else per_frame[i]
            if key != "E" and level * share < SHARED_LEVEL_SHARE * sig[i]:
                continue
            Ci = C[:, rows]
            excess += (nu / (nu - 2.0) - 1.0) * (Ci @ Ci.T) / level**2
    return excess if np.any(excess) else None


#: One-sigma per axis of a tool-side offset one orientation cannot observe: within ~17 cm
TOOL_OFFSET_SIGMA_M = 0.1
#: One-sigma relative error of an arm's move lengths: true to scale within about 0.1 %
MOVE_SCALE_SIGMA = 1e-3


def tool_offset_gain(
    problem: CalibrationProblem, out: RefineOutput, project: tuple[np.ndarray, np.ndarray]
) -> np.ndarray | None:
    """How the reported quantities move per metre of the tool-side translation the session
    cannot observe (k, m: its m unobserved directions, held at zero): M4's ``G`` for S7. None
    when every direction is observed or the poses carry no corrections."""
    m, st = out.model, out.model.st
    weights = getattr(m, "row_weights", None)
    if out.covariance_blocks is None or "E" not in m.slices or weights is None:
        return None
    basis = st.X_t_basis if st.eye_in_hand else st.Y_t_basis
    if basis.shape[1] == 3:
        return None
    # the observed directions first (their columns keep their names), then the others
    free = np.linalg.svd(np.eye(3) - basis @ basis.T)[0][:, : 3 - basis.shape[1]]
    whole = np.hstack([basis, free])
    ext = BundleModel(
        problem, replace(st, **{"X_t_basis" if st.eye_in_hand else "Y_t_basis": whole})
    )
    for name in ("sigma_px", *LEVELS.values()):  # the solve's noise and levels
        setattr(ext, name, getattr(m, name))
    nb = ext.normal_blocks(out.state, weights, keep=False)
    at = {n: i for i, n in enumerate(ext.names)}
    known = set(m.names)
    new = np.array([i for i, n in enumerate(ext.names) if n not in known])
    P0 = m.slices["E"].start
    glob = np.array([at[n] for n in m.names[:P0]])
    cross = np.vstack(  # J' W J_o (P, m) in the solve's parameter order
        [nb.A_gg[np.ix_(glob, new)], nb.A_gE[new].reshape(len(new), -1).T]
    )
    J, used = project
    C = out.covariance_blocks.submatrix(used, np.arange(len(m.names)))
    return -(J @ C @ cross) / out.sigma_px**2


def tool_offset_excess(
    problem: CalibrationProblem, out: RefineOutput, project: tuple[np.ndarray, np.ndarray]
) -> np.ndarray | None:
    """S7 (M4): :func:`tool_offset_gain` at :data:`TOOL_OFFSET_SIGMA_M` per axis; or None."""
    G = tool_offset_gain(problem, out, project)
    if G is None:
        return None
    return TOOL_OFFSET_SIGMA_M**2 * (G @ G.T)


def _positive_part(extra: np.ndarray) -> np.ndarray:
    """The positive part of a symmetric matrix: what covers both readings it compares."""
    w, V = np.linalg.eigh(0.5 * (extra + extra.T))
    cover = (V * np.clip(w, 0.0, None)) @ V.T
    return 0.5 * (cover + cover.T)


def _untold_trends(m: BundleModel) -> tuple[np.ndarray, list[bool]]:
    """Per axis, whether the groups' trend level went to the floor (below a tenth of the
    frames'); per group, whether it is too short to tell a trend from its scatter."""
    st = m.st
    sig = np.asarray(m.pose_sigma, float)
    tau = np.asarray(m.trend_sigma, float) if "V" in m.slices else np.zeros(2)
    floored = tau * m.trend_spread < SHARED_LEVEL_SHARE * sig
    short = [
        len(np.flatnonzero(st.trend_groups == g)) - 1 - d < d for g, d in enumerate(st.trend_dims)
    ]
    return floored, short


#: The ways the arm's smooth error no image places is seen (:func:`smooth_field_excess`)
SMOOTH_FIELD_WAYS = ("groups", "field")


def smooth_field_excess(
    out: RefineOutput,
    project: tuple[np.ndarray, np.ndarray] | None = None,
    ways: tuple[str, ...] = SMOOTH_FIELD_WAYS,
) -> np.ndarray | None:
    """M3 by each of ``ways``; None when no way applies. ``project``: the reported quantities'
    Jacobian (k, u) and the u parameters it uses (else the optimiser's P x P)."""
    m, st = out.model, out.model.st
    if out.covariance_blocks is None or "E" not in m.slices or m.pose_sigma is None:
        return None
    sig = np.asarray(m.pose_sigma, float)
    e = m.slices["E"]
    A = _columns(out, project, np.arange(e.start, e.stop))
    A = A / np.tile(np.repeat(sig**2, 3), (e.stop - e.start) // 6)
    parts = []
    if "groups" in ways and st.trend_dims and st.trend_coords is not None:
        floored, short = _untold_trends(m)
        fixed = st.trend_scale_fixed  # one orientation: its translation trend is not learned
        excess = None
        for g, dims in enumerate(st.trend_dims):
            carried = (floored[0] and short[g], floored[1] and (short[g] or fixed))
            if not any(carried):  # the scatter keeps as many dof as the trend takes
                continue
            k = np.flatnonzero(st.trend_groups == g)
            c = st.trend_coords[k, :dims]
            rms = np.sqrt(np.mean(np.sum(c**2, axis=1)))
            level = (sig[0], max(sig[1], MOVE_SCALE_SIGMA * rms) if fixed else sig[1])
            for a in range(6):
                if carried[a // 3]:  # A (S - L) A' of the corrections along axis a, S a trend
                    i, Ak = a // 3, A[:, 6 * k + a]
                    B = Ak @ (c / rms)
                    part = level[i] ** 2 * (B @ B.T) - sig[i] ** 2 * (Ak @ Ak.T)
                    excess = part if excess is None else excess + part
        if excess is not None:
            parts.append(excess)
    field = _linear_field(out, A) if "field" in ways else None
    if field is not None:
        parts.append(field)
    return sum(_positive_part(x) for x in parts) if parts else None


def _linear_field(out: RefineOutput, A: np.ndarray) -> np.ndarray | None:
    """:func:`smooth_field_excess`'s ``field`` way over the corrections' gains ``A`` (k, 6 F);
    None where it does not apply (a one-orientation trend, the user's levels)."""
    m, st = out.model, out.model.st
    if st.T_meas is None or len(st.T_meas) < 3:
        return None
    if "V" in m.slices:
        if m.trend_sigma is None or not (len(st.trend_dims) >= 2 or _session_trend(out)):
            return None
        tau = float(m.trend_sigma[1])
        trends = [np.flatnonzero(st.trend_groups == g) for g in range(len(st.trend_dims))]
        coords = [st.trend_coords[k, :d] for k, d in zip(trends, st.trend_dims, strict=True)]
        level = tau
        if "W" in m.slices and m.common_sigma is not None and np.any(~m.st.common_rotation):
            level = max(level, float(m.common_sigma[1]))  # its linear part >= the quadratic
        floored, short = _untold_trends(m)
        if floored[1] or any(short) or _session_trend(out):
            level = max(level, MOVE_SCALE_SIGMA)
    elif getattr(m, "level_redundancy", None):  # no trend modelled, the levels learned
        tau, level = 0.0, MOVE_SCALE_SIGMA
        trends = [np.arange(len(st.T_meas))]
        coords = [np.zeros((len(st.T_meas), 0))]
    else:
        return None
    excess = np.zeros((len(A), len(A)))
    for a in (3, 4, 5):  # the base frame's axis of the correction
        common = 0.0
        for k, c in zip(trends, coords, strict=True):
            d = st.T_meas[k, :3, 3] - st.T_meas[k, :3, 3].mean(axis=0)
            if c.shape[1]:  # the field along the trend's own directions (its basis: pinv)
                d = c @ (np.linalg.pinv(d) @ c).T
            Ak = A[:, 6 * k + a]
            common = common + Ak @ d
            if tau:
                excess -= tau**2 * ((Ak @ c) @ (Ak @ c).T)
        excess += level**2 * (common @ common.T)
    return excess


def _session_trend(out: RefineOutput) -> bool:
    """Whether the solve, with a covariance, models a classic session's one linear trend of the
    pose corrections over the whole session's positions (its scale learned)."""
    m, st = out.model, out.model.st
    if out.covariance_blocks is None or "V" not in m.slices or m.trend_sigma is None:
        return False
    whole = st.trend_groups is not None and bool(np.all(st.trend_groups == 0))
    return len(st.trend_dims) == 1 and not st.trend_scale_fixed and whole


def session_field_step(out: RefineOutput, V: np.ndarray | None = None) -> np.ndarray | None:
    """A classic session's step (P,) from its solve (one trend over all its positions) to its
    reading without that field (M5): ``-C[:, V] C[V, V]^-1 V``, ``V`` the solve's trend or a
    response (n_V, k) of it. None for any other session."""
    m = out.model
    V = out.state.V if V is None else V
    if not _session_trend(out) or V is None:
        return None
    sv = m.slices["V"]
    v = np.arange(sv.start, sv.stop)
    C = out.covariance_blocks.submatrix(np.arange(len(out.names)), v)
    try:
        return -C @ np.linalg.solve(C[v], V)
    except np.linalg.LinAlgError:
        return None


def reported_response(out: RefineOutput, response: np.ndarray) -> np.ndarray:
    """The reported value's response (P, k) to what moves the solve by ``response`` (P, k): a
    classic session's plus :data:`READING_WEIGHT` times its field step's response (the board's
    modes reach the result so); ``response`` itself for any other session."""
    v = out.model.slices.get("V")
    step = None if v is None else session_field_step(out, response[v])
    return response if step is None else response + READING_WEIGHT * step


def session_field_excess(
    out: RefineOutput, project: tuple[np.ndarray, np.ndarray] | None = None
) -> np.ndarray | None:
    """M5: the two readings' spread ``w (1 - w) d d'`` (``d`` the step between them,
    :func:`session_field_step`; ``w`` :data:`READING_WEIGHT`); None for any other session."""
    step = session_field_step(out)
    if step is None:
        return None
    d = step if project is None else project[0] @ step[project[1]]
    return READING_WEIGHT * (1.0 - READING_WEIGHT) * np.outer(d, d)


#: Fewest clusters for the sandwich (:func:`cluster_excess`): one score per cluster
MIN_CLUSTER_FRAMES = 4
#: Neighbours' residual correlation (and twice its spread) beyond which errors go together
CORRELATED_NEIGHBOURS = 0.05
#: Bonferroni level over the images for one image's misfit (:func:`images_err_together`)
MISFIT_IMAGE_P = 0.01
#: ... read only at least this share of the session's squares: a smaller excess changes little
MISFIT_IMAGE_SHARE = 0.1
#: Fewest orientation groups of two frames or more for :func:`grouped_detection_errors`
MIN_CLUSTER_GROUPS = 5
#: The groups' mean residuals' chi-square tail below which they are read
GROUPED_ERRORS_P = 0.01


def grouped_detection_errors(
    out: RefineOutput, groups: np.ndarray
) -> tuple[float, int, float] | None:
    """(statistic, dof, p-value) when the detections' errors go together over the frames of an
    orientation group (``groups`` (F,)) in images too small for :func:`images_err_together`,
    else None. Per group, camera and corner id seen twice or more, the ``n`` weighted
    residuals' mean ``m``: ``sum n m^2 / v`` (``v`` their mean square) is about chi-square on
    two dof each."""
    m = out.model
    if not m.chunks or len(groups) != len(m.problem.frames):
        return None
    if median([len(ch.corner_ids) for ch in m.chunks]) >= NEIGHBOUR_MIN_CORNERS:
        return None
    sizes = np.bincount(groups[[ch.frame_index for ch in m.chunks]])
    if np.count_nonzero(sizes >= 2) < MIN_CLUSTER_GROUPS:
        return None
    e, ok = corner_residuals(out)
    ids = np.concatenate([ch.corner_ids for ch in m.chunks])
    key = np.stack([groups[m.o_frame], m.o_cam, ids], axis=1)[ok]
    _, at, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((len(counts), 2))
    np.add.at(sums, at.ravel(), e[ok])
    v = float(np.mean(e[ok] ** 2)) if ok.any() else 0.0
    kept = counts >= 2
    if not kept.any() or not v > 0.0:
        return None
    stat = float(np.sum(np.sum(sums[kept] ** 2, axis=1) / counts[kept])) / v
    dof = 2 * int(kept.sum())
    p = float(chi2_tail(dof, stat))
    return (stat, dof, p) if p < GROUPED_ERRORS_P else None


def images_err_together(
    out: RefineOutput,
) -> tuple[tuple[float, int] | None, tuple[int, float, float] | None]:
    """Whether an image's errors go together: ``(correlated, misfit)``. ``correlated``: the
    neighbours' correlation and pairs (:func:`neighbour_correlation`) when read; else
    ``misfit``: (frame, rms over the noise, p) of the image independent errors explain least,
    its weighted squares over ``s^2`` against a chi-square on its pixel rows, when read. None
    for each not read."""
    rho, pairs = neighbour_correlation(out)
    if pairs > 0 and rho >= CORRELATED_NEIGHBOURS + 2.0 / np.sqrt(pairs):
        return (rho, pairs), None
    m = out.model
    n_px = len(out.residuals)
    if not out.sigma_px > 0:
        return None, None
    w = m.row_weights[:n_px] if m.row_weights is not None else out.inlier_rows.astype(float)
    frames = sorted(m.frame_rows, key=lambda k: m.frame_rows[k].start)  # their rows tile R
    starts = [m.frame_rows[k].start for k in frames]
    S = np.add.reduceat(w * out.residuals**2, starts) / out.sigma_px**2
    n = np.add.reduceat((w > 0).astype(int), starts)
    idx = np.flatnonzero(n >= 2 * NEIGHBOUR_MIN_CORNERS)  # as many as the neighbours' test needs
    if not len(idx):
        return None, None
    def tail(i: int) -> tuple[float, int, float, float]:
        return float(chi2_tail(n[i], S[i])), frames[i], float(np.sqrt(S[i] / n[i])), S[i] - n[i]

    # of the images with one count of rows, the one with the most squares has the least tail
    o = idx[np.lexsort((-S[idx], n[idx]))]
    p, k, ratio, excess = min(tail(i) for i in o[np.r_[True, n[o][1:] != n[o][:-1]]])
    if p == 0.0:  # tails that underflow tie: the first image of them, as over every image
        p, k, ratio, excess = min(tail(i) for i in idx)
    p = min(p * len(idx), 1.0)
    read = p < MISFIT_IMAGE_P and excess >= MISFIT_IMAGE_SHARE * float(np.sum(S))
    return None, ((k, ratio, p) if read else None)


def cluster_excess(
    out: RefineOutput, project: tuple[np.ndarray, np.ndarray], clusters: np.ndarray
) -> np.ndarray | None:
    """M6 (k, k; symmetric, not PSD) over ``clusters`` (F,): each frame's label, the frame
    itself or its orientation group. None without a covariance, with fewer than
    :data:`MIN_CLUSTER_FRAMES` clusters, or when the reported quantities use a frame's own
    columns."""
    m = out.model
    if out.covariance_blocks is None or m.row_weights is None or not out.sigma_px > 0:
        return None
    Sf = m.frame_scores(out.state, np.asarray(m.row_weights, float))
    of = np.array([clusters[k] for k in m.frame_rows])
    S = np.array([Sf[of == c].sum(axis=0) for c in distinct(of)])
    G, P0 = S.shape
    J, used = project
    if G < MIN_CLUSTER_FRAMES or np.any(used >= P0):
        return None
    gg = out.covariance_blocks.gg[used, :]  # s^2 times the rows of the reduced inverse
    Q = J @ gg  # (k, P0)
    meat = (S.T @ S) * (G / (G - 1.0))
    return Q @ meat @ Q.T / out.sigma_px**4 - J @ gg[:, used] @ J.T


#: Fewest corners of an image for its neighbours to count: with fewer its pose takes their freedom
NEIGHBOUR_MIN_CORNERS = 12


def _neighbour_pairs(points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The target's neighbouring points: each pair (a < b) at its smallest spacing."""
    d = np.linalg.norm(points_m[:, None, :] - points_m[None, :, :], axis=2)
    np.fill_diagonal(d, np.inf)
    return np.nonzero(np.triu(d <= 1.01 * d.min()))


def corner_residuals(out: RefineOutput) -> tuple[np.ndarray, np.ndarray]:
    """Every detected corner's residual (n, 2) weighted as the solve weighs it (the robust
    loss's row weights; the inliers alone without them), and whether it counts (n,)."""
    m = out.model
    n_px = len(out.residuals)
    w = m.row_weights[:n_px] if m.row_weights is not None else out.inlier_rows.astype(float)
    return (out.residuals * np.sqrt(np.maximum(w, 0.0))).reshape(-1, 2), w[0::2] > 0


def neighbour_correlation(out: RefineOutput) -> tuple[float, int]:
    """How much neighbouring corners' residuals go together, and over how many pairs: over
    every image's pairs at the target's smallest spacing, the mean product of their weighted
    residuals along the pair's line and across it, each over one coordinate's mean square; the
    larger, and the pairs; (0, 0) without one. About 0 for independent errors, with a sampling
    spread of one over the root of the pairs. Images with fewer than
    :data:`NEIGHBOUR_MIN_CORNERS` corners are left out."""
    m = out.model
    pts = m.problem.target.points_m
    if len(pts) < 2:
        return 0.0, 0
    a, b = _neighbour_pairs(pts)
    e, ok = corner_residuals(out)
    # each image's corners by id: the row of corner id i of image c in table[c, i] (-1: none)
    sizes = [len(ch.corner_ids) for ch in m.chunks]  # the images tile the corners in order
    image = np.repeat(np.arange(len(sizes)), sizes)
    seen = ok & (np.bincount(image[ok], minlength=len(sizes))[image] >= NEIGHBOUR_MIN_CORNERS)
    ids = np.concatenate([ch.corner_ids for ch in m.chunks])
    table = np.full((len(m.chunks), len(pts)), -1)
    table[image[seen], ids[seen]] = np.flatnonzero(seen)
    ia, ib = table[:, a], table[:, b]
    both = (ia >= 0) & (ib >= 0)
    pairs, corners = int(both.sum()), int(ok.sum())
    squares = float(np.sum(e[ok] ** 2))
    if pairs == 0 or squares <= 0.0:
        return 0.0, 0
    ia, ib = ia[both], ib[both]
    line = m.o_px[ib] - m.o_px[ia]  # the two corners' line in the image
    along = line / np.maximum(np.linalg.norm(line, axis=1, keepdims=True), 1e-12)
    across = np.stack([-along[:, 1], along[:, 0]], axis=1)
    per_coordinate = pairs * squares / (2 * corners)
    ea, eb = e[ia], e[ib]
    return max(
        float(np.sum(np.einsum("ij,ij->i", ea, u) * np.einsum("ij,ij->i", eb, u))) / per_coordinate
        for u in (along, across)
    ), pairs


def effective_truth(
    mount: str,
    T_base_tool_true: Sequence[np.ndarray],
    T_base_tool_measured: Sequence[np.ndarray],
    T_hand_eye: np.ndarray,
    T_target: np.ndarray,
    sigma_rot_deg: float = 0.1,
    sigma_mm: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The hand-eye and target pose ``(T_hand_eye, T_target)`` as a session can know them: the
    effective ones (docs/ERROR_MODEL.md S6), against which a simulated session is judged.

    ``mount`` names the physical truth ``T_hand_eye``, ``T_target`` of the reference camera;
    ``T_base_tool_true`` / ``_measured`` (4, 4) per frame. The arm's constant error is
    indistinguishable from a change of both, so the solver's zero-mean pose corrections converge to
    ``X' = B X``, ``Y' = Y A`` (``X`` the inverse hand-eye, ``Y`` the target pose) minimising
    ``sum_k |rot(E_k)|^2 / sigma_rot^2 + |t(E_k)|^2 / sigma_t^2`` over the corrections ``E_k``.
    """
    T_true = [np.asarray(T, dtype=float) for T in T_base_tool_true]
    T_meas = [np.asarray(T, dtype=float) for T in T_base_tool_measured]
    if len(T_true) != len(T_meas):
        raise InputError(
            f"{len(T_true)} true robot poses for {len(T_meas)} measured ones; give one per frame"
        )
    eih = mount == "eye_in_hand"
    X, Y = inv_T(np.asarray(T_hand_eye, float)), np.asarray(T_target, float)
    w = np.array([1.0 / np.radians(sigma_rot_deg)] * 3 + [1000.0 / sigma_mm] * 3)

    def corrections(p: np.ndarray) -> np.ndarray:
        A = T_from_Rt(R_from_rvec(p[:3]), p[3:6])
        B = T_from_Rt(R_from_rvec(p[6:9]), p[9:12])
        out = []
        for Tt, Tm in zip(T_true, T_meas, strict=True):
            # the pose the camera saw with the model's X' = B X, Y' = Y A (eye-in-hand:
            # X' (T)^-1 Y' = X Tt^-1 Y, so T = Y' Y^-1 Tt X^-1 X'); eye-to-hand alike
            if eih:
                T = (Y @ A) @ inv_T(Y) @ Tt @ inv_T(X) @ (B @ X)
            else:
                T = inv_T(B @ X) @ X @ Tt @ Y @ inv_T(Y @ A)
            E_rot = rvec_from_R(T[:3, :3] @ Tm[:3, :3].T)
            out.append(np.r_[E_rot, T[:3, 3] - Tm[:3, 3]] * w)
        return np.concatenate(out)

    if not T_true:
        return inv_T(X), Y
    p = least_squares(corrections, np.zeros(12)).x
    A = T_from_Rt(R_from_rvec(p[:3]), p[3:6])
    B = T_from_Rt(R_from_rvec(p[6:9]), p[9:12])
    return inv_T(B @ X), Y @ A
