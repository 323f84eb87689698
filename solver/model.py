"""The bundle model: its state, structure, residuals and Jacobians, and its Fisher information.

The model ``P_c = T_c_ref X_g M_k Y p`` of every knowledge and mount is docs/METHOD.md Sec. 5's
(the optimiser: :mod:`slidecal.solver.refine`). Rotations are updated on the left
(``R <- exp([d]x) R``); Jacobians are analytic (chain rule through
:mod:`slidecal.solver.camera`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace

import numpy as np
from threadpoolctl import ThreadpoolController

from slidecal.solver.camera import project_with_jacobians
from slidecal.solver.errors import DegenerateError
from slidecal.solver.geometry import R_from_rvec, R_from_rvecs, T_from_Rt, rvec_from_R
from slidecal.solver.problem import MOUNTS, CalibrationProblem

#: Axis names of a pose correction: rotation vector (radians), translation (metres).
POSE_AXES = ("rx", "ry", "rz", "tx", "ty", "tz")
#: The axes of the pose correction that drift linearly along a group's translations
#: (``Structure.trend_*``).
TREND_AXES = (0, 1, 2, 3, 4, 5)
_ROTATION_AXES = np.array([True, True, True, False, False, False])
#: The model's attribute holding the (rotation, translation) levels of each block of corrections:
#: the frames' own and the groups' (radians, metres), the trends' and the shared field's (per metre)
LEVELS = {"E": "pose_sigma", "U": "group_sigma", "V": "trend_sigma", "W": "common_sigma"}


@dataclass(frozen=True)
class ModelState:
    """Values of every model quantity (estimated or fixed).

    ``K`` (3, 3) and ``dist`` (5,) per camera name; ``T_cam_ref`` (4, 4) per non-reference camera;
    ``X`` (G, 4, 4) per group; ``Y`` (4, 4); ``s`` (F,) per frame index (Case 2 lengths, else 0);
    ``E`` (F, 6): corrections of the measured robot poses (rotation vector in radians, applied
    on the left in the base frame, then translation in metres), None when poses are exact.
    """

    K: dict[str, np.ndarray]
    dist: dict[str, np.ndarray]
    T_cam_ref: dict[str, np.ndarray]
    X: np.ndarray
    Y: np.ndarray
    s: np.ndarray
    E: np.ndarray | None = None
    U: np.ndarray | None = None  # (G, 6) per orientation group, added to its frames' E
    V: np.ndarray | None = None  # (n,) the trends (``Structure.trend_*``), added to their E
    W: np.ndarray | None = None  # (n,) the shared field (``Structure.common_*``), added to E


@dataclass(frozen=True)
class Structure:
    """What is fixed by the data and the knowledge, decided once before refining.

    ``group_of_frame`` (F,) group index per frame (index into ``ModelState.X``); ``M`` (F, 4, 4)
    the known motion per frame (without the unknown Case 2 lengths); ``direction`` (F, 3) board
    frame unit directions for Case 2; ``s_free`` (F,) bool; ``X_rot_basis``, ``X_t_basis``,
    ``Y_rot_basis``, ``Y_t_basis`` (3, m): observable directions of each rotation (left
    perturbation, radians) and translation (metres), m = 0 when fixed;
    ``unobservable``: name -> reason for everything fixed. ``T_meas`` (F, 4, 4): the measured
    ``T_base_tool`` when robot poses carry noise (``pose_sigma`` = (radians, metres)), else None.
    """

    group_of_frame: np.ndarray
    M: np.ndarray
    direction: np.ndarray
    s_free: np.ndarray
    X_rot_basis: np.ndarray
    X_t_basis: np.ndarray
    Y_rot_basis: np.ndarray
    Y_t_basis: np.ndarray
    unobservable: dict[str, str] = field(default_factory=dict)
    T_meas: np.ndarray | None = None
    pose_sigma: tuple[float, float] | None = None
    eye_in_hand: bool = True
    # ``pose_groups`` (F,): each frame's orientation group, for a shared correction ``U`` per
    # group with prior sigmas ``group_sigma`` (radians, metres); None: frames independent
    pose_groups: np.ndarray | None = None
    group_sigma: tuple[float, float] | None = None
    # a trend along the moves: frame k of trend group g gains ``D_g c_k``, ``c_k`` its measured
    # translation offset from the group's mean in a basis of the group's directions
    # (``trend_coords`` (F, 3), metres, zero-padded), ``D_g`` (6, trend_dims[g]) (rad/m, m/m)
    # with prior sigmas ``trend_sigma``; ``trend_groups`` (F,): trend group per frame, -1: none
    trend_groups: np.ndarray | None = None
    trend_coords: np.ndarray | None = None
    trend_dims: tuple[int, ...] = ()
    trend_sigma: tuple[float, float] | None = None
    # one orientation: the trend's translation scale is the focal length's, which no image
    # tells apart; it stays at the floor (the covariance carries it)
    trend_scale_fixed: bool = False
    # the error the trend groups share (:func:`slidecal.solver.refine.common_trend`): frame k
    # gains ``common_map[k] W`` (``common_map`` (F, 6, n)), ``W`` (n,) with prior sigmas
    # ``common_sigma`` (rad/m, m/m) on the rotation columns ``common_rotation`` (n,) and the
    # others; ``common_spread`` (rotation, translation): a level's share of a frame's (metres)
    common_map: np.ndarray | None = None
    common_rotation: np.ndarray | None = None
    common_sigma: tuple[float, float] | None = None
    common_spread: tuple[float, float] = (0.0, 0.0)


def intrinsic_names(problem: CalibrationProblem) -> tuple[str, ...]:
    """Names of the estimated intrinsics of one camera under the problem's options."""
    o = problem.options
    names = ("f",) if o.unit_aspect else ("fx", "fy")
    names += ("cx", "cy")
    if o.skew:
        names += ("s",)
    return names


def distortion_names(problem: CalibrationProblem) -> tuple[str, ...]:
    """Names of the estimated distortion coefficients."""
    o = problem.options
    return tuple(n for n, on in zip(o.distortion_names, o.distortion_mask, strict=True) if on)


@dataclass(frozen=True)
class _Chunk:
    frame_index: int
    camera: str
    rows: slice
    points: np.ndarray  # (n, 3) board
    px: np.ndarray  # (n, 2)
    key: tuple[int, str]  # (frame id, camera)
    corner_ids: np.ndarray


def _chunks(problem: CalibrationProblem) -> list[_Chunk]:
    chunks = []
    row = 0
    pts = problem.target.points_m
    for fi, frame in enumerate(problem.frames):
        for cam in problem.cameras:
            det = frame.detections.get(cam.name)
            if det is None or len(det.ids) == 0:
                continue
            rows, key = slice(row, row + 2 * len(det.ids)), (frame.id, cam.name)
            chunks.append(_Chunk(fi, cam.name, rows, pts[det.ids], det.px, key, det.ids))
            row = rows.stop
    return chunks


