"""The solver's input: a frozen description of what a calibration session observed.

Board frame and corner ids (fixed within a session format version): ``charuco``,
``chessboard`` and ``points`` as the README states them (OpenCV's board frame and ids);
``apriltag`` (corners ``4 k + j`` of tag ``tag_ids[k]``, OpenCV's marker corner order) and
``aprilgrid`` (Kalibr's tag and corner ids) as docs/results/DETECTION.md ("Target kinds and
corner ids") states them. A tag target's board frame: origin at the outer top-left corner of
the top-left tag, +x right, +y down the printed page, +z into the board (an AprilGrid's differs
from Kalibr's by ``Y = height - Y_kalibr``, ``Z = -Z_kalibr``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from slidecal.solver.camera import DISTORTION_MODELS
from slidecal.solver.errors import InputError

Mount = Literal["eye_in_hand", "eye_to_hand", "none"]
# What is known about the motion between frames (docs/METHOD.md Sec. 3 table):
# - "robot": T_base_tool measured for every frame (translations and any rotations in the robot
#   frame; board pose unknown). The general, real case; with a single translation direction and
#   known steps it is the paper's Case 1.
# - "board_translation": Frame.motion_board is the camera displacement since the group's first
#   frame in board coordinates (the paper's Case 3).
# - "board_direction": Frame.motion_board is the unit direction of that displacement in board
#   coordinates, its length unknown (the paper's Case 2).
# - "none": nothing known; every frame has its own pose (Zhang's general-motion method).
Knowledge = Literal["robot", "board_translation", "board_direction", "none"]
#: Every distortion coefficient a lens model may have (``solver/camera.py``'s DISTORTION_MODELS).
DISTORTION_NAMES = DISTORTION_MODELS["rational"]
#: The intrinsics a camera reports, in pixels (``s``: skew, with ``ModelOptions.skew``).
INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "s")


@dataclass(frozen=True)
class Target:
    """A planar calibration target. ``points_m`` (N, 3), board frame, z = 0; row i has id i."""

    kind: Literal["charuco", "chessboard", "points", "apriltag", "aprilgrid"]
    points_m: np.ndarray
    squares_x: int = 0
    squares_y: int = 0
    square_size_m: float = 0.0
    marker_size_m: float = 0.0
    dictionary: str = ""
    # apriltag, aprilgrid (see the module docstring)
    tag_size_m: float = 0.0
    tag_ids: tuple[int, ...] = ()
    tag_origins_m: tuple[tuple[float, float], ...] = ()
    tag_cols: int = 0
    tag_rows: int = 0
    tag_spacing: float = 0.0
    # the real board's one-sigma departure from this description: the bow (metres) and the
    # print's relative scale error; 0: exact (``solver/target_shape.py``)
    flatness_m: float = 0.0
    print_tolerance: float = 0.0

    @staticmethod
    def grid_points(squares_x: int, squares_y: int, square_size_m: float) -> np.ndarray:
        """Inner corners (N, 3) of a board of squares, in id order (see the module docstring)."""
        cols, rows = squares_x - 1, squares_y - 1
        c, r = np.meshgrid(np.arange(cols), np.arange(rows))
        xy = np.stack([(c.ravel() + 1) * square_size_m, (r.ravel() + 1) * square_size_m], axis=1)
        return np.column_stack([xy, np.zeros(len(xy))])

    @classmethod
    def charuco(
        cls,
        squares_x: int,
        squares_y: int,
        square_size_m: float,
        marker_size_m: float,
        dictionary: str = "DICT_5X5_100",
    ) -> Target:
        """A ChArUco board (OpenCV ``CharucoBoard`` layout and ids)."""
        return cls(
            "charuco",
            cls.grid_points(squares_x, squares_y, square_size_m),
            squares_x,
            squares_y,
            float(square_size_m),
            float(marker_size_m),
            dictionary,
        )

    @classmethod
    def chessboard(cls, squares_x: int, squares_y: int, square_size_m: float) -> Target:
        """A chessboard of ``squares_x`` by ``squares_y`` squares."""
        pts = cls.grid_points(squares_x, squares_y, square_size_m)
        return cls("chessboard", pts, squares_x, squares_y, float(square_size_m))

    @classmethod
    def apriltag(
        cls,
        tag_size_m: float,
        tag_ids: tuple[int, ...] = (0,),
        tag_origins_m: tuple[tuple[float, float], ...] | None = None,
        dictionary: str = "DICT_APRILTAG_36h11",
    ) -> Target:
        """One AprilTag (or a few): ``tag_origins_m[k]`` is tag ``tag_ids[k]``'s top-left corner.

        With ``tag_origins_m`` None there must be one tag, at the origin.
        """
        ids = tuple(int(i) for i in tag_ids)
        if not ids or len(set(ids)) != len(ids) or min(ids) < 0:
            raise InputError(f"tag_ids must be distinct non-negative tag ids, got {list(ids)}")
        if not tag_size_m > 0.0:
            raise InputError(f"tag_size_m must be positive, got {tag_size_m}")
        if tag_origins_m is None:
            if len(ids) != 1:
                raise InputError("give tag_origins_m (the top-left corner of every tag)")
            tag_origins_m = ((0.0, 0.0),)
        origins = tuple((float(x), float(y)) for x, y in tag_origins_m)
        if len(origins) != len(ids):
            raise InputError(f"{len(ids)} tag_ids but {len(origins)} tag_origins_m; give one each")
        s = float(tag_size_m)
        corners = np.array([[0.0, 0.0], [s, 0.0], [s, s], [0.0, s]])
        xy = np.concatenate([corners + np.array(o) for o in origins])
        if np.any(xy < -1e-12):
            raise InputError("tag_origins_m must put every tag at X, Y >= 0 (board frame)")
        return cls(
            "apriltag",
            np.column_stack([xy, np.zeros(len(xy))]),
            dictionary=dictionary,
            tag_size_m=s,
            tag_ids=ids,
            tag_origins_m=origins,
        )

    @classmethod
    def aprilgrid(
        cls,
        tag_cols: int,
        tag_rows: int,
        tag_size_m: float,
        tag_spacing: float,
        dictionary: str = "DICT_APRILTAG_36h11",
    ) -> Target:
        """Kalibr's AprilGrid (``tagCols``, ``tagRows``, ``tagSize``, ``tagSpacing``)."""
        if tag_cols < 1 or tag_rows < 1 or not tag_size_m > 0.0 or not tag_spacing > 0.0:
            raise InputError(
                "an aprilgrid needs tag_cols, tag_rows >= 1, tag_size_m > 0 and tag_spacing > 0 "
                "(the gap between tags as a fraction of the tag size, Kalibr's tagSpacing)"
            )
        s = float(tag_size_m)
        pitch = s * (1.0 + float(tag_spacing))
        height = tag_rows * pitch - float(tag_spacing) * s
        n_c, n_r = 2 * tag_cols, 2 * tag_rows
        r, c = np.divmod(np.arange(n_r * n_c), n_c)  # Kalibr's corner rows from the bottom
        x = (c // 2) * pitch + (c % 2) * s
        y_up = (r // 2) * pitch + (r % 2) * s
        xy = np.column_stack([x, height - y_up])
        return cls(
            "aprilgrid",
            np.column_stack([xy, np.zeros(len(xy))]),
            dictionary=dictionary,
            tag_size_m=s,
            tag_ids=tuple(range(tag_cols * tag_rows)),
            tag_cols=int(tag_cols),
            tag_rows=int(tag_rows),
            tag_spacing=float(tag_spacing),
        )

    def tag_corner_ids(self) -> dict[int, np.ndarray]:
        """Tag id -> the ids (4,) of its corners in OpenCV's marker corner order (TL, TR, BR, BL
        as printed); empty for targets without tags."""
        if self.kind == "apriltag":
            return {t: 4 * k + np.arange(4) for k, t in enumerate(self.tag_ids)}
        if self.kind == "aprilgrid":
            out = {}
            nc = 2 * self.tag_cols
            for t in self.tag_ids:
                i, k = divmod(t, self.tag_cols)
                b = 2 * i * nc + 2 * k
                out[t] = np.array([b + nc, b + nc + 1, b + 1, b])
            return out
        return {}

    @classmethod
    def points(cls, points_m: np.ndarray) -> Target:
        """Arbitrary board points: (N, 2) or (N, 3) with z = 0, board frame, metres."""
        p = np.asarray(points_m, dtype=float)
        if p.ndim != 2 or p.shape[1] not in (2, 3) or len(p) < 4:
            raise InputError("points_m must be a list of at least 4 [X, Y] board coordinates")
        if p.shape[1] == 2:
            p = np.column_stack([p, np.zeros(len(p))])
        if np.any(np.abs(p[:, 2]) > 1e-12):
            raise InputError("points_m must lie on the board plane (z = 0)")
        return cls("points", p)


@dataclass(frozen=True)
class CameraSpec:
    """A camera of the session: its name and image size in pixels."""

    name: str
    width: int
    height: int


@dataclass(frozen=True)
class Detection:
    """Target corners one camera found in one frame: ids (n,) and pixels (n, 2).

    Pixel (0, 0) is the centre of the top-left pixel. ``reason``: when the detector kept nothing
    usable, what it saw (e.g. "a chessboard of 8 x 5 inner corners where 9 x 6 were expected");
    empty otherwise. The frame keeps its place with its (possibly empty) ids.
    """

    ids: np.ndarray
    px: np.ndarray
    reason: str = ""

    def __post_init__(self) -> None:
        ids = np.asarray(self.ids, dtype=np.int64).reshape(-1)
        px = np.asarray(self.px, dtype=float).reshape(-1, 2)
        if len(ids) != len(px):
            raise InputError(f"detection has {len(ids)} ids but {len(px)} pixel positions")
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "px", px)


@dataclass(frozen=True)
class Frame:
    """One robot stop: what was measured and what each camera saw.

    ``T_base_tool`` (4, 4): measured after settling (knowledge "robot"). ``motion_board`` (3,):
    the paper's board-frame knowledge (see ``Knowledge``). ``group``: orientation group; derived
    from the measured rotations when None.
    """

    id: int
    detections: Mapping[str, Detection]
    T_base_tool: np.ndarray | None = None
    motion_board: np.ndarray | None = None
    group: int | None = None


@dataclass(frozen=True)
class ModelOptions:
    """What the camera model estimates.

    ``skew``: estimate the skew ``s`` (else 0). ``unit_aspect``: ``fx == fy``.
    ``distortion_model``: the lens model, a key of ``solver/camera.py``'s DISTORTION_MODELS; None:
    the data chooses (``solver/lens.py``), from opencv5 (:attr:`lens`).
    ``distortion``: which of its coefficients are estimated (the others stay 0): one flag each,
    or one flag for all, or opencv5's five flags for rational (k4-k6 follow k3):
    :attr:`distortion_mask`.
    ``outlier_threshold_px``: a detection whose residual exceeds this after the first solve is
    flagged and down-weighted (robust loss), never silently dropped.
    ``robot_noise_m``, ``robot_noise_deg``: one-sigma noise of each axis of the measured robot
    poses (translation, each rotation-vector component): 0, exact poses; else every pose gets a
    correction with this Gaussian prior. ``estimate_robot_noise``: learn the arm's accuracy from
    the data (robot sessions; ``robot_noise_*`` only start the estimation); False: take
    ``robot_noise_*`` as the truth.
    """

    skew: bool = False
    unit_aspect: bool = False
    distortion: tuple[bool, ...] = (True, True, True, True, True)
    outlier_threshold_px: float = 2.0
    robot_noise_m: float = 0.0
    robot_noise_deg: float = 0.0
    estimate_robot_noise: bool = True
    distortion_model: str | None = None

    @property
    def lens(self) -> str:
        """The lens model solved for (opencv5 until the data asks for another)."""
        return self.distortion_model or "opencv5"

    @property
    def distortion_names(self) -> tuple[str, ...]:
        """The lens model's coefficients, in order."""
        return DISTORTION_MODELS[self.lens]

    @property
    def distortion_mask(self) -> tuple[bool, ...]:
        """Which of :attr:`distortion_names` are estimated, one flag each."""
        n, d = len(self.distortion_names), tuple(bool(b) for b in self.distortion)
        if len(d) == n:
            return d
        if len(set(d)) == 1 or (n == 8 and len(d) == 5):
            return (d + (d[-1],) * n)[:n]
        raise InputError(
            f"options.distortion has {len(d)} flags; the {self.lens} model has "
            f"{n} ({', '.join(self.distortion_names)}): give {n} flags"
        )


@dataclass(frozen=True)
class CalibrationProblem:
    """Everything the solver needs; never modified by it."""

    target: Target
    cameras: tuple[CameraSpec, ...]
    frames: tuple[Frame, ...]
    mount: Mount = "eye_in_hand"
    knowledge: Knowledge = "robot"
    options: ModelOptions = field(default_factory=ModelOptions)
    reference_camera: str | None = None  # rigs: the camera the others are expressed against

    def camera(self, name: str) -> CameraSpec:
        """The camera named ``name``."""
        for c in self.cameras:
            if c.name == name:
                return c
        raise InputError(f"no camera named {name!r}; cameras are {[c.name for c in self.cameras]}")

    @property
    def reference(self) -> str:
        """Name of the reference camera of a rig (the first camera unless named)."""
        return self.reference_camera or self.cameras[0].name


# -- the mounts: the frame names a mount implies ---------------------------------------------------
@dataclass(frozen=True)
class MountNames:
    """The frame names a mount implies.

    ``holder``: the frame that carries the camera (``tool`` or ``base``); ``hand_eye``: the
    reference camera's hand-eye transform (``T_tool_cam`` / ``T_base_cam``); ``target``: the
    target pose (``T_base_board`` / ``T_tool_board``).
    """

    holder: str
    hand_eye: str
    target: str

    def hand_eye_of(self, camera: str) -> str:
        """``T_<holder>_<camera>``: a rig camera's hand-eye transform."""
        return f"T_{self.holder}_{camera}"


#: The one table from mount to frame names.
MOUNTS: dict[str, MountNames] = {
    "eye_in_hand": MountNames("tool", "T_tool_cam", "T_base_board"),
    "eye_to_hand": MountNames("base", "T_base_cam", "T_tool_board"),
}


def mount_names(mount: str) -> MountNames | None:
    """The frame names of ``mount`` (``eye_in_hand`` / ``eye_to_hand``), None without a robot."""
    return MOUNTS.get(mount)


def hand_eye_names(mount: str, cameras: list[str] | tuple[str, ...]) -> dict[str, str]:
    """Camera name -> the name of its hand-eye transform in a result.

    ``T_tool_cam`` / ``T_base_cam`` for a single camera, ``T_tool_<name>`` / ``T_base_<name>``
    for every camera of a rig; empty without a robot.
    """
    m = mount_names(mount)
    if m is None:
        return {}
    if len(cameras) == 1:
        return {cameras[0]: m.hand_eye}
    return {c: m.hand_eye_of(c) for c in cameras}
