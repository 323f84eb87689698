"""Levenberg-Marquardt and variance components: a problem, its structure and a start in,
a :class:`RefineOutput` out (docs/METHOD.md Secs. 5 and 6; the model: :mod:`slidecal.solver.model`).

The optimiser never reads the adequacy checks: the one check of the robot's records it may need
(when the arm's accuracy cannot explain the images) comes in as an argument.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from slidecal.solver.free_pose import FreePoseFit, free_pose_fit, model_starts, session_images
from slidecal.solver.geometry import rvec_from_R
from slidecal.solver.model import (
    LEVELS,
    BlockInverse,
    BundleModel,
    ModelState,
    NormalBlocks,
    Structure,
    orientation_groups,
)
from slidecal.solver.numeric import distinct, f_tail
from slidecal.solver.problem import CalibrationProblem


@dataclass(frozen=True)
class RefineOutput:
    """What :func:`refine` returns: the state, the named covariance and the residual story."""

    state: ModelState
    names: tuple[str, ...]
    # the covariance of the optimiser's coordinates in blocks (``covariance``: dense, on demand)
    covariance_blocks: BlockInverse | None
    residuals: np.ndarray  # (R,) pixels, outliers included
    inlier_rows: np.ndarray  # (R,) bool
    sigma_px: float
    converged: bool
    iterations: int
    outliers: tuple[tuple[int, str, int], ...]
    messages: tuple[str, ...]
    model: BundleModel
    # the robot test's free board pose per image at this solve's intrinsics, when it stood
    free_pose: FreePoseFit | None = None
    # the robot test's free-pose fit when the solve went on to learn the arm's accuracy
    test_fit: FreePoseFit | None = None
    # robot sessions: the one-sigma pose error per axis (radians, metres), (0, 0) for exact
    # poses; whether it was estimated
    robot_sigma: tuple[float, float] | None = None
    robot_sigma_estimated: bool = False
    # each source's share of that error (rad, m) by name ("pose", "group", "trend", "field"),
    # ``robot_sigma`` their root sum of squares; empty where no accuracy was learned
    robot_levels: dict[str, tuple[float, float]] = field(default_factory=dict)
    # the board's bow and tolerance (``solver/target_shape.py`` ``BoardFit``) once fitted
    board: object | None = None

    @functools.cached_property
    def covariance(self) -> np.ndarray | None:
        """The covariance (P, P) of the optimiser's coordinates ``names``; None when it could
        not be computed."""
        return None if self.covariance_blocks is None else self.covariance_blocks.dense()


def _respect_options(problem: CalibrationProblem, state: ModelState) -> ModelState:
    """The start with the model's assumptions imposed (fy = fx, zero skew, unused k = 0)."""
    o = problem.options
    K, dist = {}, {}
    for c, k in state.K.items():
        k = k.copy()
        if o.unit_aspect:
            k[0, 0] = k[1, 1] = 0.5 * (k[0, 0] + k[1, 1])
        if not o.skew:
            k[0, 1] = 0.0
        K[c] = k
        dist[c] = np.where(np.array(o.distortion_mask), state.dist[c], 0.0)
    return ModelState(K, dist, state.T_cam_ref, state.X, state.Y, state.s)


def _lm(
    model: BundleModel,
    state: ModelState,
    weights: np.ndarray,
    max_iter: int,
    lam: float = 1e-4,
) -> tuple[ModelState, bool, int, np.ndarray, float]:
    """Levenberg-Marquardt from ``state`` with the damping ``lam`` to start: the state
    reached, whether it converged, the iterations, the residuals (R,) of the state reached (the
    caller needs no new pass) and the damping reached (a warm start for the next call)."""
    nb = model.normal_blocks(state, weights)
    r = nb.r
    cost = float(np.sum(weights * r * r))
    converged = False
    it = 0
    lam_start = lam
    for it in range(1, max_iter + 1):  # noqa: B007 - the count is reported
        while True:
            try:
                delta = nb.solve(lam)
            except np.linalg.LinAlgError:
                lam *= 10.0
                if lam > 1e12:
                    return state, False, it, r, lam
                continue
            new = model.apply(state, delta)
            # with the Jacobian, kept: an accepted step's state is the next linearisation
            r_new = model.trial_residuals(new)
            cost_new = float(np.sum(weights * r_new * r_new))
            if np.isfinite(cost_new) and cost_new <= cost:
                break
            lam *= 10.0
            if lam > 1e12:
                if lam_start > 1.0:  # a warm start this stiff takes only round-off steps:
                    # once more from a light damping (the minimum, or a real step, is there)
                    state, converged, more, r, lam = _lm(
                        model, state, weights, max_iter - it + 1, 1e-6
                    )
                    return state, converged, it - 1 + more, r, lam
                return state, cost < 1e-20, it, r, lam
        # a relative decrease below 1e-10 moves no parameter by more than ~1e-5 of its std
        small_step = cost - cost_new <= 1e-10 * max(cost, 1e-30) + 1e-24
        state, cost, r = new, cost_new, r_new
        lam = max(lam / 10.0, 1e-9)
        if small_step:
            converged = True
            break
        nb = model.normal_blocks(state, weights)
    return state, converged, it, r, lam


