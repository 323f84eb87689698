"""Session directories on disk (``slidecal.session/1``, docs/FORMATS.md): read them, write them.

:func:`load_session` turns ``session.yaml``, ``images/`` and ``detections.npy``
(:data:`DETECTION_DTYPE`; older sessions hold the corners inline) into a
:class:`~slidecal.solver.problem.CalibrationProblem`; :class:`SessionWriter` appends each frame
as it is captured, so a crash loses at most the frame in flight. The keys each part accepts
are declared once, in :data:`SESSION_KEYS`.
"""

from __future__ import annotations

import io
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slidecal.drivers.ur_pose import T_from_ur_pose, ur_pose_from_T
from slidecal.routines.schema import (  # noqa: F401 - re-exported: the format layer's helpers
    Fields,
    as_array,
    dump_yaml,
    load_yaml,
    plain,
    unknown_key_error,
    write_atomic,
)
from slidecal.solver.camera import DISTORTION_MODELS
from slidecal.solver.detect import detect
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import R_from_quat_wxyz, Rx, Ry, Rz, T_from_Rt
from slidecal.solver.problem import (
    CalibrationProblem,
    CameraSpec,
    Detection,
    Frame,
    ModelOptions,
    Target,
)
from slidecal.solver.target_shape import PRINT_TOLERANCE, default_flatness_m

SESSION_FORMAT = "slidecal.session/1"
SESSION_FILE = "session.yaml"
IMAGE_DIR = "images"
DETECTIONS_FILE = "detections.npy"
#: One row per detected corner: frame id, camera (index in ``cameras:``), corner id, pixel u, v
DETECTION_DTYPE = np.dtype(
    [("frame", "<i8"), ("camera", "<i4"), ("id", "<i4"), ("u", "<f8"), ("v", "<f8")]
)
KNOWLEDGE = ("robot", "board_translation", "board_direction", "none")
MOUNTS = ("eye_in_hand", "eye_to_hand", "none")
STATUSES = ("recording", "complete", "aborted")
ROBOT_DRIVERS = ("simulated", "ur")
CAMERA_DRIVERS = ("simulated", "oak", "uvc")
OAK_SOCKET = re.compile(r"CAM_[A-H]")

#: The keys every part of ``session.yaml`` accepts (add a new field here, then read it below).
SESSION_KEYS: dict[str, tuple[str, ...]] = {
    "": (
        "format",
        "status",
        "mount",
        "knowledge",
        "target",
        "cameras",
        "reference_camera",
        "options",
        "cell",
        "cell_sha256",
        "robot_driver",
        "camera_driver",
        "devices",
        "controller",
        "limits",
        "purpose",
        "installed",
        "simulation",
        "detections_file",
        "import",  # slidecal import: the pose convention chosen and its evidence
        "frames",
        "events",
    ),
    "cameras[]": ("name", "width", "height", "socket"),
    "frames[]": ("id", "group", "T_base_tool", "motion_board", "images", "detections", "quality"),
    "detection": ("ids", "px"),
    # and transforms named T_<a>_<b>
    "simulation": ("cameras", "noise", "seed", "frames", "board_bow_mm"),
    # per frame id: the pose the simulated arm really reached and the one it reported
    "simulation.frames[]": ("id", "T_base_tool", "T_base_tool_measured"),
    "simulation.cameras.*": ("K", "distortion"),
    "simulation.noise": ("robot_mm", "robot_deg", "cameras", "kinematic_error"),
    "simulation.noise.kinematic_error": ("mm", "deg", "repeatability_mm", "repeatability_deg"),
    "simulation.noise.cameras.*": ("blur_sigma_px", "noise_std", "exposure"),
}

#: How well the real board matches its description (every kind): its bow and its print's error
TOLERANCE_KEYS = ("flatness_mm", "print_tolerance")
#: The keys of a ``target:`` block per kind (cell files and sessions): ``kind``, the kind's own
#: (:class:`Target`'s fields of those names), the tolerance
TARGET_KEYS: dict[str, tuple[str, ...]] = {
    kind: ("kind", *own, *TOLERANCE_KEYS)
    for kind, own in {
        "charuco": ("squares_x", "squares_y", "square_size_m", "marker_size_m", "dictionary"),
        "chessboard": ("squares_x", "squares_y", "square_size_m"),
        "points": ("points_m",),
        "apriltag": ("tag_size_m", "dictionary", "tag_ids", "tag_origins_m"),
        "aprilgrid": ("tag_cols", "tag_rows", "tag_size_m", "tag_spacing", "dictionary"),
    }.items()
}
TARGET_KINDS = tuple(TARGET_KEYS)

#: The keys of an ``options:`` block (cell files and sessions): the fields of
#: :class:`ModelOptions`, ``robot_noise_m`` given in millimetres
OPTIONS_KEYS = tuple(f.name.replace("noise_m", "noise_mm") for f in fields(ModelOptions))

#: How far (pixels) a given detection may lie outside its camera's image (a corner is inside)
DETECTION_MARGIN_PX = 2.0

#: Largest board (squares per side) slidecal accepts: beyond it a typo is likelier than a board.
MAX_SQUARES = 200


# ----------------------------------------------------------------------------- transforms


#: The ways a transform's rotation may be written, and its translation
ROTATION_KEYS = ("R", "rpy_deg", "q_wxyz")
TRANSLATION_KEYS = ("t_m", "t_mm")


