"""The uncertainty: the reported quantities and their covariance, of a solve or of a plan.

The optimiser (:mod:`slidecal.solver.refine`) keeps its own coordinates (the inverse hand-eye
``X`` in an observable basis, the target pose ``Y``, robot-pose corrections, ...). This module
is the one place that turns them into what a result reports: the quantities, their names,
units and perturbation convention of docs/FORMATS.md ("Covariance names"), the nuisance
parameters marginalised.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from slidecal.solver.errors import DegenerateError
from slidecal.solver.geometry import inv_T, skew
from slidecal.solver.model import (
    BundleModel,
    ModelState,
    Structure,
    build_structure,
    fisher_covariance,
)
from slidecal.solver.problem import (
    DISTORTION_NAMES,
    INTRINSIC_NAMES,
    MOUNTS,
    CalibrationProblem,
    hand_eye_names,
    mount_names,
)
from slidecal.solver.refine import ARM_SOURCES, SIGMA_FLOOR, RefineOutput, arm_structure
from slidecal.solver.result import ROT, TRANS, NamedCovariance
from slidecal.solver.robot_error import (
    ImageErrors,
    covariance_terms,
    image_errors,
    reported_response,
    session_field_step,
)
from slidecal.solver.target_shape import READING_WEIGHT, BoardFit, fit_board


# -- the optimiser's coordinates ------------------------------------------------------------------
@dataclass(frozen=True)
class Layout:
    """What the optimiser's coordinates stand for, enough to name them.

    ``cameras`` (reference first or not: any order), ``reference``; ``mount`` (``none`` without
    a robot); ``X`` (4, 4) the optimiser's inverse hand-eye (``T_cam_tool`` / ``T_cam_base``),
    ``Y`` (4, 4) the target pose, both None without a robot; ``T_cam_ref`` (4, 4) per other
    camera; the observable bases (3, m) of X's and Y's rotation and translation.
    """

    cameras: tuple[str, ...]
    reference: str
    mount: str
    X: np.ndarray | None
    Y: np.ndarray | None
    T_cam_ref: dict[str, np.ndarray]
    X_rot_basis: np.ndarray
    X_t_basis: np.ndarray
    Y_rot_basis: np.ndarray
    Y_t_basis: np.ndarray

    @property
    def rotation_reported(self) -> bool:
        """Whether the hand-eye (and target) rotation is determined by the data."""
        return self.X is not None and self.X_rot_basis.shape[1] == 3 == self.Y_rot_basis.shape[1]

    @property
    def translation_reported(self) -> bool:
        """Whether the hand-eye (and target) translation is determined by the data."""
        return self.rotation_reported and self.X_t_basis.shape[1] == 3 == self.Y_t_basis.shape[1]


def layout_of(problem: CalibrationProblem, structure: Structure, state: ModelState) -> Layout:
    """The layout of a problem (``CalibrationProblem``), its ``Structure`` and a ``ModelState``."""
    robot = problem.knowledge == "robot" and problem.mount in MOUNTS
    return Layout(
        tuple(c.name for c in problem.cameras),
        problem.reference,
        problem.mount if robot else "none",
        np.asarray(state.X[0], float) if robot else None,
        np.asarray(state.Y, float) if robot else None,
        {c: np.asarray(T, float) for c, T in state.T_cam_ref.items()},
        structure.X_rot_basis,
        structure.X_t_basis,
        structure.Y_rot_basis,
        structure.Y_t_basis,
    )


def _inverse_jacobian(T: np.ndarray) -> np.ndarray:
    """(6, 6): the perturbation (r, t) of ``inv(T)`` from that of ``T`` (left convention)."""
    R, t = T[:3, :3], T[:3, 3]
    J = np.zeros((6, 6))
    J[:3, :3] = -R.T
    J[3:, :3] = -R.T @ skew(t)
    J[3:, 3:] = -R.T
    return J


def _compose_jacobians(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(6, 6) twice: the perturbation of ``A @ B`` from that of ``A`` and from that of ``B``."""
    RA = A[:3, :3]
    JA = np.eye(6)
    JA[3:, :3] = -skew(RA @ B[:3, 3])
    JB = np.zeros((6, 6))
    JB[:3, :3] = RA
    JB[3:, 3:] = RA
    return JA, JB