#: Levenberg-Marquardt's damping (times the diagonal) at the start: the linear start is close.
LM_START_DAMPING = 1e-6
#: The variance-component phase's damping: a larger one holds back the prior-pinned directions.
VCE_STEP_DAMPING = 1e-9
#: Most variance-component steps of one solve (then the last levels are kept, with a note)
MAX_VCE_STEPS = 40
#: F test of the exact poses against a free pose per image: below it, the arm's accuracy is learned.
ROBOT_TEST_P = 1e-3
#: Smallest pose sigma kept (radians, metres): below it a component is as good as exact.
SIGMA_FLOOR = (1e-7, 1e-7)
#: Dof of the prior at the frames' own level on the groups' level (on few dof it falls to zero).
GROUP_LEVEL_PRIOR_DOF = 2.0
#: Robot sigmas beyond any arm (2 deg, 20 mm): the estimation stops, the records are wrong.
SIGMA_BEYOND = (np.radians(2.0), 0.02)
#: Smallest rms spread (metres) of a group's positions along a direction for a trend along it.
TREND_MIN_SPREAD_M = 0.005
#: Fewest frames of a classic eye-in-hand session for one trend over the whole session.
SESSION_TREND_MIN_FRAMES = 8
#: Trend frames per coordinate of the shared field (:func:`common_trend`): fewer are scatter.
COMMON_FIELD_FRAMES_PER_COORD = 3


def refine(
    problem: CalibrationProblem,
    structure: Structure,
    init: ModelState,
    *,
    max_iter: int = 100,
    robust: bool = True,
    record_check: Callable[[CalibrationProblem], str | None] | None = None,
) -> RefineOutput:
    """Minimise the reprojection error over all detections (docs/METHOD.md Sec. 5), outliers
    and each camera's noise as docs/ERROR_MODEL.md Sec. 2 says; robot sessions with
    ``options.estimate_robot_noise`` (the default) learn the arm's accuracy there too.
    ``sigma_px`` is the reference camera's noise.

    ``record_check``: what is wrong with the robot's records, told from the images alone
    (:func:`slidecal.solver.adequacy.record_check`), asked only when the exact-pose solve puts
    the poses beyond any arm or does not converge; then no accuracy is learned. None: not asked.
    """
    o = problem.options
    robot = problem.knowledge == "robot"
    if not (robot and o.estimate_robot_noise):
        out = _Solve(problem, structure, init, False).iterate(max_iter, robust).output()
        if robot:
            sig = structure.pose_sigma if structure.pose_sigma is not None else (0.0, 0.0)
            out = _with_robot(out, sig, False)
        return out
    exact = replace(structure, T_meas=None, pose_sigma=None)  # no corrections: E, U, V, W
    start = ModelState(init.K, init.dist, init.T_cam_ref, init.X, init.Y, init.s)
    s0 = _Solve(problem, exact, start, False).iterate(max_iter, robust)
    out0 = s0.output(covariance=False)  # its covariance is made only where it is the result
    images = session_images(out0.model, out0.inlier_rows)
    fit = free_pose_fit(images, out0.state.K, out0.state.dist, model_starts(out0.model, out0.state))
    if _robot_pose_test(out0, fit) > ROBOT_TEST_P:  # the poses explain the images
        return _with_robot(replace(s0.output(), free_pose=fit), (0.0, 0.0), True)
    sig0 = _pose_discrepancy(problem, out0, fit)
    beyond = any(v > lim for v, lim in zip(sig0, SIGMA_BEYOND, strict=True))
    doubt = record_check is not None and (beyond or not out0.converged)
    if doubt and record_check(problem) is not None:
        # no accuracy of an arm explains records read wrongly or paired with other images
        return _with_robot(replace(s0.output(), free_pose=fit), (0.0, 0.0), False)
    if o.robot_noise_deg > 0 or o.robot_noise_m > 0:  # the user's values: where to start
        sig0 = (
            max(np.radians(o.robot_noise_deg), SIGMA_FLOOR[0]),
            max(o.robot_noise_m, SIGMA_FLOOR[1]),
        )
    T_meas = np.stack([f.T_base_tool for f in problem.frames])
    noisy, spread = arm_structure(structure, T_meas, dict.fromkeys(ARM_SOURCES, sig0), True)
    out = _Solve(problem, noisy, out0.state, True).iterate(max_iter, robust).output()
    out = replace(out, test_fit=fit)
    m = out.model
    levels = {"pose": m.pose_sigma}
    if m.group_sigma is not None and "U" in m.slices:  # as the data say it, not its prior
        levels["group"] = m.group_sigma if m.group_sigma_data is None else m.group_sigma_data
    if "V" in m.slices:  # a trend's share of a frame's error: its level times the offset
        levels["trend"] = tuple(spread * np.asarray(m.trend_sigma))
    if "W" in m.slices:  # what the groups share: its levels times their shares
        levels["field"] = tuple(np.asarray(m.st.common_spread) * np.asarray(m.common_sigma))
    total = tuple(float(np.linalg.norm(axis)) for axis in zip(*levels.values(), strict=True))
    out = replace(out, robot_levels={k: (float(r), float(t)) for k, (r, t) in levels.items()})
    return _with_robot(out, total, True)