def transform_from_dict(f: Fields, key: str) -> np.ndarray:
    """A 4x4 transform from a mapping of one rotation (``R``, ``rpy_deg`` or ``q_wxyz``) and one
    translation (``t_m`` or ``t_mm``); the conventions: docs/FORMATS.md, "Units"."""
    sub = f.sub(key)
    assert sub is not None
    sub.only(ROTATION_KEYS + TRANSLATION_KEYS)
    for keys, what in ((ROTATION_KEYS, "rotation"), (TRANSLATION_KEYS, "translation")):
        given = [k for k in keys if sub.has(k)]
        if len(given) > 1:
            raise sub.error(given[1], f"is given with {given[0]}; give the {what} once")
    if sub.has("t_mm"):
        t = sub.array("t_mm", (3,)) / 1000.0
    else:
        t = sub.array("t_m", (3,))
    if sub.has("R"):
        R = sub.rotation("R", "; fix the values")
    elif sub.has("rpy_deg"):
        r, p, y = np.radians(sub.array("rpy_deg", (3,)))
        R = Rz(y) @ Ry(p) @ Rx(r)
    elif sub.has("q_wxyz"):
        q = sub.array("q_wxyz", (4,))
        norm = float(np.linalg.norm(q))
        if abs(norm - 1.0) > 1e-3:
            raise sub.error(
                "q_wxyz",
                f"has norm {norm:.4g}, not a unit quaternion; give [w, x, y, z] of the rotation",
            )
        R = R_from_quat_wxyz(q)
    else:
        raise sub.error(
            "R", "is missing; give R (3x3), rpy_deg ([roll, pitch, yaw] degrees) or q_wxyz"
        )
    return T_from_Rt(R, t)


def transform_to_dict(T: np.ndarray) -> dict[str, Any]:
    """``{R, t_m}`` of a 4x4 transform (the result file's shape)."""
    T = np.asarray(T, dtype=float)
    return {"R": plain(T[:3, :3]), "t_m": plain(T[:3, 3])}


def ur_pose_field(f: Fields, key: str) -> np.ndarray:
    """A UR pose ``[x, y, z, rx, ry, rz]`` (metres, axis-angle radians) as a 4x4 transform."""
    where = f.where(key)
    pose = as_array(f.get(key), (-1,), where)
    if pose.shape != (6,):
        raise InputError(
            f"has {pose.size} numbers; a UR pose is [x, y, z, rx, ry, rz] "
            "(metres, axis-angle radians)",
            where=where,
        )
    if np.linalg.norm(pose[:3]) > 100.0:
        raise InputError(
            f"is {np.linalg.norm(pose[:3]):.0f} m from the base; give positions in metres",
            where=where,
        )
    if np.any(np.abs(pose[3:]) > 2 * np.pi):
        raise InputError(
            "rotation components above 2 pi look like degrees; give the axis-angle "
            "[rx, ry, rz] in radians",
            where=where,
        )
    try:
        return T_from_ur_pose(pose)
    except ValueError as e:
        raise InputError(" ".join(str(e).split()), where=where) from None


def robot_pose_field(f: Fields, key: str) -> np.ndarray:
    """A frame's robot pose (4x4): a UR pose ``[x, y, z, rx, ry, rz]`` or, from any other
    controller, a transform (:func:`transform_from_dict`)."""
    if not isinstance(f.get(key), Mapping):
        return ur_pose_field(f, key)
    T = transform_from_dict(f, key)
    if np.linalg.norm(T[:3, 3]) > 100.0:
        unit = "t_m" if f.sub(key).has("t_m") else "t_mm"
        raise InputError(
            f"is {np.linalg.norm(T[:3, 3]):.0f} m from the base; "
            + ("millimetres go in t_mm" if unit == "t_m" else "give the position in t_mm"),
            where=f.where(f"{key}.{unit}"),
        )
    return T


# ----------------------------------------------------------------------------- targets


def _dictionary_size(name: str) -> int | None:
    """Number of markers of an OpenCV predefined ArUco dictionary (None: not one)."""
    if not re.fullmatch(r"DICT_\w+", name) or not isinstance(getattr(cv2.aruco, name, None), int):
        return None
    try:
        return int(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0])
    except cv2.error:
        return None


def target_from_dict(data: Any, file: str, exact_by_default: bool = False) -> Target:
    """A :class:`Target` from a ``target:`` block (charuco, chessboard, points, apriltag or
    aprilgrid). Its tolerance (``flatness_mm``, ``print_tolerance``) takes a real board's
    defaults when not given (``solver/target_shape.py``), or 0 with ``exact_by_default`` (a
    simulated board is exactly as described)."""
    f = Fields(data, file, "target").only(
        tuple(dict.fromkeys(k for v in TARGET_KEYS.values() for k in v))
    )
    kind = f.choice("kind", TARGET_KINDS)
    f.only(TARGET_KEYS[kind])
    target = _target_of_kind(f, kind)
    flat = f.number("flatness_mm", None, minimum=0.0) if f.has("flatness_mm") else None
    if flat is not None and flat > 20.0:
        raise f.error("flatness_mm", f"is {flat} mm; give the board's one-sigma bow in mm")
    tol = f.number("print_tolerance", None, minimum=0.0) if f.has("print_tolerance") else None
    if tol is not None and tol > 0.05:
        raise f.error(
            "print_tolerance",
            f"is {tol}; give the print's one-sigma relative error (0.0002 for 0.02 %)",
        )
    if flat is None:
        flat = 0.0 if exact_by_default else 1000.0 * default_flatness_m(target.points_m)
    if tol is None:
        tol = 0.0 if exact_by_default else PRINT_TOLERANCE
    return replace(target, flatness_m=flat / 1000.0, print_tolerance=float(tol))