class _Rows:
    """Builds the Jacobian of the named quantities with respect to the optimiser's."""

    def __init__(self, internal: tuple[str, ...]) -> None:
        self.col = {n: i for i, n in enumerate(internal)}
        self.names: list[str] = []
        self.rows: list[np.ndarray] = []

    def cols(self, names: list[str]) -> np.ndarray | None:
        if any(n not in self.col for n in names):
            return None
        return np.array([self.col[n] for n in names], dtype=int)

    def add(self, name: str, cols: np.ndarray, coef: np.ndarray) -> None:
        row = np.zeros(len(self.col))
        np.add.at(row, cols, coef)
        self.names.append(name)
        self.rows.append(row)

    def add_transform(
        self, name: str, cols: np.ndarray, J: np.ndarray, rot: bool, trans: bool
    ) -> None:
        """Rows ``name.rx`` .. ``name.tz`` (those reported) of ``J`` (6, len(cols))."""
        for k, a in enumerate(ROT + TRANS):
            if (k < 3 and rot) or (k >= 3 and trans):
                self.add(f"{name}.{a}", cols, J[k])


def _block_names(prefix: str, rot_basis: np.ndarray, t_basis: np.ndarray) -> list[str]:
    """The optimiser's names of a transform block in its observable basis."""
    return [f"{prefix}.r{k}" for k in range(rot_basis.shape[1])] + [
        f"{prefix}.t{k}" for k in range(t_basis.shape[1])
    ]


def _jacobian(layout: Layout, internal: tuple[str, ...]) -> tuple[tuple[str, ...], np.ndarray]:
    """Names of the reported quantities and their Jacobian (n, len(internal))."""
    out = _Rows(internal)
    for c in layout.cameras:
        for n in INTRINSIC_NAMES + DISTORTION_NAMES:
            i = out.cols([f"{c}.{n}"])
            if i is None and n in INTRINSIC_NAMES[:2]:  # unit aspect: one focal length for both
                i = out.cols([f"{c}.f"])
            if i is not None:
                out.add(f"{c}.{n}", i, np.ones(1))
    ref = layout.reference
    rig_cols = {}
    for c in layout.T_cam_ref:
        key = f"T_{c}_{ref}"
        i = out.cols([f"{key}.{a}" for a in ROT + TRANS])
        if i is not None:
            rig_cols[c] = i
            out.add_transform(key, i, np.eye(6), True, True)
    m = mount_names(layout.mount)
    rot, trans = layout.rotation_reported, layout.translation_reported
    Xr, Xt = layout.X_rot_basis, layout.X_t_basis
    Yr, Yt = layout.Y_rot_basis, layout.Y_t_basis
    xi = out.cols(_block_names("X0", Xr, Xt))
    yi = out.cols(_block_names("Y", Yr, Yt))
    if m is None or not rot or layout.X is None or layout.Y is None or xi is None or yi is None:
        return tuple(out.names), np.array(out.rows).reshape(len(out.names), len(internal))
    # the optimiser's X (and Y) coordinates -> X's (Y's) perturbation
    BX = np.block([[Xr, np.zeros_like(Xt)], [np.zeros_like(Xr), Xt]])
    BY = np.block([[Yr, np.zeros_like(Yt)], [np.zeros_like(Yr), Yt]])
    he = hand_eye_names(layout.mount, list(layout.cameras))
    out.add_transform(he[ref], xi, _inverse_jacobian(layout.X) @ BX, rot, trans)
    for c, T in layout.T_cam_ref.items():  # T_holder_c = inv(T_c_ref @ X), correlations kept
        if c not in rig_cols or c not in he:
            continue
        JA, JB = _compose_jacobians(T, layout.X)
        Jinv = _inverse_jacobian(T @ layout.X)
        cols = np.concatenate([rig_cols[c], xi])
        out.add_transform(he[c], cols, np.hstack([Jinv @ JA, Jinv @ JB @ BX]), rot, trans)
    out.add_transform(m.target, yi, BY, rot, trans)
    return tuple(out.names), np.array(out.rows)


def reported_names(layout: Layout, internal: tuple[str, ...]) -> tuple[str, ...]:
    """The names of the reported quantities of a layout whose optimiser names are ``internal``."""
    return _jacobian(layout, tuple(internal))[0]


def propagate(layout: Layout, internal: tuple[str, ...], cov: np.ndarray) -> NamedCovariance:
    """The covariance of the reported quantities from the optimiser's ``cov`` (P, P) named
    ``internal``: ``J cov J'`` through the Jacobian of every reported quantity (inversions and
    compositions of transforms included; nuisance parameters marginalised)."""
    return _apply(*_jacobian(layout, tuple(internal)), cov)


def named_step(layout: Layout, internal: tuple[str, ...], step: np.ndarray) -> dict[str, float]:
    """How far each reported quantity moves (first order) for the step ``step`` (P,) of the
    optimiser's coordinates named ``internal`` (radians and metres for transforms)."""
    names, J = _jacobian(layout, tuple(internal))
    return dict(zip(names, (J @ np.asarray(step, float)).tolist(), strict=True))