#: The arm's error sources of the model (docs/ERROR_MODEL.md S3-S5), as ``arm_structure`` takes
#: their levels
ARM_SOURCES = ("pose", "group", "trend", "field")


def arm_structure(
    structure: Structure,
    T_meas: np.ndarray,
    levels: Mapping[str, tuple[float, float]],
    session_trend: bool,
) -> tuple[Structure, float]:
    """``structure`` with the error model's arm (S3-S5) on the measured poses ``T_meas`` (F, 4,
    4) at ``levels``: each source's share of a frame's error (rad, m) by the names of
    ``ARM_SOURCES``; ``session_trend``: a classic eye-in-hand session may take one trend. Returns
    it and the trend frames' rms offset (metres, over every frame)."""
    pose_groups = orientation_groups(T_meas)
    trend_groups, coords, dims = translation_trends(T_meas, pose_groups)
    if not dims and session_trend and structure.eye_in_hand:
        if len(T_meas) >= SESSION_TREND_MIN_FRAMES:  # one trend over the session
            whole = np.zeros(len(T_meas), dtype=int)
            trend_groups, coords, dims = translation_trends(T_meas, whole)
    spread = float(np.sqrt(np.mean(np.sum(coords**2, axis=1)))) if dims else 1.0
    fixed = len(dims) == 1 and len(set(pose_groups.tolist())) == 1  # one orientation: fx's scale
    common, rotation, share = common_trend(T_meas, trend_groups, dims)
    trend, field_level = np.asarray(levels["trend"]) / spread, levels["field"]
    noisy = replace(
        structure,
        T_meas=T_meas,
        pose_sigma=tuple(levels["pose"]),
        pose_groups=pose_groups if _shared_groups(pose_groups) else None,
        group_sigma=tuple(levels["group"]),
        trend_groups=trend_groups if dims else None,
        trend_coords=coords if dims else None,
        trend_dims=dims,
        trend_sigma=(trend[0], SIGMA_FLOOR[1] if fixed else trend[1]) if dims else None,
        trend_scale_fixed=fixed,
        common_map=common,
        common_rotation=rotation,
        common_sigma=(field_level[0] / share[0], field_level[1] / max(share[1], 1e-3))
        if common is not None
        else None,
        common_spread=share,
    )
    return noisy, spread


def translation_trends(
    T_base_tool: np.ndarray, groups: np.ndarray
) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    """The frames' coordinates for a linear trend of the pose correction along the moves of
    each orientation group (``Structure.trend_*``): the offsets ``d_k = t_k - mean(t)`` of a
    group's measured positions (metres) in an orthonormal basis of the directions they span.
    Returns the trend group per frame (-1: none), the coordinates (F, 3), zero-padded, and
    the number of directions per trend group.
    """
    F = len(T_base_tool)
    trend_groups, coords, dims = np.full(F, -1), np.zeros((F, 3)), []
    for g in distinct(groups):
        k = np.flatnonzero(groups == g)
        if len(k) < 3:
            continue
        d = T_base_tool[k, :3, 3] - T_base_tool[k, :3, 3].mean(axis=0)
        _, sv, Vt = np.linalg.svd(d, full_matrices=False)
        spread = sv / np.sqrt(len(k))
        m = min(int(np.sum(spread > max(TREND_MIN_SPREAD_M, 0.1 * spread[0]))), len(k) - 2)
        if m < 1:
            continue
        trend_groups[k] = len(dims)
        coords[k, :m] = d @ Vt[:m].T
        dims.append(m)
    return trend_groups, coords, tuple(dims)


