"""The calibration pipeline: a problem in, a result with its diagnostics out.

1. check the problem (one clear error per bad input),
2. per camera and orientation group, joint homographies (MATH.md Sec. 3),
3. the degeneracy analysis (Sec. 7) and the linear intrinsics for the knowledge at hand,
4. per-frame board poses and the motion unknowns (hand-eye rotation from translations, Sec. 4;
   hand-eye translation where rotations make it observable),
5. maximum-likelihood refinement over all detections with covariance (Secs. 5, 6),
6. the result: named covariance, what was unobservable, a per-move scale check.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from slidecal.solver.adequacy import assess
from slidecal.solver.degeneracy import check_configuration
from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.geometry import R_from_rvec, T_from_Rt, inv_T, project_to_SO3, skew
from slidecal.solver.handeye import rotation_from_directions
from slidecal.solver.homography import group_homographies
from slidecal.solver.linear import LinearGroup, linear_intrinsics, zhang_intrinsics
from slidecal.solver.problem import DISTORTION_NAMES, CalibrationProblem, Detection
from slidecal.solver.refine import (
    ModelState,
    RefineOutput,
    build_structure,
    complement_basis,
    orientation_groups,
    refine,
    single_threaded_blas,
)
from slidecal.solver.result import (
    CalibrationResult,
    CameraEstimate,
    ScaleCheck,
    TransformEstimate,
)
from slidecal.solver.stereo import (
    infinite_homography,
    rig_linear_intrinsics,
    rig_linear_intrinsics_translation,
)

MIN_CORNERS = 6  # fewer corners than this in an image do not enter the linear step


def check_problem(problem: CalibrationProblem) -> None:
    """Raise :class:`InputError` naming the first inconsistency in ``problem``."""
    names = [c.name for c in problem.cameras]
    if not names:
        raise InputError("the session lists no cameras; add a cameras: entry")
    if len(set(names)) != len(names):
        raise InputError(f"camera names must be unique, got {names}")
    if problem.reference not in names:
        raise InputError(f"reference camera {problem.reference!r} is not one of {names}")
    n_pts = len(problem.target.points_m)
    if len(problem.frames) < 2:
        raise InputError("a calibration needs at least 2 frames; capture more")
    for i, f in enumerate(problem.frames):
        where = f"frames[{i}]"
        for cam, det in f.detections.items():
            if cam not in names:
                raise InputError(f"unknown camera {cam!r}; cameras are {names}", where)
            if len(det.ids) and (det.ids.min() < 0 or det.ids.max() >= n_pts):
                raise InputError(
                    f"corner id out of range 0..{n_pts - 1} for this target; check the target "
                    "description (squares_x, squares_y)",
                    f"{where}.detections.{cam}.ids",
                )
            if not np.all(np.isfinite(det.px)):
                raise InputError("pixel coordinates must be finite", f"{where}.detections.{cam}")
            if len(np.unique(det.ids)) != len(det.ids):
                raise InputError("a corner id appears twice", f"{where}.detections.{cam}.ids")
        if problem.knowledge == "robot":
            T = f.T_base_tool
            if T is None:
                raise InputError(
                    "T_base_tool is missing: every frame of a robot session needs "
                    "the measured pose",
                    f"{where}.T_base_tool",
                )
            T = np.asarray(T, float)
            if (
                T.shape != (4, 4)
                or not np.all(np.isfinite(T))
                or abs(np.linalg.det(T[:3, :3]) - 1) > 1e-6
            ):
                raise InputError("T_base_tool is not a rigid transform", f"{where}.T_base_tool")
        if problem.knowledge in ("board_translation", "board_direction") and (
            f.motion_board is None
        ):
            raise InputError("motion_board is missing for this knowledge", f"{where}")
    if problem.mount not in ("eye_in_hand", "eye_to_hand", "none"):
        raise InputError(f"mount must be eye_in_hand, eye_to_hand or none, not {problem.mount!r}")
    if problem.knowledge == "robot" and problem.mount == "none":
        raise InputError("a robot session needs mount: eye_in_hand or eye_to_hand")


# -- grouping and the linear step ---------------------------------------------------------------
def frame_groups(problem: CalibrationProblem) -> np.ndarray:
    """Orientation group (F,) of every frame for the linear step."""
    if problem.knowledge == "robot":
        return orientation_groups(np.stack([f.T_base_tool for f in problem.frames]))
    if problem.knowledge == "none":
        return np.arange(len(problem.frames))
    return np.array([f.group or 0 for f in problem.frames])


def _motion_vectors(problem: CalibrationProblem, idx: list[int]) -> np.ndarray:
    """Per frame of a group: the motion the linear step uses (see ``LinearGroup``)."""
    frames = [problem.frames[i] for i in idx]
    if problem.knowledge == "robot":
        p = np.array([f.T_base_tool[:3, 3] for f in frames])
        return p - p[0]
    m = np.array([np.zeros(3) if f.motion_board is None else f.motion_board for f in frames])
    return m - m[0] if problem.knowledge == "board_translation" else m


def _linear_groups(
    problem: CalibrationProblem, cams: tuple[str, ...], groups: np.ndarray, joint: bool = True
) -> list[tuple[list[int], list[LinearGroup]]]:
    """Per orientation group: the frames every camera in ``cams`` saw well enough, and one
    ``LinearGroup`` per camera (the group's homographies with a common scale: jointly refined
    with ``joint``, else the rescaled per-frame DLTs; the known motion)."""
    pts = problem.target.points_m[:, :2]
    out = []
    for g in np.unique(groups):
        idx = [
            i
            for i in np.flatnonzero(groups == g)
            if all(
                len(problem.frames[i].detections.get(c, _EMPTY).ids) >= MIN_CORNERS for c in cams
            )
        ]
        if not idx:
            continue
        motion = None if problem.knowledge == "none" else _motion_vectors(problem, idx)
        if problem.knowledge == "board_direction":
            motion = motion.copy()
            motion[0] = 0.0
        per_cam = []
        for c in cams:
            dets = [problem.frames[i].detections[c] for i in idx]
            H = group_homographies([(pts[d.ids], d.px) for d in dets], 30 if joint else 0)
            per_cam.append(LinearGroup(H, motion))
        out.append((idx, per_cam))
    return out


def linear_camera(
    problem: CalibrationProblem, cam: str, groups: np.ndarray, joint: bool = True
) -> np.ndarray:
    """Closed-form ``K`` (3, 3) of one camera (MATH.md Sec. 3; Zhang for general motion).

    ``joint``: the paper's joint homographies per orientation group (the accurate linear
    method); False uses rescaled per-frame DLTs, enough to start the refinement and faster.
    """
    spec = problem.camera(cam)
    o = problem.options
    lin_groups = [gs[0] for _, gs in _linear_groups(problem, (cam,), groups, joint)]
    if not lin_groups:
        raise DegenerateError(
            f"camera {cam!r} saw the target in no frame: check the target "
            "description and that the target is in view"
        )
    size = (spec.width, spec.height)
    if problem.knowledge == "none":
        return zhang_intrinsics(
            np.concatenate([g.H for g in lin_groups]),
            skew=o.skew,
            unit_aspect=o.unit_aspect,
            image_size=size,
        )
    knowledge = problem.knowledge
    check_configuration(
        lin_groups, knowledge, skew=o.skew, unit_aspect=o.unit_aspect, image_size=size
    )
    return linear_intrinsics(
        lin_groups, knowledge, skew=o.skew, unit_aspect=o.unit_aspect, image_size=size
    ).K


def linear_pair(
    problem: CalibrationProblem, cam: str, ref: str, groups: np.ndarray, joint: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Joint closed-form ``(K_cam, K_ref)`` of two cameras of a rig (paper Sec. IV; MATH.md
    Sec. 8): both see the same translations (eqs. 33-42) and, with two or more orientations,
    the infinite homography couples their conics (eq. 62). Raises ``DegenerateError`` when the
    common views do not determine it."""
    o = problem.options
    sizes = [(problem.camera(c).width, problem.camera(c).height) for c in (cam, ref)]
    both = _linear_groups(problem, (cam, ref), groups, joint)
    if not both:
        raise DegenerateError(f"cameras {cam!r} and {ref!r} share no view of the target")
    ga = [gs[0] for _, gs in both]
    gb = [gs[1] for _, gs in both]
    if problem.knowledge == "none":
        Ha, Hb = np.concatenate([g.H for g in ga]), np.concatenate([g.H for g in gb])
        H_inf, _ = infinite_homography(Ha, Hb, sizes=sizes)
        return rig_linear_intrinsics(
            Ha, Hb, H_inf, skew=o.skew, unit_aspect=o.unit_aspect, sizes=sizes
        )
    return rig_linear_intrinsics_translation(
        ga, gb, problem.knowledge, skew=o.skew, unit_aspect=o.unit_aspect, sizes=sizes
    )


