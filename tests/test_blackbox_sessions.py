"""The hidden real-data check, rehearsed black-box: sessions written by hand from the public
session contract (README, docs/FORMATS.md; ``tests/blackbox.py``, never slidecal's session
writer), solved by ``slidecal solve SESSION --out result.yaml`` as a user runs it, judged
against the simulation's truth by the checker's criteria.

Fast: sessions with given detections (a classic hand-eye session against OpenCV's Park, frames
with empty ids, an images-only session whose ``mount`` says something of its own) and small
rendered images (a chessboard counted in inner corners). Slow: the 2-megapixel photograph-like
images of a chessboard and a ChArUco board on a simulated real arm.
"""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import blackbox as bb  # noqa: E402

from slidecal.mocks.camera import SimCamera  # noqa: E402
from slidecal.mocks.cell import effective_truth  # noqa: E402
from slidecal.solver.camera import K_matrix  # noqa: E402
from slidecal.solver.detect import detect  # noqa: E402
from slidecal.solver.geometry import T_from_Rt, inv_T  # noqa: E402

#: a VGA camera for the fast rendered sessions
VGA = SimCamera("left", 640, 480, K_matrix(560.0, 560.0, 321.0, 238.5), np.zeros(5))


def _classic_session(tmp_path: Path, mount: str, seed: int, empty: tuple[int, ...] = ()):
    """28 frames, each at its own orientation, detections given (0.1 px noise); the frames in
    ``empty`` saw nothing (empty ids). Returns (session dir, frames, measured poses, truth)."""
    rng = np.random.default_rng(seed)
    cam = bb.CAM_1080
    tdict = bb.charuco(12, 9, 0.03, 0.022, "DICT_5X5_100")
    target = bb.target_of(tdict)
    T_base_board = bb.T_base_board_for(target)
    views = bb.varied_views(T_base_board, target, 28, rng, (0.45, 0.65), (5.0, 35.0))
    if mount == "eye_in_hand":
        true, measured = bb.arm(views, rng)
        T_cam_board = [inv_T(T @ bb.T_TOOL_CAM) @ T_base_board for T in true]
        T_hand_eye = bb.T_TOOL_CAM
    else:  # the same camera-board poses, the board on the tool, the camera on a stand
        T_tool_board = T_from_Rt(np.diag([1.0, -1.0, -1.0]), np.array([-0.18, -0.135, 0.03]))
        planned = [
            bb.T_BASE_CAM @ inv_T(T @ bb.T_TOOL_CAM) @ T_base_board @ inv_T(T_tool_board)
            for T in views
        ]
        true, measured = bb.arm([T for T in planned if bb.reachable(T)], rng)
        T_cam_board = [inv_T(bb.T_BASE_CAM) @ T @ T_tool_board for T in true]
        T_hand_eye = bb.T_BASE_CAM
    frames = []
    for k, T in enumerate(T_cam_board):
        det = bb.projected(cam, target.points_m, T, rng, 0.1)
        if k in empty:
            det = (np.zeros(0, int), np.zeros((0, 2)))
        frames.append(bb.frame_entry(k, measured[k], detection=det))
    root = bb.write_session(tmp_path / mount, tdict, cam, frames, mount=mount)
    return root, frames, measured, target, T_hand_eye


def _park(frames, measured, target, mount: str, size: tuple[int, int]) -> np.ndarray:
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


@pytest.mark.parametrize("mount", ["eye_in_hand", "eye_to_hand"])
def test_classic_hand_eye_session_with_empty_frames_agrees_with_park(tmp_path, mount):
    root, frames, measured, target, T_hand_eye = _classic_session(
        tmp_path, mount, 5 if mount == "eye_in_hand" else 6, empty=(3, 9)
    )
    code, message, result, _ = bb.solve(root, in_process=True)
    assert code == 0 and result is not None, message
    assert any("[3, 9]" in m and "skipped" in m for m in result["messages"])
    key = "T_tool_cam" if mount == "eye_in_hand" else "T_base_cam"
    est = bb.transform_of(result[key])
    park = _park(frames, measured, target, mount, (1920, 1080))
    # measured: 0.01-0.04 deg and 0.2 mm apart (both within 0.07 deg, 1 mm of the truth under
    # the arm's 1 mm, 0.1 deg error); a wrong convention or frame would be degrees off
    assert bb.rotation_deg(est, park) < 0.1
    assert np.linalg.norm(est[:3, 3] - park[:3, 3]) < 1.5e-3
    assert bb.rotation_deg(est, T_hand_eye) < 0.2
    assert max(bb.intrinsic_errors(result, bb.CAM_1080).values()) < 4.0


def _vga_chessboard_images(directory: Path, n: int, rng: np.random.Generator, skip=()):
    target = bb.target_of(bb.chessboard(9, 7, 0.03))
    T_base_board = bb.T_base_board_for(target)
    views = bb.varied_views(T_base_board, target, n, rng, (0.45, 0.6), (10.0, 40.0))
    truth = bb.eye_in_hand_truth(VGA, T_base_board, views, rng, 0.0, 0.0)
    return bb.render_frames(truth, target, directory, rng, "png", skip=set(skip))


def test_images_only_session_solves_whatever_its_mount_says(tmp_path):
    rng = np.random.default_rng(41)
    names = _vga_chessboard_images(tmp_path / "a", 12, rng, skip=(5,))
    frames = [bb.frame_entry(k, None, image=n) for k, n in enumerate(names)]
    for mount in (None, "handheld"):  # no mount, and a word of the user's own
        root = tmp_path / "a"
        bb.write_session(root, bb.chessboard(9, 7, 0.03), VGA, frames, mount=mount)
        code, message, result, _ = bb.solve(root, in_process=True)
        assert code == 0 and result is not None, message
        assert result["mount"] == "none"
        assert any("[5]" in m and "not found" in m for m in result["messages"])
        assert max(bb.intrinsic_errors(result, VGA).values()) < 4.0