def _target_of_kind(f: Fields, kind: str) -> Target:
    """The :class:`Target` of a validated ``target:`` block's kind-specific keys."""
    if kind == "points":
        pts = f.array("points_m", (-1, 2))
        if len(pts) < 4:
            raise f.error("points_m", f"has {len(pts)} points; give at least 4 [X, Y] pairs")
        if len({tuple(p) for p in pts.tolist()}) != len(pts):
            raise f.error("points_m", "has repeated points; each point may appear once")
        if np.abs(pts).max() > 10.0:
            raise f.error("points_m", "has points beyond 10 m; give the positions in metres")
        return Target.points(pts)
    if kind in ("apriltag", "aprilgrid"):
        tag = f.number("tag_size_m", positive=True)
        if tag > 2.0:
            raise f.error("tag_size_m", f"is {tag} m; give the tag size in metres (e.g. 0.088)")
        family = f.string("dictionary", "DICT_APRILTAG_36h11")
        if not re.fullmatch(r"DICT_\w+", family) or not hasattr(cv2.aruco, family):
            raise f.error(
                "dictionary",
                f"{family!r} is not an OpenCV predefined dictionary (e.g. DICT_APRILTAG_36h11)",
            )
        if kind == "aprilgrid":
            spacing = f.number("tag_spacing", positive=True)
            if spacing >= 2.0:
                raise f.error(
                    "tag_spacing",
                    f"is {spacing}; give the gap between tags as a fraction of the tag size "
                    "(Kalibr's tagSpacing, e.g. 0.3)",
                )
            cols = f.integer("tag_cols", minimum=1)
            rows = f.integer("tag_rows", minimum=1)
            return Target.aprilgrid(cols, rows, tag, spacing, family)
        ids_raw = f.get("tag_ids", [0])
        if not isinstance(ids_raw, list) or not all(
            isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in ids_raw
        ):
            raise f.error("tag_ids", "must be a list of non-negative integer tag ids")
        if not ids_raw or len(set(ids_raw)) != len(ids_raw):
            raise f.error("tag_ids", "must name at least one tag, each once")
        origins = None
        if f.has("tag_origins_m"):
            o = f.array("tag_origins_m", (-1, 2))
            if len(o) != len(ids_raw):
                raise f.error("tag_origins_m", f"has {len(o)} positions for {len(ids_raw)} tag_ids")
            origins = tuple((float(x), float(y)) for x, y in o)
        elif len(ids_raw) > 1:
            raise f.error(
                "tag_origins_m",
                "is missing; give the top-left corner [X, Y] (metres) of every tag",
            )
        return Target.apriltag(tag, tuple(ids_raw), origins, family)
    sx = f.integer("squares_x", minimum=3, maximum=MAX_SQUARES)
    sy = f.integer("squares_y", minimum=3, maximum=MAX_SQUARES)
    size = f.number("square_size_m", positive=True)
    if size > 1.0:
        raise f.error("square_size_m", f"is {size} m; give the square size in metres (e.g. 0.030)")
    if kind == "chessboard":
        return Target.chessboard(sx, sy, size)
    marker = f.number("marker_size_m", positive=True)
    if marker >= size:
        raise f.error("marker_size_m", f"({marker}) must be smaller than square_size_m ({size})")
    dictionary = f.string("dictionary", "DICT_5X5_100")
    n_dict = _dictionary_size(dictionary)
    if n_dict is None:
        raise f.error(
            "dictionary",
            f"{dictionary!r} is not an OpenCV predefined dictionary (e.g. DICT_5X5_100)",
        )
    needed = (sx * sy) // 2
    if needed > n_dict:
        raise f.error(
            "dictionary",
            f"{dictionary} has {n_dict} markers but a {sx}x{sy} ChArUco board needs {needed}; "
            "use a larger dictionary (e.g. DICT_5X5_250) or fewer squares",
        )
    return Target.charuco(sx, sy, size, marker, dictionary)


def target_to_dict(target: Target) -> dict[str, Any]:
    """The ``target:`` block of a :class:`Target`, its tolerance included."""
    d = _kind_to_dict(target)
    d["flatness_mm"] = 1000.0 * float(target.flatness_m)
    d["print_tolerance"] = float(target.print_tolerance)
    return d


def _kind_to_dict(target: Target) -> dict[str, Any]:
    """The kind-specific keys of a ``target:`` block (:data:`TARGET_KEYS`)."""
    if target.kind == "points":
        return {"kind": "points", "points_m": plain(target.points_m[:, :2])}
    keys = TARGET_KEYS[target.kind][1 : -len(TOLERANCE_KEYS)]
    if target.kind == "apriltag":  # the order slidecal has always written them in
        keys = ("tag_size_m", "tag_ids", "tag_origins_m", "dictionary")
    return {"kind": target.kind, **{k: plain(getattr(target, k)) for k in keys}}


def options_from_dict(data: Any, file: str) -> ModelOptions:
    """:class:`ModelOptions` from an ``options:`` block (absent fields keep their defaults)."""
    f = Fields(data, file, "options").only(OPTIONS_KEYS)
    base = ModelOptions()
    model = None  # the data chooses
    if f.has("distortion_model"):
        model = f.choice("distortion_model", tuple(DISTORTION_MODELS))
    names = DISTORTION_MODELS[model or "opencv5"]
    dist = (True,) * len(names)
    if f.has("distortion"):
        v = f.get("distortion")
        flags = isinstance(v, list) and all(isinstance(b, bool) for b in v)
        if not (flags and len(v) == len(names)):
            raise f.error(
                "distortion", f"must be {len(names)} booleans: which of {', '.join(names)} to fit"
            )
        dist = tuple(v)
    return ModelOptions(
        distortion_model=model,
        skew=f.boolean("skew", base.skew),
        unit_aspect=f.boolean("unit_aspect", base.unit_aspect),
        distortion=dist,  # type: ignore[arg-type]
        outlier_threshold_px=f.number(
            "outlier_threshold_px", base.outlier_threshold_px, positive=True
        ),
        robot_noise_m=f.number("robot_noise_mm", 0.0, minimum=0.0, maximum=100.0) / 1000.0,
        robot_noise_deg=f.number("robot_noise_deg", 0.0, minimum=0.0, maximum=10.0),
        estimate_robot_noise=f.boolean("estimate_robot_noise", base.estimate_robot_noise),
    )