@dataclass(frozen=True)
class BlockInverse:
    """Blocks of the inverse normal matrix (see :meth:`NormalBlocks.inverse`).

    ``EE`` (F, 6, 6): each frame's own block. ``frame_inv`` (F, 6, 6), ``coupling`` (P0, 6 F)
    and ``reduced_inv`` (P0, P0) give the frames' cross blocks ``coupling' reduced_inv
    coupling`` for :meth:`dense`; ``global_scale`` (P0,): the global parameters' scaling of
    ``reduced_inv``. The global and coupling blocks :attr:`gg` and :attr:`gE` derive from them.
    """

    EE: np.ndarray
    frame_inv: np.ndarray
    coupling: np.ndarray
    reduced_inv: np.ndarray
    global_scale: np.ndarray

    @functools.cached_property
    def gg(self) -> np.ndarray:
        """(P0, P0): the global parameters' block (the inverse of the reduced matrix)."""
        return self.reduced_inv / np.outer(self.global_scale, self.global_scale)

    @functools.cached_property
    def gE(self) -> np.ndarray:
        """(P0, F, 6): the global parameters' coupling with each frame's correction."""
        P0, F = len(self.global_scale), len(self.EE)
        return -(self.reduced_inv @ self.coupling / self.global_scale[:, None]).reshape(P0, F, 6)

    def times(self, g_g: np.ndarray, g_E: np.ndarray) -> np.ndarray:
        """``inverse @ v`` (P,) for ``v`` = (global part (P0,), frames' part (F, 6)): the
        factor form of :meth:`submatrix`, ``W' reduced_inv (W v)`` plus the frames' own
        blocks times their part (a Gauss-Newton step from an inverse already made)."""
        y = self.reduced_inv @ (g_g / self.global_scale - self.coupling @ g_E.reshape(-1))
        frames = (self.frame_inv @ g_E[:, :, None])[:, :, 0].reshape(-1) - self.coupling.T @ y
        return np.concatenate([y / self.global_scale, frames])

    def trace_with(self, blocks: NormalBlocks) -> float:
        """``trace(inverse @ M)`` for ``M`` of the same block pattern (``blocks``' normal
        matrix), without dense matrices: the hat matrix's trace over some rows."""
        return float(
            np.sum(self.gg * blocks.A_gg)
            + 2.0 * np.sum(self.gE * blocks.A_gE)
            + np.sum(self.EE * blocks.A_EE)
        )

    def dense(self) -> np.ndarray:
        """The whole inverse (P, P), frames' cross blocks included (one product of the size
        of the frames' block: only for a caller that asks for the full covariance)."""
        cross = self.coupling.T @ self.reduced_inv @ self.coupling
        return _assemble(self.gg, self.gE, self.frame_inv, cross)

    def scaled(self, factor: float) -> BlockInverse:
        """The same blocks times ``factor`` (a covariance ``s^2 (J' W J)^-1``)."""
        return replace(
            self,
            EE=factor * self.EE,
            frame_inv=factor * self.frame_inv,
            reduced_inv=factor * self.reduced_inv,
        )

    def submatrix(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """``dense()[np.ix_(rows, cols)]`` without the dense matrix: the inverse is
        ``W' reduced_inv W`` plus the frames' own ``frame_inv`` on the diagonal blocks, where
        ``W``'s column of a global parameter is its unit vector over its scale and a frame
        correction's is minus its ``coupling`` column; a few rows (the reported quantities'
        parameters) against any columns cost O(P0^2 (rows + cols))."""
        rows, cols = np.asarray(rows, int), np.asarray(cols, int)
        P0 = self.gg.shape[0]
        Si, s_g = self.reduced_inv, self.global_scale

        def factor(idx: np.ndarray) -> np.ndarray:
            W = np.zeros((P0, len(idx)))
            g = idx < P0
            W[idx[g], np.flatnonzero(g)] = 1.0 / s_g[idx[g]]
            if not g.all():
                W[:, ~g] = -self.coupling[:, idx[~g] - P0]
            return W

        out = factor(rows).T @ Si @ factor(cols)
        fr, fc = rows >= P0, cols >= P0
        if fr.any() and fc.any():  # the frames' own blocks, where a row and a column share one
            a, b = rows[fr] - P0, cols[fc] - P0
            same = (a[:, None] // 6) == (b[None, :] // 6)
            own = self.frame_inv[a[:, None] // 6, a[:, None] % 6, b[None, :] % 6]
            out[np.ix_(np.flatnonzero(fr), np.flatnonzero(fc))] += np.where(same, own, 0.0)
        return out


def _assemble(
    gg: np.ndarray, gE: np.ndarray, EE: np.ndarray, frames: np.ndarray | None = None
) -> np.ndarray:
    """The symmetric matrix (P0 + 6 F, P0 + 6 F) of the blocks ``gg`` (P0, P0), ``gE``
    (P0, F, 6) and the frames' diagonal blocks ``EE`` (F, 6, 6), added to ``frames``
    (6 F, 6 F) when given (else zero between frames)."""
    P0, F = gE.shape[:2]
    M = np.zeros((P0 + 6 * F, P0 + 6 * F))
    M[:P0, :P0] = gg
    M[:P0, P0:] = gE.reshape(P0, 6 * F)
    M[P0:, :P0] = M[:P0, P0:].T
    if frames is not None:
        M[P0:, P0:] = frames
    for k in range(F):
        c = P0 + 6 * k
        M[c : c + 6, c : c + 6] += EE[k]
    return M


@dataclass(frozen=True)
class NormalBlocks:
    """Normal equations ``J' W J``, ``J' W r`` in blocks: the global parameters (every column
    before the per-frame pose corrections ``E``) and one 6 x 6 block per frame.

    ``r`` (R,) the residuals; ``A_gg`` (P0, P0), ``g_g`` (P0,); ``A_gE`` (P0, F, 6) the coupling
    of the global parameters with frame k's correction; ``A_EE`` (F, 6, 6) the frames' own
    blocks (frames do not couple with one another), ``g_E`` (F, 6). Without pose corrections
    F = 0. The per-frame blocks are eliminated by the Schur complement, as bundle adjusters do:
    every solve and inverse costs O(F P0^2 + P0^3) instead of O((P0 + 6 F)^3).
    """

    r: np.ndarray
    A_gg: np.ndarray
    g_g: np.ndarray
    A_gE: np.ndarray
    A_EE: np.ndarray
    g_E: np.ndarray
    # the frames grouped by the global rows their ``A_gE`` touches (a frame couples with its
    # own group's and trend's shared corrections alone): per group, those rows and its frames;
    # the Schur products run block by block (by default one block: every row, every frame)
    frame_blocks: list[tuple] = field(default_factory=lambda: [(slice(None), slice(None))])

    def diagonal(self) -> tuple[np.ndarray, np.ndarray]:
        """The diagonal of ``J' W J``: global (P0,) and per frame (F, 6)."""
        return np.diagonal(self.A_gg).copy(), np.diagonal(self.A_EE, axis1=1, axis2=2).copy()

    def solve(self, lam: float = 0.0) -> np.ndarray:
        """The step ``delta`` (P,) of ``(A + lam diag(A)) delta = -g`` (Levenberg-Marquardt;
        zero diagonal entries damped by 1), per-frame blocks eliminated. Raises
        ``np.linalg.LinAlgError`` when the damped system is singular."""
        d_g, d_E = self.diagonal()
        d_g[d_g <= 0] = 1.0
        d_E[d_E <= 0] = 1.0
        A_gg = self.A_gg + lam * np.diag(d_g)
        A_EE = self.A_EE.copy()
        i6 = np.arange(6)
        A_EE[:, i6, i6] += lam * d_E
        Ei = np.linalg.inv(A_EE)  # (F, 6, 6)
        P0 = len(self.g_g)
        L, S = _reduced(A_gg, self.A_gE, Ei, self.frame_blocks)
        rhs = -self.g_g + L @ self.g_E.reshape(-1)
        d_glob = np.linalg.solve(S, rhs)
        back = -self.g_E - (d_glob @ self.A_gE.reshape(P0, -1)).reshape(-1, 6)
        d_frames = (Ei @ back[:, :, None])[:, :, 0]
        return np.concatenate([d_glob, d_frames.reshape(-1)])

    def inverse(self, check_condition: bool = False) -> BlockInverse:
        """The blocks of ``(J' W J)^-1`` that are needed: the global one (the inverse of the
        reduced matrix), the global-frame couplings and each frame's own 6 x 6 block
        ``Ei + Ei A_Eg S^-1 A_gE Ei``. Computed on the diagonally scaled matrix; a singular
        reduced matrix gets the pseudo-inverse, unless ``check_condition``: then its condition
        number (scaled) above 1e14 raises ``np.linalg.LinAlgError``. The frames' blocks carry
        their prior, so the reduced matrix decides."""
        d_g, d_E = self.diagonal()
        s_g, s_E = np.sqrt(np.maximum(d_g, 0.0)), np.sqrt(np.maximum(d_E, 0.0))
        s_g[s_g == 0] = 1.0
        s_E[s_E == 0] = 1.0
        A_gg = self.A_gg / np.outer(s_g, s_g)
        A_gE = self.A_gE / (s_g[:, None, None] * s_E[None, :, :])
        A_EE = self.A_EE / (s_E[:, :, None] * s_E[:, None, :])
        try:
            Ei = np.linalg.inv(A_EE)
        except np.linalg.LinAlgError:
            Ei = np.linalg.pinv(A_EE)
        P0 = len(s_g)
        L, S = _reduced(A_gg, A_gE, Ei, self.frame_blocks)
        if check_condition:
            cond = np.linalg.cond(S)
            if not np.isfinite(cond) or cond > 1e14:
                raise np.linalg.LinAlgError(f"normal matrix condition {cond:.1e}")
            Si = np.linalg.inv(S)
        else:
            try:
                Si = np.linalg.inv(S)
            except np.linalg.LinAlgError:
                Si = np.linalg.pinv(S)
        F = len(s_E)
        EE = Ei.copy()
        for rows, ks in self.frame_blocks:  # each frame's L_k' Si L_k over the rows it touches
            Lb = L.reshape(P0, F, 6)[_ix(rows, ks)]
            SiL = (Si[_ix(rows, rows)] @ Lb.reshape(len(Lb), -1)).reshape(Lb.shape)
            EE[ks] += np.transpose(Lb, (1, 2, 0)) @ np.transpose(SiL, (1, 0, 2))
        outer_E = s_E[:, :, None] * s_E[:, None, :]
        return BlockInverse(
            EE=EE / outer_E,
            frame_inv=Ei / outer_E,
            coupling=L / s_E.reshape(1, -1),
            reduced_inv=Si,
            global_scale=s_g,
        )


class BundleModel:
    """Residuals and analytic Jacobian of the model for one problem and structure."""

    def __init__(self, problem: CalibrationProblem, structure: Structure) -> None:
        self.problem = problem
        self.st = structure
        self.chunks = _chunks(problem)
        self.n_rows = self.chunks[-1].rows.stop if self.chunks else 0
        self.ref = problem.reference
        self.cams = [c.name for c in problem.cameras]
        self.intr = intrinsic_names(problem)
        self.dist_names = distortion_names(problem)
        self.dist_idx = [problem.options.distortion_names.index(n) for n in self.dist_names]
        n_groups = int(structure.group_of_frame.max()) + 1 if len(structure.group_of_frame) else 0
        self.n_groups = n_groups
        names: list[str] = []
        self.slices: dict[str, slice] = {}

        def add(key: str, block: list[str]) -> None:
            self.slices[key] = slice(len(names), len(names) + len(block))
            names.extend(block)

        for c in self.cams:
            add(f"intr:{c}", [f"{c}.{n}" for n in self.intr])
            if self.dist_names:
                add(f"dist:{c}", [f"{c}.{n}" for n in self.dist_names])
            if c != self.ref:
                add(f"rig:{c}", [f"T_{c}_{self.ref}.{a}" for a in POSE_AXES])
        st = structure
        poses = [(f"X:{g}", f"X{g}", st.X_rot_basis, st.X_t_basis) for g in range(n_groups)]
        for key, name, rot, t in poses + [("Y", "Y", st.Y_rot_basis, st.Y_t_basis)]:
            block = [f"{name}.r{i}" for i in range(rot.shape[1])]
            block += [f"{name}.t{i}" for i in range(t.shape[1])]
            if block:
                add(key, block)
        if structure.pose_sigma is not None and structure.pose_groups is not None:
            n_pg = int(structure.pose_groups.max()) + 1
            add("U", [f"pose_group{g}.{a}" for g in range(n_pg) for a in POSE_AXES])
        self.trend_offsets: list[int] = []  # first V index of each trend group
        if structure.pose_sigma is not None and structure.trend_sigma is not None:
            block = []
            for g, m in enumerate(structure.trend_dims):
                self.trend_offsets.append(len(block))
                block += [f"trend{g}.{POSE_AXES[a]}_d{j}" for a in TREND_AXES for j in range(m)]
            add("V", block)
        if structure.pose_sigma is not None and structure.common_sigma is not None:
            add("W", [f"shared_field.{j}" for j in range(structure.common_map.shape[2])])
        if structure.pose_sigma is not None:
            add("E", [f"pose{int(f.id)}.{a}" for f in problem.frames for a in POSE_AXES])
        self.s_frames = np.flatnonzero(structure.s_free)
        if len(self.s_frames):
            add("s", [f"s{int(problem.frames[i].id)}" for i in self.s_frames])
        self.names = tuple(names)
        self.sigma_px = 1.0  # pixel noise used to weigh the pose prior rows (set by refine)
        # one-sigma levels (radians, metres) of the priors: the structure's, then refine's
        self.pose_sigma = structure.pose_sigma
        self.group_sigma = structure.group_sigma
        self.trend_sigma = structure.trend_sigma
        self.common_sigma = structure.common_sigma
        # per block ("E", "U", "V", "W"): the last variance-component step's redundancy
        # (rotation, translation), the sum of 1 - h over its prior rows
        self.level_redundancy: dict[str, tuple[float, float]] = {}
        # the groups' level from their corrections alone, without its prior (radians, metres)
        self.group_sigma_data: tuple[float, float] | None = None
        # the last solve's row weights (inliers, per-camera noise): its covariance's
        self.row_weights: np.ndarray | None = None
        self._normal_cache: tuple | None = None  # (state, pixel weights, blocks) of the last
        self._eval_cache: tuple | None = None  # (state, evaluate's output) of the last
        self._motion_cache: tuple | None = None  # (state, true_motions) of the last
        self._index()
        self.shared_map = self._shared_map()
        if self.shared_map is not None:  # the frames by the shared corrections they move
            self.shared_blocks = _patterns(np.any(self.shared_map != 0.0, axis=1).T)

    # -- state updates -------------------------------------------------------------------------
    def apply(self, state: ModelState, delta: np.ndarray) -> ModelState:
        """The state moved by the parameter step ``delta`` (P,)."""
        K = dict(state.K)
        dist = dict(state.dist)
        T_cam_ref = dict(state.T_cam_ref)
        for c in self.cams:
            d = delta[self.slices[f"intr:{c}"]]
            k = K[c].copy()
            unit = self.problem.options.unit_aspect
            k[0, 0] += d[0]
            k[1, 1] += d[0] if unit else d[1]
            rest = d[1:] if unit else d[2:]
            k[0, 2] += rest[0]
            k[1, 2] += rest[1]
            if self.problem.options.skew:
                k[0, 1] += rest[2]
            K[c] = k
            if self.dist_names:
                dd = dist[c].copy()
                dd[self.dist_idx] += delta[self.slices[f"dist:{c}"]]
                dist[c] = dd
            if c != self.ref:
                T_cam_ref[c] = _step_T(
                    T_cam_ref[c], delta[self.slices[f"rig:{c}"]], np.eye(3), np.eye(3)
                )
        X = state.X.copy()
        for g in range(self.n_groups):
            key = f"X:{g}"
            if key in self.slices:
                X[g] = _step_T(
                    X[g], delta[self.slices[key]], self.st.X_rot_basis, self.st.X_t_basis
                )
        Y = state.Y
        if "Y" in self.slices:
            Y = _step_T(Y, delta[self.slices["Y"]], self.st.Y_rot_basis, self.st.Y_t_basis)
        s = state.s.copy()
        if len(self.s_frames):
            s[self.s_frames] += delta[self.slices["s"]]
        corrections = {}  # E, U (one row of six per frame or group), V, W
        for key in LEVELS:
            value = getattr(state, key)
            if key in self.slices:
                d = delta[self.slices[key]]
                d = d.reshape(-1, 6) if key in ("E", "U") else d
                value = (np.zeros_like(d) if value is None else value) + d
            corrections[key] = value
        return ModelState(K, dist, T_cam_ref, X, Y, s, **corrections)

    def with_corrections(self, state: ModelState) -> ModelState:
        """``state`` with zero corrections of every block the model has (``E``, ``U``, ``V``,
        ``W``) where it holds none, or a group's or trend's of another size."""
        zero = {}
        for key in ("E", "U", "V", "W"):
            if key in self.slices:
                n = self.slices[key].stop - self.slices[key].start
                shape = (n // 6, 6) if key in ("E", "U") else (n,)
                have = getattr(state, key)
                if have is None or (key != "E" and len(have) != shape[0]):
                    zero[key] = np.zeros(shape)
        return replace(state, **zero) if zero else state

    def T_ref_board(self, state: ModelState, fi: int) -> np.ndarray:
        """``T_ref_board`` (4, 4) of the reference camera at frame index ``fi``."""
        M = self.true_motions(state)[fi]
        return state.X[self.st.group_of_frame[fi]] @ M @ state.Y

    # -- residuals and Jacobian ----------------------------------------------------------------
    def camera_rows(self, ci: int, n_rows: int) -> np.ndarray:
        """Which of ``n_rows`` residual rows (the pixel rows first, two per observation, then
        any prior rows) are camera ``ci``'s pixels (bool mask)."""
        rows = np.zeros(n_rows, dtype=bool)
        idx = self.cam_obs[ci]
        rows[2 * idx] = rows[2 * idx + 1] = True
        return rows

    def _index(self) -> None:
        """Per-observation index arrays (built once): frame, group, camera, board point."""
        ch = self.chunks
        counts = [len(c.points) for c in ch]
        self.n_obs = int(sum(counts))
        self.o_frame = np.repeat([c.frame_index for c in ch], counts).astype(int)
        self.o_group = self.st.group_of_frame[self.o_frame] if self.n_obs else np.zeros(0, int)
        cam_index = {c: i for i, c in enumerate(self.cams)}
        self.o_cam = np.repeat([cam_index[c.camera] for c in ch], counts).astype(int)
        self.o_pts = np.concatenate([c.points for c in ch]) if ch else np.zeros((0, 3))
        self.o_px = np.concatenate([c.px for c in ch]) if ch else np.zeros((0, 2))
        self.cam_obs = [np.flatnonzero(self.o_cam == i) for i in range(len(self.cams))]
        s_col = np.full(len(self.problem.frames), -1)
        if len(self.s_frames):
            s_col[self.s_frames] = self.slices["s"].start + np.arange(len(self.s_frames))
        self.o_s_col = s_col[self.o_frame]
        # residual rows of each frame (contiguous: chunks come frame by frame)
        self.frame_rows: dict[int, slice] = {}
        for c in ch:
            r0 = self.frame_rows.get(c.frame_index)
            start = c.rows.start if r0 is None else r0.start
            self.frame_rows[c.frame_index] = slice(start, c.rows.stop)

    def evaluate(
        self,
        state: ModelState,
        jacobian: bool = True,
        split: bool = False,
        transposed: bool = False,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Residuals (R,) (projected minus observed, pixels) and the Jacobian (R, P).

        Vectorised over all observations; rows ``2 i, 2 i + 1`` are observation i's u and v.
        ``split`` (with pose corrections, whose columns come last): the pixel rows' Jacobian
        without the pose-correction columns (2 n, P0) and, third, each observation's block of
        its own frame's correction (n, 2, 6); the prior rows are left to the caller.
        ``transposed`` (with ``split``, or without pose corrections): the pixel rows' Jacobian
        transposed, (P, 2 n), every u row first, then every v row (``axis_rows``' order).
        """
        n, P_ = self.n_obs, len(self.names)
        st = self.st
        Ms = self.true_motions(state)
        f, g = self.o_frame, self.o_group
        RY, tY = state.Y[:3, :3], state.Y[:3, 3]
        q_Y = self.o_pts @ RY.T
        p_Y = q_Y + tY
        one_group, one_camera = self.n_groups == 1, len(self.cams) == 1
        if one_group:  # the robot cases: one X, so each frame's RX RM (made once, gathered)
            RX0 = state.X[0, :3, :3]
            RX = np.broadcast_to(RX0, (n, 3, 3))
            RXM = (RX0 @ Ms[:, :3, :3])[f]
            q_X = _mv(RXM, p_Y) + (Ms[:, :3, 3] @ RX0.T)[f]
            p_M = q_X @ RX0
            p_X = q_X + state.X[0, :3, 3]
        else:
            RX = state.X[g, :3, :3]
            p_M = _mv(Ms[f, :3, :3], p_Y) + Ms[f, :3, 3]
            q_X = _mv(RX, p_M)
            p_X = q_X + state.X[g, :3, 3]
        T_cr = [state.T_cam_ref.get(c, np.eye(4)) for c in self.cams]
        if one_camera:
            q_cr = P = p_X
        else:  # camera by camera: one 3x3 product each (no per-observation rotations)
            q_cr, P = np.empty((n, 3)), np.empty((n, 3))
            for ci, T in enumerate(T_cr):
                idx = self.cam_obs[ci]
                q_cr[idx] = p_X[idx] @ T[:3, :3].T
                P[idx] = q_cr[idx] + T[:3, 3]
        px = np.empty((n, 2))
        projections = []
        for ci, c in enumerate(self.cams):
            idx = self.cam_obs[ci]
            pr = project_with_jacobians(state.K[c], state.dist[c], P[idx], jacobians=jacobian)
            px[idx] = pr.px
            projections.append(pr)
        priors = self._priors(state)
        r = np.concatenate([(px - self.o_px).reshape(-1), *(sc * v for _, sc, v in priors)])
        if not jacobian:
            return r, None
        if split:  # the shared corrections' columns derive from the pose block (normal_blocks)
            P_ = self.shared_start
            assert self.slices["E"].stop == len(self.names)
        J = np.zeros((n, 2, P_), order="F" if transposed else "C")
        A = np.empty((n, 2, 3))  # d px / d p_X
        unit, skew_on = self.problem.options.unit_aspect, self.problem.options.skew
        for ci, c in enumerate(self.cams):
            pr = projections[ci]
            idx = slice(None) if one_camera else self.cam_obs[ci]  # a slice scatters faster
            A[idx] = pr.d_P if one_camera else _rmul(pr.d_P, T_cr[ci][:3, :3])
            dK = pr.d_K
            cols = [dK[:, :, 0] + dK[:, :, 1]] if unit else [dK[:, :, 0], dK[:, :, 1]]
            cols += [dK[:, :, 2], dK[:, :, 3]]
            if skew_on:
                cols.append(dK[:, :, 4])
            _put_rows(J, idx, self.slices[f"intr:{c}"], cols)
            if self.dist_names:
                lens = [pr.d_dist[:, :, k] for k in self.dist_idx]
                _put_rows(J, idx, self.slices[f"dist:{c}"], lens)
            if c != self.ref:
                rig = np.concatenate([_cross_rows(q_cr[idx], pr.d_P), pr.d_P], axis=2)
                _put_rows(J, idx, self.slices[f"rig:{c}"], [rig[:, :, j] for j in range(6)])
        mx = st.X_rot_basis.shape[1] + st.X_t_basis.shape[1]
        if mx and self.n_groups == 1:  # written in place (no product with an identity basis)
            _put_pose(J, self.slices["X:0"].start, q_X, A, st.X_rot_basis, st.X_t_basis)
        elif mx:  # one X per group: each observation's columns are its group's
            blk = np.concatenate(
                [_rmul(_cross_rows(q_X, A), st.X_rot_basis), _rmul(A, st.X_t_basis)],
                axis=2,
            )
            _put_cols(J, self.slices["X:0"].start + g[:, None] * mx + np.arange(mx), blk)
        if "Y" in self.slices:  # d px / d p_Y = A RX RM: per frame RX RM, gathered once
            A2 = A @ (RXM if one_group else RX @ Ms[f, :3, :3])
            _put_pose(J, self.slices["Y"].start, q_Y, A2, st.Y_rot_basis, st.Y_t_basis)
        has_s = self.o_s_col >= 0
        if len(self.s_frames):
            d = np.einsum("nij,nj->ni", RX[has_s], -st.direction[f[has_s]])
            vals = np.einsum("nab,nb->na", A[has_s], d)
            rows = np.flatnonzero(has_s)
            J[rows, 0, self.o_s_col[has_s]] = vals[:, 0]
            J[rows, 1, self.o_s_col[has_s]] = vals[:, 1]
        if "E" in self.slices:
            blk = self._pose_block(A, RX, A2, p_Y, p_M, Ms)
            if split:
                return r, self._pixel_jacobian(J, transposed), blk
            if self.shared_map is not None:  # they move each frame like its own, through S
                shared = slice(self.shared_start, self.slices["E"].start)
                J[:, :, shared] = np.einsum("nab,nbm->nam", blk, self.shared_map[f])
            _put_cols(J, self.slices["E"].start + f[:, None] * 6 + np.arange(6), blk)
            blocks = [J.reshape(2 * n, P_)]
            for sl, scale, _ in priors:
                prior = np.zeros((sl.stop - sl.start, P_))
                prior[np.arange(prior.shape[0]), np.arange(sl.start, sl.stop)] = scale
                blocks.append(prior)
            return r, np.vstack(blocks)
        return r, self._pixel_jacobian(J, transposed)

    @staticmethod
    def _pixel_jacobian(J: np.ndarray, transposed: bool) -> np.ndarray:
        """``J`` (n, 2, P) as the (2 n, P) Jacobian, or (a view) as its transpose (P, 2 n) in
        ``axis_rows`` order when ``transposed`` (``J`` then Fortran-ordered)."""
        n, _, P_ = J.shape
        return J.reshape(2 * n, P_, order="F").T if transposed else J.reshape(2 * n, P_)

    def normal_blocks(
        self, state: ModelState, weights: np.ndarray, keep: bool = True
    ) -> NormalBlocks:
        """``J' W J`` and ``J' W r`` split into the global parameters and the per-frame blocks.

        Each frame's six correction columns touch only its rows (and one prior row each), so
        their blocks are accumulated per frame. The evaluation is kept for the last state, and
        the pixel blocks for the last weights unless ``keep`` is False (a one-off weighting).
        """
        ax = self.axis_rows
        if "E" not in self.slices:
            r, JT = self._evaluation(state)
            A, g = self._weighted_gram(JT, weights[ax], r[ax])
            P0 = JT.shape[0]
            return NormalBlocks(
                r, A, g, np.zeros((P0, 0, 6)), np.zeros((0, 6, 6)), np.zeros((0, 6)), []
            )
        n = self.n_obs
        sl = self.slices["E"]
        P0, F = sl.start, len(self.problem.frames)
        w, wp = weights[: 2 * n], weights[2 * n : 2 * n + 6 * F]
        cache = self._normal_cache if keep else None
        if cache is not None and cache[0] is state and np.array_equal(cache[1], w):
            rp, A_gg, g_g, A_gE, A_EE, g_E, blocks = cache[2:]  # only the priors' weights moved
        else:
            # JT (P1, 2 n): the columns before the shared ones, transposed, in axis_rows order
            r, JT, B = self._evaluation(state)
            rp = r[: 2 * n]
            P1 = JT.shape[0]
            A_gg, g_g = self._weighted_gram(JT, w[ax], rp[ax])
            A_gE = np.zeros((P1, F, 6))
            A_EE = np.zeros((F, 6, 6))
            g_E = np.zeros((F, 6))
            B2 = B.reshape(2 * n, 6)
            Bw = B2 * w[:, None]
            Bw3 = Bw.reshape(n, 2, 6)
            for k, rows in self.frame_rows.items():  # each frame's rows are contiguous
                Bwk = Bw[rows]
                a, b = rows.start // 2, rows.stop // 2  # its observations: u, then v columns
                A_gE[:, k] = JT[:, a:b] @ Bw3[a:b, 0] + JT[:, n + a : n + b] @ Bw3[a:b, 1]
                A_EE[k] = B2[rows].T @ Bwk
                g_E[k] = Bwk.T @ rp[rows]
            if P1 < P0:  # the shared corrections: their columns are the frames' ones times S
                A_gg, g_g, A_gE = self._with_shared(A_gg, g_g, A_gE, A_EE, g_E)
            blocks = _patterns(np.any(A_gE != 0.0, axis=2))
            if keep:
                self._normal_cache = (state, w.copy(), rp, A_gg, g_g, A_gE, A_EE, g_E, blocks)
        ps = self.prior_scale("E")
        r_prior = [ps * state.E.reshape(-1)]
        A_EE = A_EE.copy()
        idx = np.arange(6)
        A_EE[:, idx, idx] += (wp * ps * ps).reshape(F, 6)
        g_E = g_E + (wp * ps * r_prior[0]).reshape(F, 6)
        shared = self._priors(state)[1:]
        if shared:
            A_gg, g_g = A_gg.copy(), g_g.copy()
        row = 2 * n + 6 * F
        for su, pu, values in shared:  # the groups' U, then the trends' V
            iu = np.arange(su.start, su.stop)
            wu = weights[row : row + len(iu)]
            row += len(iu)
            r_prior.append(pu * values)
            A_gg[iu, iu] += wu * pu * pu
            g_g[iu] += wu * pu * r_prior[-1]
        return NormalBlocks(np.concatenate([rp, *r_prior]), A_gg, g_g, A_gE, A_EE, g_E, blocks)

    @property
    def shared_start(self) -> int:
        """First column of the corrections shared by several frames (the groups' ``U``, the
        trends' ``V``; they sit just before the frames' ``E``); ``E``'s start without them."""
        for key in ("U", "V", "W", "E"):
            if key in self.slices:
                return self.slices[key].start
        return len(self.names)

    def _shared_map(self) -> np.ndarray | None:
        """``S`` (F, 6, m): the shared corrections' m columns as combinations of the frames'
        correction columns, ``J_shared = J_E S`` (a group's correction moves each of its frames
        like the frame's own; a trend's like the frame's own times its offset ``c_k``). None
        without shared corrections."""
        if "E" not in self.slices:
            return None
        s0, st = self.shared_start, self.st
        F, m = len(self.problem.frames), self.slices["E"].start - s0
        if m == 0:
            return None
        S = np.zeros((F, 6, m))
        k = np.arange(F)
        if "U" in self.slices:
            u0 = self.slices["U"].start - s0
            for a in range(6):
                S[k, a, u0 + 6 * st.pose_groups + a] = 1.0
        if "V" in self.slices:
            v0 = self.slices["V"].start - s0
            for g, dims in enumerate(st.trend_dims):
                kg = np.flatnonzero(st.trend_groups == g)
                o = v0 + self.trend_offsets[g]
                for ai, a in enumerate(TREND_AXES):
                    S[kg, a, o + ai * dims : o + (ai + 1) * dims] = st.trend_coords[kg, :dims]
        if "W" in self.slices:
            sw = self.slices["W"]
            S[:, :, sw.start - s0 : sw.stop - s0] = st.common_map
        return S

    def _with_shared(
        self,
        A_gg: np.ndarray,
        g_g: np.ndarray,
        A_gE: np.ndarray,
        A_EE: np.ndarray,
        g_E: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The global blocks extended by the shared corrections' columns ``J_E S``
        (:meth:`_shared_map`), from the frames' pixel blocks alone: ``A_gE S``, ``S' A_EE S``,
        ``S' A_EE`` and ``S' g_E`` (block-diagonal products, no pass over the rows)."""
        S = self.shared_map
        F, _, m = S.shape
        P1 = len(g_g)
        S2 = S.reshape(6 * F, m)
        Z = A_EE @ S  # (F, 6, m); A_EE is symmetric: Z[k]' = S[k]' A_EE[k]
        A_ss, A_gs = np.zeros((m, m)), np.zeros((P1, m))
        for cols, ks in self.shared_blocks:  # a frame's S touches a few columns
            Sb, Zb = S[ks][:, :, cols], Z[ks][:, :, cols]
            Sb = Sb.reshape(-1, Sb.shape[2])
            A_ss[_ix(cols, cols)] += Sb.T @ Zb.reshape(len(Sb), -1)
            A_gs[:, cols] += A_gE[:, ks].reshape(P1, -1) @ Sb
        A = np.empty((P1 + m, P1 + m))
        A[:P1, :P1], A[:P1, P1:], A[P1:, :P1], A[P1:, P1:] = A_gg, A_gs, A_gs.T, A_ss
        g = np.concatenate([g_g, S2.T @ g_E.reshape(-1)])
        return A, g, np.concatenate([A_gE, np.transpose(Z, (2, 0, 1))], axis=0)

    @staticmethod
    def _weighted_gram(
        JT: np.ndarray, w: np.ndarray, r: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """``J' W J`` and ``J' W r`` of the pixel rows from ``JT`` = J' (P, 2 n), C-ordered,
        with ``w`` (>= 0) and ``r`` in its column order: ``(J' W^1/2)(J' W^1/2)'``, one
        symmetric product of a row-major matrix. Columns of zero weight are left out when they
        are a quarter or more."""
        nz = w != 0
        if np.count_nonzero(nz) < 0.75 * len(w):
            JT, w, r = JT[:, nz], w[nz], r[nz]
        if np.all(w == 1.0):  # unit weights: the same products without a weighted copy
            return JT @ JT.T, JT @ r
        sw = np.sqrt(w)
        Js = JT * sw
        return Js @ Js.T, Js @ (sw * r)

    @functools.cached_property
    def axis_rows(self) -> np.ndarray:
        """(2 n,) the pixel rows reordered as the transposed Jacobian's columns: every
        observation's u row, then every v row (``evaluate(..., transposed=True)``)."""
        rows = np.arange(2 * self.n_obs)
        return np.concatenate([rows[0::2], rows[1::2]])

    def pixel_step(self, state: ModelState, delta: np.ndarray) -> np.ndarray:
        """``J delta`` over the pixel rows (2 n,) with the Jacobian at ``state`` (evaluated
        once and kept): the pixel residuals of the step ``delta`` to first order, without a
        new evaluation. Pose corrections only (``E`` in the model)."""
        _, JT, B = self._evaluation(state)
        P1 = JT.shape[0]
        d = (delta[:P1] @ JT).reshape(2, -1).T.reshape(-1)  # from axis_rows' order
        sl = self.slices["E"]
        dE = delta[sl].reshape(-1, 6)
        if self.shared_map is not None:  # the shared corrections move each frame like its own
            S = self.shared_map
            F, _, m = S.shape
            dE = dE + (S.reshape(6 * F, m) @ delta[P1 : sl.start]).reshape(F, 6)
        d += np.einsum("nac,nc->na", B, dE[self.o_frame]).reshape(-1)
        return d

    def pixel_gradient(self, state: ModelState, weights: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``J' W v`` (P,) over the pixel rows (``v``, ``weights``: (2 n,)) with the Jacobian at
        ``state`` (evaluated once and kept): the adjoint of :meth:`pixel_step`, the gradient a
        perturbation ``v`` of the pixel residuals gives, without the normal matrix."""
        n = self.n_obs
        wv = weights[: 2 * n] * v
        if "E" not in self.slices:
            return self._evaluation(state)[1] @ wv[self.axis_rows]
        _, JT, B = self._evaluation(state)
        g_E = np.zeros((len(self.problem.frames), 6))
        np.add.at(g_E, self.o_frame, np.einsum("nac,na->nc", B, wv.reshape(n, 2)))
        parts = [JT @ wv[self.axis_rows]]
        if self.shared_map is not None:  # the shared corrections gather their frames' parts
            parts.append(self.shared_map.reshape(-1, self.shared_map.shape[2]).T @ g_E.ravel())
        return np.concatenate([*parts, g_E.ravel()])

    def trial_residuals(self, state: ModelState) -> np.ndarray:
        """Residuals (R,) of ``state``, evaluated with the Jacobian the normal equations use
        and kept (:meth:`_evaluation`): a step Levenberg-Marquardt accepts (nearly all) is where
        it linearises next, so its residuals are not computed twice."""
        return self._evaluation(state)[0]

    def _evaluation(self, state: ModelState) -> tuple:
        """``evaluate(state)`` with the Jacobian (split with pose corrections), kept for the
        last state (a state is immutable: the same object, the same values)."""
        cache = self._eval_cache
        if cache is not None and cache[0] is state:
            return cache[1]
        out = self.evaluate(state, split="E" in self.slices, transposed=True)
        self._eval_cache = (state, out)
        return out

    def frame_scores(self, state: ModelState, weights: np.ndarray) -> np.ndarray:
        """Each frame's share of ``J' W r`` from its pixel rows, over the global columns (every
        column before the frames' own corrections ``E``, the shared ones included): (F_seen,
        P0), frames in ``frame_rows`` order. A frame's own correction takes no share of the
        others' rows, and at the minimum its score, pixels and prior together, is zero: these
        are the frames' whole scores (the terms of a covariance with frames as clusters)."""
        n = self.n_obs
        ev = self._evaluation(state)
        r, JT = ev[0], ev[1]
        wr = np.asarray(weights[: 2 * n], float) * r[: 2 * n]
        wr_ax = wr[self.axis_rows]  # JT's column order: every u row, then every v row
        split = "E" in self.slices
        S = self.shared_map if split else None
        out = []
        for k, rows in self.frame_rows.items():
            a, b = rows.start // 2, rows.stop // 2
            g = JT[:, a:b] @ wr_ax[a:b] + JT[:, n + a : n + b] @ wr_ax[n + a : n + b]
            if S is not None:  # the shared corrections' columns are the frame's own times S
                g_E = np.einsum("oij,oi->j", ev[2][a:b], wr[2 * a : 2 * b].reshape(-1, 2))
                g = np.concatenate([g, S[k].T @ g_E])
            out.append(g)
        return np.array(out)

    def _priors(self, state: ModelState) -> list[tuple[slice, np.ndarray, np.ndarray]]:
        """(columns, pixel-unit prior scale, values) of every block of corrections the model has:
        the frames' ``E``, then the groups' ``U``, the trends' ``V`` and the field's ``W``, as
        their prior rows follow the pixels'."""
        keys = [k for k in LEVELS if k in self.slices]
        return [(self.slices[k], self.prior_scale(k), getattr(state, k).ravel()) for k in keys]

    @property
    def trend_spread(self) -> float:
        """Rms (metres) of the trend frames' offsets from their groups' means: a trend level
        times it is the trend's share of a frame's correction."""
        c = self.st.trend_coords[self.st.trend_groups >= 0]
        return float(np.sqrt(np.mean(np.sum(c**2, axis=1))))

    def pose_corrections(self, state: ModelState) -> np.ndarray | None:
        """(F, 6) the whole correction of every measured pose (rotation vector, translation):
        its own, its orientation group's and its group's trend at its offset; None without."""
        if state.E is None:
            return None
        if self.shared_map is None:
            return state.E.copy()
        parts = []  # the shared corrections' values, in their columns' order
        for key, values in (("U", state.U), ("V", state.V), ("W", state.W)):
            if key in self.slices:
                sl = self.slices[key]
                parts.append(np.zeros(sl.stop - sl.start) if values is None else values.ravel())
        S = self.shared_map
        F, _, m = S.shape
        return state.E + (S.reshape(6 * F, m) @ np.concatenate(parts)).reshape(F, 6)

    def rotation_rows(self, key: str) -> np.ndarray:
        """(n,) bool over the coordinates of the corrections ``key``: True for a rotation's."""
        if key == "V":
            return np.concatenate(
                [np.repeat(np.array(TREND_AXES) < 3, m) for m in self.st.trend_dims]
            )
        if key == "W":
            return self.st.common_rotation
        sl = self.slices[key]
        return np.tile(_ROTATION_AXES, (sl.stop - sl.start) // 6)

    def prior_scale(self, key: str) -> np.ndarray:
        """(n,) pixel-unit scale of the prior rows of the corrections ``key``: sigma_px / level."""
        rot, t = getattr(self, LEVELS[key])
        return self.sigma_px * np.where(self.rotation_rows(key), 1.0 / rot, 1.0 / t)

    def level_share(self, key: str) -> float | tuple[float, float]:
        """A level of the corrections ``key`` times this is its share of a frame's correction
        (per axis): 1 for the frames' own and the groups', the trend frames' rms offset for the
        trends (metres), (rotation, translation) for the shared field (``Structure``)."""
        if key == "V":
            return self.trend_spread
        return self.st.common_spread if key == "W" else 1.0

    def true_motions(self, state: ModelState) -> np.ndarray:
        """``M_k`` (F, 4, 4) with the Case 2 lengths and the robot pose corrections applied
        (read-only: kept for the last state, which every frame's ``T_ref_board`` asks for)."""
        cache = self._motion_cache
        if cache is not None and cache[0] is state:
            return cache[1]
        st = self.st
        if st.pose_sigma is not None and state.E is not None:
            E = self.pose_corrections(state)
            R = np.einsum("nij,njk->nik", R_from_rvecs(E[:, :3]), st.T_meas[:, :3, :3])
            t = st.T_meas[:, :3, 3] + E[:, 3:]
            Ms = np.tile(np.eye(4), (len(R), 1, 1))
            if st.eye_in_hand:  # the inverse of (R, t): (R', -R' t)
                Ms[:, :3, :3] = np.transpose(R, (0, 2, 1))
                Ms[:, :3, 3] = -np.einsum("nji,nj->ni", R, t)
            else:
                Ms[:, :3, :3], Ms[:, :3, 3] = R, t
        else:
            Ms = st.M.copy()
        if len(self.s_frames):
            Ms[self.s_frames, :3, 3] -= state.s[self.s_frames, None] * st.direction[self.s_frames]
        Ms.setflags(write=False)
        self._motion_cache = (state, Ms)
        return Ms

    def _pose_block(
        self,
        A: np.ndarray,
        RX: np.ndarray,
        A2: np.ndarray,
        p_Y: np.ndarray,
        p_M: np.ndarray,
        Ms: np.ndarray,
    ) -> np.ndarray:
        """d px / d (pose correction) (n, 2, 6) of every observation's frame, from ``A`` and
        ``A2`` = d px / d p_X and d px / d p_Y (n, 2, 3).

        The correction acts on the measured pose as ``R <- exp([d]x) R``, ``t <- t + tau``;
        a row ``a`` of a Jacobian times ``[v]x`` is ``(a x v)'``.
        """
        t_M = Ms[:, :3, 3]
        if self.st.eye_in_hand:  # M = T^-1: p_M = R' (p_Y - t), d p_M = R' [p_Y - t]x d - R' tau
            t = -np.einsum("kji,kj->ki", Ms[:, :3, :3], t_M)  # each frame's t = -R M's t
            blk = np.empty(A2.shape[:2] + (6,))
            _cross_rows(t[self.o_frame] - p_Y, A2, blk[:, :, :3])  # -(v x a) = (-v) x a
            np.negative(A2, out=blk[:, :, 3:])
            return blk
        B = _rmul(A, RX[0]) if self.n_groups == 1 else A @ RX  # d px / d p_M
        # M = T: p_M = R p_Y + t, d p_M = -[R p_Y]x d + tau
        return np.concatenate([_cross_rows(p_M - t_M[self.o_frame], B), B], axis=2)


def _reduced(
    A_gg: np.ndarray, A_gE: np.ndarray, Ei: np.ndarray, blocks: list[tuple[np.ndarray, ...]]
) -> tuple[np.ndarray, np.ndarray]:
    """``L = A_gE Ei`` per frame (P0, 6 F) and the reduced matrix ``S = A_gg - L A_gE'``, made
    as ``A_gg - M M'`` with ``M = A_gE C`` per frame, ``C C' = Ei``, where ``Ei`` is positive
    definite (one symmetric product: half the work of ``L A_gE'``), block by block of
    ``blocks`` (:attr:`NormalBlocks.frame_blocks`)."""
    L = _per_frame(A_gE, Ei)
    try:
        M = N = _per_frame(A_gE, np.linalg.cholesky(Ei))
    except np.linalg.LinAlgError:
        M, N = L, A_gE
    S = A_gg.copy()
    for rows, ks in blocks:
        Mb = M[_ix(rows, ks)]
        Mb = Mb.reshape(len(Mb), -1)
        Nb = Mb if N is M else N[_ix(rows, ks)].reshape(len(Mb), -1)
        S[_ix(rows, rows)] -= Mb @ Nb.T
    return L.reshape(len(A_gg), -1), S


#: Frames from which the Schur products run by blocks: with fewer, the blocks' gathers cost
#: more than the products they save
SCHUR_BLOCK_FRAMES = 100


def _patterns(touched: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The frames (columns of ``touched`` (m, F), bool) grouped by the rows they touch: per
    group, those rows and its frames (frames that touch none left out); one block of all of
    them where there are fewer than ``SCHUR_BLOCK_FRAMES`` frames."""
    if touched.shape[1] < SCHUR_BLOCK_FRAMES:
        return [(slice(None), slice(None))]
    patterns: dict[bytes, list[int]] = {}
    for k, key in enumerate(np.packbits(touched, axis=0).T):
        patterns.setdefault(key.tobytes(), []).append(k)
    blocks = [(np.flatnonzero(touched[:, ks[0]]), np.array(ks)) for ks in patterns.values()]
    return [(rows, ks) for rows, ks in blocks if len(rows)]


def _ix(rows: np.ndarray | slice, cols: np.ndarray | slice) -> tuple:
    """``np.ix_(rows, cols)``, or the two slices as they are (a view of the whole)."""
    return (rows, cols) if isinstance(rows, slice) else np.ix_(rows, cols)


def _per_frame(A_gE: np.ndarray, Ei: np.ndarray) -> np.ndarray:
    """``A_gE[:, k] @ Ei[k]`` for every frame k: (P0, F, 6), C-ordered, from (P0, F, 6) and Ei."""
    out = np.empty(A_gE.shape)
    np.matmul(np.transpose(A_gE, (1, 0, 2)), Ei, out=np.transpose(out, (1, 0, 2)))
    return out


def _mv(M: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Matrix-vector products (n, 3) of stacks ``M`` (n, 3, 3) and ``v`` (n, 3)."""
    return np.einsum("nij,nj->ni", M, v)


def _put_rows(J: np.ndarray, idx: np.ndarray | slice, cols: slice, vals: list[np.ndarray]) -> None:
    """``J[idx, :, cols] = vals`` for ``J`` (n, 2, P), one (n, 2) column of ``vals`` at a time
    (in the Fortran-ordered ``J`` of a solve each is one contiguous block)."""
    for j, col in enumerate(vals):
        J[idx, :, cols.start + j] = col


def _put_cols(J: np.ndarray, cols: np.ndarray, vals: np.ndarray) -> None:
    """``J[k, :, cols[k]] = vals[k]`` for every row k of ``J`` (n, 2, P), ``cols`` (n, m)."""
    rows = np.arange(len(cols))[:, None]
    J[rows, 0, cols] = vals[:, 0, :]
    J[rows, 1, cols] = vals[:, 1, :]


def _put_pose(
    J: np.ndarray, c0: int, q: np.ndarray, A: np.ndarray, rot_basis: np.ndarray, t_basis: np.ndarray
) -> None:
    """Write a pose's columns into ``J`` (n, 2, P) from column ``c0``: d px / d (left rotation)
    ``cross(q, A rows)`` times ``rot_basis`` (3, mr), then d px / d translation ``A`` (n, 2, 3)
    times ``t_basis`` (3, mt); a full basis (the identity) is written without its product."""
    mr, mt = rot_basis.shape[1], t_basis.shape[1]
    if np.array_equal(rot_basis, np.eye(3)):
        _cross_rows(q, A, J[:, :, c0 : c0 + 3])
    elif mr:
        J[:, :, c0 : c0 + mr] = _rmul(_cross_rows(q, A), rot_basis)
    if mt:
        c1 = c0 + mr
        J[:, :, c1 : c1 + mt] = A if np.array_equal(t_basis, np.eye(3)) else _rmul(A, t_basis)


def _cross_rows(q: np.ndarray, A: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``cross(q_n, A_n[i])`` (n, m, 3) of vectors ``q`` (n, 3) with the rows of ``A``
    (n, m, 3) (``np.cross`` with broadcasting, without its copies), into ``out`` when given."""
    out = np.empty(A.shape) if out is None else out
    q0, q1, q2 = q[:, 0, None], q[:, 1, None], q[:, 2, None]
    a0, a1, a2 = A[:, :, 0], A[:, :, 1], A[:, :, 2]
    out[:, :, 0] = q1 * a2 - q2 * a1
    out[:, :, 1] = q2 * a0 - q0 * a2
    out[:, :, 2] = q0 * a1 - q1 * a0
    return out


def _rmul(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` for a stack ``A`` (n, a, b) and one matrix ``B`` (b, c), as one product."""
    n, a, b = A.shape
    return (A.reshape(n * a, b) @ B).reshape(n, a, B.shape[1])


def _step_T(T: np.ndarray, d: np.ndarray, rot_basis: np.ndarray, t_basis: np.ndarray) -> np.ndarray:
    mr = rot_basis.shape[1]
    R = R_from_rvec(rot_basis @ d[:mr]) @ T[:3, :3] if mr else T[:3, :3]
    t = T[:3, 3] + t_basis @ d[mr : mr + t_basis.shape[1]]
    return T_from_Rt(R, t)


@functools.cache
def _blas_controller() -> ThreadpoolController:
    """One controller for the process (building one scans the loaded libraries), built on
    first use, when numpy's BLAS is loaded."""
    return ThreadpoolController()


def single_threaded_blas(fn):  # noqa: ANN001, ANN201 - a plain decorator
    """Run ``fn`` with one BLAS thread: the normal matrices are small (tens of columns), where
    a threaded BLAS's spinning threads cost far more than they gain on a busy machine."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        with _blas_controller().limit(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper


@single_threaded_blas
def fisher_covariance(
    problem: CalibrationProblem,
    structure: Structure,
    truth: ModelState,
    sigma_px: float,
    camera_sigma_px: dict[str, float] | None = None,
) -> tuple[tuple[str, ...], np.ndarray]:
    """The Cramer-Rao bound (docs/METHOD.md Sec. 6): ``(J' W J)^-1`` at the true state.

    ``problem`` holds the detections' ids (their pixel values are not used). ``sigma_px``: the
    pixel noise (per coordinate); ``camera_sigma_px``: per camera name, when the cameras of a
    rig differ (the others keep ``sigma_px``). Returns the parameter names and the covariance.
    """
    model = BundleModel(problem, structure)
    model.sigma_px = sigma_px
    _, J = model.evaluate(model.with_corrections(truth))
    w = np.ones(J.shape[0])
    for ci, c in enumerate(model.cams):
        sc = (camera_sigma_px or {}).get(c, sigma_px)
        idx = model.cam_obs[ci]
        w[2 * idx] = w[2 * idx + 1] = (sigma_px / sc) ** 2
    Jw = J * np.sqrt(w)[:, None]
    scale = np.linalg.norm(Jw, axis=0)
    scale[scale == 0] = 1.0
    # from the QR of the scaled Jacobian, not from its normal matrix: a near-redundant lens model
    # (rational k1-k6 on a narrow field) squares a condition of 1e9 past double precision
    Ri = np.linalg.inv(np.linalg.qr(Jw / scale, mode="r"))
    cov = sigma_px**2 * (Ri @ Ri.T) / np.outer(scale, scale)
    return model.names, cov


def orientation_groups(T_base_tool: np.ndarray, tol_deg: float = 0.5) -> np.ndarray:
    """Group index (F,) per frame: frames whose tool orientations agree within ``tol_deg``.

    The first frame not yet grouped founds the next group; a frame joins the first group whose
    founder it agrees with (vectorised over the frames, one pass per group).
    """
    R = np.asarray(T_base_tool, dtype=float)[:, :3, :3]
    out = np.full(len(R), -1, dtype=int)
    g = 0
    while np.any(out < 0):
        free = np.flatnonzero(out < 0)
        rel = R[free] @ R[free[0]].T  # (n, 3, 3)
        w = np.stack(
            [rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]],
            axis=1,
        )
        angle = np.arctan2(
            0.5 * np.linalg.norm(w, axis=1), 0.5 * (np.trace(rel, axis1=1, axis2=2) - 1)
        )
        out[free[np.degrees(angle) < tol_deg]] = g
        out[free[0]] = g
        g += 1
    return out


def complement_basis(u: np.ndarray) -> np.ndarray:
    """Orthonormal basis (3, 2) of the plane perpendicular to ``u`` (3,)."""
    u = u / np.linalg.norm(u)
    return np.linalg.svd(np.eye(3) - np.outer(u, u))[0][:, :2]


def build_structure(problem: CalibrationProblem, R_X: np.ndarray | None = None) -> Structure:
    """Decide groups, known motions and what is observable (docs/METHOD.md Secs. 3, 4, 7).

    ``R_X`` (3, 3): the current estimate of X's rotation, needed only to express an unobservable
    hand-eye translation direction in X's frame when all rotations share one axis.
    """
    frames = problem.frames
    F = len(frames)
    unobs: dict[str, str] = {}
    direction = np.zeros((F, 3))
    s_free = np.zeros(F, dtype=bool)
    M = np.tile(np.eye(4), (F, 1, 1))
    I3, none = np.eye(3), np.zeros((3, 0))
    X_rot, X_t, Y_rot, Y_t = I3, I3, none, none
    kn = problem.knowledge
    if kn == "robot":
        T = np.stack([f.T_base_tool for f in frames])
        M = np.linalg.inv(T) if problem.mount == "eye_in_hand" else T  # one batched call
        groups = np.zeros(F, dtype=int)
        Y_rot, Y_t = I3, I3
        # rotation axes relative to the first frame: the hand-eye translation is observable
        # across them (Tsai-Lenz)
        R0 = T[0, :3, :3]
        axes = []
        for t in T[1:]:
            rel = R0.T @ t[:3, :3] if problem.mount == "eye_in_hand" else t[:3, :3] @ R0.T
            v = rvec_from_R(rel)
            if np.linalg.norm(v) > np.radians(1.0):
                axes.append(v / np.linalg.norm(v))
        he = MOUNTS[problem.mount].hand_eye
        if not axes:
            X_t = none
            unobs[f"{he}.t"] = (
                "the session holds no rotations between frames, so the hand-eye translation is "
                "unobservable (docs/METHOD.md Sec. 4); add orientation groups tilted about two "
                "non-parallel axes"
            )
            # with no rotations and one translation direction, X R_M Y can rotate about that
            # direction without changing any image (gauge): fix Y's rotation about it
            d = np.array([M[k, :3, 3] - M[0, :3, 3] for k in range(1, F)]).reshape(-1, 3)
            d = d[np.linalg.norm(d, axis=1) > 1e-9]
            if len(d) == 0:
                raise DegenerateError(
                    "the robot never moved between frames: translate the camera between captures"
                )
            _, sv, Vt = np.linalg.svd(d)
            if len(sv) < 2 or sv[1] < 0.02 * sv[0]:
                Y_rot = complement_basis(M[0, :3, :3].T @ Vt[0])
                unobs[f"{he}.R"] = (
                    "all translations are parallel, so the hand-eye rotation about that direction "
                    "is unobservable; translate along at least two non-parallel directions"
                )
        else:
            _, sv, Vt = np.linalg.svd(np.asarray(axes))
            if len(sv) < 2 or sv[1] < 0.05 * sv[0]:
                X_t = complement_basis((I3 if R_X is None else R_X) @ Vt[0])
                unobs[f"{he}.t_along_rotation_axis"] = (
                    "all rotations share one axis, so the hand-eye translation along it is "
                    "unobservable; tilt about a second, non-parallel axis"
                )
    elif kn in ("board_translation", "board_direction"):
        groups = np.array([f.group if f.group is not None else 0 for f in frames], dtype=int)
        for k, f in enumerate(frames):
            m = np.zeros(3) if f.motion_board is None else np.asarray(f.motion_board, float)
            if kn == "board_translation":
                M[k, :3, 3] = -m
            elif np.linalg.norm(m) > 0:
                direction[k] = m / np.linalg.norm(m)
                s_free[k] = True
    else:  # "none": Zhang, one free pose per frame
        groups = np.arange(F)
    _, groups = np.unique(groups, return_inverse=True)
    o = problem.options
    noisy = kn == "robot" and (o.robot_noise_m > 0 or o.robot_noise_deg > 0)
    return Structure(
        groups,
        M,
        direction,
        s_free,
        X_rot,
        X_t,
        Y_rot,
        Y_t,
        unobs,
        T_meas=np.stack([f.T_base_tool for f in frames]) if noisy else None,
        pose_sigma=(max(np.radians(o.robot_noise_deg), 1e-9), max(o.robot_noise_m, 1e-9))
        if noisy
        else None,
        eye_in_hand=problem.mount != "eye_to_hand",
    )
