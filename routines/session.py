"""Session directories on disk (``/work/shared/SESSION_FORMAT.md``): read them, write them.

A session is everything one run observed: ``SESSION_DIR/session.yaml`` plus the images under
``SESSION_DIR/images/``. :func:`read_session` turns it into a
:class:`~slidecal.solver.problem.CalibrationProblem`; :class:`SessionWriter` creates it and
appends each frame the moment it is captured, rewriting ``session.yaml`` atomically (temporary
file, fsync, rename), so a crash loses at most the frame in flight.

Fields beyond the contract (all optional, additive, so the format stays ``slidecal.session/1``):

- ``knowledge``: ``robot`` | ``board_translation`` | ``board_direction`` | ``none`` (default:
  ``robot`` when every frame has ``T_base_tool``, ``none`` when no frame has one).
- ``reference_camera``: the camera a rig's other cameras are expressed against.
- ``options``: ``{skew, unit_aspect, distortion: [k1, k2, p1, p2, k3 as booleans],
  outlier_threshold_px, robot_noise_mm, robot_noise_deg}`` (``ModelOptions``; the robot noise
  is the one-sigma error of each axis of the measured poses, 0 treats them as exact).
- ``frames[i].group``: orientation group; ``frames[i].motion_board``: the paper's board-frame
  motion knowledge (3 numbers, metres or a unit direction).
- ``frames[i].quality``: per camera, what the detector said (``ok``, ``reasons``,
  ``homography_rms_px``, ``coverage``); informative only.
- ``events``: what happened during the run (``{kind, message, frame, time_s}``), e.g. a fault.
- ``status``: ``recording`` | ``complete`` | ``aborted``.
- ``simulation``: the truth of a simulated run under the result file's names:
  ``cameras: {name: {K, distortion}}``, ``T_tool_cam`` (or ``T_base_cam``; ``T_tool_<name>`` per
  camera of a rig), ``T_base_board`` (or ``T_tool_board``), ``T_<name>_<ref>``, ``noise``,
  ``seed``. Transforms are ``{R: 3x3, t_m: [x, y, z]}``.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from slidecal.drivers.ur_pose import T_from_ur_pose, ur_pose_from_T
from slidecal.solver.errors import InputError
from slidecal.solver.problem import (
    CalibrationProblem,
    CameraSpec,
    Detection,
    Frame,
    ModelOptions,
    Target,
)

SESSION_FORMAT = "slidecal.session/1"
SESSION_FILE = "session.yaml"
IMAGE_DIR = "images"
KNOWLEDGE = ("robot", "board_translation", "board_direction", "none")
MOUNTS = ("eye_in_hand", "eye_to_hand", "none")
TARGET_KINDS = ("charuco", "chessboard", "points")

_Loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_Dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


# ----------------------------------------------------------------------------- YAML helpers


def plain(obj: Any) -> Any:
    """``obj`` with numpy arrays and scalars turned into lists and Python numbers (for YAML)."""
    if isinstance(obj, np.ndarray):
        return plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Mapping):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [plain(v) for v in obj]
    return obj


def dump_yaml(data: Any) -> str:
    """YAML text of ``data`` (numbers in flow-style leaf lists, keys in insertion order)."""
    return yaml.dump(
        plain(data), Dumper=_Dumper, default_flow_style=None, sort_keys=False, width=100
    )


def write_atomic(path: Path, text: str | bytes) -> None:
    """Write ``path`` so that it holds either its old or its new content, never a mix.

    The text goes to a temporary file in the same directory, is flushed and fsynced, then
    renamed over ``path``; the directory is fsynced so the rename survives a power cut. When
    writing fails (a full disk) the temporary file is removed and the error raised.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    data = text.encode() if isinstance(text, str) else text
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:  # a full disk, a signal: leave the old file and no temporary one
        try:
            tmp.unlink()
        except OSError:
            pass
        raise
    _fsync_dir(path.parent)


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # platforms without directory handles (Windows)
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def load_yaml(path: Path, what: str) -> Any:
    """Parse a YAML file; a missing or malformed file is an ``InputError`` naming it."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} not found; check the path", where=str(path))
    try:
        with open(path, encoding="utf-8") as f:
            return yaml.load(f, Loader=_Loader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = f" at line {mark.line + 1}" if mark is not None else ""
        raise InputError(
            f"not valid YAML{line} ({getattr(e, 'problem', e)}); fix the syntax", where=path.name
        ) from None


# ----------------------------------------------------------------------------- field checks


class Fields:
    """Typed access to one mapping of a YAML file; every failure names ``file: path.field``."""

    def __init__(self, data: Any, file: str, path: str = "") -> None:
        self.file, self.path = file, path
        if not isinstance(data, Mapping):
            raise InputError(
                f"must be a mapping of fields, got {type(data).__name__}", where=self.where()
            )
        self.data = data

    def where(self, key: str | None = None) -> str:
        """``file: path.key`` for error messages."""
        p = self.path if key is None else (f"{self.path}.{key}" if self.path else key)
        return f"{self.file}: {p}" if p else self.file

    def error(self, key: str | None, message: str) -> InputError:
        """An ``InputError`` about ``key``."""
        return InputError(message, where=self.where(key))

    def has(self, key: str) -> bool:
        """Whether ``key`` is present and not null."""
        return self.data.get(key) is not None

    def get(self, key: str, default: Any = None) -> Any:
        """The raw value, ``default`` when absent or null."""
        v = self.data.get(key)
        return default if v is None else v

    def require(self, key: str) -> Any:
        """The raw value; a missing key is an error."""
        if not self.has(key):
            raise self.error(key, "is missing; add it (see SESSION_FORMAT.md)")
        return self.data[key]

    def sub(self, key: str, required: bool = True) -> Fields | None:
        """The nested mapping at ``key``."""
        if not self.has(key):
            if required:
                raise self.error(key, "is missing; add it (see SESSION_FORMAT.md)")
            return None
        return Fields(self.data[key], self.file, f"{self.path}.{key}" if self.path else key)

    def choice(self, key: str, options: Sequence[str], default: str | None = None) -> str:
        """A string among ``options``."""
        v = self.get(key, default) if default is not None else self.require(key)
        if v not in options:
            raise self.error(key, f"is {v!r}; use one of {', '.join(options)}")
        return str(v)

    def number(
        self,
        key: str,
        default: float | None = None,
        positive: bool = False,
        minimum: float | None = None,
    ) -> float:
        """A finite float (optionally > 0 or >= minimum)."""
        v = self.require(key) if default is None else self.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
            raise self.error(key, f"must be a number, got {v!r}")
        if positive and v <= 0:
            raise self.error(key, f"must be positive, got {v!r}")
        if minimum is not None and v < minimum:
            raise self.error(key, f"must be at least {minimum}, got {v!r}")
        return float(v)

    def integer(self, key: str, default: int | None = None, minimum: int | None = None) -> int:
        """An int (optionally >= minimum)."""
        v = self.require(key) if default is None else self.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.error(key, f"must be an integer, got {v!r}")
        if minimum is not None and v < minimum:
            raise self.error(key, f"must be at least {minimum}, got {v!r}")
        return int(v)

    def boolean(self, key: str, default: bool) -> bool:
        """A bool."""
        v = self.get(key, default)
        if not isinstance(v, bool):
            raise self.error(key, f"must be true or false, got {v!r}")
        return v

    def string(self, key: str, default: str | None = None) -> str:
        """A non-empty string."""
        v = self.require(key) if default is None else self.get(key, default)
        if not isinstance(v, str) or not v:
            raise self.error(key, f"must be a non-empty string, got {v!r}")
        return v

    def array(self, key: str, shape: tuple[int, ...], default: Any = None) -> np.ndarray:
        """A float array of ``shape`` (-1 for any length), finite."""
        v = self.require(key) if default is None else self.get(key, default)
        return as_array(v, shape, self.where(key))


def as_array(value: Any, shape: tuple[int, ...], where: str) -> np.ndarray:
    """``value`` as a finite float array of ``shape`` (-1: any length); else an ``InputError``."""
    want = "x".join("n" if s < 0 else str(s) for s in shape)
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"must be a {want} array of numbers, got {value!r}", where=where) from None
    if a.size == 0 and len(shape) == 2 and shape[0] < 0:
        a = a.reshape(0, shape[1])
    ok = a.ndim == len(shape) and all(s < 0 or s == n for s, n in zip(shape, a.shape, strict=True))
    if not ok:
        raise InputError(f"must be a {want} array, got shape {list(a.shape)}", where=where)
    if not np.all(np.isfinite(a)):
        raise InputError("must hold finite numbers only (no NaN, no inf)", where=where)
    return a


def transform_from_dict(f: Fields, key: str) -> np.ndarray:
    """A 4x4 transform from ``{R: 3x3, t_m: [x, y, z]}`` or ``{rpy_deg: [r, p, y], t_m}``.

    ``rpy_deg`` follows the teach pendant (X-Y-Z fixed axes: ``R = Rz(y) Ry(p) Rx(r)``).
    """
    from slidecal.solver.geometry import Rx, Ry, Rz, T_from_Rt

    sub = f.sub(key)
    assert sub is not None
    t = sub.array("t_m", (3,))
    if sub.has("R"):
        R = sub.array("R", (3, 3))
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise sub.error("R", "is not a rotation matrix (orthonormal, det +1); fix the values")
    elif sub.has("rpy_deg"):
        r, p, y = np.radians(sub.array("rpy_deg", (3,)))
        R = Rz(y) @ Ry(p) @ Rx(r)
    else:
        raise sub.error("R", "is missing; give R (3x3) or rpy_deg ([roll, pitch, yaw] degrees)")
    return T_from_Rt(R, t)


def transform_to_dict(T: np.ndarray) -> dict[str, Any]:
    """``{R, t_m}`` of a 4x4 transform (the result file's shape)."""
    T = np.asarray(T, dtype=float)
    return {"R": plain(T[:3, :3]), "t_m": plain(T[:3, 3])}


# ----------------------------------------------------------------------------- targets


def target_from_dict(data: Any, file: str, path: str = "target") -> Target:
    """A :class:`Target` from a ``target:`` block (charuco, chessboard or points)."""
    f = Fields(data, file, path)
    kind = f.choice("kind", TARGET_KINDS)
    if kind == "points":
        pts = f.array("points_m", (-1, 2))
        if len(pts) < 4:
            raise f.error("points_m", f"has {len(pts)} points; give at least 4 [X, Y] pairs")
        return Target.points(pts)
    sx = f.integer("squares_x", minimum=3)
    sy = f.integer("squares_y", minimum=3)
    size = f.number("square_size_m", positive=True)
    if size > 1.0:
        raise f.error("square_size_m", f"is {size} m; give the square size in metres (e.g. 0.030)")
    if kind == "chessboard":
        return Target.chessboard(sx, sy, size)
    marker = f.number("marker_size_m", positive=True)
    if marker >= size:
        raise f.error("marker_size_m", f"({marker}) must be smaller than square_size_m ({size})")
    dictionary = f.string("dictionary", "DICT_5X5_100")
    import cv2

    if not re.fullmatch(r"DICT_\w+", dictionary) or not hasattr(cv2.aruco, dictionary):
        raise f.error(
            "dictionary",
            f"{dictionary!r} is not an OpenCV predefined dictionary (e.g. DICT_5X5_100)",
        )
    return Target.charuco(sx, sy, size, marker, dictionary)


def target_to_dict(target: Target) -> dict[str, Any]:
    """The ``target:`` block of a :class:`Target`."""
    if target.kind == "points":
        return {"kind": "points", "points_m": plain(target.points_m[:, :2])}
    d: dict[str, Any] = {
        "kind": target.kind,
        "squares_x": target.squares_x,
        "squares_y": target.squares_y,
        "square_size_m": target.square_size_m,
    }
    if target.kind == "charuco":
        d["marker_size_m"] = target.marker_size_m
        d["dictionary"] = target.dictionary
    return d


def options_from_dict(data: Any, file: str, path: str = "options") -> ModelOptions:
    """:class:`ModelOptions` from an ``options:`` block (absent fields keep their defaults)."""
    f = Fields(data, file, path)
    base = ModelOptions()
    dist = base.distortion
    if f.has("distortion"):
        v = f.get("distortion")
        if not (isinstance(v, list) and len(v) == 5 and all(isinstance(b, bool) for b in v)):
            raise f.error("distortion", "must be 5 booleans: which of k1, k2, p1, p2, k3 to fit")
        dist = tuple(v)
    return ModelOptions(
        skew=f.boolean("skew", base.skew),
        unit_aspect=f.boolean("unit_aspect", base.unit_aspect),
        distortion=dist,  # type: ignore[arg-type]
        outlier_threshold_px=f.number(
            "outlier_threshold_px", base.outlier_threshold_px, positive=True
        ),
        robot_noise_m=f.number("robot_noise_mm", 0.0, minimum=0.0) / 1000.0,
        robot_noise_deg=f.number("robot_noise_deg", 0.0, minimum=0.0),
    )


def options_to_dict(options: ModelOptions) -> dict[str, Any]:
    """The ``options:`` block of :class:`ModelOptions`."""
    return {
        "skew": options.skew,
        "unit_aspect": options.unit_aspect,
        "distortion": list(options.distortion),
        "outlier_threshold_px": options.outlier_threshold_px,
        "robot_noise_mm": options.robot_noise_m * 1000.0,
        "robot_noise_deg": options.robot_noise_deg,
    }


# ----------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class Session:
    """A session read from disk: the solver's problem plus what the run recorded around it.

    ``simulation``: the truth block of a simulated run (None for real runs). ``events``: what
    happened (faults, aborts). ``quality``: per (frame id, camera) the detector's report.
    """

    directory: Path
    problem: CalibrationProblem
    simulation: dict[str, Any] | None = None
    events: tuple[dict[str, Any], ...] = ()
    status: str = "complete"
    quality: dict[tuple[int, str], dict[str, Any]] = field(default_factory=dict)
    images: dict[tuple[int, str], Path] = field(default_factory=dict)


def read_session(directory: str | Path, detect_images: bool = True) -> CalibrationProblem:
    """The :class:`CalibrationProblem` a session directory holds (see :func:`load_session`)."""
    return load_session(directory, detect_images=detect_images).problem


def load_session(directory: str | Path, detect_images: bool = True) -> Session:
    """Read and validate ``directory/session.yaml``.

    Detections given in the file are used as they are; a camera with an image but no detections
    is detected with :func:`slidecal.solver.detect.detect` (``detect_images``; otherwise it is an
    error). Frames keep their entries when a camera saw nothing (empty ids). Without robot
    poses, knowledge and mount become ``"none"``. Every problem is an ``InputError`` naming
    ``session.yaml: <field>``.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(
            "is not a session directory; give the folder that holds session.yaml",
            where=str(directory),
        )
    data = load_yaml(directory / SESSION_FILE, "session.yaml")
    f = Fields(data, SESSION_FILE)
    _check_format(f, SESSION_FORMAT, "session")
    target = target_from_dict(f.require("target"), SESSION_FILE)

    cams = f.require("cameras")
    if not isinstance(cams, list) or not cams:
        raise f.error("cameras", "must be a list of {name, width, height}; add the cameras")
    cameras: list[CameraSpec] = []
    for i, c in enumerate(cams):
        cf = Fields(c, SESSION_FILE, f"cameras[{i}]")
        name = cf.string("name")
        if any(x.name == name for x in cameras):
            raise cf.error("name", f"{name!r} appears twice; camera names must be unique")
        cameras.append(
            CameraSpec(name, cf.integer("width", minimum=1), cf.integer("height", minimum=1))
        )
    names = [c.name for c in cameras]

    raw_frames = f.require("frames")
    if not isinstance(raw_frames, list):
        raise f.error("frames", "must be a list of frames")
    frames: list[Frame] = []
    quality: dict[tuple[int, str], dict[str, Any]] = {}
    images: dict[tuple[int, str], Path] = {}
    for i, fr in enumerate(raw_frames):
        frame, q, im = _read_frame(
            Fields(fr, SESSION_FILE, f"frames[{i}]"), directory, target, cameras, detect_images
        )
        if any(x.id == frame.id for x in frames):
            raise InputError(
                f"frame id {frame.id} appears twice; ids must be unique",
                where=f"{SESSION_FILE}: frames[{i}].id",
            )
        frames.append(frame)
        quality.update(q)
        images.update(im)

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
            raise f.error("knowledge", "is 'robot' but no frame has a T_base_tool; remove it")
        mount = "none"
    if knowledge in ("board_translation", "board_direction"):
        for i, fr in enumerate(frames):
            if fr.motion_board is None:
                raise InputError(
                    f"is missing; knowledge {knowledge!r} needs motion_board on every frame",
                    where=f"{SESSION_FILE}: frames[{i}].motion_board",
                )
    ref = f.get("reference_camera")
    if ref is not None and ref not in names:
        raise f.error("reference_camera", f"{ref!r} is not a camera; cameras are {names}")
    options = options_from_dict(f.get("options", {}), SESSION_FILE)
    problem = CalibrationProblem(
        target=target,
        cameras=tuple(cameras),
        frames=tuple(frames),
        mount=mount,  # type: ignore[arg-type]
        knowledge=knowledge,  # type: ignore[arg-type]
        options=options,
        reference_camera=ref,
    )
    events = f.get("events", [])
    if not isinstance(events, list):
        raise f.error("events", "must be a list")
    sim = f.get("simulation")
    if sim is not None and not isinstance(sim, Mapping):
        raise f.error("simulation", "must be a mapping (the simulated truth)")
    return Session(
        directory=directory,
        problem=problem,
        simulation=dict(sim) if sim is not None else None,
        events=tuple(events),
        status=str(f.get("status", "complete")),
        quality=quality,
        images=images,
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
) -> tuple[Frame, dict[tuple[int, str], dict[str, Any]], dict[tuple[int, str], Path]]:
    fid = f.integer("id", minimum=0)
    names = [c.name for c in cameras]
    T = None
    if f.has("T_base_tool"):
        v = f.get("T_base_tool")
        where = f.where("T_base_tool")
        pose = as_array(v, (-1,), where)
        if pose.shape != (6,):
            raise InputError(
                f"has {pose.size} numbers; a UR pose is [x, y, z, rx, ry, rz] "
                "(metres, axis-angle radians)",
                where=where,
            )
        try:
            T = T_from_ur_pose(pose)
        except ValueError as e:
            raise InputError(str(e), where=where) from None
    motion = f.array("motion_board", (3,)) if f.has("motion_board") else None
    group = f.integer("group", minimum=0) if f.has("group") else None

    image_paths: dict[str, Path] = {}
    ims = f.sub("images", required=False)
    if ims is not None:
        for name, rel in ims.data.items():
            if name not in names:
                raise ims.error(str(name), f"unknown camera {name!r}; cameras are {names}")
            if not isinstance(rel, str):
                raise ims.error(str(name), f"must be a path relative to the session, got {rel!r}")
            image_paths[str(name)] = directory / rel

    detections: dict[str, Detection] = {}
    dets = f.sub("detections", required=False)
    if dets is not None:
        for name in dets.data:
            if name not in names:
                raise dets.error(str(name), f"unknown camera {name!r}; cameras are {names}")
            df = dets.sub(str(name))
            assert df is not None
            detections[str(name)] = _read_detection(df, target)

    for name, path in image_paths.items():
        if name in detections:
            continue
        if not path.is_file():
            raise ims.error(  # type: ignore[union-attr]
                name, f"image {path.name} not found; restore it or give detections for {name!r}"
            )
        if not detect_images:
            raise ims.error(  # type: ignore[union-attr]
                name, "has an image but no detections, and detection was turned off"
            )
        detections[name] = _detect_file(path, target, ims.where(name))  # type: ignore[union-attr]
    quality: dict[tuple[int, str], dict[str, Any]] = {}
    q = f.sub("quality", required=False)
    if q is not None:
        for name, v in q.data.items():
            quality[(fid, str(name))] = dict(v) if isinstance(v, Mapping) else {"value": v}
    frame = Frame(id=fid, detections=detections, T_base_tool=T, motion_board=motion, group=group)
    return frame, quality, {(fid, n): p for n, p in image_paths.items()}


def _read_detection(f: Fields, target: Target) -> Detection:
    ids_raw = f.get("ids", [])
    px_raw = f.get("px", [])
    if not isinstance(ids_raw, list) or not all(
        isinstance(i, int) and not isinstance(i, bool) for i in ids_raw
    ):
        raise f.error("ids", "must be a list of integer corner ids")
    px = as_array(px_raw, (-1, 2), f.where("px"))
    if len(ids_raw) != len(px):
        raise f.error(
            "px", f"has {len(px)} positions for {len(ids_raw)} ids; give one [u, v] per id"
        )
    ids = np.asarray(ids_raw, dtype=np.int64)
    n = len(target.points_m)
    bad = ids[(ids < 0) | (ids >= n)]
    if len(bad):
        raise f.error("ids", f"id {int(bad[0])} is not on the target (ids are 0..{n - 1})")
    if len(np.unique(ids)) != len(ids):
        raise f.error("ids", "has repeated ids; each corner may appear once per image")
    return Detection(ids, px)


def _detect_file(path: Path, target: Target, where: str) -> Detection:
    import cv2

    from slidecal.solver.detect import detect

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path.name} is not a readable image; replace it", where=where)
    return detect(image, target).detection


# ----------------------------------------------------------------------------- writing


def detection_to_dict(det: Detection) -> dict[str, Any]:
    """``{ids, px}`` of a detection."""
    return {"ids": [int(i) for i in det.ids], "px": plain(np.asarray(det.px, dtype=float))}


class SessionWriter:
    """Create a session directory and append frames as they are captured.

    Each :meth:`append_frame` writes the images (PNG) first and then rewrites ``session.yaml``
    atomically, so the file on disk always describes complete frames only.
    """

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
        overwrite: bool = False,
    ) -> None:
        self.directory = Path(directory)
        if (self.directory / SESSION_FILE).exists() and not overwrite:
            raise InputError(
                "already holds a session; choose a new --out directory or delete the old one",
                where=str(self.directory),
            )
        if mount not in MOUNTS:
            raise InputError(f"mount {mount!r} unknown; use one of {', '.join(MOUNTS)}")
        if knowledge not in KNOWLEDGE:
            raise InputError(f"knowledge {knowledge!r} unknown; use one of {', '.join(KNOWLEDGE)}")
        (self.directory / IMAGE_DIR).mkdir(parents=True, exist_ok=True)
        self.target = target
        self.cameras = tuple(cameras)
        self._names = [c.name for c in self.cameras]
        self.data: dict[str, Any] = {"format": SESSION_FORMAT, "status": "recording"}
        if mount != "none":
            self.data["mount"] = mount
        self.data["knowledge"] = knowledge
        self.data["target"] = target_to_dict(target)
        self.data["cameras"] = [
            {"name": c.name, "width": int(c.width), "height": int(c.height)} for c in cameras
        ]
        if reference_camera is not None:
            self.data["reference_camera"] = reference_camera
        self.data["options"] = options_to_dict(options or ModelOptions())
        if extra:
            self.data.update(plain(dict(extra)))
        if simulation is not None:
            self.data["simulation"] = plain(dict(simulation))
        self.data["frames"] = []
        self.data["events"] = []
        self._write()

    @classmethod
    def reopen(cls, directory: str | Path) -> SessionWriter:
        """Continue writing an existing session (``slidecal run --resume``): its frames and
        events are kept, new frames are appended, ``status`` goes back to ``recording``."""
        directory = Path(directory)
        data = load_yaml(directory / SESSION_FILE, "session file")
        f = Fields(data, SESSION_FILE)
        _check_format(f, SESSION_FORMAT, "session")
        cams = f.require("cameras")
        if not isinstance(cams, list):
            raise f.error("cameras", "must be a list of {name, width, height}")
        w = cls.__new__(cls)
        w.directory = directory
        w.target = target_from_dict(f.require("target"), SESSION_FILE)
        w.cameras = tuple(
            CameraSpec(
                c.string("name"), c.integer("width", minimum=1), c.integer("height", minimum=1)
            )
            for c in (Fields(x, SESSION_FILE, f"cameras[{i}]") for i, x in enumerate(cams))
        )
        w._names = [c.name for c in w.cameras]
        w.data = dict(data)
        w.data.setdefault("frames", [])
        w.data.setdefault("events", [])
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
        extra: Mapping[str, Any] | None = None,
        frame_id: int | None = None,
    ) -> int:
        """Write one frame now and return its id (``frame_id``, default: the next free id).

        ``T_base_tool`` (4, 4), metres: the pose measured after settling (None without a robot).
        ``images``: uint8 (H, W) or (H, W, 3) per camera name, saved as PNG. ``detections``:
        per camera (an empty detection when the camera saw nothing). ``motion_board`` (3,):
        board-frame motion knowledge (paper's cases).
        """
        import cv2

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
            entry["detections"] = {n: detection_to_dict(d) for n, d in detections.items()}
        if quality:
            entry["quality"] = plain({n: dict(q) for n, q in quality.items()})
        if extra:
            entry.update(plain(dict(extra)))
        self.data["frames"].append(entry)
        self._write()
        return fid

    def add_event(self, kind: str, message: str, **fields: Any) -> None:
        """Record what happened (a fault, an abort) in ``events`` and write the file now."""
        self.data["events"].append({"kind": kind, "message": message, **plain(fields)})
        self._write()

    def set_simulation(self, simulation: Mapping[str, Any]) -> None:
        """Record the simulated truth (``simulation:`` block)."""
        self.data["simulation"] = plain(dict(simulation))
        self._write()

    def finish(self, status: str = "complete") -> Path:
        """Mark the session ``complete`` (or ``aborted``) and return its directory."""
        self.data["status"] = status
        self._write()
        return self.directory

    def _write(self) -> None:
        write_atomic(self.directory / SESSION_FILE, dump_yaml(self.data))


def write_session(
    directory: str | Path,
    problem: CalibrationProblem,
    simulation: Mapping[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a problem (detections only, no images) as a session directory."""
    w = SessionWriter(
        directory,
        problem.target,
        problem.cameras,
        mount=problem.mount,
        knowledge=problem.knowledge,
        options=problem.options,
        reference_camera=problem.reference_camera,
        simulation=simulation,
        overwrite=overwrite,
    )
    for fr in problem.frames:
        w.append_frame(
            fr.T_base_tool,
            detections=fr.detections,
            group=fr.group,
            motion_board=fr.motion_board,
            frame_id=fr.id,
        )
    return w.finish()