def common_trend(
    T_base_tool: np.ndarray, trend_groups: np.ndarray, trend_dims: tuple[int, ...]
) -> tuple[np.ndarray | None, np.ndarray | None, tuple[float, float]]:
    """The smooth error every trend group shares (``Structure.common_*``): its map (F, 6, n)
    from its n coordinates to each frame's correction, which of them are rotations (n,), and
    what a level of each kind (rotation, translation) is in a frame's correction (metres: the
    coordinates' rms over the frames); ``(None, None, (0, 0))`` with fewer than two trend groups
    (S5 of docs/ERROR_MODEL.md).
    """
    none = (None, None, (0.0, 0.0))
    if len(trend_dims) < 2:
        return none
    k = np.flatnonzero(trend_groups >= 0)
    within = T_base_tool[k].copy()  # each frame's offset from its own group's mean
    for g in range(len(trend_dims)):
        kg = trend_groups[k] == g
        within[kg, :3, 3] -= within[kg, :3, 3].mean(axis=0)
    _, c, dims = translation_trends(within, np.zeros(len(k), dtype=int))
    if not dims or len(k) < COMMON_FIELD_FRAMES_PER_COORD * 3 * dims[0]:
        return none
    F, m = len(T_base_tool), dims[0]
    cols: list[np.ndarray] = []
    for a in range(3):  # the rotation about axis a grows along each spanned direction
        for j in range(m):
            col = np.zeros((F, 6))
            col[k, a] = c[:, j]
            cols.append(col)
    _, p, pdims = translation_trends(T_base_tool[k], np.zeros(len(k), dtype=int))
    n_rot = len(cols)
    if pdims and len(k) >= COMMON_FIELD_FRAMES_PER_COORD * 3 * pdims[0] * (pdims[0] + 1) // 2:
        scale = float(np.sqrt(np.mean(np.sum(p**2, axis=1))))
        u = p[:, : pdims[0]] / scale  # the positions' coordinates at unit rms
        for i in range(pdims[0]):
            for j in range(i, pdims[0]):
                q = u[:, i] * u[:, j]
                q = (q - q.mean()) * scale  # metres at the positions' rms
                for a in range(3):
                    col = np.zeros((F, 6))
                    col[k, 3 + a] = q
                    cols.append(col)
    common = np.stack(cols, axis=2)
    rotation = np.arange(len(cols)) < n_rot

    def share(columns: np.ndarray) -> float:  # a level's rms share of a frame's, per axis
        return float(np.sqrt(np.sum(common[k][:, :, columns] ** 2) / (3 * len(k))))

    return common, rotation, (share(rotation), share(~rotation) if (~rotation).any() else 0.0)


def _shared_groups(pose_groups: np.ndarray) -> bool:
    """Whether a shared correction per orientation group adds anything: two or more groups,
    each of two or more frames (one frame's would be its own correction again)."""
    counts = np.bincount(pose_groups)
    return len(counts) > 1 and int(counts.min()) >= 2


def _with_robot(out: RefineOutput, sigma: tuple[float, float], estimated: bool) -> RefineOutput:
    sigma = (float(sigma[0]), float(sigma[1]))
    return replace(out, robot_sigma=sigma, robot_sigma_estimated=estimated)


def _robot_pose_test(out: RefineOutput, fit) -> float:  # noqa: ANN001 - FreePoseFit
    """p-value of the F test: robot-pose model against free poses.

    Nested models on the same inlier detections and intrinsics: the free-pose fit spends 6
    unknowns per image where the robot model spends its motion unknowns. Each camera's sums
    are weighed by its floor noise.
    """

    m = out.model
    rss_r = rss_f = 0.0
    rows = images = 0
    for ch in m.chunks:
        key = (ch.frame_index, ch.camera)
        sig = fit.sigma_px.get(ch.camera, float("nan"))
        if key not in fit.rss or not sig > 0:
            continue
        r = out.residuals[ch.rows][out.inlier_rows[ch.rows]]
        rss_r += float(r @ r) / sig**2
        rss_f += fit.rss[key] / sig**2
        rows += fit.rows[key]
        images += 1
    shape = sum(
        sl.stop - sl.start for k, sl in m.slices.items() if k.startswith(("intr:", "dist:"))
    )
    d1 = max(6 * images - (len(m.names) - shape), 1)
    d2 = max(rows - 6 * images, 1)
    if rss_f <= 0:  # no image to test
        return 1.0
    F = ((rss_r - rss_f) / d1) / (rss_f / d2)
    return float(f_tail(d1, d2, max(F, 0.0)))


