"""A black-box checker of ``slidecal solve``: sessions written by hand from the public session
contract (README, docs/FORMATS.md), never with slidecal's own session writer, and judged
against the simulation's truth as a user's acceptance check would judge them.

The scenes: a 2-megapixel colour camera (photograph-like images: defocus, chromatic
aberration, shot noise, Bayer, JPEG, uneven light, glare) on or beside a UR5e whose kinematics
err like an uncalibrated real arm (``mocks/scenarios.py`` ``real_arm_poses``: about 1 mm and
0.1 deg, smooth, plus repeatability). Used by ``tests/test_blackbox_sessions.py``; run
``python tests/blackbox.py [--full]`` for the figures (``--full``: the 2-megapixel image
sessions too).
"""

from __future__ import annotations

import contextlib
import io
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from slidecal.drivers import ur_kinematics as urk
from slidecal.mocks.camera import SimCamera
from slidecal.mocks.render import Photo, render_target
from slidecal.mocks.scenarios import real_arm_poses
from slidecal.solver import geometry as geo
from slidecal.solver.camera import K_matrix, project
from slidecal.solver.detect import detect
from slidecal.solver.geometry import T_from_Rt, inv_T, rvec_from_R
from slidecal.solver.problem import Target

SLIDECAL = str(Path(sys.executable).parent / "slidecal")

#: the harshest imaging the photograph-like renderer offers that a real cell still shows:
#: twice the default defocus and chromatic aberration, JPEG 80, stronger uneven light and glare
HARSH = Photo(
    aperture_mm=4.0,
    chromatic_red=1e-3,
    chromatic_blue=-1e-3,
    jpeg_quality=80,
    vignetting=0.4,
    gradient=0.3,
    glare_spots=1,
    glare_strength=0.6,
)
#: a 2-megapixel colour camera (1920 x 1080) with a real lens's distortion
CAM_1080 = SimCamera(
    "left",
    1920,
    1080,
    K_matrix(1480.0, 1478.5, 963.2, 537.4),
    np.array([-0.09, 0.11, 4e-4, -3e-4, 0.0]),
    blur_sigma_px=0.7,
    noise_std=2.5,
    colour=True,
    photo=HARSH,
)
#: a 2-megapixel grey camera (1600 x 1200)
CAM_1200 = SimCamera(
    "left",
    1600,
    1200,
    K_matrix(1390.0, 1391.2, 801.7, 597.9),
    np.array([-0.11, 0.09, -3e-4, 2e-4, 0.0]),
    blur_sigma_px=0.7,
    noise_std=2.5,
    colour=False,
    photo=replace(HARSH, bayer=False),
)
T_TOOL_CAM = T_from_Rt(
    geo.R_from_rvec(np.radians([1.2, -1.7, 90.0])), np.array([0.04, -0.055, 0.085])
)
#: the board on the table, print up (board +z into the table), in the UR5e's reach
R_BASE_BOARD = np.diag([-1.0, 1.0, -1.0])
#: eye-to-hand: a camera on a stand looking at the arm's workspace
T_BASE_CAM = T_from_Rt(
    geo.look_at_R_cam_world(np.array([0.95, 0.45, 0.55]), np.array([0.45, 0.0, 0.3]), [0, 0, -1]).T,
    np.array([0.95, 0.45, 0.55]),
)
#: an AprilTag on the tool, its print facing away from the flange
T_TOOL_TAG = T_from_Rt(
    geo.R_from_rvec(np.radians([180.0, 0.0, 0.0])), np.array([-0.06, -0.06, 0.03])
)


# ----------------------------------------------------------------------------- the contract
def chessboard(squares_x: int, squares_y: int, square_size_m: float) -> dict[str, Any]:
    return {
        "kind": "chessboard",
        "squares_x": squares_x,
        "squares_y": squares_y,
        "square_size_m": square_size_m,
    }