_EMPTY = Detection(np.zeros(0, dtype=int), np.zeros((0, 2)))  # what a camera that saw nothing saw


# -- poses and motion initialisation ------------------------------------------------------------
def pnp_pose(
    K: np.ndarray,
    dist: np.ndarray,
    board_pts: np.ndarray,
    px: np.ndarray,
    fast: bool = False,
    guess: np.ndarray | None = None,
) -> np.ndarray | None:
    """``T_cam_board`` (4, 4) from one image of the planar target, or None when it fails.

    ``fast``: OpenCV's IPPE (closed form for planar targets, five times faster, within
    micrometres of the iterative solver on consistent data: enough for a start); otherwise the
    iterative reprojection-error minimum (what the scale check needs: on inconsistent data,
    e.g. a wrong square size, IPPE's closed form hides part of the scale error). ``guess``
    (4, 4): a start for the iterative minimum (the minimum itself depends on the image only).
    """
    if len(px) < 4:
        return None
    obj, img = board_pts.astype(np.float64), px.astype(np.float64)
    if guess is not None:
        rvec0, _ = cv2.Rodrigues(guess[:3, :3])
        ok, rvec, tvec = cv2.solvePnP(
            obj,
            img,
            K,
            dist,
            rvec0,
            guess[:3, 3].reshape(3, 1).copy(),
            useExtrinsicGuess=True,
            flags=cv2.SOLVEPNP_ITERATIVE,
        )
    else:
        flags = cv2.SOLVEPNP_IPPE if fast else cv2.SOLVEPNP_ITERATIVE
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=flags)
    if not ok:
        return None
    R, _ = cv2.Rodrigues(rvec)
    return T_from_Rt(R, tvec.reshape(3))