def options_to_dict(options: ModelOptions) -> dict[str, Any]:
    """The ``options:`` block of :class:`ModelOptions` (``robot_noise_mm``: ``robot_noise_m``)."""
    d = {k: plain(getattr(options, k.replace("_mm", "_m"))) for k in OPTIONS_KEYS}
    d["robot_noise_mm"] *= 1000.0
    d["distortion"] = list(options.distortion_mask)
    if options.distortion_model is None:  # the data chooses
        del d["distortion_model"]
    return d


# ----------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class Session:
    """A session read from disk: the solver's problem plus what the run recorded around it.

    ``simulation``: the truth block (None for real runs); ``events``: faults, aborts;
    ``detect_reasons``: per (frame id, camera) why an image detected on reading gave nothing;
    ``cell``/``cell_sha256``: the cell file (None in older sessions); ``sockets``: OAK board
    socket per camera; ``limits``: the ``limits:`` block.
    """

    directory: Path
    problem: CalibrationProblem
    simulation: dict[str, Any] | None = None
    events: tuple[dict[str, Any], ...] = ()
    status: str = "complete"
    cell: str | None = None
    cell_sha256: str | None = None
    camera_driver: str | None = None
    sockets: dict[str, str] = field(default_factory=dict)
    detect_reasons: dict[tuple[int, str], tuple[str, ...]] = field(default_factory=dict)
    limits: Any = None


def load_session(directory: str | Path, detect_images: bool = True) -> Session:
    """Read and validate ``directory/session.yaml``; a camera with an image but no detections is
    detected (``detect_images``, else an error). Without robot poses, knowledge and mount become
    ``"none"``. Every problem is an ``InputError`` naming ``session.yaml: <field>``."""
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(
            "is not a session directory; give the folder that holds session.yaml",
            where=str(directory),
        )
    data = load_yaml(directory / SESSION_FILE, "session.yaml")
    return session_from_dict(data, directory, detect_images)


def session_from_dict(data: Any, directory: Path, detect_images: bool = True) -> Session:
    """Validate a parsed ``session.yaml`` of ``directory`` (see :func:`load_session`)."""
    f = Fields(data, SESSION_FILE)
    _check_format(f, SESSION_FORMAT, "session")
    f.only(SESSION_KEYS[""])
    target = target_from_dict(f.require("target"), SESSION_FILE)

    cameras, sockets = _cameras(f)
    names = [c.name for c in cameras]
    table = _detection_table(f, directory, len(cameras))

    frames: list[Frame] = []
    reasons: dict[tuple[int, str], tuple[str, ...]] = {}
    ids_seen: set[int] = set()
    for ff in f.entries("frames", hint="frame {id, T_base_tool, detections}"):
        frame = _read_frame(ff, directory, target, cameras, detect_images, reasons, table)
        if frame.id in ids_seen:
            raise ff.error("id", f"frame id {frame.id} appears twice; ids must be unique")
        ids_seen.add(frame.id)
        frames.append(frame)

    with_pose = [fr.T_base_tool is not None for fr in frames]
    if any(with_pose) and not all(with_pose):
        i = with_pose.index(False)
        raise InputError(
            "is missing while other frames have one; give a pose for every frame or for none",
            where=f"{SESSION_FILE}: frames[{i}].T_base_tool",
        )
    has_robot = bool(frames) and all(with_pose)
    if has_robot:
        knowledge = f.choice("knowledge", KNOWLEDGE, "robot")
        mount = f.choice("mount", MOUNTS, "eye_in_hand")
    else:
        knowledge = f.choice("knowledge", KNOWLEDGE, "none")
        if knowledge == "robot":
            why = "the session holds no frames" if not frames else "no frame has a T_base_tool"
            raise f.error("knowledge", f"is 'robot' but {why}; record frames with robot poses")
        # without robot poses there is no mount: whatever the file says of it is not used (a
        # word of the user's own is no reason to refuse images that calibrate a camera)
        if f.has("mount") and not isinstance(f.get("mount"), str):
            f.choice("mount", MOUNTS)
        mount = "none"
    if knowledge in ("board_translation", "board_direction"):
        for i, fr in enumerate(frames):
            if fr.motion_board is None:
                raise InputError(
                    f"is missing; knowledge {knowledge!r} needs motion_board on every frame",
                    where=f"{SESSION_FILE}: frames[{i}].motion_board",
                )
    ref = f.camera("reference_camera", names) if f.has("reference_camera") else None
    options = options_from_dict(f.get("options", {}), SESSION_FILE)
    problem = CalibrationProblem(
        target=target,
        cameras=cameras,
        frames=tuple(frames),
        mount=mount,  # type: ignore[arg-type]
        knowledge=knowledge,  # type: ignore[arg-type]
        options=options,
        reference_camera=ref,
    )
    events = _events(f)
    sim = _simulation_truth(f.sub("simulation", required=False), names)
    sha = f.string("cell_sha256", "-") if f.has("cell_sha256") else None
    if sha is not None and not re.fullmatch(r"[0-9a-f]{64}", sha):
        raise f.error("cell_sha256", "must be 64 lowercase hex digits (a SHA-256)")
    if f.has("robot_driver"):  # recorded, not used
        f.choice("robot_driver", ROBOT_DRIVERS)
    return Session(
        directory=directory,
        problem=problem,
        simulation=sim,
        events=events,
        status=f.choice("status", STATUSES, "complete"),
        cell=f.string("cell", "-") if f.has("cell") else None,
        cell_sha256=sha,
        camera_driver=f.choice("camera_driver", CAMERA_DRIVERS, "oak")
        if f.has("camera_driver")
        else None,
        sockets=sockets,
        detect_reasons=reasons,
        limits=f.get("limits"),
    )