def charuco(sx: int, sy: int, square_m: float, marker_m: float, dictionary: str) -> dict:
    return {
        "kind": "charuco",
        "squares_x": sx,
        "squares_y": sy,
        "square_size_m": square_m,
        "marker_size_m": marker_m,
        "dictionary": dictionary,
    }


def ur_pose(T: np.ndarray) -> list[float]:
    """``[x, y, z, rx, ry, rz]``: metres, axis-angle radians (a UR controller's pose)."""
    return [float(v) for v in T[:3, 3]] + [float(v) for v in rvec_from_R(T[:3, :3])]


def write_session(
    directory: Path,
    target: dict[str, Any],
    camera: SimCamera,
    frames: list[dict[str, Any]],
    mount: str | None = "eye_in_hand",
) -> Path:
    """``directory/session.yaml`` as a user writes it: plain YAML of the contract's keys."""
    directory.mkdir(parents=True, exist_ok=True)
    doc: dict[str, Any] = {"format": "slidecal.session/1"}
    if mount is not None:
        doc["mount"] = mount
    doc["target"] = target
    doc["cameras"] = [{"name": camera.name, "width": camera.width, "height": camera.height}]
    doc["frames"] = frames
    (directory / "session.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return directory


def frame_entry(
    k: int,
    T_base_tool: np.ndarray | None,
    image: str | None = None,
    detection: tuple[np.ndarray, np.ndarray] | None = None,
    camera: str = "left",
) -> dict[str, Any]:
    e: dict[str, Any] = {"id": k}
    if T_base_tool is not None:
        e["T_base_tool"] = ur_pose(T_base_tool)
    if image is not None:
        e["images"] = {camera: image}
    if detection is not None:
        ids, px = detection
        e["detections"] = {
            camera: {"ids": [int(i) for i in ids], "px": [[float(u), float(v)] for u, v in px]}
        }
    return e


def solve(
    session: Path, out: Path | None = None, in_process: bool = False
) -> tuple[int, str, dict | None, float]:
    """``slidecal solve SESSION --out result.yaml --quiet`` as a user runs it: exit code,
    stderr + stdout, the result (None when none was written) and the wall time.
    ``in_process``: the console script's ``main`` in this process (the same code without the
    second or so a new interpreter takes to import)."""
    out = out or session / "result.yaml"
    out.unlink(missing_ok=True)  # a checker solves each session afresh
    argv = ["solve", str(session), "--out", str(out), "--quiet"]
    t0 = time.perf_counter()
    if in_process:
        from slidecal.routines.cli import main

        text = io.StringIO()
        with contextlib.redirect_stdout(text), contextlib.redirect_stderr(text):
            code = main(argv)
        message = text.getvalue()
    else:
        p = subprocess.run([SLIDECAL, *argv], capture_output=True, text=True, timeout=900)
        code, message = p.returncode, p.stderr + p.stdout
    dt = time.perf_counter() - t0
    result = yaml.safe_load(out.read_text()) if out.is_file() else None
    return code, message.strip(), result, dt


# ----------------------------------------------------------------------------- scenes
def target_of(t: dict[str, Any]) -> Target:
    """The simulator's target for a contract ``target`` (for rendering and the truth)."""
    if t["kind"] == "chessboard":
        return Target.chessboard(t["squares_x"], t["squares_y"], t["square_size_m"])
    return Target.charuco(
        t["squares_x"], t["squares_y"], t["square_size_m"], t["marker_size_m"], t["dictionary"]
    )


def board_extent_m(target: Target) -> tuple[float, float]:
    s = target.square_size_m
    return target.squares_x * s, target.squares_y * s


def T_base_board_for(target: Target, centre=(0.45, 0.0, -0.2)) -> np.ndarray:
    """The board flat on a table below the arm's base, its centre at ``centre`` (base frame,
    metres)."""
    w, h = board_extent_m(target)
    c = np.asarray(centre, float)
    return T_from_Rt(R_BASE_BOARD, c - R_BASE_BOARD @ np.array([w / 2, h / 2, 0.0]))


def view_pose(
    T_base_board: np.ndarray,
    target: Target,
    tilt_deg: tuple[float, float],
    distance: float,
    roll_deg: float = 0.0,
    offset_m=(0.0, 0.0),
) -> np.ndarray:
    """``T_base_tool`` of a camera looking at the board's centre (plus ``offset_m`` on the
    board) from ``distance`` m, the view tilted by ``tilt_deg`` about the board's x and y."""
    w, h = board_extent_m(target)
    centre = T_base_board[:3, :3] @ np.array([w / 2 + offset_m[0], h / 2 + offset_m[1], 0.0])
    centre = centre + T_base_board[:3, 3]
    up_board = T_base_board[:3, :3] @ np.array([0.0, -1.0, 0.0])  # board -y: image up
    normal = -T_base_board[:3, 2]  # from the print towards the camera
    d = (
        geo.Rx(np.radians(tilt_deg[0]))
        @ geo.Ry(np.radians(tilt_deg[1]))
        @ np.array([0.0, 0.0, 1.0])
    )
    view = T_base_board[:3, :3] @ np.array([d[0], d[1], -d[2]])
    view = view if view @ normal > 0 else -view
    p = centre + distance * view
    R_base_cam = geo.look_at_R_cam_world(p, centre, up_board).T @ geo.Rz(np.radians(roll_deg))
    return T_from_Rt(R_base_cam, p) @ inv_T(T_TOOL_CAM)


def translations(T: np.ndarray, n: int, rng: np.random.Generator) -> list[np.ndarray]:
    """``n`` poses at ``T``'s orientation, moved 40-80 mm in non-coplanar camera directions
    (each with a component along the viewing axis)."""
    R_base_cam = (T @ T_TOOL_CAM)[:3, :3]
    out = []
    for _ in range(n):
        d = rng.normal(size=3)
        d[2] = np.sign(d[2] or 1.0) * max(abs(d[2]), 0.5)
        d /= np.linalg.norm(d)
        m = R_base_cam @ d * rng.uniform(0.04, 0.08)
        out.append(T_from_Rt(T[:3, :3], T[:3, 3] + m))
    return out


def reachable(T_base_tool: np.ndarray) -> bool:
    """A UR5e reaches ``T_base_tool`` away from its singularities."""
    return any(urk.singularity(q) is None for q in urk.ik(T_base_tool, urk.Q_HOME))


def varied_views(
    T_base_board: np.ndarray,
    target: Target,
    n: int,
    rng: np.random.Generator,
    distance_m=(0.5, 0.7),
    tilt_deg=(15.0, 35.0),
) -> list[np.ndarray]:
    """``n`` reachable poses, each at its own orientation: tilts of ``tilt_deg`` in random
    directions, rolls of +-25 deg, the board's centre moved by up to 3 cm."""
    out: list[np.ndarray] = []
    while len(out) < n:
        a = rng.uniform(0, 2 * np.pi)
        tilt = rng.uniform(*tilt_deg) * np.array([np.cos(a), np.sin(a)])
        T = view_pose(
            T_base_board,
            target,
            (float(tilt[0]), float(tilt[1])),
            rng.uniform(*distance_m),
            rng.uniform(-25, 25),
            tuple(rng.uniform(-0.03, 0.03, 2)),
        )
        if reachable(T):
            out.append(T)
    return out


@dataclass
class Truth:
    """What the simulation knows: the camera, the mount's transforms, true and measured poses."""

    camera: SimCamera
    mount: str
    T_hand_eye: np.ndarray  # T_tool_cam or T_base_cam
    T_target: np.ndarray  # T_base_board or T_tool_board
    true: np.ndarray  # (F, 4, 4) where the arm really was
    measured: np.ndarray  # (F, 4, 4) what it reported
    T_cam_board: list[np.ndarray] = field(default_factory=list)


def arm(
    planned: list[np.ndarray], rng: np.random.Generator, arm_mm: float = 1.0, arm_deg: float = 0.1
) -> tuple[np.ndarray, np.ndarray]:
    """(true, measured) poses of a UR5e with a real arm's kinematic error."""
    planned_a = np.stack(planned)
    return real_arm_poses(planned_a, rng, arm_mm, arm_deg), planned_a


def eye_in_hand_truth(
    camera: SimCamera,
    T_base_board: np.ndarray,
    planned: list[np.ndarray],
    rng: np.random.Generator,
    arm_mm: float = 1.0,
    arm_deg: float = 0.1,
) -> Truth:
    true, measured = arm(planned, rng, arm_mm, arm_deg)
    t = Truth(camera, "eye_in_hand", T_TOOL_CAM, T_base_board, true, measured)
    t.T_cam_board = [inv_T(T @ T_TOOL_CAM) @ T_base_board for T in true]
    return t


def render_frames(
    truth: Truth,
    target: Target,
    directory: Path,
    rng: np.random.Generator,
    ext: str = "png",
    skip: set[int] = frozenset(),
) -> list[str]:
    """Render every frame's image into ``directory/images`` (``ext``: png or jpg); a frame in
    ``skip`` shows a blank wall instead (the detector must miss it)."""
    (directory / "images").mkdir(parents=True, exist_ok=True)
    names = []
    for k, T in enumerate(truth.T_cam_board):
        if k in skip:
            T = T_from_Rt(np.eye(3), np.array([5.0, 5.0, 1.0])) @ T  # the board out of view
        img = render_target(target, truth.camera, T, rng)
        name = f"images/{k:04d}_left.{ext}"
        params = [cv2.IMWRITE_JPEG_QUALITY, 88] if ext == "jpg" else []
        cv2.imwrite(str(directory / name), img, params)
        names.append(name)
    return names


def projected(
    camera: SimCamera,
    target_points_m: np.ndarray,
    T_cam_board: np.ndarray,
    rng: np.random.Generator,
    sigma_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The corners inside the image (2 px margin), with Gaussian noise ``sigma_px``."""
    p_cam = target_points_m @ T_cam_board[:3, :3].T + T_cam_board[:3, 3]
    px = project(camera.K, camera.dist, p_cam)
    ok = (
        (p_cam[:, 2] > 0)
        & (px[:, 0] > 2)
        & (px[:, 0] < camera.width - 3)
        & (px[:, 1] > 2)
        & (px[:, 1] < camera.height - 3)
    )
    ids = np.flatnonzero(ok)
    return ids, px[ok] + rng.normal(0.0, sigma_px, (len(ids), 2))


# ----------------------------------------------------------------------------- judging
def intrinsic_errors(result: dict, camera: SimCamera, name: str = "left") -> dict[str, float]:
    """Per estimated intrinsic: |error| / reported std (inf when no std is reported)."""
    c = result["cameras"][name]
    K = np.asarray(c["K"], float)
    dist = np.asarray(c["distortion"], float)
    truth = {
        "fx": camera.K[0, 0],
        "fy": camera.K[1, 1],
        "cx": camera.K[0, 2],
        "cy": camera.K[1, 2],
    }
    est = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    for i, k in enumerate(("k1", "k2", "p1", "p2", "k3")):
        truth[k], est[k] = camera.dist[i], dist[i]
    out = {}
    for k, std in (c.get("std") or {}).items():
        if k in truth and std:
            out[k] = abs(est[k] - truth[k]) / std
    return out


def fx_error_pct(result: dict, camera: SimCamera, name: str = "left") -> float:
    return 100.0 * abs(result["cameras"][name]["K"][0][0] / camera.K[0, 0] - 1.0)


def transform_of(est: dict) -> np.ndarray:
    return T_from_Rt(np.asarray(est["R"], float), np.asarray(est["t_m"], float))


def hand_eye_errors(result: dict, key: str, T_true: np.ndarray) -> dict[str, float]:
    """The reported hand-eye against ``T_true``: per component |error| / std from the result's
    covariance (its names ``key.rx`` .. ``key.tz``: R' = exp([r]x) R, t' = t + dt)."""
    est = result[key]
    t = est["t_m"] if est["t_m"] is not None else T_true[:3, 3]  # an unobservable translation
    T = T_from_Rt(np.asarray(est["R"], float), np.asarray(t, float))
    r = rvec_from_R(T_true[:3, :3] @ T[:3, :3].T)
    dt = T_true[:3, 3] - T[:3, 3]
    names = result["parameter_names"]
    cov = np.asarray(result["covariance"], float)
    out = {}
    for i, a in enumerate(("rx", "ry", "rz", "tx", "ty", "tz")):
        n = f"{key}.{a}"
        if n in names:
            j = names.index(n)
            e = r[i] if i < 3 else dt[i - 3]
            out[a] = abs(e) / np.sqrt(cov[j, j])
    return out


def rotation_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(rvec_from_R(A[:3, :3] @ B[:3, :3].T))))


# ----------------------------------------------------------------------------- the sessions
def classic_session(directory: Path, mount: str, seed: int, empty: tuple[int, ...] = ()):
    """28 frames, each at its own orientation, detections given (0.1 px noise); the frames in
    ``empty`` saw nothing (empty ids). Returns (session dir, frames, measured poses, truth)."""
    rng = np.random.default_rng(seed)
    cam = CAM_1080
    tdict = charuco(12, 9, 0.03, 0.022, "DICT_5X5_100")
    target = target_of(tdict)
    T_base_board = T_base_board_for(target)
    views = varied_views(T_base_board, target, 28, rng, (0.45, 0.65), (5.0, 35.0))
    if mount == "eye_in_hand":
        true, measured = arm(views, rng)
        T_cam_board = [inv_T(T @ T_TOOL_CAM) @ T_base_board for T in true]
        T_hand_eye = T_TOOL_CAM
    else:  # the same camera-board poses, the board on the tool, the camera on a stand
        T_tool_board = T_from_Rt(np.diag([1.0, -1.0, -1.0]), np.array([-0.18, -0.135, 0.03]))
        planned = [
            T_BASE_CAM @ inv_T(T @ T_TOOL_CAM) @ T_base_board @ inv_T(T_tool_board) for T in views
        ]
        true, measured = arm([T for T in planned if reachable(T)], rng)
        T_cam_board = [inv_T(T_BASE_CAM) @ T @ T_tool_board for T in true]
        T_hand_eye = T_BASE_CAM
    frames = []
    for k, T in enumerate(T_cam_board):
        det = projected(cam, target.points_m, T, rng, 0.1)
        if k in empty:
            det = (np.zeros(0, int), np.zeros((0, 2)))
        frames.append(frame_entry(k, measured[k], detection=det))
    root = write_session(directory / mount, tdict, cam, frames, mount=mount)
    return root, frames, measured, target, T_hand_eye


def park(frames, measured, target, mount: str, size: tuple[int, int]) -> np.ndarray:
    """The checker's reference: cv2.calibrateCamera on the same detections, then
    cv2.calibrateHandEye (Park) with the board poses it gives."""
    used = [k for k, f in enumerate(frames) if len(f["detections"]["left"]["ids"]) >= 6]
    obj = [
        target.points_m[np.array(frames[k]["detections"]["left"]["ids"])].astype(np.float32)
        for k in used
    ]
    img = [np.array(frames[k]["detections"]["left"]["px"], np.float32) for k in used]
    _, _, _, rv, tv = cv2.calibrateCamera(obj, img, size, None, None)
    # eye-to-hand: OpenCV takes the base in the gripper frame as the "gripper" pose
    Tg = [measured[k] if mount == "eye_in_hand" else inv_T(measured[k]) for k in used]
    R, t = cv2.calibrateHandEye(
        [T[:3, :3] for T in Tg],
        [T[:3, 3] for T in Tg],
        [cv2.Rodrigues(r)[0] for r in rv],
        [t.ravel() for t in tv],
        method=cv2.CALIB_HAND_EYE_PARK,
    )
    return T_from_Rt(R, t.ravel())


def eye_in_hand_2mp(directory: Path, tdict: dict, cam: SimCamera, ext: str, seed: int):
    """30 frames: 13 translation-only (one orientation), 17 each at its own orientation; the
    arm errs by 1 mm / 0.1 deg. Returns (full session, 13-frame session, truth, target)."""
    rng = np.random.default_rng(seed)
    target = target_of(tdict)
    T_base_board = T_base_board_for(target)
    T0 = view_pose(T_base_board, target, (22.0, 8.0), 0.6)
    planned = [T0, *translations(T0, 12, rng)]
    planned += varied_views(T_base_board, target, 17, rng)
    truth = eye_in_hand_truth(cam, T_base_board, planned, rng)
    full = directory / "full"
    names = render_frames(truth, target, full, rng, ext)
    frames = [frame_entry(k, truth.measured[k], image=n) for k, n in enumerate(names)]
    write_session(full, tdict, cam, frames)
    t13 = directory / "t13"
    (t13 / "images").mkdir(parents=True)
    for n in names[:13]:
        shutil.copy(full / n, t13 / n)
    write_session(t13, tdict, cam, frames[:13])
    return full, t13, truth, target


def translation_only_session(
    directory: Path, seed: int, arm_mm: float = 1.0, sigma_px: float = 0.05
) -> Truth:
    """The checker's 13 translation-only frames with given detections: the 2-megapixel grey
    camera over a ChArUco board (12 x 9 squares of 30 mm) 0.6 m away at one orientation, 12
    moves of 40-80 mm; the arm errs by ``arm_mm`` (and ``arm_mm / 10`` deg)."""
    rng = np.random.default_rng(seed)
    tdict = charuco(12, 9, 0.03, 0.022, "DICT_5X5_100")
    target = target_of(tdict)
    T_base_board = T_base_board_for(target)
    T0 = view_pose(T_base_board, target, (22.0, 8.0), 0.6)
    planned = [T0, *translations(T0, 12, rng)]
    truth = eye_in_hand_truth(CAM_1200, T_base_board, planned, rng, arm_mm, arm_mm / 10.0)
    frames = [
        frame_entry(
            k, truth.measured[k], detection=projected(CAM_1200, target.points_m, T, rng, sigma_px)
        )
        for k, T in enumerate(truth.T_cam_board)
    ]
    write_session(directory, tdict, CAM_1200, frames)
    return truth


def images_only_session(
    directory: Path,
    camera: SimCamera,
    n: int,
    skip: int | None,
    seed: int,
    mount: str | None = None,
) -> None:
    """``n`` chessboard images (10 x 7 squares of 30 mm) from views 0.4-0.6 m away tilted by
    5-40 deg, no robot poses; frame ``skip`` shows a wall."""
    rng = np.random.default_rng(seed)
    tdict = chessboard(10, 7, 0.03)
    target = target_of(tdict)
    T_base_board = T_base_board_for(target)
    views = varied_views(T_base_board, target, n, rng, (0.4, 0.6), (5.0, 40.0))
    truth = eye_in_hand_truth(camera, T_base_board, views, rng)
    names = render_frames(truth, target, directory, rng, "png", skip={skip} - {None})
    frames = [frame_entry(k, None, image=name) for k, name in enumerate(names)]
    write_session(directory, tdict, camera, frames, mount=mount)


# ----------------------------------------------------------------------------- eye-to-hand tag
#: one AprilTag (36h11) of 100 mm on the tool, described as the checker may describe it without
#: knowing slidecal's ``apriltag`` kind: its 4 outer corners as ``points`` (OpenCV's order:
#: top-left, top-right, bottom-right, bottom-left as printed), detections given
TAG_SIDE_M = 0.10
TAG_POINTS_M = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float) * TAG_SIDE_M
#: 7 tag orientations seen by the camera: (tilt about x, tilt about y, roll) deg
TAG_TILTS_DEG = ((0, 0, 0), (30, 0, 10), (-30, 0, -10), (0, 30, 20), (0, -30, -20), (22, 22, 30))
TAG_TILTS_DEG = (*TAG_TILTS_DEG, (-22, -22, -30))


def eye_to_hand_tag_session(
    directory: Path, seed: int, arm_mm: float = 0.8, sigma_px: float = 0.1, n_frames: int = 205
) -> Truth:
    """The checker's eye-to-hand session: a fixed 2-megapixel camera, one AprilTag on the tool,
    ``n_frames`` frames in 7 orientations at random places across the image 0.45-0.85 m away,
    the arm off by about ``arm_mm`` (and ``arm_mm / 10`` deg); the tag's 4 corners given as
    detections with ``sigma_px`` noise (corners within 2 px of the border are not seen, so a
    few frames have fewer than 4)."""
    rng = np.random.default_rng(seed)
    cam = CAM_1080
    points = np.column_stack([TAG_POINTS_M, np.zeros(4)])
    planned: list[np.ndarray] = []
    per = [n_frames // 7 + (o < n_frames % 7) for o in range(7)]
    for (ax, ay, rz), n in zip(TAG_TILTS_DEG, per, strict=True):
        R = geo.Rz(np.radians(rz)) @ geo.Rx(np.radians(ax)) @ geo.Ry(np.radians(ay))
        group: list[np.ndarray] = []
        while len(group) < n:
            z = rng.uniform(0.45, 0.85)
            u, v = rng.uniform(150, cam.width - 150), rng.uniform(120, cam.height - 120)
            c = np.array([(u - cam.K[0, 2]) / cam.K[0, 0], (v - cam.K[1, 2]) / cam.K[1, 1], 1.0])
            T_cam_tag = T_from_Rt(R, z * c - R @ np.array([TAG_SIDE_M / 2, TAG_SIDE_M / 2, 0]))
            T = T_BASE_CAM @ T_cam_tag @ inv_T(T_TOOL_TAG)
            if reachable(T):
                group.append(T)
        planned += group
    true, measured = arm(planned, rng, arm_mm, arm_mm / 10.0)
    truth = Truth(cam, "eye_to_hand", T_BASE_CAM, T_TOOL_TAG, true, measured)
    truth.T_cam_board = [inv_T(T_BASE_CAM) @ T @ T_TOOL_TAG for T in true]
    frames = [
        frame_entry(k, measured[k], detection=projected(cam, points, T, rng, sigma_px))
        for k, T in enumerate(truth.T_cam_board)
    ]
    target = {"kind": "points", "points_m": TAG_POINTS_M.tolist()}
    write_session(directory, target, cam, frames, mount="eye_to_hand")
    return truth


# ----------------------------------------------------------------------------- figures
def _row(name: str, code: int, message: str, result: dict | None, dt: float, cam: SimCamera) -> str:
    if result is None:
        return f"| {name} | {code} | - | - | {dt:.1f} | {message[:160]} |"
    e = intrinsic_errors(result, cam)
    worst = max(e, key=e.get)
    msgs = "; ".join(result.get("messages") or []) or "-"
    return (
        f"| {name} | {code} | {fx_error_pct(result, cam):.3f} | {e[worst]:.2f} ({worst}) | "
        f"{dt:.1f} | {msgs[:160]} |"
    )


def _detection_figures(directory: Path, target: Target) -> str:
    found, times = 0, []
    images = sorted((directory / "images").iterdir())
    for path in images:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        t0 = time.perf_counter()
        found += detect(img, target).ok
        times.append(time.perf_counter() - t0)
    return f"{found}/{len(images)} found, {np.median(times):.3f} s median, {max(times):.3f} s max"


def main(argv: list[str] | None = None) -> int:
    """Print the rehearsal's figures as a Markdown table (``--full``: the rendered 2-megapixel
    sessions too, some minutes)."""
    import argparse
    import tempfile

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("--full", action="store_true")
    ap.add_argument(
        "--tag-seeds",
        type=int,
        default=16,
        help="eye-to-hand tag sessions (seeds 0..N-1); their rms error/std follows the table",
    )
    ap.add_argument(
        "--translation-seeds",
        type=int,
        default=0,
        help="13-frame translation-only sessions (seeds 0..N-1): rms error/std, fx within 0.1 %%",
    )
    args = ap.parse_args(argv)
    tag_z: list[dict[str, float]] = []
    trans_z: list[dict[str, float]] = []
    trans_fx: list[float] = []
    print("| session | exit | fx error % | max abs(error)/std | solve s | messages |")
    print("| --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for mount, seed in (("eye_in_hand", 5), ("eye_to_hand", 6)):
            d, frames, measured, target, _ = classic_session(root, mount, seed, empty=(3, 9))
            code, msg, res, dt = solve(d)
            print(_row(f"classic hand-eye {mount}", code, msg, res, dt, CAM_1080))
            if res is not None:
                key = "T_tool_cam" if mount == "eye_in_hand" else "T_base_cam"
                T, T_park = (
                    transform_of(res[key]),
                    park(frames, measured, target, mount, (1920, 1080)),
                )
                print(
                    f"|  vs cv2 Park | | | {rotation_deg(T, T_park):.3f} deg, "
                    f"{1000 * np.linalg.norm(T[:3, 3] - T_park[:3, 3]):.2f} mm | | |"
                )
        for seed in range(args.tag_seeds):
            d = root / f"tag{seed}"
            truth = eye_to_hand_tag_session(d, seed)
            code, msg, res, dt = solve(d, in_process=True)
            print(_row(f"eye-to-hand tag seed {seed}", code, msg, res, dt, CAM_1080))
            if res is not None:
                tag_z.append(intrinsic_errors(res, truth.camera))
        for seed in range(args.translation_seeds):
            d = root / f"trans{seed}"
            truth = translation_only_session(d, seed)
            code, msg, res, dt = solve(d, in_process=True)
            print(_row(f"translation-only seed {seed}", code, msg, res, dt, truth.camera))
            if res is not None:
                trans_z.append(intrinsic_errors(res, truth.camera))
                trans_fx.append(fx_error_pct(res, truth.camera))
        if args.full:
            for kind, cam, ext in (("chessboard", CAM_1080, "png"), ("charuco", CAM_1200, "jpg")):
                tdict = (
                    chessboard(11, 8, 0.035)
                    if kind == "chessboard"
                    else charuco(12, 9, 0.03, 0.022, "DICT_5X5_100")
                )
                d = root / kind
                full, t13, _, target = eye_in_hand_2mp(d, tdict, cam, ext, 2)
                print(
                    f"| {kind} {cam.width}x{cam.height} {ext}: {_detection_figures(full, target)} |"
                )
                print(_row(f"{kind} 30 frames", *solve(full), cam))
                print(_row(f"{kind} 13 translation-only", *solve(t13), cam))
            d = root / "images_only"
            images_only_session(d, CAM_1200, 50, skip=17, seed=4)
            print(_row("images only, 50, frame 17 blank", *solve(d), CAM_1200))
    for label, zs in (("eye-to-hand tag", tag_z), ("translation-only", trans_z)):
        if not zs:
            continue
        names = [n for n in zs[0] if n in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")]
        z = np.array([[t.get(n, np.nan) for n in names] for t in zs])
        rms = np.sqrt(np.nanmean(z**2, axis=0))
        print(
            f"\n{label}, {len(zs)} sessions: rms abs(error)/std "
            + ", ".join(f"{n} {v:.2f}" for n, v in zip(names, rms, strict=True))
            + f"; sessions with an intrinsic beyond 3 std: {int(np.sum(np.nanmax(z, axis=1) > 3))}"
        )
    if trans_fx:
        within = int(np.sum(np.abs(trans_fx) < 0.1))
        print(f"translation-only: fx within 0.1 % of the truth in {within} of {len(trans_fx)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