def _frame_poses(
    problem: CalibrationProblem,
    cam: str,
    K: np.ndarray,
    dist: np.ndarray,
    fast: bool = False,
    guesses: dict[int, np.ndarray] | None = None,
) -> dict[int, np.ndarray]:
    pts = problem.target.points_m
    poses = {}
    for i, f in enumerate(problem.frames):
        det = f.detections.get(cam)
        if det is None or len(det.ids) < MIN_CORNERS:
            continue
        T = pnp_pose(K, dist, pts[det.ids], det.px, fast, (guesses or {}).get(i))
        if T is not None and T[2, 3] > 0:
            poses[i] = T
    return poses


def _average_T(Ts: list[np.ndarray]) -> np.ndarray:
    R = project_to_SO3(np.sum([T[:3, :3] for T in Ts], axis=0))
    return T_from_Rt(R, np.mean([T[:3, 3] for T in Ts], axis=0))


def _align(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking the direction of ``a`` (3,) onto that of ``b``."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else R_from_rvec(np.pi * complement_basis(a)[:, 0])
    return R_from_rvec(v / np.linalg.norm(v) * np.arctan2(np.linalg.norm(v), c))


def init_motion(
    problem: CalibrationProblem, poses: dict[int, np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Initial ``X`` (G, 4, 4), ``Y`` (4, 4), ``s`` (F,) from per-frame reference-camera poses.

    Robot knowledge: within an orientation group, ``t_cam_board(k) - t_cam_board(0) = R_X
    (t_M(k) - t_M(0))`` (camera displacement in camera axes against the known motion), so
    ``R_X`` is the orthogonal Procrustes solution over all such pairs (MATH.md Sec. 4); then
    ``X^-1 T_cam_board(k) = M_k Y`` is linear in ``R_X' t_X`` and ``t_Y`` (with the hand-eye
    translation fixed at 0 when no rotations make it observable).
    """
    st = build_structure(problem)
    F = len(problem.frames)
    s = np.zeros(F)
    if problem.knowledge == "none":
        X = np.stack([poses.get(i, np.eye(4)) for i in range(F)])
        missing = [problem.frames[i].id for i in range(F) if i not in poses]
        if missing:
            raise DegenerateError(
                f"frames {missing} have too few corners in the reference "
                "camera for general-motion calibration; drop them"
            )
        return X, np.eye(4), s
    if problem.knowledge in ("board_translation", "board_direction"):
        G = int(st.group_of_frame.max()) + 1
        X = np.tile(np.eye(4), (G, 1, 1))
        for g in range(G):
            idx = [i for i in np.flatnonzero(st.group_of_frame == g) if i in poses]
            if not idx:
                raise DegenerateError(f"orientation group {g} has no usable image")
            X[g] = poses[idx[0]] @ inv_T(st.M[idx[0]])
            for i in idx:
                if st.s_free[i]:
                    d = X[g][:3, :3] @ st.direction[i]
                    s[i] = -d @ (poses[i][:3, 3] - X[g][:3, 3])
        return X, np.eye(4), s
    groups = frame_groups(problem)
    d_cam, d_M = [], []
    for g in np.unique(groups):
        idx = [i for i in np.flatnonzero(groups == g) if i in poses]
        for a in range(len(idx)):
            for b in range(a + 1, len(idx)):
                i, j = idx[a], idx[b]
                d_cam.append(poses[j][:3, 3] - poses[i][:3, 3])
                d_M.append(st.M[j][:3, 3] - st.M[i][:3, 3])
    if len(d_M) == 0:
        raise DegenerateError(
            "no orientation group has two usable frames: translate the robot "
            "between captures at each tilt"
        )
    d_cam, d_M = np.array(d_cam), np.array(d_M)
    if st.Y_rot_basis.shape[1] == 3:
        R_X = rotation_from_directions(d_cam, d_M)
    else:  # one translation direction: any R_X mapping it onto the camera's will do (gauge)
        R_X = _align(d_M.T @ np.sign(d_M @ d_M[0]), d_cam.T @ np.sign(d_M @ d_M[0]))
    idx = sorted(poses)
    rows, rhs = [], []
    for i in idx:
        R_M = st.M[i][:3, :3]
        rows.append(np.hstack([np.eye(3), R_M]))
        rhs.append(R_X.T @ poses[i][:3, 3] - st.M[i][:3, 3])
    A, b = np.vstack(rows), np.concatenate(rhs)
    if st.X_t_basis.shape[1] == 3:
        sol = np.linalg.lstsq(A, b, rcond=None)[0]
        u, t_Y = sol[:3], sol[3:]
    else:
        u = np.zeros(3)
        t_Y = np.linalg.lstsq(A[:, 3:], b, rcond=None)[0]
    X = T_from_Rt(R_X, R_X @ u)
    R_Y = project_to_SO3(
        np.sum([st.M[i][:3, :3].T @ R_X.T @ poses[i][:3, :3] for i in idx], axis=0)
    )
    return X[None], T_from_Rt(R_Y, t_Y), s


# -- the whole pipeline -------------------------------------------------------------------------
@single_threaded_blas
def calibrate(
    problem: CalibrationProblem, *, joint_homographies: bool = False
) -> CalibrationResult:
    """Calibrate every camera, the hand-eye transform and the rig from one session.

    ``joint_homographies``: start from the paper's linear method with jointly refined
    homographies (``result.linear`` is then that method's estimate); by default the start uses
    rescaled per-frame DLTs, which the refinement does not need improved (same optimum,
    measured) and costs a third of the solve time less.
    """
    check_problem(problem)
    groups = frame_groups(problem)
    zero = np.zeros(5)
    jh = joint_homographies
    K_lin = {c.name: linear_camera(problem, c.name, groups, jh) for c in problem.cameras}
    ref = problem.reference
    notes: list[str] = []
    for c in K_lin:
        if c == ref:
            continue
        try:  # the rig's joint linear step; the separate estimate stays when it cannot run
            K_lin[c] = linear_pair(problem, c, ref, groups, jh)[0]
        except (DegenerateError, np.linalg.LinAlgError) as e:
            notes.append(
                f"joint linear step of {c!r} with {ref!r} skipped ({e}); "
                "started from the separate estimate"
            )
    poses = {c: _frame_poses(problem, c, K_lin[c], zero, fast=True) for c in K_lin}
    if len(poses[ref]) < 2:
        raise DegenerateError(
            f"the reference camera {ref!r} saw the target in fewer than 2 "
            "frames; choose another reference_camera or capture more"
        )
    T_cam_ref = {}
    apart = []  # cameras that never share a view with the reference
    for c in K_lin:
        if c == ref:
            continue
        both = [i for i in poses[c] if i in poses[ref]]
        if not both:
            if problem.knowledge != "robot" or len(poses[c]) == 0:
                raise DegenerateError(
                    f"cameras {c!r} and {ref!r} never saw the target in the same frame; "
                    "without robot poses the rig extrinsics need common views"
                )
            apart.append(c)
            continue
        T_cam_ref[c] = _average_T([poses[c][i] @ inv_T(poses[ref][i]) for i in both])
    # a frame the reference camera missed still has a pose through another camera of the rig
    ref_poses = dict(poses[ref])
    for c, T in T_cam_ref.items():
        for i, T_c_board in poses[c].items():
            ref_poses.setdefault(i, inv_T(T) @ T_c_board)
    X, Y, s = init_motion(problem, ref_poses)
    if apart:  # the measured robot motion carries the reference camera to their frames
        st = build_structure(problem)
        for c in apart:
            T_cam_ref[c] = _average_T(
                [
                    T_c_board @ inv_T(X[st.group_of_frame[i]] @ st.M[i] @ Y)
                    for i, T_c_board in poses[c].items()
                ]
            )
    init = ModelState(K_lin, {c: zero.copy() for c in K_lin}, T_cam_ref, X, Y, s)
    structure = build_structure(problem, X[0][:3, :3])
    out = refine(problem, structure, init)
    if notes:
        out = replace(out, messages=out.messages + tuple(notes))
    return _result(problem, out, K_lin, groups)


def _kept(out: RefineOutput) -> np.ndarray:
    """Indices of the parameters a result reports (all but the robot-pose corrections)."""
    keep = np.ones(len(out.names), dtype=bool)
    for key in ("E", "U"):  # per-frame and per-group robot-pose corrections
        if key in out.model.slices:
            keep[out.model.slices[key]] = False
    return np.flatnonzero(keep)


def _block_cov(out: RefineOutput, key: str) -> np.ndarray | None:
    if out.covariance is None or key not in out.model.slices:
        return None
    sl = out.model.slices[key]
    return out.covariance[sl, sl]


def _std_rot_deg(C: np.ndarray | None) -> float | None:
    return None if C is None else float(np.degrees(np.sqrt(max(np.trace(C), 0.0))))


def _std_t_mm(C: np.ndarray | None) -> float | None:
    return None if C is None else float(1000.0 * np.sqrt(max(np.trace(C), 0.0)))


def _result(
    problem: CalibrationProblem, out: RefineOutput, K_lin: dict[str, np.ndarray], groups: np.ndarray
) -> CalibrationResult:
    model, st, state = out.model, out.model.st, out.state
    cov = out.covariance
    names = out.names
    cams = {}
    for spec in problem.cameras:
        c = spec.name
        std = {}
        for n in model.intr + model.dist_names:
            full = f"{c}.{n}"
            if cov is not None and full in names:
                i = names.index(full)
                v = float(np.sqrt(max(cov[i, i], 0.0)))
                if n == "f":
                    std["fx"] = std["fy"] = v
                else:
                    std[n] = v
        rows = np.concatenate(
            [np.r_[ch.rows] for ch in model.chunks if ch.camera == c] or [np.zeros(0, int)]
        )
        rows = rows[out.inlier_rows[rows]] if len(rows) else rows
        rms = float(np.sqrt(np.mean(out.residuals[rows] ** 2) * 2)) if len(rows) else float("nan")
        cams[c] = CameraEstimate(c, spec.width, spec.height, state.K[c], state.dist[c], std, rms)
    unobs = dict(st.unobservable)
    for i, on in enumerate(problem.options.distortion):
        if not on:
            unobs.setdefault(f"distortion.{DISTORTION_NAMES[i]}", "fixed at 0 by the options")
    hand_eye = T_target = None
    if problem.knowledge == "robot":
        he_name = "T_tool_cam" if problem.mount == "eye_in_hand" else "T_base_cam"
        tgt_name = "T_base_board" if problem.mount == "eye_in_hand" else "T_tool_board"
        Xm = state.X[0]
        C = _block_cov(out, "X:0")
        Br, Bt = st.X_rot_basis, st.X_t_basis
        T_he = inv_T(Xm)
        rot_ok = f"{he_name}.R" not in unobs
        t_ok = rot_ok and Bt.shape[1] == 3
        std_r = std_t = None
        if C is not None:
            mr = Br.shape[1]
            std_r = _std_rot_deg(Br @ C[:mr, :mr] @ Br.T) if rot_ok else None
            if t_ok:
                J = np.hstack([-Xm[:3, :3].T @ skew(Xm[:3, 3]) @ Br, -Xm[:3, :3].T @ Bt])
                std_t = _std_t_mm(J @ C @ J.T)
        hand_eye = TransformEstimate(
            he_name, T_he[:3, :3] if rot_ok else None, T_he[:3, 3] if t_ok else None, std_r, std_t
        )
        CY = _block_cov(out, "Y")
        mr = st.Y_rot_basis.shape[1]
        T_target = TransformEstimate(
            tgt_name,
            state.Y[:3, :3],
            state.Y[:3, 3],
            _std_rot_deg(st.Y_rot_basis @ CY[:mr, :mr] @ st.Y_rot_basis.T)
            if CY is not None
            else None,
            _std_t_mm(CY[mr:, mr:]) if CY is not None else None,
        )
    rig = {}
    H_inf = {}
    ref = problem.reference
    for c, T in state.T_cam_ref.items():
        C = _block_cov(out, f"rig:{c}")
        rig[f"T_{c}_{ref}"] = TransformEstimate(
            f"T_{c}_{ref}",
            T[:3, :3],
            T[:3, 3],
            _std_rot_deg(C[:3, :3]) if C is not None else None,
            _std_t_mm(C[3:, 3:]) if C is not None else None,
        )
        Hab = state.K[c] @ T[:3, :3] @ np.linalg.inv(state.K[ref])
        H_inf[f"{c}<-{ref}"] = Hab / Hab[2, 2]
    residuals = {}
    for ch in model.chunks:
        r = out.residuals[ch.rows]
        residuals[ch.key] = float(np.sqrt(np.mean(r**2) * 2))
    inl = out.residuals[out.inlier_rows]
    rms = float(np.sqrt(np.mean(inl**2) * 2)) if len(inl) else float("nan")
    adequacy, robot_accuracy = assess(problem, out)
    return CalibrationResult(
        cameras=cams,
        hand_eye=hand_eye,
        rig=rig,
        T_target=T_target,
        converged=out.converged,
        iterations=out.iterations,
        reproj_rms_px=rms,
        sigma_px=out.sigma_px,
        # the robot-pose corrections are nuisance parameters: the result keeps the marginal
        # covariance of everything else (the matching block of the full inverse)
        parameter_names=tuple(names[i] for i in _kept(out)),
        covariance=None if cov is None else cov[np.ix_(_kept(out), _kept(out))],
        residuals_px=residuals,
        outliers=out.outliers,
        unobservable=unobs,
        messages=out.messages,
        scale_checks=scale_checks(
            problem,
            state,
            groups,
            {i: model.T_ref_board(state, i) for i in range(len(problem.frames))},
        ),
        H_inf=H_inf,
        linear=K_lin,
        mount=problem.mount,
        reference_camera=ref,
        adequacy=adequacy,
        robot_accuracy=robot_accuracy,
    )


def scale_checks(
    problem: CalibrationProblem,
    state: ModelState,
    groups: np.ndarray,
    guesses: dict[int, np.ndarray] | None = None,
) -> tuple[ScaleCheck, ...]:
    """Per move within an orientation group: the translation the reference camera saw (from a
    PnP pose per frame with the final intrinsics: the image alone, ``guesses`` only start it)
    against the robot's. A ratio away from 1 means a wrong square size or a wrong robot/TCP
    scale."""
    if problem.knowledge != "robot":
        return ()
    ref = problem.reference
    poses = _frame_poses(problem, ref, state.K[ref], state.dist[ref], guesses=guesses)
    checks = []
    for g in np.unique(groups):
        idx = [i for i in np.flatnonzero(groups == g) if i in poses]
        for a, b in zip(idx[:-1], idx[1:], strict=True):
            Ca = inv_T(poses[a])[:3, 3]
            Cb = inv_T(poses[b])[:3, 3]
            pa = problem.frames[a].T_base_tool[:3, 3]
            pb = problem.frames[b].T_base_tool[:3, 3]
            robot = float(np.linalg.norm(pb - pa)) * 1000.0
            if robot < 1.0:
                continue
            checks.append(
                ScaleCheck(
                    problem.frames[a].id,
                    problem.frames[b].id,
                    robot,
                    float(np.linalg.norm(Cb - Ca)) * 1000.0,
                )
            )
    return tuple(checks)
