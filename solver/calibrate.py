"""The calibration pipeline: a problem in, a result with its diagnostics out.

1. check the problem; skip images with fewer than 4 points and frames that saw nothing,
2. per camera and orientation group, the homographies and the linear intrinsics (Secs. 3, 7;
   Zhang for classic hand-eye sessions),
3. per-frame board poses and the motion unknowns (Sec. 4, or AX = XB),
4. the refinement with the arm's accuracy learned (Secs. 5, 6), pose and image outliers left
   out and the session solved again,
5. the result: the reported covariance, what was unobservable, the adequacy and scale checks.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from slidecal.solver.adequacy import (
    LEFT_OUT,
    MAX_CLASSIC_SCALE_SE,
    ImageOutlier,
    PoseOutlier,
    assess,
    bad_images_note,
    classic,
    classic_scale_fit,
    final_free_pose_fit,
    image_outlier,
    pose_outlier,
    record_check,
    scale_moves,
    static_rotation,
    unchecked_scale_note,
)
from slidecal.solver.camera import opencv_view, zero_distortion
from slidecal.solver.degeneracy import check_configuration
from slidecal.solver.detect import resolve_half_turns
from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.free_pose import FreePoseFit, pnp_from
from slidecal.solver.geometry import R_from_rvec, T_from_Rt, inv_T, project_to_SO3
from slidecal.solver.handeye import ax_xb_park_martin, n_directions, rotation_from_directions
from slidecal.solver.homography import group_homographies
from slidecal.solver.lens import choose_lens
from slidecal.solver.linear import (
    LinearGroup,
    focal_from_homographies,
    linear_intrinsics,
    zhang_intrinsics,
)
from slidecal.solver.model import (
    BundleModel,
    ModelState,
    Structure,
    build_structure,
    complement_basis,
    orientation_groups,
    single_threaded_blas,
)
from slidecal.solver.numeric import distinct, median
from slidecal.solver.problem import (
    DISTORTION_NAMES,
    INTRINSIC_NAMES,
    CalibrationProblem,
    Detection,
    Frame,
    hand_eye_names,
    mount_names,
)
from slidecal.solver.refine import RefineOutput, refine
from slidecal.solver.result import (
    BoardShape,
    CalibrationResult,
    CameraEstimate,
    NamedCovariance,
    ScaleCheck,
    TransformEstimate,
)
from slidecal.solver.stereo import (
    infinite_homography,
    rig_linear_intrinsics,
    rig_linear_intrinsics_translation,
)
from slidecal.solver.target_shape import BoardFit
from slidecal.solver.uncertainty import Reported, layout_of, named_step, reported_covariance

# An image with fewer points than this is skipped: a homography and a planar pose need 4.
MIN_CORNERS = 4
# Robot positions farther apart than this (and 20 target sizes) are millimetres given as metres.
MAX_SPAN_M = 20.0


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
    _check_frames(problem, n_pts)
    if problem.knowledge == "robot":
        p = np.array([np.asarray(f.T_base_tool, float)[:3, 3] for f in problem.frames])
        span = np.linalg.norm(p - p[0], axis=1)
        pts = problem.target.points_m
        extent = float(np.ptp(pts, axis=0).max()) if len(pts) else 0.0
        if span.max() > max(MAX_SPAN_M, 20.0 * extent):
            raise InputError(
                "T_base_tool translations look like millimetres; give metres (frame "
                f"{problem.frames[int(np.argmax(span))].id} is {span.max():.0f} m from frame "
                f"{problem.frames[0].id})",
                f"frames[{int(np.argmax(span))}].T_base_tool",
            )
    if problem.mount not in ("eye_in_hand", "eye_to_hand", "none"):
        raise InputError(f"mount must be eye_in_hand, eye_to_hand or none, not {problem.mount!r}")
    if problem.knowledge == "robot" and problem.mount == "none":
        raise InputError("a robot session needs mount: eye_in_hand or eye_to_hand")


def _check_frames(problem: CalibrationProblem, n_pts: int) -> None:
    """Raise :class:`InputError` naming what is wrong with the first frame of ``problem`` where
    something is (its detections, its pose or motion for the knowledge): all checked at once."""
    names = [c.name for c in problem.cameras]
    dets = [(i, c, d) for i, f in enumerate(problem.frames) for c, d in f.detections.items()]
    ids = np.concatenate([np.zeros(0, int), *(d.ids for *_, d in dets)])
    px = np.concatenate([np.zeros((0, 2)), *(d.px for *_, d in dets)])
    k = np.repeat(np.arange(len(dets)), [len(d.ids) for *_, d in dets])  # each corner's image
    k_o, ids_o = np.array([k, ids])[:, np.lexsort((ids, k))]  # each image's ids in order
    fails = np.zeros((len(dets), 4), bool)  # per image, in the order they are told below
    fails[[j for j, (_, c, _) in enumerate(dets) if c not in names], 0] = True
    fails[k[(ids < 0) | (ids >= n_pts)], 1] = True
    fails[k[~np.isfinite(px).all(axis=1)], 2] = True
    fails[k_o[1:][(k_o[1:] == k_o[:-1]) & (ids_o[1:] == ids_o[:-1])], 3] = True
    image_frame = np.array([i for i, _, _ in dets], dtype=int)
    bad = np.zeros((len(problem.frames), 4), bool)  # per frame: an image, then as told below
    bad[image_frame[fails.any(axis=1)], 0] = True
    if problem.knowledge == "robot":  # a missing pose (None) reads as nan
        T = [np.asarray(f.T_base_tool, float) for f in problem.frames]
        M = np.array([t if t.shape == (4, 4) else np.full((4, 4), np.nan) for t in T])
        rigid = np.isfinite(M).all(axis=(1, 2))
        rigid[rigid] = abs(np.linalg.det(M[rigid, :3, :3]) - 1) <= 1e-6
        bad[:, 1], bad[:, 2] = [f.T_base_tool is None for f in problem.frames], ~rigid
    if problem.knowledge in ("board_translation", "board_direction"):
        bad[:, 3] = [f.motion_board is None for f in problem.frames]
    if not bad.any():
        return
    i = int(np.flatnonzero(bad.any(axis=1))[0])
    where = f"frames[{i}]"
    for j in np.flatnonzero(fails.any(axis=1) & (image_frame == i))[:1]:
        field = f"{where}.detections.{dets[j][1]}"
        raise InputError(
            *[
                (f"unknown camera {dets[j][1]!r}; cameras are {names}", where),
                (
                    f"corner id out of range 0..{n_pts - 1} for this target; check the target "
                    "description (squares_x, squares_y)",
                    f"{field}.ids",
                ),
                ("pixel coordinates must be finite", field),
                ("a corner id appears twice", f"{field}.ids"),
            ][int(np.argmax(fails[j]))]
        )
    if bad[i, 1]:
        raise InputError(
            "T_base_tool is missing: every frame of a robot session needs the measured pose",
            f"{where}.T_base_tool",
        )
    if bad[i, 2]:
        raise InputError("T_base_tool is not a rigid transform", f"{where}.T_base_tool")
    raise InputError("motion_board is missing for this knowledge", f"{where}")


def usable_frames(problem: CalibrationProblem) -> tuple[CalibrationProblem, tuple[str, ...]]:
    """The problem without the images and frames that cannot enter the solve, and why.

    An image with fewer than ``MIN_CORNERS`` points is skipped; a frame in which no camera kept
    an image is skipped whole. Returns the reduced problem (frame ids unchanged) and one message
    per skip. Raises ``DegenerateError`` when fewer than 2 frames remain.
    """
    kept: list[Frame] = []
    notes: list[str] = []
    empty: list[int] = []
    for f in problem.frames:
        dets = {}
        for cam, det in f.detections.items():
            if len(det.ids) >= MIN_CORNERS:
                dets[cam] = det
            elif len(det.ids):
                notes.append(
                    f"frame {f.id}: camera {cam!r} found {len(det.ids)} target points, fewer "
                    f"than the {MIN_CORNERS} a pose needs; image skipped"
                )
        if dets:
            kept.append(replace(f, detections=dets) if len(dets) < len(f.detections) else f)
        else:
            empty.append(f.id)
    if empty:
        notes.append(
            f"frames {empty}: the target was not found (at least {MIN_CORNERS} points) by any "
            "camera; skipped"
        )
    if len(kept) < 2:
        raise DegenerateError(
            f"only {len(kept)} of {len(problem.frames)} frames saw the target (at least "
            f"{MIN_CORNERS} points)"
            + (f"; the detection found nothing usable in frames {empty}" if empty else "")
            + ": check those images (focus, exposure, the target description) or capture more "
            "frames with the target in view"
        )
    if len(kept) == len(problem.frames) and not notes:
        return problem, ()
    return replace(problem, frames=tuple(kept)), tuple(notes)


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
    problem: CalibrationProblem,
    cams: tuple[str, ...],
    groups: np.ndarray,
    joint: bool,
    cache: dict,
) -> list[tuple[list[int], list[LinearGroup]]]:
    """Per orientation group: the frames every camera in ``cams`` saw well enough, and one
    ``LinearGroup`` per camera (homographies with a common scale: jointly refined with
    ``joint``, else rescaled per-frame DLTs). ``cache``: the homographies by (camera, frames,
    joint), filled here."""
    pts = problem.target.points_m[:, :2]
    out = []
    for g in distinct(groups):
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
            key = (c, tuple(int(i) for i in idx), joint)
            if key not in cache:
                dets = [problem.frames[i].detections[c] for i in idx]
                H = group_homographies([(pts[d.ids], d.px) for d in dets], 30 if joint else 0)
                H.setflags(write=False)  # shared by every use
                cache[key] = H
            per_cam.append(LinearGroup(cache[key], motion))
        out.append((idx, per_cam))
    return out


def _plausible(K: np.ndarray, size: tuple[int, int]) -> bool:
    """A start worth refining: principal point in the image, aspect ratio within 1:2."""
    w, h = size
    ratio = K[0, 0] / K[1, 1]
    return -0.5 <= K[0, 2] <= w - 0.5 and -0.5 <= K[1, 2] <= h - 0.5 and 0.5 < ratio < 2.0


def _rotation_enters(st: Structure) -> bool:
    """Whether X's rotation enters ``build_structure``: only through an unobservable hand-eye
    translation direction (all rotations about one axis: a basis of the two others)."""
    return st.X_t_basis.shape[1] == 2


def _with_rotation(problem: CalibrationProblem, st: Structure, R_X: np.ndarray) -> Structure:
    """``build_structure(problem, R_X)`` given ``st = build_structure(problem)``."""
    return build_structure(problem, R_X) if _rotation_enters(st) else st


def _best_start(problem: CalibrationProblem, cam: str, candidates: list[np.ndarray]) -> int:
    """Index of the start ``K`` (3, 3) whose PnP poses and hand-eye start (:func:`init_motion`)
    predict the detections best through the robot poses (smallest median reprojection error).
    """
    o = problem.options
    exact = replace(problem, options=replace(o, robot_noise_m=0.0, robot_noise_deg=0.0))
    zero = zero_distortion(o.lens)
    groups = frame_groups(exact)
    st = model = None  # the structure and its model, shared by the candidates where they can be
    best, best_err = 0, np.inf
    for k, K in enumerate(candidates):
        poses = _frame_poses(exact, cam, K, zero, fast=True)
        if len(poses) < 3:
            continue
        try:
            st = build_structure(exact) if st is None else st
            X, Y, s = init_motion(exact, poses, groups, st)
        except DegenerateError:
            continue
        if model is None or _rotation_enters(st):
            model = BundleModel(exact, _with_rotation(exact, st, X[0][:3, :3]))
        r, _ = model.evaluate(ModelState({cam: K}, {cam: zero}, {}, X, Y, s), jacobian=False)
        err = float(median(np.hypot(r[0::2], r[1::2])))
        if np.isfinite(err) and err < best_err:
            best, best_err = k, err
    return best


def linear_camera(
    problem: CalibrationProblem,
    cam: str,
    groups: np.ndarray,
    joint: bool,
    notes: list[str],
    focal_sweep: bool,
    homographies: dict,
) -> np.ndarray:
    """Closed-form ``K`` (3, 3) of one camera (docs/METHOD.md Sec. 3; Zhang for general motion).

    ``joint``: the paper's joint homographies per orientation group, else rescaled per-frame
    DLTs. A robot session without translation groups whose Zhang estimate is implausible, or
    with ``focal_sweep``, starts from the image centre and the focal length that fits the images
    best through the robot poses; ``notes`` receives a line when Zhang's estimate is not the
    start.
    """
    spec = problem.camera(cam)
    o = problem.options
    lin_groups = [gs[0] for _, gs in _linear_groups(problem, (cam,), groups, joint, homographies)]
    if not lin_groups:
        raise DegenerateError(
            f"camera {cam!r} saw the target (at least {MIN_CORNERS} points) in no frame: check "
            "the target description and that the target is in view"
        )
    n_seen = sum(len(g.H) for g in lin_groups)
    size = (spec.width, spec.height)
    if problem.knowledge == "none" or all(len(g.H) < 2 for g in lin_groups):
        # general motion, or a classic hand-eye session (no two frames at one orientation):
        # Zhang from the homographies of all frames
        n_need = 3 if o.skew else 2
        if len(lin_groups) < n_need:
            raise DegenerateError(
                f"camera {cam!r} saw the target in {len(lin_groups)} of {len(problem.frames)} "
                f"frames: the intrinsics need at least {n_need} views at different orientations; "
                "capture more frames at different tilts"
                + ("" if problem.knowledge == "none" else ", or translate between captures")
            )
        Hs = np.concatenate([g.H for g in lin_groups])
        candidates, reason = [], "not positive definite"
        try:
            K = zhang_intrinsics(Hs, skew=o.skew, unit_aspect=o.unit_aspect, image_size=size)
            if problem.knowledge != "robot" or (_plausible(K, size) and not focal_sweep):
                return K
            if _plausible(K, size):
                candidates.append(K)
                reason = "a worse fit to the images through the robot poses"
            else:
                reason = "implausible"
        except DegenerateError:
            if problem.knowledge != "robot":
                raise
        # few or noisy points per image: the robot poses decide the focal length of the start
        # (square pixels, principal point at the centre), Zhang's estimate competing
        n_zhang = len(candidates)
        Kf = focal_from_homographies(Hs, image_size=size)
        factors = np.concatenate([[1.0], np.geomspace(0.25, 4.0, 17)])
        if len(problem.cameras) > 1:  # the rig's cameras share the robot poses: keep it simple
            factors = factors[:1]
        for factor in factors:
            Kc = Kf.copy()
            Kc[0, 0] = Kc[1, 1] = Kf[0, 0] * factor
            candidates.append(Kc)
        best = _best_start(problem, cam, candidates) if len(problem.cameras) == 1 else 0
        if best >= n_zhang:
            notes.append(
                f"camera {cam!r}: Zhang's closed form was {reason} for these views; the "
                "refinement started from the image centre and the focal length that fits the "
                "images best through the robot poses"
            )
        return candidates[best]
    knowledge = problem.knowledge
    try:
        opts = {"skew": o.skew, "unit_aspect": o.unit_aspect, "image_size": size}
        system = check_configuration(lin_groups, knowledge, **opts)
        return linear_intrinsics(lin_groups, knowledge, **opts, system=system).K
    except DegenerateError as e:
        if n_seen == len(problem.frames):
            raise
        raise DegenerateError(
            f"{e} (camera {cam!r} found the target, at least {MIN_CORNERS} points, in "
            f"{n_seen} of {len(problem.frames)} frames: the detection failed in the others)"
        ) from None


def linear_pair(
    problem: CalibrationProblem,
    cam: str,
    ref: str,
    groups: np.ndarray,
    joint: bool,
    homographies: dict,
) -> tuple[np.ndarray, np.ndarray]:
    """Joint closed-form ``(K_cam, K_ref)`` of two cameras of a rig (paper Sec. IV; docs/METHOD.md
    Sec. 8): both see the same translations (eqs. 33-42) and, with two or more orientations,
    the infinite homography couples their conics (eq. 62). Raises ``DegenerateError`` when the
    common views do not determine it."""
    o = problem.options
    sizes = [(problem.camera(c).width, problem.camera(c).height) for c in (cam, ref)]
    both = _linear_groups(problem, (cam, ref), groups, joint, homographies)
    if not both:
        raise DegenerateError(f"cameras {cam!r} and {ref!r} share no view of the target")
    ga = [gs[0] for _, gs in both]
    gb = [gs[1] for _, gs in both]
    multi = [k for k, g in enumerate(ga) if len(g.H) >= 2]  # groups with a translation
    if problem.knowledge == "none" or not multi:  # general motion only
        Ha, Hb = np.concatenate([g.H for g in ga]), np.concatenate([g.H for g in gb])
        H_inf, _ = infinite_homography(Ha, Hb, sizes=sizes)
        return rig_linear_intrinsics(
            Ha, Hb, H_inf, skew=o.skew, unit_aspect=o.unit_aspect, sizes=sizes
        )
    return rig_linear_intrinsics_translation(
        [ga[k] for k in multi],
        [gb[k] for k in multi],
        problem.knowledge,
        skew=o.skew,
        unit_aspect=o.unit_aspect,
        sizes=sizes,
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

    ``fast``: OpenCV's IPPE (closed form, enough for a start); otherwise the iterative
    reprojection-error minimum (the scale check's: IPPE hides part of a scale error).
    ``guess`` (4, 4): a start for the iterative minimum.
    """
    obj, img = np.asarray(board_pts, np.float64), np.asarray(px, np.float64)
    if guess is not None:
        return pnp_from(obj, img, K, dist, guess)
    flags = cv2.SOLVEPNP_IPPE if fast else cv2.SOLVEPNP_ITERATIVE
    K, dist, img = opencv_view(K, dist, img)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=flags)
    return T_from_Rt(cv2.Rodrigues(rvec)[0], tvec.reshape(3)) if ok else None