def _cameras(f: Fields) -> tuple[tuple[CameraSpec, ...], dict[str, str]]:
    """The session's cameras and the OAK board socket of those that give one."""
    cameras: list[CameraSpec] = []
    sockets: dict[str, str] = {}
    hint = "camera {name, width, height}"
    for cf in f.entries("cameras", SESSION_KEYS["cameras[]"], non_empty=True, hint=hint):
        cameras.append(camera_spec(cf, [x.name for x in cameras]))
        if cf.has("socket"):
            sockets[cameras[-1].name] = _socket(cf)
    return tuple(cameras), sockets


def camera_spec(cf: Fields, taken: Sequence[str]) -> CameraSpec:
    """A camera's ``{name, width, height}`` (cell files and sessions); ``taken``: the names
    already read, which this one must not repeat."""
    name = cf.string("name")
    if name in taken:
        raise cf.error("name", f"{name!r} appears twice; camera names must be unique")
    return CameraSpec(
        name,
        cf.integer("width", minimum=1, maximum=100_000),
        cf.integer("height", minimum=1, maximum=100_000),
    )


def _socket(cf: Fields) -> str:
    s = cf.string("socket")
    if not OAK_SOCKET.fullmatch(s):
        raise cf.error("socket", f"is {s!r}; an OAK board socket is CAM_A .. CAM_H")
    return s


def _events(f: Fields) -> tuple[dict[str, Any], ...]:
    out = []
    for ef in f.entries("events", required=False):
        ef.string("kind")
        ef.string("message")
        out.append(dict(ef.data))
    return tuple(out)


def _simulation_truth(f: Fields | None, names: Sequence[str]) -> dict[str, Any] | None:
    """The ``simulation:`` block, checked: transforms are rotations, cameras known, K 3x3."""
    if f is None:
        return None
    for key in f.data:
        if isinstance(key, str) and re.fullmatch(r"T_\w+_\w+", key):
            transform_from_dict(f, key)
        elif key not in SESSION_KEYS["simulation"]:
            raise unknown_key_error(f.where(str(key)), key, SESSION_KEYS["simulation"])
    cf = f.section("cameras")
    for name in cf.cameras(names):
        c = cf.section(name, SESSION_KEYS["simulation.cameras.*"])
        c.array("K", (3, 3))
        c.distortion("distortion")
    nf = f.section("noise", SESSION_KEYS["simulation.noise"])
    nf.number("robot_mm", 0.0, minimum=0.0)
    nf.number("robot_deg", 0.0, minimum=0.0)
    kf = nf.section("kinematic_error", SESSION_KEYS["simulation.noise.kinematic_error"])
    for k in SESSION_KEYS["simulation.noise.kinematic_error"]:
        kf.number(k, 0.0, minimum=0.0)
    ncf = nf.section("cameras")
    for name in ncf.data:
        c = ncf.section(str(name), SESSION_KEYS["simulation.noise.cameras.*"])
        for k in SESSION_KEYS["simulation.noise.cameras.*"]:
            c.number(k, 0.0, minimum=0.0)
    if f.has("seed"):
        f.integer("seed", minimum=0)
    if f.has("board_bow_mm"):
        f.array("board_bow_mm", (2,))
    frames = f.list("frames", required=False)
    if _plain_truth_frames(frames):
        return dict(f.data)
    seen: set[int] = set()
    for ff in f.entries("frames", SESSION_KEYS["simulation.frames[]"], required=False):
        fid = ff.integer("id", minimum=0)
        if fid in seen:
            raise ff.error("id", f"frame {fid} is listed twice; give each frame's truth once")
        seen.add(fid)
        ur_pose_field(ff, "T_base_tool")
        ur_pose_field(ff, "T_base_tool_measured")
    return dict(f.data)


def _plain_truth_frames(frames: list[Any]) -> bool:
    """Whether the simulated truth's frames pass every check at once (ids unique, UR poses of 6
    finite numbers in metres and radians): a simulated run's thousand frames are then read
    without checking each field apart, which is what names a bad one."""
    keys = SESSION_KEYS["simulation.frames[]"]
    poses = []
    for fr in frames:
        if type(fr) is not dict or len(fr) != len(keys) or any(k not in fr for k in keys):
            return False
        if type(fr["id"]) is not int or fr["id"] < 0:
            return False
        for k in keys[1:]:
            if type(fr[k]) is not list or len(fr[k]) != 6:
                return False
            poses.append(fr[k])
    if any(type(v) is not float and type(v) is not int for p in poses for v in p):
        return False
    p = np.array(poses, dtype=float).reshape(-1, 6)
    return bool(
        len({fr["id"] for fr in frames}) == len(frames)
        and np.isfinite(p).all()
        and (np.linalg.norm(p[:, :3], axis=1) <= 100.0).all()
        and (np.abs(p[:, 3:]) <= 2 * np.pi).all()
    )


def _check_format(f: Fields, expected: str, what: str) -> None:
    fmt = f.require("format")
    if fmt == expected:
        return
    family, _, version = expected.rpartition("/")
    if isinstance(fmt, str) and fmt.startswith(family + "/"):
        raise f.error(
            "format",
            f"is {fmt!r}; this slidecal reads {expected!r}: upgrade slidecal to read this {what}",
        )
    raise f.error("format", f"is {fmt!r}, not a slidecal {what} file; expected {expected!r}")


