"""Does the model explain the data? The detector's noise, measured without the robot model.

A robot-pose model that is wrong (poses taken as exact when the arm errs by a millimetre, angles
in degrees read as radians, a wrong square size) leaves residuals larger than the detector's
noise. To say so, the detector's noise must be known independently of the robot poses: here it
is the residual of a fit of every image alone, with the solution's intrinsics and distortion and
a free board pose per image (:func:`free_pose_fit`). That residual is the floor of the detector
and the lens model; what the robot model leaves above it is the robot model's share.

:func:`assess` compares the two per camera and per image, reads the robot's accuracy as the
camera saw it (the per-frame pose corrections of the refinement) and marks the result unusable,
with the figure and its limit, when the model cannot explain the data.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from slidecal.solver.camera import project
from slidecal.solver.geometry import T_from_Rt
from slidecal.solver.result import ModelAdequacy, RobotAccuracy

if TYPE_CHECKING:
    from slidecal.solver.problem import CalibrationProblem
    from slidecal.solver.refine import RefineOutput

#: A camera whose robot-model residual exceeds its free-pose (detector) floor by this factor is
#: not explained by the model (about 1.0 when it is; sampling spread a few percent).
MAX_NORMALISED_RMS = 1.5
#: One image this far above the floor: the frame's pose or detection is wrong.
MAX_FRAME_NORMALISED_RMS = 4.0
#: Robot accuracy beyond anything a working arm has (ISO 9283 accuracy of uncalibrated
#: industrial arms: about 1 mm and 0.2 deg): units or frames are wrong, not the arm.
MAX_ROBOT_TRANSLATION_MM = 10.0
MAX_ROBOT_ROTATION_DEG = 1.0
#: The free-pose fit itself above this: the lens model or the detections are wrong (a corner
#: detector on a sharp image is good to a few tenths of a pixel).
MAX_DETECTOR_NOISE_PX = 1.5
#: The robot's translation errors growing with the moves like this (the camera sees the moves
#: this much longer or shorter than the robot reports): a wrong square size or robot units, not
#: an arm's accuracy (real arms: 0.1-0.5 % with a printed board's own scale error).
MAX_SCALE_ERROR = 0.02


@dataclass(frozen=True)
class FreePoseFit:
    """Per image ``(frame index, camera)``: residual sum of squares (pixels^2), rows used and
    the fitted ``T_cam_board``; ``sigma_px`` per camera: ``sqrt(sum rss / sum(rows - 6))``."""

    rss: dict[tuple[int, str], float]
    rows: dict[tuple[int, str], int]
    T_cam_board: dict[tuple[int, str], np.ndarray]
    sigma_px: dict[str, float]


def free_pose_fit(
    images: list[tuple[int, str, np.ndarray, np.ndarray]],
    K: dict[str, np.ndarray],
    dist: dict[str, np.ndarray],
    starts: dict[tuple[int, str], np.ndarray] | None = None,
    closed_form: bool = True,
) -> FreePoseFit:
    """Fit a free board pose to every image with fixed intrinsics and distortion.

    ``images``: (frame index, camera, board points (n, 3), pixels (n, 2)) of the inlier
    detections. Each pose is the reprojection-error minimum of OpenCV's iterative PnP, started
    from the better of ``starts`` (``T_cam_board`` per (frame index, camera), e.g. the robot
    model's prediction) and the closed-form planar solution (IPPE), so that a wildly wrong
    robot model cannot spoil the floor it is judged against. Images with fewer than 4 points
    are skipped. The candidate poses are scored for all images at once (one projection per
    camera), not image by image. ``closed_form`` False: the closed form only for the images
    without a start, or whose start PnP does not refine (the starts are free-pose minima
    already, e.g. of an earlier fit).
    """
    todo = [
        (fi, cam, pts.astype(np.float64), px.astype(np.float64))
        for fi, cam, pts, px in images
        if len(pts) >= 4
    ]
    starts = starts or {}
    refined: list[np.ndarray | None] = []
    closed: list[np.ndarray | None] = []
    for fi, cam, obj, img in todo:
        T0 = starts.get((fi, cam))
        good_start = T0 is not None and T0[2, 3] > 0
        refined.append(_pnp(obj, img, K[cam], dist[cam], T0) if good_start else None)
        if good_start and not closed_form and refined[-1] is not None:
            closed.append(None)
            continue
        ok, rv, tv = cv2.solvePnP(obj, img, K[cam], dist[cam], flags=cv2.SOLVEPNP_IPPE)
        closed.append(T_from_Rt(cv2.Rodrigues(rv)[0], tv.reshape(3)) if ok else None)
    best = _scored(todo, refined, K, dist)
    closed_rss = _scored(todo, closed, K, dist)
    # the closed form is refined only when it beats the refined model start (a wrong robot
    # model starting the pose in the wrong basin)
    alt: list[np.ndarray | None] = [None] * len(todo)
    for k, (_, cam, obj, img) in enumerate(todo):
        if closed_rss[k] is not None and (best[k] is None or closed_rss[k] < best[k]):
            alt[k] = _pnp(obj, img, K[cam], dist[cam], closed[k])
    alt_rss = _scored(todo, alt, K, dist)
    rss: dict[tuple[int, str], float] = {}
    rows: dict[tuple[int, str], int] = {}
    poses: dict[tuple[int, str], np.ndarray] = {}
    sums: dict[str, list[float]] = {}
    for k, (fi, cam, obj, _) in enumerate(todo):
        T, e = refined[k], best[k]
        if alt_rss[k] is not None and (e is None or alt_rss[k] < e):
            T, e = alt[k], alt_rss[k]
        if e is None:
            continue
        key = (fi, cam)
        rss[key], rows[key], poses[key] = e, 2 * len(obj), T
        acc = sums.setdefault(cam, [0.0, 0])
        acc[0] += e
        acc[1] += 2 * len(obj) - 6
    sigma = {c: float(np.sqrt(t / d)) if d > 0 else float("nan") for c, (t, d) in sums.items()}
    return FreePoseFit(rss, rows, poses, sigma)


def _scored(
    todo: list[tuple[int, str, np.ndarray, np.ndarray]],
    poses: list[np.ndarray | None],
    K: dict[str, np.ndarray],
    dist: dict[str, np.ndarray],
) -> list[float | None]:
    """Per image of ``todo`` (frame index, camera, board points, pixels): the residual sum of
    squares (pixels^2) of its board pose ``T_cam_board`` in ``poses``; None without a pose or
    with the board behind the camera. One projection per camera for all its images."""
    out: list[float | None] = [None] * len(todo)
    for cam in dict.fromkeys(c for _, c, _, _ in todo):
        sel = [k for k, (_, c, _, _) in enumerate(todo) if c == cam and poses[k] is not None]
        if not sel:
            continue
        n = np.array([len(todo[k][2]) for k in sel])
        T = np.repeat(np.stack([poses[k] for k in sel]), n, axis=0)  # each point's pose
        obj = np.concatenate([todo[k][2] for k in sel])
        P = np.einsum("nij,nj->ni", T[:, :3, :3], obj) + T[:, :3, 3]
        e = project(K[cam], dist[cam], P) - np.concatenate([todo[k][3] for k in sel])
        first = np.concatenate([[0], np.cumsum(n)[:-1]])
        rss = np.add.reduceat(np.sum(e * e, axis=1), first)
        front = np.minimum.reduceat(P[:, 2], first) > 0
        for k, r, f in zip(sel, rss, front, strict=True):
            if f:
                out[k] = float(r)
    return out


def _pnp(
    obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray, T0: np.ndarray
) -> np.ndarray | None:
    """OpenCV's iterative PnP (the reprojection-error minimum) started at ``T0``: the pose
    ``T_cam_board``, or None when it fails."""
    rv0 = cv2.Rodrigues(T0[:3, :3])[0]
    ok, rv, tv = cv2.solvePnP(
        obj, img, K, dist, rv0, T0[:3, 3].reshape(3, 1).copy(), True, cv2.SOLVEPNP_ITERATIVE
    )
    if not ok:
        return None
    return T_from_Rt(cv2.Rodrigues(rv)[0], tv.reshape(3))


def session_images(out: RefineOutput) -> list[tuple[int, str, np.ndarray, np.ndarray]]:
    """The inlier detections of a refinement as ``free_pose_fit`` takes them."""
    images = []
    for ch in out.model.chunks:
        keep = out.inlier_rows[ch.rows][0::2]
        images.append((ch.frame_index, ch.camera, ch.points[keep], ch.px[keep]))
    return images


def model_starts(out: RefineOutput) -> dict[tuple[int, str], np.ndarray]:
    """``T_cam_board`` per (frame index, camera) as the refined robot model predicts it."""
    m, state = out.model, out.state
    starts = {}
    for ch in m.chunks:
        T = m.T_ref_board(state, ch.frame_index)
        if ch.camera != m.ref:
            T = state.T_cam_ref[ch.camera] @ T
        starts[(ch.frame_index, ch.camera)] = T
    return starts


def _parameters_used(out: RefineOutput) -> dict[str, float]:
    """Per camera: how many parameters its inlier pixel rows pay for (the trace of the hat
    matrix over those rows; pose corrections under a prior count by how much the pixels, not
    the prior, determine them). Rows weigh alike: exact for one camera, close for rigs whose
    cameras' noise levels are alike."""
    m = out.model
    n_px = len(out.inlier_rows)
    # pixel rows, then one prior row per pose-correction coordinate (the shared ones, then the
    # frames'; they are the last columns)
    n_all = n_px + (len(m.names) - m.shared_start if "E" in m.slices else 0)
    w = np.ones(n_all)
    w[:n_px] = out.inlier_rows
    normal = m.normal_blocks(out.state, w)
    # the blocks of the inverse that are needed: the refinement's covariance over s^2 when it
    # was made with these weights (one camera: the solve's own row weights are these), else
    # inverted here
    same = m.row_weights is not None and np.array_equal(m.row_weights, w)
    if same and out.covariance_blocks is not None and out.sigma_px > 0:
        Ni = out.covariance_blocks.scaled(1.0 / out.sigma_px**2)
    else:
        Ni = normal.inverse()
    used = {}
    for ci, c in enumerate(m.cams):
        wc = np.where(m.camera_rows(ci, n_all), w, 0.0)
        used[c] = Ni.trace_with(m.normal_blocks(out.state, wc))
    return used


def final_free_pose_fit(out: RefineOutput) -> FreePoseFit:
    """The free-pose fit of a refinement's inlier detections at its final intrinsics: the robot
    test's when the refinement kept it as its own (same detections, intrinsics and starts);
    started from the robot test's poses when the refinement went on to learn the arm's accuracy
    (free minima at nearly the same intrinsics: no closed form needed); else started from the
    refinement's predictions, with the closed form as a guard."""
    if out.free_pose is not None:
        return out.free_pose
    images = session_images(out)
    if out.test_fit is not None:  # its poses: the free minima at nearly these intrinsics
        return free_pose_fit(
            images, out.state.K, out.state.dist, out.test_fit.T_cam_board, closed_form=False
        )
    return free_pose_fit(images, out.state.K, out.state.dist, model_starts(out))


def assess(
    problem: CalibrationProblem,
    out: RefineOutput,
    fit: FreePoseFit | None = None,
    groups: np.ndarray | None = None,
) -> tuple[ModelAdequacy, RobotAccuracy | None]:
    """The model-adequacy test and the robot's accuracy of a refinement (see the module doc).

    ``fit``: :func:`final_free_pose_fit` of ``out``, ``groups``: the frames' orientation groups
    (robot sessions), when the caller already has them."""
    if fit is None:
        fit = final_free_pose_fit(out)
    m = out.model
    reasons: list[str] = []
    per_frame: list[tuple[int, str, float]] = []
    normalised: dict[str, float] = {}
    frame_ids = [f.id for f in problem.frames]
    used = _parameters_used(out)
    for c in m.cams:
        sig = fit.sigma_px.get(c, float("nan"))
        chunks = [ch for ch in m.chunks if ch.camera == c]
        rss = n = 0.0
        for ch in chunks:
            inl = out.inlier_rows[ch.rows]
            r = out.residuals[ch.rows][inl]
            if len(r) == 0:
                continue
            rss += float(r @ r)
            n += len(r)
            if sig > 0:
                per_frame.append(
                    (int(frame_ids[ch.frame_index]), c, float(np.sqrt(np.mean(r * r)) / sig))
                )
        if not (sig > 0) or n == 0:
            continue
        # the robot model's noise estimate against the floor, each from its own redundancy:
        # the image-wise fit spends 6 rows per image on its pose, the robot model the share of
        # its parameters (pose corrections under their prior count in part) this camera's rows
        # carry; both estimate the detector's noise when the model is adequate, whatever the
        # number of points per image
        redundancy = max(n - used.get(c, 0.0), 1.0)
        normalised[c] = float(np.sqrt(rss / redundancy) / sig)
        if normalised[c] > MAX_NORMALISED_RMS:
            reasons.append(
                f"camera {c!r}: the residuals are {normalised[c]:.2f} times the detector's noise "
                f"({sig:.3f} px from a free pose per image; limit {MAX_NORMALISED_RMS}): the robot "
                "poses or the model do not explain the images"
            )
        if sig > MAX_DETECTOR_NOISE_PX:
            reasons.append(
                f"camera {c!r}: even a free board pose per image leaves {sig:.2f} px rms (limit "
                f"{MAX_DETECTOR_NOISE_PX} px): the lens model, the target description or the "
                "detections are wrong"
            )
    per_frame.sort(key=lambda x: -x[2])
    bad = [f for f in per_frame if f[2] > MAX_FRAME_NORMALISED_RMS]
    if bad:
        reasons.append(
            f"{len(bad)} image(s) above {MAX_FRAME_NORMALISED_RMS} times the detector's noise "
            f"(worst: frame {bad[0][0]} {bad[0][1]!r}, {bad[0][2]:.1f}): check those frames' "
            "poses and detections"
        )
    robot = robot_accuracy(problem, out)
    k = _move_scale(problem, fit, m.ref, groups)
    if k is not None and abs(k) > MAX_SCALE_ERROR:
        reasons.append(
            f"the camera sees the robot's moves {100 * k:+.1f} % longer than the robot reports "
            f"(limit {100 * MAX_SCALE_ERROR:.0f} %): check the target's square_size_m and that "
            "the robot poses are in metres"
        )
    if robot is not None:
        if robot.translation_mm > MAX_ROBOT_TRANSLATION_MM:
            reasons.append(
                f"the robot poses would be off by {robot.translation_mm:.1f} mm rms per axis "
                f"(limit {MAX_ROBOT_TRANSLATION_MM} mm): check the pose units (metres), the "
                "square size and the TCP"
            )
        if robot.rotation_deg > MAX_ROBOT_ROTATION_DEG:
            reasons.append(
                f"the robot orientations would be off by {robot.rotation_deg:.2f} deg rms per "
                f"axis (limit {MAX_ROBOT_ROTATION_DEG} deg): check that rotations are axis-angle "
                "vectors in radians and the frame conventions"
            )
    adequacy = ModelAdequacy(
        detector_noise_px=dict(fit.sigma_px),
        normalised_rms=normalised,
        worst_frames=tuple(per_frame[:5]),
        adequate=not reasons,
        reasons=tuple(reasons),
    )
    return adequacy, robot


def _move_scale(
    problem: CalibrationProblem, fit: FreePoseFit, ref: str, groups: np.ndarray | None = None
) -> float | None:
    """Median over the moves at one orientation of (camera-seen length / robot length) - 1.

    The camera's own view of each move (free board poses of the reference camera: the camera
    centre eye-in-hand, the board origin eye-to-hand) against the measured tool translation;
    None without such moves (of at least 5 mm). ``groups``: ``orientation_groups`` of the
    measured poses when the caller has them.
    """
    if problem.knowledge != "robot":
        return None
    from slidecal.solver.refine import orientation_groups

    T = np.stack([f.T_base_tool for f in problem.frames])
    groups = orientation_groups(T) if groups is None else groups
    ratios = []
    for g in np.unique(groups):
        idx = [i for i in np.flatnonzero(groups == g) if (i, ref) in fit.T_cam_board]
        for a, b in zip(idx[:-1], idx[1:], strict=True):
            robot = float(np.linalg.norm(T[b, :3, 3] - T[a, :3, 3]))
            if robot < 0.005:
                continue
            Ta, Tb = fit.T_cam_board[(a, ref)], fit.T_cam_board[(b, ref)]
            if problem.mount == "eye_in_hand":
                seen = np.linalg.norm(Ta[:3, :3].T @ Ta[:3, 3] - Tb[:3, :3].T @ Tb[:3, 3])
            else:
                seen = np.linalg.norm(Tb[:3, 3] - Ta[:3, 3])
            ratios.append(seen / robot)
    return float(np.median(ratios)) - 1.0 if ratios else None


def robot_accuracy(problem: CalibrationProblem, out: RefineOutput) -> RobotAccuracy | None:
    """The robot's pose accuracy the refinement estimated (None without robot poses)."""
    if problem.knowledge != "robot":
        return None
    sig = out.robot_sigma
    if sig is None:
        return None
    worst: list[tuple[int, float, float]] = []
    E = out.model.pose_corrections(out.state)
    if E is not None:
        for f, e in zip(problem.frames, E, strict=True):
            worst.append(
                (
                    int(f.id),
                    float(1000.0 * np.linalg.norm(e[3:])),
                    float(np.degrees(np.linalg.norm(e[:3]))),
                )
            )
        worst.sort(
            key=lambda w: (
                -(w[1] / max(1000.0 * sig[1], 1e-6) + w[2] / max(np.degrees(sig[0]), 1e-9))
            )
        )
    return RobotAccuracy(
        translation_mm=float(1000.0 * sig[1]),
        rotation_deg=float(np.degrees(sig[0])),
        worst_frames=tuple(worst[:5]),
        estimated=out.robot_sigma_estimated,
    )