def _frame_poses(
    problem: CalibrationProblem,
    cam: str,
    K: np.ndarray,
    dist: np.ndarray,
    fast: bool = False,
    guesses: dict[int, np.ndarray] | None = None,
    only: list[int] | None = None,
) -> dict[int, np.ndarray]:
    """``T_cam_board`` per frame index of camera ``cam`` (PnP; ``only``: of these frames)."""
    pts = problem.target.points_m
    poses = {}
    for i in range(len(problem.frames)) if only is None else only:
        det = problem.frames[i].detections.get(cam)
        if det is None or len(det.ids) < MIN_CORNERS:
            continue
        T = pnp_pose(K, dist, pts[det.ids], det.px, fast, (guesses or {}).get(i))
        if T is not None and T[2, 3] > 0:
            poses[i] = T
    return poses


def _average_T(Ts: list[np.ndarray]) -> np.ndarray:
    R = project_to_SO3(np.sum([T[:3, :3] for T in Ts], axis=0))
    return T_from_Rt(R, np.mean([T[:3, 3] for T in Ts], axis=0))


def _align_translations(d_cam: np.ndarray, d_M: np.ndarray) -> np.ndarray:
    """``R_X`` (3, 3), the smallest rotation taking the one robot translation direction onto the
    camera's."""
    sign = np.sign(d_M @ d_M[0])
    a, b = d_M.T @ sign, d_cam.T @ sign
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else R_from_rvec(np.pi * complement_basis(a)[:, 0])
    return R_from_rvec(v / np.linalg.norm(v) * np.arctan2(np.linalg.norm(v), c))


