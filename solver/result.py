"""The solver's output: estimates with their diagnostics.

Nothing here is a made-up number: a quantity the data cannot determine is ``None`` and named in
``CalibrationResult.unobservable`` with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from slidecal.solver.geometry import T_from_Rt

#: A transform's perturbation, rotation vector (radians) then translation (metres), named so in
#: a covariance (``T_tool_cam.rx`` .. ``T_tool_cam.tz``): docs/FORMATS.md
ROT = ("rx", "ry", "rz")
TRANS = ("tx", "ty", "tz")


@dataclass(frozen=True)
class NamedCovariance:
    """A covariance whose rows are named reported quantities (:mod:`slidecal.solver.uncertainty`
    names them and states the convention)."""

    names: tuple[str, ...]
    matrix: np.ndarray

    def block(self, names: list[str] | tuple[str, ...]) -> np.ndarray | None:
        """The covariance of ``names`` (n, n), None unless all are present."""
        where = {n: i for i, n in enumerate(self.names)}
        if any(n not in where for n in names):
            return None
        i = np.array([where[n] for n in names], dtype=int)
        return self.matrix[np.ix_(i, i)]

    def std(self, name: str) -> float | None:
        """One-sigma of ``name``, None when it is not estimated."""
        C = self.block((name,))
        return None if C is None else float(np.sqrt(max(C[0, 0], 0.0)))

    def std_rot_deg(self, transform: str) -> float | None:
        """One-sigma rotation error of ``transform`` (root of the trace, degrees), or None."""
        C = self.block(tuple(f"{transform}.{a}" for a in ROT))
        return None if C is None else float(np.degrees(np.sqrt(max(np.trace(C), 0.0))))

    def std_t_mm(self, transform: str) -> float | None:
        """One-sigma translation error of ``transform`` (root of the trace, mm), or None."""
        C = self.block(tuple(f"{transform}.{a}" for a in TRANS))
        return None if C is None else float(1000.0 * np.sqrt(max(np.trace(C), 0.0)))


@dataclass(frozen=True)
class CameraEstimate:
    """One camera's intrinsics. ``K`` (3, 3) pixels; ``distortion`` (5,) k1 k2 p1 p2 k3 (OpenCV
    order); ``std``: one-sigma of each estimated parameter by name (fx, fy, cx, cy, s, k1, ...);
    ``reproj_rms_px``: root mean square reprojection error of this camera's inlier detections."""

    name: str
    width: int
    height: int
    K: np.ndarray
    distortion: np.ndarray
    std: dict[str, float]
    reproj_rms_px: float


@dataclass(frozen=True)
class TransformEstimate:
    """A rigid transform ``T_a_b`` whose translation may be unobservable.

    ``R`` (3, 3); ``t_m`` (3,) metres or None when the data cannot determine it;
    ``std_rot_deg``: one-sigma rotation error (root of the trace of the rotation covariance, as an
    angle); ``std_t_mm``: one-sigma translation error (root of the trace), None with ``t_m``.
    ``R`` itself is None when even the rotation is unobservable.
    """

    name: str
    R: np.ndarray | None
    t_m: np.ndarray | None
    std_rot_deg: float | None = None
    std_t_mm: float | None = None

    @property
    def T(self) -> np.ndarray | None:
        """The 4x4 transform, or None unless rotation and translation are both known."""
        if self.R is None or self.t_m is None:
            return None
        return T_from_Rt(self.R, self.t_m)


@dataclass(frozen=True)
class ScaleCheck:
    """Per move: the translation length the camera saw against the robot's (docs/METHOD.md Sec. 3).

    A ratio far from 1 means a wrong board square size or a wrong TCP/robot scale.
    ``frame_a``, ``frame_b``: the frame ids of the move; lengths in millimetres.
    """

    frame_a: int
    frame_b: int
    robot_mm: float
    camera_mm: float

    @property
    def ratio(self) -> float:
        """camera_mm / robot_mm."""
        return self.camera_mm / self.robot_mm if self.robot_mm > 0 else float("nan")


@dataclass(frozen=True)
class ModelAdequacy:
    """Whether the model explains the data, judged against the noise the detector is known to have.

    ``normalised_rms``: per camera, the reprojection rms divided by ``detector_noise_px`` (about 1
    when the model is adequate; much more means the model or the robot poses cannot explain the
    images). ``worst_frames``: (frame id, camera, normalised rms of that image), worst first.
    ``adequate``: False when the result must not be used; ``reasons`` says why, one line each,
    with the figure and its limit.
    """

    detector_noise_px: dict[str, float]
    normalised_rms: dict[str, float]
    worst_frames: tuple[tuple[int, str, float], ...]
    adequate: bool
    reasons: tuple[str, ...] = ()