def _read_frame(
    f: Fields,
    directory: Path,
    target: Target,
    cameras: Sequence[CameraSpec],
    detect_images: bool,
    reasons: dict[tuple[int, str], tuple[str, ...]],
    table: DetectionTable | None,
) -> Frame:
    """One frame; ``reasons`` collects why an image detected here gave nothing usable."""
    f.only(SESSION_KEYS["frames[]"])
    fid = f.integer("id", minimum=0)
    names = [c.name for c in cameras]
    T = robot_pose_field(f, "T_base_tool") if f.has("T_base_tool") else None
    motion = f.array("motion_board", (3,)) if f.has("motion_board") else None
    group = f.integer("group", minimum=0) if f.has("group") else None

    ims = f.section("images")
    image_paths = {name: directory / _inside(ims, name) for name in ims.cameras(names)}

    detections: dict[str, Detection] = {}
    dets = f.section("detections")
    for name in dets.cameras(names):
        k = names.index(name)
        value = dets.data[name]
        if isinstance(value, int) and not isinstance(value, bool):
            detections[name] = _stored_detection(dets, name, (fid, k), table, target, cameras[k])
        else:
            detections[name] = _read_detection(dets.section(name), target, cameras[k])

    for name, path in image_paths.items():
        if name in detections:
            continue
        if path.is_dir():
            raise ims.error(
                name, f"{path.name} is a folder, not an image; give the image file's path"
            )
        if not path.is_file():
            raise ims.error(
                name, f"image {path.name} not found; restore it or give detections for {name!r}"
            )
        if not detect_images:
            raise ims.error(name, "has an image but no detections, and detection was turned off")
        spec = cameras[names.index(name)]
        detections[name], why = _detect_file(path, target, ims.where(name), spec)
        if why:
            reasons[(fid, name)] = why
    q = f.section("quality")
    for name in q.cameras(names):
        q.section(name)
    return Frame(id=fid, detections=detections, T_base_tool=T, motion_board=motion, group=group)


def _read_detection(f: Fields, target: Target, camera: CameraSpec) -> Detection:
    """A detection given inline, ``{ids, px}``."""
    f.only(SESSION_KEYS["detection"])
    ids_raw = f.get("ids", [])
    if not isinstance(ids_raw, list) or not all(
        isinstance(i, int) and not isinstance(i, bool) for i in ids_raw
    ):
        raise f.error("ids", "must be a list of integer corner ids")
    px = as_array(f.get("px", []), (-1, 2), f.where("px"))
    if len(ids_raw) != len(px):
        raise f.error(
            "px", f"has {len(px)} positions for {len(ids_raw)} ids; give one [u, v] per id"
        )
    ids = np.asarray(ids_raw, dtype=np.int64)
    return _checked_detection(ids, px, f.where("ids"), f.where("px"), target, camera)


def _stored_detection(
    f: Fields,
    name: str,
    key: tuple[int, int],
    table: DetectionTable | None,
    target: Target,
    camera: CameraSpec,
) -> Detection:
    """A detection whose corners (``key``: frame id, camera index) are in the detections file;
    ``f.data[name]`` counts them."""
    n = f.integer(name, minimum=0)
    if table is None:
        raise f.error(
            name,
            f"counts {n} corners but the session names no detections_file; give "
            f"detections_file: {DETECTIONS_FILE} or the corners inline as {{ids, px}}",
        )
    ids, px = table.rows.get(key, (np.zeros(0, np.int64), np.zeros((0, 2))))
    where = f"{table.name}: frame {key[0]}, camera {name!r}"
    if len(ids) != n:
        raise InputError(
            f"holds {len(ids)} corners where session.yaml counts {n}; the file is damaged or "
            "belongs to another session: restore the session's own file",
            where=where,
        )
    return _checked_detection(ids, px, where, where, target, camera)


def _checked_detection(
    ids: np.ndarray,
    px: np.ndarray,
    where_ids: str,
    where_px: str,
    target: Target,
    camera: CameraSpec,
) -> Detection:
    """``Detection(ids, px)`` once its ids are on the target, once each, and its pixels finite
    and inside the camera's image."""
    n = len(target.points_m)
    bad = (ids < 0) | (ids >= n)
    if bad.any():
        raise InputError(
            f"id {ids[bad][0]} is not on the target (ids are 0..{n - 1})", where=where_ids
        )
    if len(set(ids.tolist())) != len(ids):
        raise InputError("has repeated ids; each corner may appear once per image", where=where_ids)
    if not np.isfinite(px).all():
        raise InputError("must hold finite numbers only (no NaN, no inf)", where=where_px)
    w, h = camera.width, camera.height
    outside = (px[:, 0] < -DETECTION_MARGIN_PX - 0.5) | (px[:, 0] > w - 0.5 + DETECTION_MARGIN_PX)
    outside |= (px[:, 1] < -DETECTION_MARGIN_PX - 0.5) | (px[:, 1] > h - 0.5 + DETECTION_MARGIN_PX)
    if outside.any():
        u, v = px[np.flatnonzero(outside)[0]]
        raise InputError(
            f"[{u:.1f}, {v:.1f}] lies outside the {w} x {h} image of camera {camera.name!r}; give "
            "pixels of that image (u across, v down; check the cameras' width and height)",
            where=where_px,
        )
    return Detection(ids, px)


@dataclass(frozen=True)
class DetectionTable:
    """The detections file read: per (frame id, camera index) its corner ids and pixels."""

    name: str
    rows: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]


def _detection_table(f: Fields, directory: Path, n_cameras: int) -> DetectionTable | None:
    """The table ``detections_file`` names (None when the session names none)."""
    if not f.has("detections_file"):
        return None
    rel = _inside(f, "detections_file")
    path = directory / rel
    if not path.is_file():
        raise f.error(
            "detections_file", f"{rel} not found; restore it (it holds the frames' corners)"
        )
    try:
        table = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        why = " ".join(str(e).split())
        raise InputError(
            f"is not a readable .npy file ({why}); restore the session's own file", where=rel
        ) from None
    if table.ndim != 1 or table.dtype != DETECTION_DTYPE:
        fields = ", ".join(f"{n} {DETECTION_DTYPE[n].name}" for n in DETECTION_DTYPE.names)
        raise InputError(
            f"is not a detections table (a 1-d array of records {fields}); restore the "
            "session's own file",
            where=rel,
        )
    table = table[(table["camera"] >= 0) & (table["camera"] < n_cameras)]
    key = table["frame"].astype(np.int64) * n_cameras + table["camera"]
    order = np.argsort(key, kind="stable")
    keys, starts, counts = np.unique(key[order], return_index=True, return_counts=True)
    ids = table["id"][order].astype(np.int64)
    px = np.column_stack([table["u"][order], table["v"][order]]).astype(float)
    rows = {
        divmod(k, n_cameras): (ids[a : a + c], px[a : a + c])
        for k, a, c in zip(keys.tolist(), starts.tolist(), counts.tolist(), strict=True)
    }
    return DetectionTable(rel, rows)