def _pose_discrepancy(problem: CalibrationProblem, out: RefineOutput, fit) -> tuple[float, float]:  # noqa: ANN001
    """Rms per axis (radians, metres) of the tool poses the images imply (free poses through
    the fitted hand-eye and target) against the measured ones: where the estimation starts."""
    m, st = out.model, out.state
    seen = [i for i in range(len(problem.frames)) if (i, m.ref) in fit.T_cam_board]
    if not seen:
        return 1e-4, 1e-4
    T_cb = np.stack([fit.T_cam_board[(i, m.ref)] for i in seen])
    X = st.X[m.st.group_of_frame[seen]]
    if m.st.eye_in_hand:
        T = st.Y @ np.linalg.inv(T_cb) @ X
    else:
        T = np.linalg.inv(X) @ T_cb @ np.linalg.inv(st.Y)
    T_meas = np.stack([problem.frames[i].T_base_tool for i in seen])
    rot = [rvec_from_R(R) for R in T[:, :3, :3] @ np.swapaxes(T_meas[:, :3, :3], 1, 2)]
    tr = T[:, :3, 3] - T_meas[:, :3, 3]
    return (
        max(float(np.sqrt(np.mean(np.square(rot)))), SIGMA_FLOOR[0]),
        max(float(np.sqrt(np.mean(np.square(tr)))), SIGMA_FLOOR[1]),
    )