def _rotation_ax_xb(groups: np.ndarray, M: np.ndarray, poses: dict[int, np.ndarray]) -> np.ndarray:
    """``R_X`` (3, 3) of ``T_cam_board(k) = X M_k Y`` from general motions (classic hand-eye).

    Between frames ``i``, ``j``: ``P_i P_j^-1 = X (M_i M_j^-1) X^-1``, an ``AX = XB`` problem
    solved by Park and Martin over all pairs of orientation groups (one frame each).
    """
    rep = {}
    for i in sorted(poses):
        rep.setdefault(int(groups[i]), i)
    idx = list(rep.values())
    if len(idx) < 3:
        raise DegenerateError(
            f"the board was seen at {len(idx)} orientation(s): the hand-eye rotation from "
            "general motions needs at least 3 orientations, about two non-parallel axes"
        )
    a, b = np.triu_indices(len(idx), 1)
    P = np.array([poses[i] for i in idx])
    Mi = M[idx]
    P_inv = np.array([inv_T(T) for T in P])
    M_inv = np.array([inv_T(T) for T in Mi])
    return ax_xb_park_martin(P[a] @ P_inv[b], Mi[a] @ M_inv[b])[:3, :3]


def init_motion(
    problem: CalibrationProblem,
    poses: dict[int, np.ndarray],
    groups: np.ndarray,
    st: Structure,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Initial ``X`` (G, 4, 4), ``Y`` (4, 4), ``s`` (F,) from per-frame reference-camera poses.

    Robot knowledge: ``R_X`` by Procrustes over the camera's displacements within each group
    against the robot's (docs/METHOD.md Sec. 4), then ``X^-1 T_cam_board(k) = M_k Y`` linear in
    ``R_X' t_X`` and ``t_Y`` (``t_X`` 0 when no rotation observes it). ``groups``, ``st``: the
    problem's :func:`frame_groups` and ``build_structure(problem)``.
    """
    F = len(problem.frames)
    s = np.zeros(F)
    if problem.knowledge == "none":
        X = np.stack([poses[i] for i in range(F)])  # _pass skipped the frames without one
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
    d_cam, d_M = [np.zeros((0, 3))], [np.zeros((0, 3))]
    for g in distinct(groups):  # every pair of frames a < b of a group (n^2 / 2 of them)
        idx = np.array([i for i in np.flatnonzero(groups == g) if i in poses], dtype=int)
        a, b = np.triu_indices(len(idx), 1)
        t_cam = np.array([poses[i][:3, 3] for i in idx]).reshape(-1, 3)
        d_cam.append(t_cam[b] - t_cam[a])
        d_M.append(st.M[idx[b], :3, 3] - st.M[idx[a], :3, 3])
    d_cam, d_M = np.concatenate(d_cam), np.concatenate(d_M)
    n_dir = n_directions(d_M)
    rotations = st.X_t_basis.shape[1] > 0  # the robot rotates between some frames
    if n_dir >= 2:  # translations in two directions or more (docs/METHOD.md Sec. 4)
        R_X = rotation_from_directions(d_cam, d_M)
    elif rotations:
        try:  # general motions between the orientations: AX = XB
            R_X = _rotation_ax_xb(groups, st.M, poses)
        except DegenerateError:
            if n_dir == 0:
                raise
            R_X = _align_translations(d_cam, d_M)
    elif n_dir == 1:  # one translation direction: any R_X mapping it onto the camera's (gauge)
        R_X = _align_translations(d_cam, d_M)
    else:
        raise DegenerateError(
            "the robot neither translated between frames at one orientation nor rotated "
            f"between frames ({len(poses)} frames with a board pose): capture frames at "
            "different tilts, or translate the robot between captures at each tilt"
        )
    idx = sorted(poses)
    P, M = np.array([poses[i] for i in idx]), st.M[idx]
    A = np.concatenate([np.broadcast_to(np.eye(3), (len(idx), 3, 3)), M[:, :3, :3]], axis=2)
    A, b = A.reshape(-1, 6), ((R_X.T @ P[:, :3, 3:])[:, :, 0] - M[:, :3, 3]).reshape(-1)
    if st.X_t_basis.shape[1] == 3:
        sol = np.linalg.lstsq(A, b, rcond=None)[0]
        u, t_Y = sol[:3], sol[3:]
    else:
        u = np.zeros(3)
        t_Y = np.linalg.lstsq(A[:, 3:], b, rcond=None)[0]
    X = T_from_Rt(R_X, R_X @ u)
    R_Y = project_to_SO3(np.sum(np.swapaxes(M[:, :3, :3], 1, 2) @ R_X.T @ P[:, :3, :3], axis=0))
    return X[None], T_from_Rt(R_Y, t_Y), s


# -- the whole pipeline -------------------------------------------------------------------------
@single_threaded_blas
def calibrate(
    problem: CalibrationProblem, *, joint_homographies: bool = False
) -> CalibrationResult:
    """Calibrate every camera, the hand-eye transform and the rig from one session.

    ``joint_homographies``: start from the paper's linear method with jointly refined
    homographies (``result.linear`` is then that method's estimate); by default rescaled
    per-frame DLTs (the same optimum, faster). A pose or image outlier
    (``adequacy.pose_outlier``, ``adequacy.image_outlier``) is left out and the session solved
    again, at most one frame in ten (at least one); the lens model is tested (``solver/lens.py``).
    """
    problem, turned = resolve_half_turns(problem)  # a symmetric board read the right way round

    def solve(p: CalibrationProblem) -> CalibrationResult:
        return _pipeline(p, joint_homographies, False, ())

    res = choose_lens(problem, solve(problem), solve)
    return replace(res, messages=(*turned, *res.messages)) if turned else res


@dataclass
class _Pass:
    """One pass of the pipeline over a problem: its solve, and what it asks of the loop.

    ``again``: the problem to solve next (an outlier left out, or frames without a board pose
    skipped), ``prefix`` the lines the result then opens with, ``gone`` the frame left out for
    its pose; ``bad``: the outlier left out (its pass is finished should the next one fail);
    ``result``: a restart's."""

    problem: CalibrationProblem
    notes: list[str]
    out: RefineOutput | None = None
    K_lin: dict[str, np.ndarray] = field(default_factory=dict)
    groups: np.ndarray | None = None
    fit: FreePoseFit | None = None
    again: CalibrationProblem | None = None
    prefix: tuple[str, ...] = ()
    bad: PoseOutlier | ImageOutlier | None = None
    gone: tuple[int, float, float] | None = None
    result: CalibrationResult | None = None


def _pipeline(
    problem: CalibrationProblem,
    jh: bool,
    focal_sweep: bool,
    left_out: tuple[PoseOutlier | ImageOutlier, ...],
) -> CalibrationResult:
    """:func:`calibrate`'s loop: solve, and while the solve leaves a frame (or an image) out,
    solve again without it; when a solve without it fails, the pass that left it out is
    finished with it kept. ``left_out``: the frames left out before (a restart's)."""
    passes: list[_Pass] = []  # the passes that asked for another, outermost first
    while True:
        try:
            p = _pass(problem, jh, focal_sweep, left_out)
            if p.again is None:
                res = p.result if p.result is not None else _finish(p)
                break
        except DegenerateError as e:
            res = _fall_back(passes, e)
            break
        passes.append(p)
        problem = p.again
        if p.bad is not None:
            left_out = (*left_out, p.bad)
    for p in reversed(passes):  # the lines of what each pass left out, outermost first
        ra = res.robot_accuracy
        if ra is not None and p.gone is not None:
            ra = replace(ra, left_out=(p.gone, *ra.left_out))
        res = replace(res, messages=(*p.prefix, *res.messages), robot_accuracy=ra)
    return res


def _fall_back(passes: list[_Pass], error: DegenerateError) -> CalibrationResult:
    """The result of the innermost pass of ``passes`` that left an outlier out, finished with
    the outlier kept because the solve without it failed (``error``); the passes after it are
    dropped. ``error`` itself when no pass did."""
    while True:
        while passes and passes[-1].bad is None:
            passes.pop()
        if not passes:
            raise error
        p = passes.pop()
        p.notes.append(f"{p.bad.describe()}; it stays in the solve: without it, {error}")
        try:
            return _finish(p)
        except DegenerateError as e:
            error = e


def _pass(
    problem: CalibrationProblem,
    jh: bool,
    focal_sweep: bool,
    left_out: tuple[PoseOutlier | ImageOutlier, ...],
) -> _Pass:
    """One solve of ``problem`` with the frames ``left_out`` so far for their poses or images:
    the linear start, the refinement and the outlier tests."""
    check_problem(problem)
    full = problem
    problem, notes_skipped = usable_frames(problem)
    notes: list[str] = list(notes_skipped)
    groups = frame_groups(problem)
    zero = zero_distortion(problem.options.lens)
    K_lin = {}
    H_cache: dict = {}  # every camera's homographies, reused by the rig's pairs
    for c in problem.cameras:
        try:
            K_lin[c.name] = linear_camera(problem, c.name, groups, jh, notes, focal_sweep, H_cache)
        except DegenerateError as e:
            paired = record_check(problem)
            if paired is not None:  # the cause, told from the images alone
                raise DegenerateError(f"{paired} (the linear start failed: {e})") from None
            if not notes_skipped:
                raise
            raise DegenerateError(
                f"{e} ({len(full.frames) - len(problem.frames)} of {len(full.frames)} frames, "
                "and some images, were skipped because the target was not found in them: see "
                "whether the detection failed there)"
            ) from None
    ref = problem.reference
    for c in K_lin:
        if c == ref:
            continue
        try:  # the rig's joint linear step; the separate estimate stays when it cannot run
            K_lin[c] = linear_pair(problem, c, ref, groups, jh, H_cache)[0]
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
    missing = [i for i in range(len(problem.frames)) if i not in ref_poses]
    if missing and problem.knowledge == "none":  # each frame needs its own pose: skip it
        kept = tuple(f for i, f in enumerate(problem.frames) if i in ref_poses)
        ids = [problem.frames[i].id for i in missing]
        if len(kept) < 2:
            raise DegenerateError(
                f"the board pose could be computed in {len(kept)} frame(s) only (not in "
                f"frames {ids}): capture more frames with the whole target in view"
            )
        note = f"frames {ids}: no board pose could be computed from the image; skipped"
        again = replace(problem, frames=kept)
        return _Pass(problem, notes, again=again, prefix=(*notes_skipped, note))
    st = build_structure(problem)
    try:
        X, Y, s = init_motion(problem, ref_poses, groups, st)
    except DegenerateError:
        paired = record_check(problem)  # the cause told from the images alone, and it alone
        if paired is None:
            raise
        raise DegenerateError(paired) from None
    if apart:  # the measured robot motion carries the reference camera to their frames
        for c in apart:
            T_cam_ref[c] = _average_T(
                [
                    T_c_board @ inv_T(X[st.group_of_frame[i]] @ st.M[i] @ Y)
                    for i, T_c_board in poses[c].items()
                ]
            )
    init = ModelState(K_lin, {c: zero.copy() for c in K_lin}, T_cam_ref, X, Y, s)
    structure = _with_rotation(problem, st, X[0][:3, :3])
    out = refine(problem, structure, init, record_check=record_check)
    is_classic = problem.knowledge == "robot" and np.bincount(groups).max() == 1
    if not out.converged and is_classic and len(problem.cameras) == 1 and not focal_sweep:
        retry = _pipeline(full, jh, True, left_out)
        if retry.converged:
            note = (
                "the refinement from Zhang's start did not converge; it was restarted from the "
                "focal length that fits the images best through the robot poses"
            )
            return _Pass(problem, notes, result=replace(retry, messages=(*retry.messages, note)))
    p = _Pass(problem, notes, out, K_lin, groups)
    bad = pose_outlier(problem, out, groups) if out.converged else None
    if bad is None and out.converged:
        p.fit = final_free_pose_fit(out)  # the adequacy test's and the scale checks' poses
        bad = image_outlier(problem, out, p.fit)
    if bad is None:
        return p
    whole = [o for o in left_out if not getattr(o, "image_only", False)]  # frames, not images
    n_all = len(problem.frames) + len(whole)
    allowed = max(1, n_all // 10)
    if len(left_out) < allowed:
        others = {}  # a rig's frame keeps its other cameras' images
        if isinstance(bad, ImageOutlier):
            dets = problem.frames[bad.index].detections
            others = {c: d for c, d in dets.items() if c != bad.camera and len(d.ids)}
        image_only = bool(others)
        if image_only:
            bad = replace(bad, image_only=True)
            kept = tuple(
                replace(f, detections=others) if i == bad.index else f
                for i, f in enumerate(problem.frames)
            )
        else:
            kept = tuple(f for i, f in enumerate(problem.frames) if i != bad.index)
        stays = "; the frame's other images stay in it" if image_only else ""
        note = f"{bad.describe()}: {LEFT_OUT} ({bad.causes}){stays}; the session keeps it"
        p.again, p.bad, p.prefix = replace(problem, frames=kept), bad, (*notes_skipped, note)
        if not image_only:
            p.gone = (bad.frame, bad.translation_mm, bad.rotation_deg)
    elif isinstance(bad, PoseOutlier):  # images beyond it: the adequacy test weighs them
        notes.append(
            f"{bad.describe()}; no more than {allowed} of {n_all} frames are left out for "
            "their poses: check that each image is paired with the pose it was taken at"
        )
    return p


def _finish(p: _Pass) -> CalibrationResult:
    """The result of a pass's solve: its free-pose fit, the board's scale a classic session's
    images read, what is reported (:func:`slidecal.solver.uncertainty.reported_covariance`)
    and the checks on it."""
    problem, out = p.problem, p.out
    fit = final_free_pose_fit(out) if p.fit is None else p.fit
    if p.notes:
        out = replace(out, messages=out.messages + tuple(p.notes))
    scale = session_scale(problem, out, fit, p.groups)
    reported = reported_covariance(problem, out, p.groups, scale)
    return _result(problem, out, reported, p.K_lin, p.groups, fit)


def session_scale(
    problem: CalibrationProblem, out: RefineOutput, fit: FreePoseFit, groups: np.ndarray
) -> float:
    """How far a classic session's camera/robot length ratio is from 1 beyond what its fit can
    tell from noise (:func:`slidecal.solver.adequacy.classic_scale_fit`):
    ``sqrt(max(0, (ratio - 1)^2 - (2 se)^2))``, relative; 0 for any other session or where its
    geometry does not pin the ratio. The covariance carries it as the board's scale
    uncertainty: a classic session cannot tell a board's scale from the arm's."""
    poses = _fitted_poses(out, fit) if problem.knowledge == "robot" else {}
    if not classic(groups, poses):
        return 0.0
    scale = classic_scale_fit(problem, poses, static_rotation(out.state, problem.mount))
    if scale is None or scale[1] > MAX_CLASSIC_SCALE_SE:
        return 0.0
    ratio, se, _ = scale
    return float(np.sqrt(max(0.0, (ratio - 1.0) ** 2 - (2.0 * se) ** 2)))


def _field_note(
    problem: CalibrationProblem, out: RefineOutput, step: np.ndarray
) -> tuple[str, ...]:
    """A line saying how far a classic session's two readings of its arm's linear field put
    the hand-eye apart (``session_field_step``), from half a millimetre or 0.05 deg."""
    layout = layout_of(problem, out.model.st, out.state)
    frames = mount_names(layout.mount)  # a classic session's: a robot's mount
    d = named_step(layout, tuple(out.names), step)
    he = frames.hand_eye
    rot = [d.get(f"{he}.{a}", 0.0) for a in ("rx", "ry", "rz")]
    t = [d.get(f"{he}.{a}", 0.0) for a in ("tx", "ty", "tz")]
    rot_deg, t_mm = float(np.degrees(np.linalg.norm(rot))), float(1000.0 * np.linalg.norm(t))
    if rot_deg < 0.05 and t_mm < 0.5:
        return ()
    return (
        f"the arm's error varies linearly over the session's positions (learned from the "
        f"frames); read without that field, {he} would move by {rot_deg:.3f} deg and "
        f"{t_mm:.2f} mm: the images cannot tell which reading is the arm's, so it is reported "
        "halfway and the difference is in its uncertainty (docs/ROBOT_ACCURACY.md, "
        "'Two readings of the field')",
    )


def _correlation_note(
    problem: CalibrationProblem,
    seen: tuple[float, int] | None,
    misfit: tuple[int, float, float] | None,
) -> tuple[str, ...]:
    """A line when the covariance was read image by image: why (``images_err_together``: the
    neighbours' correlation, else one image's misfit)."""
    why = None
    if seen is not None:
        why = (
            f"the residuals of neighbouring corners go together (correlation {seen[0]:.2f} "
            f"over {seen[1]} pairs; about 0 when each corner's error is its own)"
        )
    elif misfit is not None:
        k, ratio, p = misfit
        why = (
            f"the residuals of frame {problem.frames[k].id} are {ratio:.2f} times the noise of "
            f"the session (p = {p:.1e} with each corner's error its own; a glare spot or a "
            "misplaced corner makes some of an image's corners err together)"
        )
    if why is None:
        return ()
    return (
        f"{why}: the uncertainty is taken from the images' spread, image by image "
        "(docs/METHOD.md Sec. 6)",
    )


def _grouped_note(grouped: tuple[float, int, float] | None) -> tuple[str, ...]:
    """A line when the covariance was read with the orientation groups as clusters."""
    if grouped is None:
        return ()
    stat, dof, p = grouped
    return (
        "the detections' errors go together over the frames of an orientation group (the "
        f"corners' mean residuals per group give chi-square {stat:.0f} on {dof} degrees of "
        f"freedom, p = {p:.1e} with each detection's error its own): the uncertainty is taken "
        "from the groups' spread, group by group (docs/METHOD.md Sec. 6)",
    )


def _result(
    problem: CalibrationProblem,
    out: RefineOutput,
    reported: Reported,
    K_lin: dict[str, np.ndarray],
    groups: np.ndarray,
    fit: FreePoseFit,
) -> CalibrationResult:
    """The result of a finished solve ``out`` as ``reported``, with its checks and notes."""
    model, st, state = out.model, out.model.st, reported.state
    named, images = reported.covariance, reported.images
    field_note = ()
    if reported.field_step is not None:
        field_note = _field_note(problem, out, reported.field_step)
    cams = {}
    for spec in problem.cameras:
        c = spec.name
        names = (*INTRINSIC_NAMES, *DISTORTION_NAMES) if named is not None else ()
        std = {n: v for n in names if (v := named.std(f"{c}.{n}")) is not None}
        n_px = len(out.inlier_rows)
        rows = (
            model.camera_rows(model.cams.index(c), n_px) & out.inlier_rows
            if c in model.cams
            else np.zeros(n_px, dtype=bool)
        )
        rms = _rms_px(out.residuals[:n_px][rows])
        cams[c] = CameraEstimate(c, spec.width, spec.height, state.K[c], state.dist[c], std, rms)
    unobs = dict(st.unobservable)
    o = problem.options
    for n, on in zip(o.distortion_names, o.distortion_mask, strict=True):
        if not on:
            unobs.setdefault(f"distortion.{n}", "fixed at 0 by the options")
    layout = layout_of(problem, st, state)
    frames = mount_names(layout.mount)
    hand_eye = T_target = None
    if frames is not None:
        he_name, tgt_name = frames.hand_eye, frames.target
        he_key = hand_eye_names(problem.mount, [c.name for c in problem.cameras])[problem.reference]
        rot_ok, t_ok = layout.rotation_reported, layout.translation_reported
        T_he = inv_T(state.X[0])
        hand_eye = _estimate(he_name, T_he, rot_ok, t_ok, named, he_key)
        # the target pose is tied to the hand-eye transform: what the data cannot determine of
        # one, it cannot determine of the other (no made-up numbers)
        if not rot_ok:
            unobs[f"{tgt_name}.R"] = (
                f"depends on the hand-eye rotation ({he_name}.R), which this session cannot "
                "determine; translate along at least two non-parallel directions"
            )
        if not t_ok:
            unobs[f"{tgt_name}.t"] = (
                f"depends on the hand-eye translation ({he_name}.t), which this session cannot "
                "determine; add orientations tilted about two non-parallel axes"
            )
        T_target = _estimate(tgt_name, state.Y, rot_ok, t_ok, named)
    rig = {}
    H_inf = {}
    ref = problem.reference
    for c, T in state.T_cam_ref.items():
        key = f"T_{c}_{ref}"
        rig[key] = _estimate(key, T, True, True, named)
        Hab = state.K[c] @ T[:3, :3] @ np.linalg.inv(state.K[ref])
        H_inf[f"{c}<-{ref}"] = Hab / Hab[2, 2]
    residuals = {ch.key: _rms_px(out.residuals[ch.rows]) for ch in model.chunks}
    adequacy, robot_accuracy = assess(problem, out, fit, groups)
    known = _fitted_poses(out, fit)  # the scale checks' poses; the model guesses the others'
    guesses = {i: model.T_ref_board(state, i) for i in range(len(problem.frames)) if i not in known}
    poses = image_poses(problem, state, guesses, known)
    checks = scale_checks(problem, state, groups, poses)
    if not checks and poses:  # a classic session whose geometry leaves its scale unchecked
        scale_note = unchecked_scale_note(
            problem, poses, static_rotation(state, problem.mount), groups
        )
    else:
        scale_note = ()
    return CalibrationResult(
        cameras=cams,
        hand_eye=hand_eye,
        rig=rig,
        T_target=T_target,
        converged=out.converged,
        iterations=out.iterations,
        reproj_rms_px=_rms_px(out.residuals[out.inlier_rows]),
        sigma_px=out.sigma_px,
        # the reported quantities (solver/uncertainty.py): robot-pose corrections and board
        # poses are nuisance parameters, marginalised
        parameter_names=reported.names,
        covariance=named.matrix if named is not None else None,
        residuals_px=residuals,
        outliers=out.outliers,
        unobservable=unobs,
        messages=out.messages
        + (
            _correlation_note(problem, images.correlated, images.misfit)
            + _grouped_note(images.grouped)
            if named is not None
            else ()
        )
        + field_note
        + bad_images_note(adequacy)
        + scale_note,
        scale_checks=checks,
        H_inf=H_inf,
        linear=K_lin,
        mount=problem.mount,
        reference_camera=ref,
        adequacy=adequacy,
        robot_accuracy=robot_accuracy,
        board=_board_shape(problem, reported.board),
    )


def _rms_px(r: np.ndarray) -> float:
    """Rms image error (px) of the pixel residuals ``r`` (u, v interleaved); nan for none."""
    return float(np.sqrt(np.mean(r**2) * 2)) if len(r) else float("nan")


def _estimate(
    name: str, T: np.ndarray, rot_ok: bool, t_ok: bool, named: NamedCovariance | None, key: str = ""
) -> TransformEstimate:
    """``T`` (4, 4) as the result reports it: its rotation and translation where observable,
    with their stds from ``named`` under ``key`` (or ``name``)."""
    key = key or name
    return TransformEstimate(
        name,
        T[:3, :3] if rot_ok else None,
        T[:3, 3] if t_ok else None,
        named.std_rot_deg(key) if named is not None else None,
        named.std_t_mm(key) if named is not None else None,
    )


def _board_shape(problem: CalibrationProblem, fit: BoardFit | None) -> BoardShape | None:
    """The result's :class:`BoardShape` of a board fit (None without one)."""
    if fit is None or (problem.target.flatness_m <= 0 and problem.target.print_tolerance <= 0):
        return None  # a board described as exact: a scale carried for the session alone
    sd = np.sqrt(np.clip(np.diag(fit.bow_cov), 0.0, None))
    return BoardShape(
        (float(1000.0 * fit.bow_m[0]), float(1000.0 * fit.bow_m[1])),
        (float(1000.0 * sd[0]), float(1000.0 * sd[1])),
        float(1000.0 * problem.target.flatness_m),
        float(problem.target.print_tolerance),
    )


def _fitted_poses(out: RefineOutput, fit: FreePoseFit) -> dict[int, np.ndarray]:
    """The reference camera's ``T_cam_board`` per frame index from a free-pose fit at this
    state's intrinsics, for the images without a flagged detection: the PnP minimum
    :func:`scale_checks` would compute again."""
    m = out.model
    return {
        ch.frame_index: fit.T_cam_board[(ch.frame_index, m.ref)]
        for ch in m.chunks
        if ch.camera == m.ref
        and (ch.frame_index, m.ref) in fit.T_cam_board
        and out.inlier_rows[ch.rows].all()
    }


def image_poses(
    problem: CalibrationProblem,
    state: ModelState,
    guesses: dict[int, np.ndarray] | None = None,
    known: dict[int, np.ndarray] | None = None,
) -> dict[int, np.ndarray]:
    """The reference camera's ``T_cam_board`` per frame index from its image alone (PnP with
    the final intrinsics; ``guesses`` only start it), for the frames ``known`` does not hold
    already; {} for a session without robot poses."""
    if problem.knowledge != "robot":
        return {}
    ref = problem.reference
    poses = dict(known or {})
    todo = [i for i in range(len(problem.frames)) if i not in poses]
    if todo:
        poses.update(
            _frame_poses(problem, ref, state.K[ref], state.dist[ref], guesses=guesses, only=todo)
        )
    return poses


def scale_checks(
    problem: CalibrationProblem,
    state: ModelState,
    groups: np.ndarray,
    poses: dict[int, np.ndarray],
) -> tuple[ScaleCheck, ...]:
    """Per move (:func:`slidecal.solver.adequacy.scale_moves`): its length as the reference
    camera saw it (``poses``: frame index -> ``T_cam_board``, :func:`image_poses`) against the
    robot's; a ratio away from 1 means a wrong square size or robot/TCP scale."""
    if problem.knowledge != "robot":
        return ()
    moves = scale_moves(problem, poses, static_rotation(state, problem.mount), groups, 0.001)
    ids = [f.id for f in problem.frames]
    return tuple(ScaleCheck(ids[a], ids[b], 1000.0 * r, 1000.0 * c) for a, b, r, c in moves)