def _inside(f: Fields, key: str) -> str:
    """A path relative to the session, refused when it leaves it."""
    rel = f.get(key)
    if not isinstance(rel, str) or not rel.strip():
        raise f.error(key, f"must be a path relative to the session, got {rel!r}")
    if Path(rel).is_absolute() or ".." in Path(rel).parts:
        raise f.error(key, f"{rel!r} leaves the session; give a path inside it")
    return rel


def _detect_file(
    path: Path, target: Target, where: str, camera: CameraSpec
) -> tuple[Detection, tuple[str, ...]]:
    """The detection of an image file, and the detector's reasons when it found nothing usable."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path.name} is not a readable image; replace it", where=where)
    h, w = image.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise InputError(
            f"{path.name} is {w} x {h} pixels, but camera {camera.name!r} is "
            f"{camera.width} x {camera.height}; give the cameras' width and height of their "
            "images (or images of that size)",
            where=where,
        )
    report = detect(image, target)
    return report.detection, () if report.ok else tuple(report.reasons)


# ----------------------------------------------------------------------------- writing


def _npy_header(n_rows: int) -> bytes:
    """The ``.npy`` header of a detections table of ``n_rows`` rows; numpy pads it so that its
    length does not change as the table grows (rewritten in place)."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf,
        {
            "descr": np.lib.format.dtype_to_descr(DETECTION_DTYPE),
            "fortran_order": False,
            "shape": (n_rows,),
        },
    )
    return buf.getvalue()


def _append_rows(path: Path, n_rows: int, rows: np.ndarray) -> int:
    """Write ``rows`` after the first ``n_rows`` of the table at ``path`` (over any rows of a
    frame that was in flight), then the header that counts them; return the new count."""
    with open(path, "r+b") as f:
        f.seek(len(_npy_header(n_rows)) + n_rows * DETECTION_DTYPE.itemsize)
        f.write(rows.tobytes())
        f.truncate()
        f.flush()
        os.fsync(f.fileno())
        f.seek(0)
        f.write(_npy_header(n_rows + len(rows)))
        f.flush()
        os.fsync(f.fileno())
    return n_rows + len(rows)