@dataclass(frozen=True)
class RobotAccuracy:
    """The robot's pose accuracy as the camera sees it.

    ``translation_mm``, ``rotation_deg``: the estimated one-sigma per-axis pose error (rms);
    ``worst_frames``: (frame id, translation error mm, rotation error deg), worst first;
    ``estimated``: True when learned from the data, False when the user's prior was used as is;
    ``left_out``: (frame id, translation error mm, rotation error deg) of the frames the solve
    left out for their pose or image, in that order (a rig frame keeping other images is not);
    ``levels``: (translation mm, rotation deg) of each source the solve learned ("pose",
    "group", "trend", "field": docs/ERROR_MODEL.md S3-S5), whose root sum of squares is the
    accuracy (empty where not learned; not written to result files).
    """

    translation_mm: float
    rotation_deg: float
    worst_frames: tuple[tuple[int, float, float], ...]
    estimated: bool
    left_out: tuple[tuple[int, float, float], ...] = ()
    levels: dict[str, tuple[float, float]] = field(default_factory=dict, compare=False)


@dataclass(frozen=True)
class BoardShape:
    """The board as the solve saw it (``solver/target_shape.py``).

    ``bow_mm`` (x, y): the estimated bow along the board's axes (centre against edges, +z into
    the board), ``bow_std_mm`` its one-sigma; ``flatness_mm``, ``print_tolerance``: the
    tolerance the solve assumed.
    """

    bow_mm: tuple[float, float]
    bow_std_mm: tuple[float, float]
    flatness_mm: float
    print_tolerance: float


@dataclass(frozen=True)
class CalibrationResult:
    """Everything a solve determined, and how well.

    ``hand_eye``: ``T_tool_cam`` (eye-in-hand) or ``T_base_cam`` (eye-to-hand) of the reference
    camera, None without a robot. ``rig``: ``T_<name>_<reference>`` for every other camera.
    ``T_target``: ``T_base_board`` (eye-in-hand) or ``T_tool_board`` (eye-to-hand).
    ``H_inf``: infinite homographies ``x_a ~ H x_b`` keyed ``"a<-b"`` (docs/METHOD.md Sec. 8).
    ``parameter_names`` name the rows of ``covariance`` (:mod:`slidecal.solver.uncertainty`).
    ``residuals_px``: per (frame id, camera) the rms reprojection error. ``outliers``: (frame
    id, camera, corner id) flagged by the robust loss. ``sigma_px``: ``s`` of docs/METHOD.md
    Sec. 6. ``unobservable``: parameter name -> why it was fixed. ``messages``: soft failures
    and notes. ``linear``: the closed-form intrinsics per camera. ``adequacy``: the
    model-adequacy test; ``robot_accuracy``: the arm's accuracy as the data shows it;
    ``board``: the board's bow (None for a board taken as exact).
    """

    cameras: dict[str, CameraEstimate]
    hand_eye: TransformEstimate | None
    rig: dict[str, TransformEstimate]
    T_target: TransformEstimate | None
    converged: bool
    iterations: int
    reproj_rms_px: float
    sigma_px: float
    parameter_names: tuple[str, ...]
    covariance: np.ndarray | None
    residuals_px: dict[tuple[int, str], float]
    outliers: tuple[tuple[int, str, int], ...]
    unobservable: dict[str, str]
    messages: tuple[str, ...]
    scale_checks: tuple[ScaleCheck, ...] = ()
    H_inf: dict[str, np.ndarray] = field(default_factory=dict)
    linear: dict[str, np.ndarray] = field(default_factory=dict)
    mount: str = "eye_in_hand"
    reference_camera: str = ""
    adequacy: ModelAdequacy | None = None
    robot_accuracy: RobotAccuracy | None = None
    board: BoardShape | None = None

    @property
    def named_covariance(self) -> NamedCovariance | None:
        """``covariance`` with its names (std of a transform's rotation and translation)."""
        if self.covariance is None:
            return None
        return NamedCovariance(tuple(self.parameter_names), np.asarray(self.covariance, float))