def test_chessboard_counted_in_inner_corners_is_refused_with_the_fix(tmp_path):
    rng = np.random.default_rng(42)
    names = _vga_chessboard_images(tmp_path / "b", 3, rng)
    frames = [bb.frame_entry(k, None, image=n) for k, n in enumerate(names)]
    # the printed board has 9 x 7 squares; the user counted its 8 x 6 inner corners
    root = bb.write_session(tmp_path / "b", bb.chessboard(8, 6, 0.03), VGA, frames, mount=None)
    code, message, result, _ = bb.solve(root, in_process=True)
    assert code == 2 and result is None and "Traceback" not in message
    assert "set squares_x: 9, squares_y: 7" in message
    assert len(message.strip().splitlines()) == 1


# ----------------------------------------------------------------------------- 2 megapixels
def _eye_in_hand_2mp(tmp_path: Path, tdict: dict, cam: SimCamera, ext: str, seed: int):
    """30 frames: 13 translation-only (one orientation), 17 each at its own orientation; the
    arm errs by 1 mm / 0.1 deg. Returns (full session, 13-frame session, truth, target)."""
    rng = np.random.default_rng(seed)
    target = bb.target_of(tdict)
    T_base_board = bb.T_base_board_for(target)
    T0 = bb.view_pose(T_base_board, target, (22.0, 8.0), 0.6)
    planned = [T0, *bb.translations(T0, 12, rng)]
    planned += bb.varied_views(T_base_board, target, 17, rng)
    truth = bb.eye_in_hand_truth(cam, T_base_board, planned, rng)
    full = tmp_path / "full"
    names = bb.render_frames(truth, target, full, rng, ext)
    frames = [bb.frame_entry(k, truth.measured[k], image=n) for k, n in enumerate(names)]
    bb.write_session(full, tdict, cam, frames)
    t13 = tmp_path / "t13"
    (t13 / "images").mkdir(parents=True)
    for n in names[:13]:
        shutil.copy(full / n, t13 / n)
    bb.write_session(t13, tdict, cam, frames[:13])
    return full, t13, truth, target


@pytest.mark.slow
@pytest.mark.parametrize(
    "kind, cam, ext",
    [
        ("chessboard", bb.CAM_1080, "png"),  # colour 1920 x 1080, PNG
        ("charuco", bb.CAM_1200, "jpg"),  # grey 1600 x 1200, JPEG
    ],
)
def test_eye_in_hand_2_megapixel_photographs(tmp_path, kind, cam, ext):
    tdict = (
        bb.chessboard(11, 8, 0.035)
        if kind == "chessboard"
        else bb.charuco(12, 9, 0.03, 0.022, "DICT_5X5_100")
    )
    full, t13, truth, target = _eye_in_hand_2mp(tmp_path, tdict, cam, ext, 2)
    # the board in every frame, within the time per image
    times = []
    for k in range(30):
        img = cv2.imread(str(full / f"images/{k:04d}_left.{ext}"), cv2.IMREAD_UNCHANGED)
        t0 = time.perf_counter()
        rep = detect(img, target)
        times.append(time.perf_counter() - t0)
        assert rep.ok, (k, rep.reasons)
    assert np.median(times) < 0.3  # measured 0.04-0.1 s (the median: a loaded machine's spikes)
    code, message, result, _ = bb.solve(full)
    assert code == 0 and result is not None, message
    assert not result["messages"]
    assert max(bb.intrinsic_errors(result, cam).values()) < 3.0
    ra = result["robot_accuracy"]
    T_he, _ = effective_truth(
        "eye_in_hand",
        truth.true,
        truth.measured,
        bb.T_TOOL_CAM,
        truth.T_target,
        max(ra["rotation_deg"], 1e-4),
        max(ra["translation_mm"], 1e-3),
    )
    assert max(bb.hand_eye_errors(result, "T_tool_cam", T_he).values()) < 3.0
    # the 13 translation-only frames alone: fx within 3 of its reported std; that std is below
    # 0.1 % (the arm's smooth error changes each 40-80 mm move by 0.1-0.8 %, which bounds fx:
    # measured 0.15 % error at a reported 0.09-0.1 % on both boards)
    code, message, r13, _ = bb.solve(t13)
    assert code == 0 and r13 is not None, message
    assert max(bb.intrinsic_errors(r13, cam).values()) < 3.0
    assert r13["cameras"]["left"]["std"]["fx"] / cam.K[0, 0] < 1e-3
    assert r13["T_tool_cam"]["t_m"] is None  # no rotation: the translation is unobservable


def test_eye_to_hand_one_tag_as_points_with_given_detections(tmp_path):
    # 205 frames in 7 orientations, the arm 0.8 mm off; a few frames see only 3 corners
    truth = bb.eye_to_hand_tag_session(tmp_path / "tag", seed=1)
    code, message, result, _ = bb.solve(tmp_path / "tag", in_process=True)
    assert code == 0 and result is not None, message
    assert result["mount"] == "eye_to_hand"
    # every intrinsic within 3 of its std: holds for this seed; tests/test_blackbox_reproducers.py
    # holds one where it does not (the std is too small under the arm's smooth error)
    assert max(bb.intrinsic_errors(result, truth.camera).values()) < 3.0
    assert bb.fx_error_pct(result, truth.camera) < 0.1