class _Solve:
    """One solve's mutable state: the model, the state, the inlier rows and per-camera weights,
    and the variance components' iteration (Foerstner's steps with Steffensen's acceleration).
    ``estimate``: estimate the pose prior's sigmas and each camera's noise by variance
    components (the structure must carry pose corrections)."""

    def __init__(
        self, problem: CalibrationProblem, structure: Structure, init: ModelState, estimate: bool
    ) -> None:
        model = BundleModel(problem, structure)
        self.problem, self.model = problem, model
        n_px = model.n_rows
        n_prior = sum(sl.stop - sl.start for k, sl in model.slices.items() if k in LEVELS)
        self.n_px, self.n_prior = n_px, n_prior
        self.estimate = estimate and n_prior > 0
        self.inlier = np.ones(n_px + n_prior, dtype=bool)
        self.cam_w = np.ones(n_px + n_prior)  # per-camera noise weights, relative to the ref
        self.cam_rows = [model.camera_rows(ci, n_px + n_prior) for ci in range(len(model.cams))]
        self.state = model.with_corrections(_respect_options(problem, init))
        model.sigma_px = 0.2  # a typical corner noise; re-estimated when poses are noisy
        self.total_it = 0
        self.converged = False
        self.P = len(model.names)
        self.n_obs_rows = max(n_px, 1)
        self.camera_blocks: dict[int, tuple] = {}
        self.vce_step = 0
        self.creeping = False  # the levels still moved after MAX_VCE_STEPS (a note says so)
        self.last_step: dict[str, float] = {}

    def noise(self, r: np.ndarray, w: np.ndarray) -> float:
        dof = max(int(np.sum(w[: self.n_px] > 0)) + self.n_prior - self.P, 1)
        return float(np.sqrt(np.sum(w * r * r) / dof))

    def variance_components(self, nb: NormalBlocks, Ni: BlockInverse, delta: np.ndarray) -> bool:
        """One Foerstner step at the state ``delta`` (P,) from ``state``, to first order
        (``nb``: the normal equations at ``state``, ``Ni`` their inverse): every camera's noise
        and the two pose sigmas from their residuals and redundancy numbers; True when one
        moved by more than 2-3 %."""
        model, state, inlier, n_px = self.model, self.state, self.inlier, self.n_px
        r = nb.r.copy()
        r[:n_px] += model.pixel_step(state, delta)
        moved = model.apply(state, delta)  # E, U and V at the step (linear in delta)
        # the hat matrix's diagonal over the prior rows of each block of corrections
        diag = {"E": np.diagonal(Ni.EE, axis1=1, axis2=2).reshape(-1)}
        for key in ("U", "V", "W"):
            if key in model.slices:
                diag[key] = np.diagonal(Ni.gg)[model.slices[key]]
        hats = {k: np.clip(model.prior_scale(k) ** 2 * d, 0.0, 1.0) for k, d in diag.items()}
        sig = []
        for ci, rows in enumerate(self.cam_rows):
            m = rows & inlier
            if not m.any():
                sig.append(np.nan)
                continue
            if len(self.cam_rows) == 1:  # the hat matrix's trace is P: the prior rows take sum(h)
                used = len(model.names) - float(sum(np.sum(h) for h in hats.values()))
            else:
                used = self.camera_trace(Ni, ci, m)
            sig.append(np.sqrt(np.sum(r[m] ** 2) / max(m.sum() - used, 1.0)))
        sig = np.array(sig)
        ref_i = model.cams.index(model.ref)
        new_pose, changed = self.levels_step("E", moved.E.reshape(-1), hats["E"])
        self.vce_step += 1
        ok = np.isfinite(sig) & (sig > 0)
        if ok[ref_i]:
            if abs(sig[ref_i] / model.sigma_px - 1.0) > 0.02:
                changed = True
            model.sigma_px = float(sig[ref_i])
            if len(model.cams) > 1 and np.all(ok):
                new_w = np.ones(n_px + self.n_prior)
                for rows, sc in zip(self.cam_rows, sig, strict=True):
                    new_w[rows] = (sig[ref_i] / sc) ** 2
                if np.max(np.abs(new_w / self.cam_w - 1.0)) > 0.02:
                    changed = True
                self.cam_w = new_w
        model.pose_sigma = new_pose
        for key in ("U", "V", "W"):  # the groups', the trends' and the field's own two levels
            if key in hats:
                values = getattr(moved, key).reshape(-1)
                level, shifted = self.levels_step(key, values, hats[key])
                setattr(model, LEVELS[key], level)
                changed |= shifted
        if any(v > lim for v, lim in zip(new_pose, SIGMA_BEYOND, strict=True)):
            return False
        return changed

    def camera_trace(self, Ni: BlockInverse, ci: int, m: np.ndarray) -> float:
        """The hat matrix's trace over camera ``ci``'s inlier rows ``m``: the parameters its
        rows take. The camera's pixel blocks are made once per linearisation (its weight is
        one number over its rows: a factor)."""
        hit = self.camera_blocks.get(ci)
        if hit is None or hit[0] is not self.state or not np.array_equal(hit[1], m):
            blocks = self.model.normal_blocks(self.state, m.astype(float), keep=False)
            hit = (self.state, m.copy(), blocks)
            self.camera_blocks[ci] = hit
        return float(self.cam_w[np.flatnonzero(m)[0]]) * Ni.trace_with(hit[2])

    def levels_step(
        self, key: str, values: np.ndarray, h_s: np.ndarray
    ) -> tuple[tuple[float, float], bool]:
        """Foerstner's step for the two levels (rotation, translation) of the corrections ``key``
        (``values``, the hat matrix's diagonal ``h_s`` over their prior rows; the shared ones
        after the frames' own ``E``); the new levels and whether one that matters moved by more
        than 3 %. A share of a frame's correction (``BundleModel.level_share``) below a tenth of
        the frames' own level adds under 1 % to their variance, and its creeping keeps no
        iteration going."""
        model = self.model
        new, moved, reds, data = [], False, [], []
        rot, per_frame = model.rotation_rows(key), model.level_share(key)
        for comp, floor, old, own in zip(
            (rot, ~rot), SIGMA_FLOOR, getattr(model, LEVELS[key]), model.pose_sigma, strict=True
        ):
            red = float(np.sum(1.0 - h_s[comp]))
            reds.append(red)
            if not comp.any():
                new.append(old)
                continue
            tiny = 1e-12 if key == "E" else 1e-6  # below it the prior alone holds them
            v = np.sqrt(np.sum(values[comp] ** 2) / red) if red > tiny else floor
            if key == "E" and self.vce_step < 2 and red > 0.2 * comp.sum():
                # the first steps jump to the moment estimate mean(e^2 / (1 - h)^2 - c) of the
                # corrections' pixel-only estimates e / (1 - h), noise variance c = s h / (1 - h):
                # Foerstner's iteration alone converges slowly from above when the pixels pin
                # each pose about as well as the arm's accuracy does
                one = 1.0 - h_s[comp]
                pinned = one > 1e-9  # a correction the prior alone holds has no pixel estimate
                e, one, hc = values[comp][pinned], one[pinned], h_s[comp][pinned]
                m = float(np.mean(e**2 / one**2 - old**2 * hc / one)) if len(e) else 0.0
                if m > floor**2:
                    v = min(v, np.sqrt(m))
            elif key == "U":  # the groups' level, under its prior at the frames' own
                nu = GROUP_LEVEL_PRIOR_DOF
                data.append(float(v) if red > 1e-6 else 0.0)
                v = np.sqrt((np.sum(values[comp] ** 2) + nu * own**2) / (red + nu))
            elif key != "E" and self.vce_step > 2 and v < old and red < 0.25 * comp.sum():
                # falling while the prior holds three quarters of it: the images do not
                # support a level of its own; the frames' own corrections carry this part
                v = old if key == "W" else floor
            translation = len(new) == 1  # the levels come as (rotation, translation)
            if key == "V" and translation and model.st.trend_scale_fixed:
                v = floor  # the translation trend of one orientation (Structure)
            v = max(float(v), floor)
            if self.vce_step > (1 if key == "E" else 2):
                v = max(self.accelerate(f"{key}{comp[0]}", old, v, floor), floor)
            share = per_frame if np.isscalar(per_frame) else per_frame[len(new)]
            big = max(v, old) > max(2 * floor, 0.1 * own / max(share, 1e-12))
            if abs(v / old - 1.0) > 0.03 and big:
                moved = True
            new.append(v)
        model.level_redundancy[key] = (reds[0], reds[1])
        if len(data) == 2:
            model.group_sigma_data = (data[0], data[1])
        return (new[0], new[1]), moved

    def accelerate(self, key: str, old: float, new: float, floor: float) -> float:
        """Steffensen in log space: two successive steps in the same direction give the
        iteration's geometric rate, and the step is stretched to the fixed point it implies
        (at most 4 times)."""
        if new <= floor or old <= floor:
            self.last_step.pop(key, None)
            return new
        d = float(np.log(new / old))
        prev = self.last_step.get(key)
        self.last_step[key] = d
        if prev is None or d * prev <= 0 or abs(d) >= abs(prev):
            return new
        rho = d / prev
        return float(old * np.exp(d * min(1.0 / (1.0 - rho), 4.0)))

    def settle_levels(self) -> bool:
        """The noise levels to their fixed point at the present linearisation: Foerstner's
        steps, each at the Gauss-Newton step the last levels give, to first order (a step
        costs a solve and an inverse of the reduced system, no evaluation); True when they
        moved."""
        moved = False
        while self.vce_step < MAX_VCE_STEPS:
            nb = self.model.normal_blocks(self.state, self.inlier * self.cam_w)
            Ni = nb.inverse()  # the redundancy numbers' and the step's
            delta = -Ni.times(nb.g_g, nb.g_E)
            if not np.all(np.isfinite(delta)):
                delta = np.zeros(self.P)
            if not self.variance_components(nb, Ni, delta):
                break
            moved = True
        return moved

    def _reweigh(self, r: np.ndarray) -> bool:
        """Exact-pose solves: each camera's weight and the prior rows' pixel noise to their
        fixed point; True when one moved."""
        model, changed = self.model, False
        if len(model.cams) > 1:  # per-camera noise: reweigh to a fixed point
            sig = []  # each camera's own noise (its share of the dof the parameters take)
            for rows in self.cam_rows:
                m = rows & self.inlier
                n = int(m.sum())
                dof = max(n - self.P * n / self.n_obs_rows, 1.0)
                sig.append(np.sqrt(np.sum(r[m] ** 2) / dof) if n else np.nan)
            sig = np.array(sig)
            ref_i = model.cams.index(model.ref)
            ok = np.isfinite(sig) & (sig > 0)
            if ok[ref_i] and np.all(ok):
                new_w = np.ones(self.n_px + self.n_prior)
                for rows, sc in zip(self.cam_rows, sig, strict=True):
                    new_w[rows] = (sig[ref_i] / sc) ** 2
                if np.max(np.abs(new_w / self.cam_w - 1.0)) > 0.04:
                    self.cam_w, changed = new_w, True
        if self.n_prior:  # the prior rows are weighed by the pixel noise: a fixed point
            sigma = self.noise(r, self.inlier * self.cam_w)
            if abs(sigma / model.sigma_px - 1.0) > 0.02:
                model.sigma_px, changed = sigma, True
        return changed

    def _flag_outliers(self, r: np.ndarray) -> bool:
        """Detections beyond both the options' threshold and 5 times their camera's noise get
        zero weight; True when the set is unchanged."""
        n_px, inlier, cam_w = self.n_px, self.inlier, self.cam_w
        per_pt = np.hypot(r[0:n_px:2], r[1:n_px:2])
        inl = inlier[0:n_px:2]
        sigma = self.noise(r, inlier * cam_w)
        thresh = np.maximum(
            self.problem.options.outlier_threshold_px, 5.0 * sigma / np.sqrt(cam_w[0:n_px:2])
        )
        new_out = per_pt > thresh
        if np.array_equal(new_out, ~inl):
            return True
        inlier[:n_px] = np.repeat(~new_out, 2)
        return False

    def iterate(self, max_iter: int, robust: bool) -> _Solve:
        """Levenberg-Marquardt to convergence with the weights, levels and outliers to their
        fixed point (returns the solve). With ``estimate``: the levels settle at the present
        linearisation, one Gauss-Newton step moves the state under them, and again; at the joint
        fixed point the first level step moves nothing and the state is converged fully."""
        model, estimate = self.model, self.estimate
        if estimate:
            r0 = model.trial_residuals(self.state)  # with the Jacobian the first step takes
            model.sigma_px = max(self.noise(r0, self.inlier * self.cam_w), 1e-3)
        steps = min(1, max_iter) if estimate else max_iter
        lam = LM_START_DAMPING
        for _ in range(40 if estimate else 10):
            weights = self.inlier * self.cam_w
            # the full solves after the levels' steps start from the damping the last step
            # reached (a fresh one damps the weakly determined pose corrections' directions)
            warm = estimate and steps == max_iter
            start = VCE_STEP_DAMPING if estimate else LM_START_DAMPING
            self.state, self.converged, it, r, lam = _lm(
                model, self.state, weights, steps, lam if warm else start
            )
            self.total_it += it
            changed = False
            if estimate:
                if self.vce_step < MAX_VCE_STEPS:
                    changed = self.settle_levels()
                else:  # still creeping: the last levels are kept and the parameters converged
                    # under them, so the estimate is the minimum of a definite model
                    self.creeping = True
                if not changed and steps < max_iter:
                    steps, changed = max_iter, True  # converge fully at the final levels
            else:
                changed = self._reweigh(r)
            if changed:
                continue
            if not robust or self._flag_outliers(r):
                break
        else:
            if estimate:  # the levels still creep: converge the parameters under the last
                self.state, self.converged, it, _, _ = _lm(
                    model, self.state, self.inlier * self.cam_w, max_iter
                )
                self.total_it += it
                self.creeping = True
        return self

    def output(self, covariance: bool = True) -> RefineOutput:
        """The solve's covariance (unless not ``covariance``), outliers and messages at the
        state reached."""
        model, state, n_px, P = self.model, self.state, self.n_px, self.P
        weights = self.inlier * self.cam_w
        model.row_weights = weights  # the solve's last row weights (its covariance's)
        nb = model.normal_blocks(state, weights) if covariance else None
        r = nb.r if covariance else model.trial_residuals(state)
        inlier_rows = self.inlier.copy()
        n_in = int(inlier_rows[:n_px].sum())
        dof = n_in + self.n_prior - P
        messages: list[str] = []
        if self.creeping:
            messages.append(
                f"the noise levels were still moving after {self.vce_step} updates; the last "
                "ones were kept"
            )
        sigma_px = self.noise(r, weights)
        cov = None
        if covariance and dof <= 0:
            messages.append(
                f"covariance not computed: {n_in} residuals for {P} parameters; capture more "
                "frames"
            )
        elif covariance:
            try:
                cov = nb.inverse(check_condition=True).scaled(sigma_px**2)
            except np.linalg.LinAlgError as e:
                messages.append(
                    f"covariance not computed ({e}): some parameter is barely observable; "
                    "add tilts or frames covering the image"
                )
        r, inlier_rows = r[:n_px], inlier_rows[:n_px]
        outliers: list[tuple[int, str, int]] = []
        for ch in model.chunks:
            w = weights[ch.rows][0::2]
            for cid in ch.corner_ids[w == 0]:
                outliers.append((ch.key[0], ch.camera, int(cid)))
        if not self.converged:
            messages.append(
                f"refinement stopped after {self.total_it} iterations without converging"
            )
        return RefineOutput(
            state, model.names, cov, r, inlier_rows, sigma_px, self.converged, self.total_it,
            tuple(outliers), tuple(messages), model,
        )