def _apply(names: tuple[str, ...], J: np.ndarray, cov: np.ndarray) -> NamedCovariance:
    """``J cov J'`` over the columns ``J`` uses, named ``names``."""
    Ju, used = _used(J)
    C = Ju @ np.asarray(cov, float)[np.ix_(used, used)] @ Ju.T
    return NamedCovariance(names, 0.5 * (C + C.T))


def _used(J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``J`` restricted to the parameters it uses, and their indices: the projection of the
    optimiser's coordinates onto the reported quantities."""
    used = np.flatnonzero(np.any(J != 0, axis=0))
    return J[:, used], used


def result_covariance(
    problem: CalibrationProblem, out: RefineOutput, images: ImageErrors, groups: np.ndarray
) -> tuple[tuple[str, ...], NamedCovariance | None]:
    """The reported quantities of a refinement (``RefineOutput``) of ``problem`` and their
    named covariance (None when the refinement has none): the model's own ``J C J'`` plus
    every term of the error model (:func:`slidecal.solver.robot_error.covariance_terms`;
    ``images``: how the images' errors read, ``groups`` (F,): the orientation groups)."""
    layout = layout_of(problem, out.model.st, out.state)
    if out.covariance_blocks is None:
        return reported_names(layout, out.names), None
    names, J = _jacobian(layout, tuple(out.names))
    project = _used(J)  # the reported quantities from the parameters they use
    C = project[0] @ out.covariance_blocks.submatrix(project[1], project[1]) @ project[0].T
    named = NamedCovariance(names, 0.5 * (C + C.T))
    for extra in covariance_terms(problem, out, project, images, groups):
        named = NamedCovariance(names, named.matrix + extra)
    return names, named


# -- a finished solve, as reported ------------------------------------------------------------
@dataclass(frozen=True)
class Reported:
    """A finished solve as reported (:func:`reported_covariance`): ``state`` the reported value,
    ``names`` and ``covariance`` (None without one) the reported quantities', ``board`` the
    board's fit (None for an exact board), ``images`` how the images' errors read,
    ``field_step`` a classic session's step to its reading without its field (else None)."""

    state: ModelState
    names: tuple[str, ...]
    covariance: NamedCovariance | None
    board: BoardFit | None
    images: ImageErrors
    field_step: np.ndarray | None


def reported_covariance(
    problem: CalibrationProblem,
    out: RefineOutput,
    groups: np.ndarray,
    board_scale: float = 0.0,
) -> Reported:
    """The one way from a finished solve (``out`` of ``problem``; ``groups`` (F,): its frames'
    orientation groups) to its reported value and covariance, whatever the session
    (docs/ERROR_MODEL.md Sec. 3). ``board_scale``: the least relative scale uncertainty of the
    board (a classic session's unexplained length ratio)."""
    board = with_session_scale(problem, out, fit_board(problem, out), board_scale)
    if board is not None:  # its modes' response at the reported value (a classic session's)
        board = replace(board, response=reported_response(out, board.response))
        out = replace(out, board=board)
    images = image_errors(problem, out, groups)
    names, named = result_covariance(problem, out, images, groups)
    state = out.state
    if board is not None:  # between the readings of the board's misfit: G w bow (M5)
        state = out.model.apply(state, READING_WEIGHT * (board.response[:, 3:] @ board.bow_m))
    field_step = session_field_step(out)  # a classic session: with its arm's field or not
    if field_step is not None:
        state = out.model.apply(state, READING_WEIGHT * field_step)
    return Reported(state, names, named, board, images, field_step)


def with_session_scale(
    problem: CalibrationProblem, out: RefineOutput, board: BoardFit | None, scale: float
) -> BoardFit | None:
    """``board`` (the session's :func:`fit_board`) with its scale mode's second moment at
    least ``scale^2``, the others kept; for a board described as exact (no fit), a fit of the
    scale mode alone (no bow read: the estimate stays)."""
    if scale <= 0.0:
        return board
    if board is None:
        exact = replace(problem.target, print_tolerance=scale, flatness_m=0.0)
        board = fit_board(replace(problem, target=exact), out)
        if board is None:
            return None
        return replace(board, mode_cov=np.diag([scale**2, 0.0, 0.0, 0.0, 0.0]))
    if board.mode_cov[0, 0] >= scale**2:
        return board
    mode_cov = board.mode_cov.copy()
    mode_cov[0, 0] = scale**2
    return replace(board, mode_cov=mode_cov)


# -- predictions at a known state -----------------------------------------------------------------
def predicted_covariance(
    problem: CalibrationProblem,
    truth: ModelState,
    sigma_px: float,
    *,
    structure: Structure | None = None,
    camera_sigma_px: dict[str, float] | None = None,
) -> NamedCovariance:
    """The Cramer-Rao bound (docs/METHOD.md Sec. 6) of the reported quantities at ``truth``.

    ``problem`` holds the detections' ids (their pixel values are not used); ``sigma_px``: the
    pixel noise (per coordinate); ``camera_sigma_px``: per camera, when the cameras of a rig
    differ. ``structure``: what is observable (``build_structure`` of the problem at the true
    hand-eye rotation when None). The arm's per-pose error enters at the level of
    ``problem.options`` (``robot_noise_deg``, ``robot_noise_m``; exact poses when both are 0).
    """
    st = build_structure(problem, truth.X[0][:3, :3]) if structure is None else structure
    names, cov = fisher_covariance(problem, st, truth, sigma_px, camera_sigma_px)
    return propagate(layout_of(problem, st, truth), names, cov)


def equal_weight_covariance(
    problem: CalibrationProblem,
    truth: ModelState,
    camera_sigma_px: dict[str, float],
    *,
    structure: Structure | None = None,
) -> NamedCovariance:
    """The covariance of the reported quantities for an estimator that weighs every pixel row
    alike (and the robot-pose prior rows by the pooled noise) when each camera's corner noise
    is ``camera_sigma_px`` (pixels, per axis): the sandwich ``A^-1 B A^-1`` at ``truth``. It
    equals :func:`predicted_covariance` when all cameras are equally noisy and cannot beat it
    otherwise."""
    st = build_structure(problem, truth.X[0][:3, :3]) if structure is None else structure
    model = BundleModel(problem, st)
    model.sigma_px = 1.0  # prior rows in units of their own sigma
    state = model.with_corrections(truth)
    _, J = model.evaluate(state)
    sig_rows = np.repeat(np.array([camera_sigma_px[c] for c in model.cams])[model.o_cam], 2)
    n_px = len(sig_rows)
    Jw = J.copy()
    Jw[:n_px] /= sig_rows[:, None]  # whitened: every row has unit noise
    scale = np.sqrt(np.sum(Jw * Jw, axis=0))
    scale[scale == 0] = 1.0
    Js = Jw / scale
    w = np.ones(len(J))  # the estimator's weights on the whitened rows
    w[:n_px] = sig_rows**2
    w[n_px:] = float(np.mean(sig_rows**2))
    Ai = np.linalg.inv(Js.T @ (w[:, None] * Js))
    cov = Ai @ (Js.T @ ((w**2)[:, None] * Js)) @ Ai / np.outer(scale, scale)
    return propagate(layout_of(problem, st, truth), model.names, cov)


@dataclass(frozen=True)
class FrameInformation:
    """Each frame's Fisher information on the shared parameters, and how to name its inverse.

    ``per_frame`` (F, P, P): in the optimiser's coordinates (opaque: sum the frames of a plan,
    invert, then :meth:`named`); a frame's own robot-pose correction is marginalised out, so the
    information of a set of frames is the sum of theirs. ``kinds`` (P,): ``intrinsics``,
    ``distortion`` or ``pose`` per coordinate (for a weak prior).
    """

    per_frame: np.ndarray
    kinds: tuple[str, ...]
    layout: Layout
    internal: tuple[str, ...]
    _map: tuple[tuple[str, ...], np.ndarray] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:  # the Jacobian once: a planner reads thousands of sums
        object.__setattr__(self, "_map", _jacobian(self.layout, self.internal))

    def named(self, cov: np.ndarray) -> NamedCovariance:
        """The named covariance of an inverse (P, P) of summed information."""
        return _apply(*self._map, cov)


def frame_information(
    problem: CalibrationProblem, structure: Structure, truth: ModelState, sigma_px: float
) -> FrameInformation:
    """The Fisher information of every frame of ``problem`` (each must see the target) at
    ``truth``, pixel noise ``sigma_px``; robot-pose corrections (Gaussian prior of the
    ``structure``) marginalised by a Schur complement (docs/METHOD.md Sec. 6)."""
    model = BundleModel(problem, structure)
    model.sigma_px = sigma_px
    truth = model.with_corrections(truth)
    _, J = model.evaluate(truth)
    e_sl = model.slices.get("E")
    P = e_sl.start if e_sl is not None else len(model.names)
    out = np.empty((len(problem.frames), P, P))
    by_frame = {ch.frame_index: ch.rows for ch in model.chunks}
    for k in range(len(problem.frames)):
        rows = by_frame[k]
        Jt = J[rows, :P]
        A = Jt.T @ Jt
        if e_sl is not None:
            cols = slice(e_sl.start + 6 * k, e_sl.start + 6 * k + 6)
            Je = J[rows, cols]
            prior = J[model.n_rows + 6 * k : model.n_rows + 6 * k + 6, cols]
            B = Je.T @ Je + prior.T @ prior
            C = Jt.T @ Je
            A = A - C @ np.linalg.solve(B, C.T)
        out[k] = A / sigma_px**2
    kinds = []
    for key, sl in model.slices.items():
        kind = {"intr": "intrinsics", "dist": "distortion"}.get(key.split(":")[0], "pose")
        kinds += [kind] * (min(sl.stop, P) - sl.start)
    return FrameInformation(
        out, tuple(kinds[:P]), layout_of(problem, structure, truth), model.names[:P]
    )


# -- result files of earlier versions -------------------------------------------------------------
def legacy_layout(
    internal: tuple[str, ...],
    cameras: tuple[str, ...],
    reference: str,
    mount: str,
    T_hand_eye: np.ndarray | None,
    T_target: np.ndarray | None,
    T_cam_ref: dict[str, np.ndarray],
) -> Layout:
    """The layout of a covariance written with the optimiser's names (result files before the
    named model): the hand-eye ``T_hand_eye`` and target pose ``T_target`` as reported (None
    when not determined); bases are the identity for the blocks written whole, otherwise the
    block is not reported (its basis is not in the file)."""

    def basis(prefix: str) -> np.ndarray:
        n = sum(1 for x in internal if x.startswith(prefix))
        return np.eye(3) if n == 3 else np.zeros((3, 0))

    robot = mount in MOUNTS and T_hand_eye is not None and T_target is not None
    return Layout(
        cameras,
        reference,
        mount if robot else "none",
        inv_T(T_hand_eye) if robot else None,
        T_target if robot else None,
        T_cam_ref,
        basis("X0.r"),
        basis("X0.t"),
        basis("Y.r"),
        basis("Y.t"),
    )


def is_legacy(names: tuple[str, ...] | list[str]) -> bool:
    """Whether covariance row names are the optimiser's (a result of an earlier version)."""
    pat = re.compile(r"(X\d+|Y)\.[rt]\d|s\d+|.+\.f")
    return any(pat.fullmatch(n) for n in names)


# -- a plan's prediction (the planner's) -------------------------------------------------------
def planned_covariance(
    problem: CalibrationProblem,
    truth: ModelState,
    sigma_px: float,
    *,
    levels: Mapping[str, tuple[float, float]] | None = None,
    per_frame: bool = False,
) -> NamedCovariance | FrameInformation:
    """What a solve of the planned ``problem`` (exact detections: their ids count) would report
    at ``truth`` when its corners err by ``sigma_px`` and its arm as ``levels`` say: the
    Cramer-Rao bound under the solve's arm (:func:`slidecal.solver.refine.arm_structure`), named.
    ``levels``: each source's share of a frame's error (rad, m) by name, as
    ``RefineOutput.robot_levels`` (a source it lacks at ``SIGMA_FLOOR``); None: every source at
    ``problem.options``'s ``robot_noise_*``. Raises ``DegenerateError`` when the plan leaves a
    reported quantity unobservable. ``per_frame``: each frame's information instead
    (:class:`FrameInformation`, every transform taken as observable).
    """
    st = build_structure(problem, truth.X[0][:3, :3])
    o = problem.options
    sig = (max(np.radians(o.robot_noise_deg), SIGMA_FLOOR[0]), max(o.robot_noise_m, SIGMA_FLOOR[1]))
    given = levels if levels else dict.fromkeys(ARM_SOURCES, sig)
    lv = {k: np.maximum(given.get(k, SIGMA_FLOOR), SIGMA_FLOOR) for k in ARM_SOURCES}
    T = np.stack([f.T_base_tool for f in problem.frames])
    st = replace(st, T_meas=T, pose_sigma=tuple(lv["pose"]))
    if per_frame:
        I3 = np.eye(3)
        full = replace(st, X_rot_basis=I3, X_t_basis=I3, Y_rot_basis=I3, Y_t_basis=I3)
        return frame_information(problem, full, truth, sigma_px)
    if st.unobservable:
        name, why = next(iter(st.unobservable.items()))
        raise DegenerateError(f"the plan leaves {name} unobservable: {why}")
    st = arm_structure(st, T, lv, False)[0]
    names, cov = fisher_covariance(problem, st, truth, sigma_px)
    return propagate(layout_of(problem, st, truth), names, cov)
