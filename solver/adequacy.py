"""Does the model explain the data? :func:`assess` holds the robot model's residuals against
the free-pose floor (:func:`free_pose_fit`) per camera and per image, reads the robot's accuracy
from the pose corrections and marks the result unusable, with the figure and its limit, when the
model cannot explain the data; the record checks tell wrongly read or paired robot records from
the images alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np

from slidecal.solver.detect import board_poses, half_turn_symmetric, half_turn_T, half_turns
from slidecal.solver.free_pose import FreePoseFit, free_pose_fit, model_starts, session_images
from slidecal.solver.geometry import (
    R_from_quat_wxyz,
    Rx,
    Ry,
    Rz,
    T_from_Rt,
    inv_T,
    project_to_SO3,
    quat_wxyz_from_R,
    rotation_angle_deg,
)
from slidecal.solver.model import ModelState
from slidecal.solver.numeric import distinct, median
from slidecal.solver.problem import CalibrationProblem
from slidecal.solver.refine import RefineOutput
from slidecal.solver.result import ModelAdequacy, RobotAccuracy

#: Robot-model residuals over the free-pose (detector) floor beyond which a camera is unexplained.
MAX_NORMALISED_RMS = 1.5
#: One image this far above the floor: the frame's pose or detection is wrong.
MAX_FRAME_NORMALISED_RMS = 4.0
#: Such images' share of the session's squares from which the result leans on them: unusable.
MAX_BAD_IMAGE_SHARE = 0.1
#: Robot accuracy beyond any working arm: units or frames are wrong, not the arm.
MAX_ROBOT_TRANSLATION_MM = 10.0
MAX_ROBOT_ROTATION_DEG = 1.0
#: The free-pose fit itself above this: the lens model or the detections are wrong.
MAX_DETECTOR_NOISE_PX = 1.5
#: Moves seen this much longer or shorter than the robot reports: a wrong square size or unit.
MAX_SCALE_ERROR = 0.02


def _parameters_used(out: RefineOutput) -> dict[str, float]:
    """Per camera: how many parameters its inlier pixel rows pay for (the trace of the hat
    matrix over those rows; pose corrections under a prior count by how much the pixels, not
    the prior, determine them). Rows weigh alike: exact for one camera, close for rigs whose
    cameras' noise levels are alike."""
    m = out.model
    n_px = len(out.inlier_rows)
    # pixel rows, then one prior row per pose-correction coordinate (the last columns)
    n_all = n_px + (len(m.names) - m.shared_start if "E" in m.slices else 0)
    w = np.ones(n_all)
    w[:n_px] = out.inlier_rows
    normal = m.normal_blocks(out.state, w)
    # the refinement's covariance over s^2 when made with these weights, else inverted here
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
    test's when the refinement kept it, started from its poses when the refinement went on to
    learn the arm's accuracy, else from the refinement's predictions."""
    if out.free_pose is not None:
        return out.free_pose
    images = session_images(out.model, out.inlier_rows)
    if out.test_fit is not None:  # its poses: the free minima at nearly these intrinsics
        return free_pose_fit(
            images, out.state.K, out.state.dist, out.test_fit.T_cam_board, closed_form=False
        )
    return free_pose_fit(images, out.state.K, out.state.dist, model_starts(out.model, out.state))


def _image_scores(out: RefineOutput, fit: FreePoseFit) -> list[tuple[int, str, float, float, int]]:
    """Every image's (frame index, camera, rms of its inlier residuals over its camera's
    free-pose floor, sum of their squares, their count); images of a camera without a floor
    or without inliers are left out."""
    scores = []
    for ch in out.model.chunks:
        sig = fit.sigma_px.get(ch.camera, float("nan"))
        r = out.residuals[ch.rows][out.inlier_rows[ch.rows]]
        if len(r) and sig > 0:
            rr = float(r @ r)
            scores.append(
                (ch.frame_index, ch.camera, float(np.sqrt(rr / len(r)) / sig), rr, len(r))
            )
    return scores


@dataclass(frozen=True)
class ImageOutlier:
    """An image whose residuals are far beyond its camera's detector noise
    (:data:`MAX_FRAME_NORMALISED_RMS`): ``index`` (position in the problem's frames),
    ``frame`` (id), ``camera``, ``ratio`` (its rms over the noise), ``noise_px`` (the noise:
    the free-pose fit's). ``image_only``: the frame's other cameras' images stay in the solve
    (a rig's frame), only this image is left out."""

    index: int
    frame: int
    camera: str
    ratio: float
    noise_px: float
    translation_mm: float  # the frame's pose correction (the record of a frame left out)
    rotation_deg: float
    image_only: bool = False
    causes: ClassVar[str] = (
        "a corner misplaced by a glare or a blur, or misdetected; or a pose the arm did not reach"
    )

    def describe(self) -> str:
        """One line: the frame, its image and how far off."""
        return (
            f"frame {self.frame}: its image of {self.camera!r} has residuals {self.ratio:.1f} "
            f"times the detector's noise ({self.noise_px:.3f} px from a free pose per image)"
        )


def image_outlier(
    problem: CalibrationProblem, out: RefineOutput, fit: FreePoseFit
) -> ImageOutlier | None:
    """The robot session's image farthest beyond :data:`MAX_FRAME_NORMALISED_RMS` times its
    camera's detector noise, None when every image is within it (or without robot poses: an
    image-only model poses each image freely, as the floor does)."""
    if problem.knowledge != "robot":
        return None
    scores = _image_scores(out, fit)
    if not scores:
        return None
    k, cam, ratio, _, _ = max(scores, key=lambda x: x[2])
    if ratio <= MAX_FRAME_NORMALISED_RMS:
        return None
    E = out.model.pose_corrections(out.state)
    e = np.zeros(6) if E is None else E[k]
    return ImageOutlier(
        k,
        int(problem.frames[k].id),
        cam,
        ratio,
        float(fit.sigma_px[cam]),
        float(1000.0 * np.linalg.norm(e[3:])),
        float(np.degrees(np.linalg.norm(e[:3]))),
    )


def assess(
    problem: CalibrationProblem,
    out: RefineOutput,
    fit: FreePoseFit,
    groups: np.ndarray,
) -> tuple[ModelAdequacy, RobotAccuracy | None]:
    """The model-adequacy test and the robot's accuracy of a refinement (see the module doc).

    ``fit``: :func:`final_free_pose_fit` of ``out``, ``groups``: the frames' orientation groups
    (robot sessions)."""
    m = out.model
    reasons: list[str] = []
    frame_ids = [f.id for f in problem.frames]
    scores = _image_scores(out, fit)
    per_frame = [(int(frame_ids[k]), c, ratio) for k, c, ratio, _, _ in scores]
    # each image's squares beyond its floor, and the session's squares
    beyond = {(int(frame_ids[k]), c): rr - n * fit.sigma_px[c] ** 2 for k, c, _, rr, n in scores}
    squares = sum(rr for *_, rr, _ in scores)
    normalised: dict[str, float] = {}
    used = _parameters_used(out)
    for c in m.cams:
        sig = fit.sigma_px.get(c, float("nan"))
        rss = sum(rr for _, cam, _, rr, _ in scores if cam == c)
        n = sum(k for _, cam, _, _, k in scores if cam == c)
        if not (sig > 0) or n == 0:
            continue
        # the robot model's noise against the floor, each over its own redundancy (the
        # free-pose fit spends 6 rows per image, the robot model this camera's share of its
        # parameters)
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
    share = sum(beyond[f[:2]] for f in bad) / squares if bad and squares > 0 else 0.0
    if bad and share >= MAX_BAD_IMAGE_SHARE:
        reasons.append(
            f"{len(bad)} image(s) above {MAX_FRAME_NORMALISED_RMS} times the detector's noise "
            f"(worst: frame {bad[0][0]} {bad[0][1]!r}, {bad[0][2]:.1f}; "
            f"{100 * share:.0f} % of the session's squares): check those frames' poses and "
            "detections"
        )
    robot = robot_accuracy(problem, out)
    moves = []  # of 5 mm or more, as the reference camera's free poses and the robot see them
    if problem.knowledge == "robot":
        poses = {i: T for (i, cam), T in fit.T_cam_board.items() if cam == m.ref}
        R_static = static_rotation(out.state, problem.mount)
        moves = scale_moves(problem, poses, R_static, groups, 0.005)
    k = median([c / r for _, _, r, c in moves]) - 1.0 if moves else 0.0
    if abs(k) > MAX_SCALE_ERROR:
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
    if (reasons or not out.converged) and (paired := record_check(problem)) is not None:
        # the cause, told from the images alone: the other figures come from wrong records
        reasons[:] = [paired]
    adequacy = ModelAdequacy(
        detector_noise_px=dict(fit.sigma_px),
        normalised_rms=normalised,
        worst_frames=tuple(per_frame[:5]),
        adequate=not reasons,
        reasons=tuple(reasons),
    )
    return adequacy, robot


#: The robot's and the camera's rotation angles between two frames agree to this when paired.
MAX_PAIRING_ROTATION_DEG = 0.5
#: Pairs of frames whose relative rotation (robot's or camera's) is at least this are tested by
#: their rotation angles; pairs below ``PAIRING_SAME_ORIENTATION_DEG`` by their move lengths.
PAIRING_MIN_ROTATION_DEG = 2.0
PAIRING_SAME_ORIENTATION_DEG = 0.5
#: A pure move's camera/robot length ratio, over the session's median, agrees to this when paired.
MAX_PAIRING_LENGTH = 0.05
#: Shifts of the poses against the images that are tried, in frames.
PAIRING_SHIFTS = (-2, -1, 1, 2)


def _images_alone(
    problem: CalibrationProblem, min_points: int = 6
) -> tuple[list[int], list[np.ndarray]] | None:
    """The reference camera's board poses ``T_cam_board`` from the images alone
    (:func:`board_poses`) on the images with ``min_points`` points or more, and the frame
    indices they belong to; None when the session cannot give them (no robot poses, one
    orientation, fewer than 4 such images)."""
    if problem.knowledge != "robot":
        return None
    T_tool = np.stack([f.T_base_tool for f in problem.frames])
    spread = max(rotation_angle_deg(T_tool[0, :3, :3], T[:3, :3]) for T in T_tool)
    if spread < PAIRING_MIN_ROTATION_DEG:  # one orientation: no pose from the images alone
        return None
    seen = board_poses(problem, problem.reference, min_points)
    return (list(seen), list(seen.values())) if len(seen) >= 4 else None


def record_check(problem: CalibrationProblem) -> str | None:
    """What is wrong with the robot's records, told from the images alone: read in another
    convention (:func:`convention_check`: one reading then fits every frame), else paired with
    the wrong images (:func:`_pairing`; a rotation read in the wrong convention also
    changes the angles between frames, so the convention is asked first). One OpenCV
    calibration for both; None when neither is found. Run it for a result already in doubt."""
    seen = _images_alone(problem)
    if seen is None:
        return convention_check(problem)  # a lone tag's images: that test alone
    return _convention(problem, *seen) or _pairing(problem, *seen)


def _pairing(problem: CalibrationProblem, frames: list[int], T_cam: list[np.ndarray]) -> str | None:
    """Whether the robot poses and the images are paired as recorded, told without the robot
    model from the images-alone poses ``T_cam`` of ``frames``: the reference camera's motion
    between every two frames must have the robot's rotation angle, and a pure move the robot's
    length up to one scale (limits ``MAX_PAIRING_ROTATION_DEG``, ``MAX_PAIRING_LENGTH``). Names
    the shift of ``PAIRING_SHIFTS`` that fits, or the frames that disagree; None when they agree
    or the session cannot tell."""
    T_tool = np.stack([f.T_base_tool for f in problem.frames])

    def scores(shift: int, T_cam: list[np.ndarray] = T_cam) -> dict[tuple[int, int], float]:
        seen = moving_point(np.stack(T_cam), problem.mount)
        rot: dict[tuple[int, int], float] = {}
        length: dict[tuple[int, int], float] = {}
        for a in range(len(frames)):
            for b in range(a + 1, len(frames)):
                i, j = frames[a] + shift, frames[b] + shift
                if not (0 <= i < len(T_tool) and 0 <= j < len(T_tool)):
                    continue
                robot = rotation_angle_deg(T_tool[i, :3, :3].T @ T_tool[j, :3, :3])
                camera = rotation_angle_deg(T_cam[a][:3, :3], T_cam[b][:3, :3])
                if max(robot, camera) >= PAIRING_MIN_ROTATION_DEG:
                    rot[(a, b)] = abs(robot - camera) / MAX_PAIRING_ROTATION_DEG
                elif max(robot, camera) < PAIRING_SAME_ORIENTATION_DEG:
                    move = float(np.linalg.norm(T_tool[j, :3, 3] - T_tool[i, :3, 3]))
                    if move >= 0.005:
                        length[(a, b)] = float(np.linalg.norm(seen[b] - seen[a])) / move
        if length:
            k = median(list(length.values()))
            length = {p: abs(v / k - 1.0) / MAX_PAIRING_LENGTH for p, v in length.items()}
        return rot | length

    recorded = scores(0)
    if len(recorded) < 3:
        return None
    what = (
        "the robot poses disagree with the camera's own view of the motion (the images alone: "
        f"rotation angles between frames to {MAX_PAIRING_ROTATION_DEG} deg, move lengths to "
        f"{100 * MAX_PAIRING_LENGTH:.0f} %)"
    )
    overall = median(list(recorded.values()))
    bad = []
    for a in range(len(frames)):
        mine = [v for (p, q), v in recorded.items() if a in (p, q)]
        if len(mine) >= 3 and median(mine) > 1.0:
            bad.append(int(problem.frames[frames[a]].id))
    if overall <= 1.0 and not bad:
        return None
    wrong = float(np.mean(np.array(list(recorded.values())) > 1.0))
    if half_turn_symmetric(problem.target):  # a board read the other way round, not a pairing
        turned = half_turns([T[:3, :3] for T in T_cam], [T_tool[k, :3, :3] for k in frames])[0]
        H = half_turn_T(problem.target)
        again = [T @ H if turned[a] else T for a, T in enumerate(T_cam)]
        sc = np.array(list(scores(0, again).values()))
        if turned.any() and median(sc) <= 1.0 and np.mean(sc > 1.0) < wrong / 3:
            sx, sy = problem.target.squares_x, problem.target.squares_y
            return (
                f"frames {[int(problem.frames[frames[a]].id) for a in np.flatnonzero(turned)]}: "
                f"{what} until their board is turned by half a turn: the {sx} x {sy}-square "
                "chessboard looks the same after a half turn and its corner 0 was read at the "
                "opposite corner there, not a pairing fault; slidecal's solve turns such frames "
                "back by the robot's rotations, or use a board with one odd and one even count "
                "of squares"
            )
    shifted = []  # (fraction of pairs that disagree, shift) of the shifts that fit
    for shift in PAIRING_SHIFTS:
        sc = np.array(list(scores(shift).values()))
        if len(sc) >= 3 and median(sc) <= 1.0 and np.mean(sc > 1.0) < wrong / 3:
            shifted.append((float(np.mean(sc > 1.0)), shift))
    end = "; check how the poses and the images are logged and paired"
    if shifted:
        _, shift = min(shifted)
        return (
            f"{what} in {100 * wrong:.0f} % of the pairs of frames, and in "
            f"{100 * min(shifted)[0]:.0f} % when each image takes the pose recorded {abs(shift)} "
            f"frame(s) {'later' if shift > 0 else 'earlier'}: the poses are shifted against the "
            "images, not paired as recorded" + end
        )
    if overall > 1.0:
        return (
            f"{what} in most pairs of frames ({overall:.1f} times the limit, median over "
            f"{len(recorded)} pairs): the poses and the images are not paired as recorded, or "
            "the rotations are not axis-angle vectors of T_base_tool in radians (degrees?)" + end
        )
    return (
        f"frames {bad}: {what} in most of their pairs with the other frames: those images are "
        "paired with other poses (swapped, or read at another stop)" + end
    )


#: The records as read must spread this many times the limits for another reading to be named.
CONVENTION_MARGIN = 2.0


def _rpy(R: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (radians)."""
    pitch = float(-np.arcsin(np.clip(R[2, 0], -1.0, 1.0)))
    return float(np.arctan2(R[2, 1], R[2, 2])), pitch, float(np.arctan2(R[1, 0], R[0, 0]))


def _read_as(kind: str, T: np.ndarray) -> np.ndarray:
    """The pose a record meant when slidecal read it as ``T`` under the mistake ``kind``."""
    R = T[:3, :3]
    if kind == "inverted":
        return inv_T(T)
    if kind == "transposed":
        R = R.T
    elif kind == "quaternion scalar last":  # [x, y, z, w] read as [w, x, y, z]
        w, x, y, z = quat_wxyz_from_R(R)
        R = R_from_quat_wxyz(np.array([z, w, x, y]))
    elif kind == "angles reversed":  # [yaw, pitch, roll] (KUKA's A, B, C) read as [roll, ...]
        roll, pitch, yaw = _rpy(R)
        R = Rz(roll) @ Ry(pitch) @ Rx(yaw)
    else:  # "rotations composed the other way": R = Rx(roll) Ry(pitch) Rz(yaw)
        roll, pitch, yaw = _rpy(R)
        R = Rx(roll) @ Ry(pitch) @ Rz(yaw)
    return T_from_Rt(R, T[:3, 3])


#: The readings tried, each with what it means and its fix (``{other}``: the other mount).
CONVENTIONS = (
    (
        "inverted",
        "the records are T_tool_base (the base in the tool's frame), not T_base_tool, or the "
        "camera is mounted the other way ({other})",
        "invert the poses, or set mount: {other}",
    ),
    (
        "transposed",
        "the rotation matrices are transposed (their rows, not their columns, are the tool's axes)",
        "transpose R",
    ),
    (
        "quaternion scalar last",
        "the quaternions are [x, y, z, w] (ROS's order), read as [w, x, y, z]",
        "give q_wxyz with the scalar first",
    ),
    (
        "angles reversed",
        "the angles are [yaw, pitch, roll] (KUKA's A, B, C), read as [roll, pitch, yaw]",
        "give rpy_deg as [roll, pitch, yaw] (KUKA: [C, B, A])",
    ),
    (
        "rotations composed the other way",
        "the angles compose as Rx(roll) Ry(pitch) Rz(yaw), read as Rz(yaw) Ry(pitch) Rx(roll)",
        "convert them to the fixed-axes X-Y-Z convention of rpy_deg",
    ),
)


def fixed_spread(
    T_tool: np.ndarray, T_cam: list[np.ndarray], eye_in_hand: bool
) -> tuple[float, float]:
    """How much what must stay fixed moves through the poses ``T_tool`` (``T_base_tool``) and
    the images-alone ``T_cam`` (``T_cam_board``), with the hand-eye that fits them best (Park's
    method): rms rotation (deg) and translation (mm) about its mean. Eye-in-hand that is the
    board in the base frame, eye-to-hand the target on the tool."""
    G = list(T_tool) if eye_in_hand else [inv_T(T) for T in T_tool]
    try:
        R, t = cv2.calibrateHandEye(
            [g[:3, :3] for g in G],
            [g[:3, 3] for g in G],
            [c[:3, :3] for c in T_cam],
            [c[:3, 3] for c in T_cam],
            method=cv2.CALIB_HAND_EYE_PARK,
        )
    except cv2.error:
        return float("inf"), float("inf")
    X = T_from_Rt(R, np.asarray(t).reshape(3))
    fixed = np.stack([g @ X @ c for g, c in zip(G, T_cam, strict=True)])
    if not np.all(np.isfinite(fixed)):
        return float("inf"), float("inf")
    R_mean = project_to_SO3(fixed[:, :3, :3].mean(axis=0))
    rot = float(np.sqrt(np.mean([rotation_angle_deg(R_mean, f[:3, :3]) ** 2 for f in fixed])))
    t_m = fixed[:, :3, 3]
    return rot, 1000.0 * float(np.sqrt(np.mean(np.sum((t_m - t_m.mean(axis=0)) ** 2, axis=1))))


def convention_check(problem: CalibrationProblem) -> str | None:
    """Whether the robot's records were read in their own convention, told from the images
    alone: through the right poses and the best hand-eye, the board stays fixed in the base
    frame (eye-to-hand: the target on the tool) within the arm's accuracy. Otherwise the
    readings of ``CONVENTIONS`` are tried and the one that fits is named with its fix. None
    when the poses as read fit, no reading does, or the session has one orientation. Images of
    4 or 5 points (a lone tag) serve when the session has no others. Costs an OpenCV
    calibration."""
    seen = _images_alone(problem) or _images_alone(problem, 4)
    return None if seen is None else _convention(problem, *seen)


def _convention(
    problem: CalibrationProblem, frames: list[int], T_cam: list[np.ndarray]
) -> str | None:
    """:func:`convention_check` on the images-alone poses ``T_cam`` of ``frames``."""
    eye_in_hand = problem.mount == "eye_in_hand"
    T_tool = np.stack([problem.frames[k].T_base_tool for k in frames])
    rot_lim, t_lim = MAX_PAIRING_ROTATION_DEG, MAX_ROBOT_TRANSLATION_MM
    as_read = fixed_spread(T_tool, T_cam, eye_in_hand)
    if as_read[0] <= CONVENTION_MARGIN * rot_lim and as_read[1] <= CONVENTION_MARGIN * t_lim:
        return None
    fits = []
    for kind, meaning, fix in CONVENTIONS:
        rot, t_mm = fixed_spread(np.stack([_read_as(kind, T) for T in T_tool]), T_cam, eye_in_hand)
        if rot <= rot_lim and t_mm <= t_lim:
            fits.append((rot / rot_lim + t_mm / t_lim, rot, t_mm, meaning, fix))
    if not fits:
        return None
    _, rot, t_mm, meaning, fix = min(fits)
    other = "eye_to_hand" if eye_in_hand else "eye_in_hand"
    fixed = "the board's pose in the base frame" if eye_in_hand else "the target's pose on the tool"
    return (
        f"the robot poses as read do not fit the camera's own view of the motion ({fixed}, which "
        f"must stay fixed, spreads through them by {as_read[0]:.1f} deg and {as_read[1]:.0f} mm; "
        f"the images alone), and they fit when read otherwise ({rot:.2f} deg, {t_mm:.1f} mm): "
        f"{meaning.format(other=other)}; {fix.format(other=other)}"
    )


def moving_point(T_cam_board: np.ndarray, mount: str) -> np.ndarray:
    """What moves with the robot, as the camera sees it: the camera centre in the board's frame
    (eye-in-hand) or the board's origin in the camera's (eye-to-hand); a pure move of the tool
    moves it by the tool's translation (up to a rotation). ``T_cam_board`` (..., 4, 4)."""
    if mount == "eye_in_hand":
        return -np.einsum("...ji,...j->...i", T_cam_board[..., :3, :3], T_cam_board[..., :3, 3])
    return T_cam_board[..., :3, 3]


def bad_images_note(adequacy: ModelAdequacy | None) -> tuple[str, ...]:
    """The line naming the images above :data:`MAX_FRAME_NORMALISED_RMS` that an adequate
    result does not lean on (their share of the squares below :data:`MAX_BAD_IMAGE_SHARE`);
    () when there are none."""
    if adequacy is None or not adequacy.adequate:
        return ()
    bad = [f for f in adequacy.worst_frames if f[2] > MAX_FRAME_NORMALISED_RMS]
    if not bad:
        return ()
    names = ", ".join(f"{fid} {cam!r} ({ratio:.1f})" for fid, cam, ratio in bad)
    return (
        f"image(s) of frame {names} above {MAX_FRAME_NORMALISED_RMS} times the detector's "
        "noise: check their poses and detections; under "
        f"{100 * MAX_BAD_IMAGE_SHARE:.0f} % of the session's squares, the result does not lean "
        "on them",
    )


#: A classic session's scale is checked only where its geometry pins it to this relative se.
MAX_CLASSIC_SCALE_SE = 0.003


def classic(groups: np.ndarray, frames: list[int] | dict[int, np.ndarray]) -> bool:
    """Whether no two of ``frames`` (frame indices) share an orientation group (``groups``):
    a classic hand-eye session, as far as those frames go."""
    idx = sorted(frames)
    return bool(idx) and int(np.bincount(np.asarray(groups)[idx]).max()) < 2


def static_rotation(state: ModelState, mount: str) -> np.ndarray:
    """The rotation from the base into the frame that stays still while the tool moves: the
    board's (eye-in-hand) or the camera's (eye-to-hand), from a refinement's state."""
    if mount == "eye_in_hand":
        return state.Y[:3, :3].T  # Y = T_base_board
    return state.X[0][:3, :3]  # X = T_cam_base


def classic_scale_fit(
    problem: CalibrationProblem, poses: dict[int, np.ndarray], R_static_base: np.ndarray
) -> tuple[float, float, np.ndarray] | None:
    """The camera/robot length ratio of a session from the images alone: ``(ratio, relative
    standard error, q)``, ``q`` (metres) the tool-frame place of :func:`moving_point`; None
    with fewer than four posed frames or when the geometry leaves the scale free.

    Linear least squares of ``lambda a_k = R (p_k + R_k q) + t`` in ``lambda``, ``q``, ``t``:
    ``a_k`` the moving point in the still frame (``poses``: frame index -> ``T_cam_board``),
    ``R`` = ``R_static_base``, ``p_k``, ``R_k`` the measured tool pose. The ratio is
    ``1 / lambda``; its standard error takes the arm's error as independent per frame."""
    idx = sorted(poses)
    if len(idx) < 4:
        return None
    rows, rhs = [], []
    for i in idx:
        T = problem.frames[i].T_base_tool
        a = moving_point(poses[i], problem.mount)
        rows.append(np.hstack([a[:, None], -(R_static_base @ T[:3, :3]), -np.eye(3)]))
        rhs.append(R_static_base @ T[:3, 3])
    A, y = np.vstack(rows), np.concatenate(rhs)
    U, sv, Vt = np.linalg.svd(A, full_matrices=False)
    if not sv[-1] > 1e-9 * sv[0]:  # the geometry leaves the scale free
        return None
    x = Vt.T @ ((U.T @ y) / sv)
    r = y - A @ x
    var = float(r @ r / (len(y) - A.shape[1]) * np.sum((Vt[:, 0] / sv) ** 2))
    lam = float(x[0])
    if not lam > 0:
        return None
    return 1.0 / lam, float(np.sqrt(var)) / lam, x[1:4]


def scale_moves(
    problem: CalibrationProblem,
    poses: dict[int, np.ndarray],
    R_static_base: np.ndarray,
    groups: np.ndarray,
    min_move_m: float,
) -> list[tuple[int, int, float, float]]:
    """The moves whose length both the camera and the robot tell, ``(frame index a, b, robot
    length, camera length)`` in metres, of at least ``min_move_m`` for the robot; ``poses``:
    frame index -> ``T_cam_board`` from the images alone; ``groups``: the frames'
    ``orientation_groups``. Consecutive frames of an orientation group;
    a classic session (one frame per orientation) uses the point :func:`classic_scale_fit`
    places on the tool, when the fit pins the ratio (:data:`MAX_CLASSIC_SCALE_SE`)."""
    T = np.stack([f.T_base_tool for f in problem.frames])
    q = np.zeros(3)
    chains = [[i for i in np.flatnonzero(groups == g) if i in poses] for g in distinct(groups)]
    if classic(groups, poses):
        fit = classic_scale_fit(problem, poses, R_static_base)
        if fit is None or fit[1] > MAX_CLASSIC_SCALE_SE:
            return []
        q, chains = fit[2], [sorted(poses)]
    tip = T[:, :3, :3] @ q + T[:, :3, 3]  # the tool's point q in the base frame, per frame
    moves = []
    for idx in (np.asarray(c, int) for c in chains if len(c) > 1):
        robot = np.linalg.norm(tip[idx[1:]] - tip[idx[:-1]], axis=1)
        seen = moving_point(np.stack([poses[i] for i in idx]), problem.mount)
        camera = np.linalg.norm(seen[1:] - seen[:-1], axis=1)
        moves += [
            (int(a), int(b), float(r), float(c))
            for a, b, r, c in zip(idx[:-1], idx[1:], robot, camera, strict=True)
            if r >= min_move_m
        ]
    return moves


def unchecked_scale_note(
    problem: CalibrationProblem,
    poses: dict[int, np.ndarray],
    R_static_base: np.ndarray,
    groups: np.ndarray,
) -> tuple[str, ...]:
    """The line saying that a classic session's geometry leaves its camera/robot scale
    unchecked (:func:`scale_moves` gives it no move), with the frames' distances from the
    board and what would let it be checked; () for any other session. ``poses``: frame index
    -> ``T_cam_board`` from the images alone."""
    if len(poses) < 4:
        return ()
    if not classic(groups, poses):  # moves at one orientation: checked
        return ()
    fit = classic_scale_fit(problem, poses, R_static_base)
    if fit is not None and fit[1] <= MAX_CLASSIC_SCALE_SE:
        return ()
    centre = problem.target.points_m.mean(axis=0)
    dist = [float(np.linalg.norm(T[:3, :3] @ centre + T[:3, 3])) for T in poses.values()]
    pinned = "not at all" if fit is None else f"only to {100 * fit[1]:.1f} %"
    return (
        "the camera/robot scale (the board's square size against the robot's lengths) is not "
        f"checked: every frame is {min(dist):.2f}-{max(dist):.2f} m from the board, which pins "
        f"it {pinned}, and a wrong square size would move the hand-eye along the viewing "
        "direction unseen; frames nearer to and farther from the board let it be checked",
    )


#: A pose correction this many times the typical frame's (robust) is a gross error, not the arm.
POSE_OUTLIER_RATIO = 5.0
#: The words of the message that names a frame left out for its pose (the verdict lists them)
LEFT_OUT = "left out of the solve"
#: The words every finding of :func:`record_check` says (the verdict leads with it alone)
RECORDS_WRONG = "the camera's own view of the motion"
#: Fewest frames with pose corrections for the test (the typical size must mean something).
POSE_OUTLIER_MIN_FRAMES = 8
#: Neighbours, in space and in time, a frame's correction is held against: a glitch stands alone.
POSE_OUTLIER_NEIGHBOURS = 4


@dataclass(frozen=True)
class PoseOutlier:
    """A frame whose robot pose the images contradict far beyond the arm's accuracy elsewhere.

    ``index``: position in the problem's frames; ``frame``: its id; ``rotation_deg`` /
    ``translation_mm``: the size of its pose correction; ``others_rotation_deg`` /
    ``others_translation_mm``: the typical frame's (robust rms); ``ratio``: the larger of the
    two ratios.
    """

    index: int
    frame: int
    rotation_deg: float
    translation_mm: float
    others_rotation_deg: float
    others_translation_mm: float
    ratio: float
    causes: ClassVar[str] = (
        "a pose read before the arm settled, a glitch of the record, or an image paired with "
        "another pose"
    )

    def describe(self) -> str:
        """One line: the frame, its pose's misfit and the others'."""
        return (
            f"frame {self.frame}: its robot pose is {self.translation_mm:.2f} mm and "
            f"{self.rotation_deg:.3f} deg off what its images show, {self.ratio:.1f} times a "
            f"typical frame's ({self.others_translation_mm:.2f} mm, "
            f"{self.others_rotation_deg:.3f} deg)"
        )


def pose_outlier(
    problem: CalibrationProblem, out: RefineOutput, groups: np.ndarray
) -> PoseOutlier | None:
    """The frame whose robot pose correction is largest against the typical frame's, when it is
    beyond ``POSE_OUTLIER_RATIO`` (rotation and translation tested apart) and its correction
    less the median of its neighbours' is too, in space and in time
    (:func:`_pose_neighbours`); None without pose corrections, with fewer than
    ``POSE_OUTLIER_MIN_FRAMES`` frames or when every frame is within the ratio. ``groups``: the
    frames' orientation groups."""
    if problem.knowledge != "robot" or "E" not in out.model.slices:
        return None
    E = out.model.pose_corrections(out.state)
    if E is None or len(E) < POSE_OUTLIER_MIN_FRAMES:
        return None
    sizes = [np.linalg.norm(E[:, :3], axis=1), np.linalg.norm(E[:, 3:], axis=1)]
    # the rms of a Gaussian 3-vector from its median square (chi-square(3)'s median: 2.366)
    typical = [float(np.sqrt(3.0 * median(size**2) / 2.366)) for size in sizes]

    def ratio(e: np.ndarray) -> np.ndarray:  # (n, 6) corrections -> (n,) against the typical
        parts = [np.linalg.norm(e[:, :3], axis=1), np.linalg.norm(e[:, 3:], axis=1)]
        per = zip(parts, typical, strict=True)
        return np.max([p / t if t > 0 else np.zeros(len(e)) for p, t in per], axis=0)

    ratios = ratio(E)
    T = np.stack([f.T_base_tool for f in problem.frames])
    for k in np.argsort(-ratios):
        if ratios[k] <= POSE_OUTLIER_RATIO:
            return None
        local = [E[k] - np.median(E[nb], axis=0) for nb in _pose_neighbours(T, groups, int(k))]
        if min(float(ratio(d[None])[0]) for d in local) > POSE_OUTLIER_RATIO:
            break
    else:
        return None
    k = int(k)
    return PoseOutlier(
        index=k,
        frame=int(problem.frames[k].id),
        rotation_deg=float(np.degrees(sizes[0][k])),
        translation_mm=float(1000.0 * sizes[1][k]),
        others_rotation_deg=float(np.degrees(typical[0])),
        others_translation_mm=float(1000.0 * typical[1]),
        ratio=float(ratios[k]),
    )


def _pose_neighbours(T_base_tool: np.ndarray, groups: np.ndarray, k: int) -> list[np.ndarray]:
    """Frame ``k``'s neighbours (:data:`POSE_OUTLIER_NEIGHBOURS` each): its nearest in tool
    position within its orientation group (``groups``; within the session when the group has
    fewer other frames), and the frames recorded just before and after it."""
    n, F = POSE_OUTLIER_NEIGHBOURS, len(T_base_tool)
    others = np.delete(np.arange(F), k)
    same = others[groups[others] == groups[k]]
    pool = same if len(same) >= n else others
    dist = np.linalg.norm(T_base_tool[pool, :3, 3] - T_base_tool[k, :3, 3], axis=1)
    space = pool[np.argsort(dist, kind="stable")[:n]]
    lo = min(max(k - n // 2, 0), F - 1 - n)
    time = np.array([i for i in range(lo, lo + n + 1) if i != k][:n])
    return [space, time]


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
        norms = np.linalg.norm(E.reshape(-1, 2, 3), axis=2)  # (F, 2): rotation, translation
        for f, (r, t) in zip(problem.frames, norms, strict=True):
            worst.append((int(f.id), float(1000.0 * t), float(np.degrees(r))))
        t_sig, r_sig = max(1000.0 * sig[1], 1e-6), max(np.degrees(sig[0]), 1e-9)
        worst.sort(key=lambda w: -(w[1] / t_sig + w[2] / r_sig))
    return RobotAccuracy(
        translation_mm=float(1000.0 * sig[1]),
        rotation_deg=float(np.degrees(sig[0])),
        worst_frames=tuple(worst[:5]),
        estimated=out.robot_sigma_estimated,
        levels={k: (1000.0 * t, float(np.degrees(r))) for k, (r, t) in out.robot_levels.items()},
    )