class SessionWriter:
    """Create a session directory and append frames as they are captured (images, then corners,
    then ``session.yaml`` atomically: the files always describe complete frames only)."""

    def __init__(
        self,
        directory: str | Path,
        target: Target,
        cameras: Sequence[CameraSpec],
        mount: str = "eye_in_hand",
        knowledge: str = "robot",
        options: ModelOptions | None = None,
        reference_camera: str | None = None,
        simulation: Mapping[str, Any] | None = None,
        extra: Mapping[str, Any] | None = None,
        sockets: Mapping[str, str] | None = None,
    ) -> None:
        self.directory = Path(directory)
        for k in extra or {}:  # a field the reader would refuse
            if k not in SESSION_KEYS[""]:
                raise InputError(
                    f"{k!r} is not a session field of {SESSION_FORMAT}; declare it in SESSION_KEYS"
                )
        if (self.directory / SESSION_FILE).exists():
            raise InputError(
                "already holds a session; choose a new --out directory or delete the old one",
                where=str(self.directory),
            )
        (self.directory / IMAGE_DIR).mkdir(parents=True, exist_ok=True)
        self._names = [c.name for c in cameras]
        self.data: dict[str, Any] = {"format": SESSION_FORMAT, "status": "recording"}
        if mount != "none":
            self.data["mount"] = mount
        self.data["knowledge"] = knowledge
        self.data["target"] = target_to_dict(target)
        self.data["cameras"] = []
        for c in cameras:
            entry = {"name": c.name, "width": int(c.width), "height": int(c.height)}
            if sockets and sockets.get(c.name):
                entry["socket"] = str(sockets[c.name])
            self.data["cameras"].append(entry)
        if reference_camera is not None:
            self.data["reference_camera"] = reference_camera
        self.data["options"] = options_to_dict(options or ModelOptions())
        if extra:
            self.data.update(plain(dict(extra)))
        if simulation is not None:
            self.data["simulation"] = plain(dict(simulation))
        self.data["frames"] = []
        self.data["events"] = []
        self._rows = 0
        self._write()

    @classmethod
    def reopen(cls, directory: str | Path) -> SessionWriter:
        """Continue writing an existing session (``slidecal run --resume``): its frames and
        events are kept, new frames are appended, ``status`` goes back to ``recording``."""
        directory = Path(directory)
        data = load_yaml(directory / SESSION_FILE, "session file")
        f = Fields(data, SESSION_FILE)
        _check_format(f, SESSION_FORMAT, "session")
        w = cls.__new__(cls)
        w.directory = directory
        target_from_dict(f.require("target"), SESSION_FILE)  # refused now, not at the solve
        w._names = [c.name for c in _cameras(f)[0]]
        w.data = dict(data)
        w.data.setdefault("frames", [])
        w.data.setdefault("events", [])
        # the rows the listed frames count; a frame in flight's rows beyond them are overwritten
        w._rows = sum(
            v
            for fr in w.data["frames"]
            if isinstance(fr, Mapping) and isinstance(fr.get("detections"), Mapping)
            for v in fr["detections"].values()
            if isinstance(v, int) and not isinstance(v, bool)
        )
        w.data["status"] = "recording"
        w._write()
        return w

    @property
    def n_frames(self) -> int:
        """Number of frames written so far."""
        return len(self.data["frames"])

    def append_frame(
        self,
        T_base_tool: np.ndarray | None,
        images: Mapping[str, np.ndarray] | None = None,
        detections: Mapping[str, Detection] | None = None,
        group: int | None = None,
        quality: Mapping[str, Mapping[str, Any]] | None = None,
        motion_board: np.ndarray | None = None,
        frame_id: int | None = None,
        T_base_tool_true: np.ndarray | None = None,
    ) -> int:
        """Write one frame now and return its id (``frame_id``, default: the next free id).

        ``T_base_tool`` (4, 4) m: the measured pose (None without a robot); ``images``: uint8 (H, W)
        or (H, W, 3) per camera, saved as PNG; ``detections`` per camera; ``motion_board`` (3,):
        board-frame motion knowledge; ``T_base_tool_true`` (4, 4): the pose the simulated arm really
        reached (kept only with a ``simulation:`` block).
        """
        used = [int(fr["id"]) for fr in self.data["frames"]]
        fid = (max(used) + 1 if used else 0) if frame_id is None else int(frame_id)
        if fid in used:
            raise InputError(f"frame id {fid} is already in the session; ids must be unique")
        entry: dict[str, Any] = {"id": fid}
        if group is not None:
            entry["group"] = int(group)
        if T_base_tool is not None:
            entry["T_base_tool"] = ur_pose_from_T(np.asarray(T_base_tool, dtype=float))
        if motion_board is not None:
            entry["motion_board"] = plain(np.asarray(motion_board, dtype=float).reshape(3))
        for name in list(images or {}) + list(detections or {}):
            if name not in self._names:
                raise InputError(f"unknown camera {name!r}; cameras are {self._names}")
        if images:
            entry["images"] = {}
            for name, img in images.items():
                rel = f"{IMAGE_DIR}/{fid:04d}_{name}.png"
                tmp = self.directory / IMAGE_DIR / f".{fid:04d}_{name}.tmp.png"
                if not cv2.imwrite(str(tmp), np.asarray(img)):
                    raise InputError(f"could not write image {rel}; check the disk and rights")
                os.replace(tmp, self.directory / rel)
                entry["images"][name] = rel
        if detections:
            entry["detections"] = {n: len(d.ids) for n, d in detections.items()}
            self._append_detections(fid, detections)
        if quality:
            entry["quality"] = plain({n: dict(q) for n, q in quality.items()})
        self.data["frames"].append(entry)
        sim = self.data.get("simulation")
        if T_base_tool_true is not None and sim is not None and T_base_tool is not None:
            sim.setdefault("frames", []).append(
                {
                    "id": fid,
                    "T_base_tool": ur_pose_from_T(np.asarray(T_base_tool_true, dtype=float)),
                    "T_base_tool_measured": entry["T_base_tool"],
                }
            )
        self._write()
        return fid

    def _append_detections(self, fid: int, detections: Mapping[str, Detection]) -> None:
        path = self.directory / self.data.setdefault("detections_file", DETECTIONS_FILE)
        if self._rows == 0 or not path.is_file():  # a new table (over an old session's)
            write_atomic(path, _npy_header(0))
            self._rows = 0
        parts = []
        for name, d in detections.items():
            rows = np.zeros(len(d.ids), DETECTION_DTYPE)
            rows["frame"], rows["camera"], rows["id"] = fid, self._names.index(name), d.ids
            rows["u"], rows["v"] = d.px[:, 0], d.px[:, 1]
            parts.append(rows)
        self._rows = _append_rows(path, self._rows, np.concatenate(parts))

    def add_event(self, kind: str, message: str, **fields: Any) -> None:
        """Record what happened (a fault, an abort) in ``events`` and write the file now."""
        self.data["events"].append({"kind": kind, "message": message, **plain(fields)})
        self._write()

    def finish(self, status: str = "complete") -> Path:
        """Mark the session ``complete`` (or ``aborted``) and return its directory."""
        self.data["status"] = status
        self._write()
        return self.directory

    def _write(self) -> None:
        write_atomic(self.directory / SESSION_FILE, self._text())

    def _text(self) -> str:
        """``dump_yaml(self.data)``, the text of each frame and of its simulated truth made once
        (neither changes once written): appending stays linear in the frames, not quadratic. The
        rest is dumped with those lists empty, and the cached text fills them."""
        cache = self.__dict__.setdefault("_item_text", {"frames": [], "simulation": []})
        data, sim = dict(self.data, frames=[]), self.data.get("simulation")
        lists = {"frames": (self.data["frames"], 0)}  # key -> (its frames, how deep they are)
        if isinstance(sim, Mapping) and isinstance(sim.get("frames"), list):
            data["simulation"] = dict(sim, frames=[])
            lists["simulation"] = (sim["frames"], 2)
        text = dump_yaml(data)
        for key, (items, indent) in lists.items():  # the top-level frames: the only ones unindented
            empty = f"\n{' ' * indent}frames: []\n"
            at = text.index(empty, text.index(f"\n{key}:\n") if indent else 0)
            fill = _list_text("frames", items, cache[key], indent)
            text = text[: at + 1] + fill + text[at + len(empty) :]
        return text


def _list_text(key: str, items: list[Any], cache: list[str], indent: int) -> str:
    """``key: [items]`` as a block list ``indent`` deep, each item's text cached in ``cache``."""
    cache.extend(dump_yaml([x], indent) for x in items[len(cache) :])
    pad = " " * indent
    return f"{pad}{key}:\n" + "".join(cache) if items else f"{pad}{key}: []\n"
