"""Every hand-eye session solved: classic (all orientations different), mixed, a 4-point tag;
frames that saw nothing skipped, never a reason to refuse; no made-up numbers."""

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from slidecal.mocks import scenarios as sc
from slidecal.mocks.truth import hand_eye_bounds
from slidecal.routines.session import SESSION_FILE
from slidecal.solver.adequacy import (
    MAX_CLASSIC_SCALE_SE,
    classic_scale_fit,
    scale_moves,
    unchecked_scale_note,
)
from slidecal.solver.calibrate import calibrate, frame_groups, pnp_pose
from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.geometry import (
    T_from_Rt,
    inv_T,
    look_at_R_cam_world,
    rotation_angle_deg,
)
from slidecal.solver.handeye import ax_xb_park_martin
from slidecal.solver.homography import homography_dlt
from slidecal.solver.problem import (
    CalibrationProblem,
    CameraSpec,
    Detection,
    Frame,
    ModelOptions,
    Target,
)
from slidecal.solver.uncertainty import predicted_covariance
from tests.helpers import random_rotation
from tests.session_io import read_session

EMPTY = Detection(np.zeros(0, int), np.zeros((0, 2)))
NO_DIST = ModelOptions(distortion=sc.NO_DISTORTION)


def _check_truth(res, s, rtol=1e-6):
    Kt = s.truth.K["cam"]
    np.testing.assert_allclose(res.cameras["cam"].K, Kt, rtol=rtol, atol=rtol * Kt[0, 0])
    assert rotation_angle_deg(res.hand_eye.R, s.T_hand_eye[:3, :3]) < 1e-6
    np.testing.assert_allclose(res.hand_eye.t_m, s.T_hand_eye[:3, 3], atol=1e-8)
    np.testing.assert_allclose(res.T_target.T, s.T_target, atol=1e-8)
    assert res.converged and res.reproj_rms_px < 1e-6


def _errors_in_std(res, s):
    """Errors of fx, fy, cx, cy and the hand-eye over their reported one-sigma."""
    cam, Kt = res.cameras["cam"], s.truth.K["cam"]
    out = {
        n: abs(cam.K[a, b] - Kt[a, b]) / cam.std[n]
        for n, (a, b) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items()
    }
    he = res.hand_eye
    out["rot"] = rotation_angle_deg(he.R, s.T_hand_eye[:3, :3]) / he.std_rot_deg
    out["t"] = 1000 * np.linalg.norm(he.t_m - s.T_hand_eye[:3, 3]) / he.std_t_mm
    return out


# -- the closed forms ---------------------------------------------------------------------------
def test_homography_from_exactly_four_points():
    """Four points (a single tag) determine a homography; the DLT took the wrong singular
    vector of the 8 x 9 system (an SVD without full matrices)."""
    rng = np.random.default_rng(0)
    H = np.array([[900.0, 40.0, 600.0], [-30.0, 870.0, 420.0], [0.05, -0.1, 1.0]])
    xy = np.array([[-0.04, -0.04], [0.04, -0.04], [0.04, 0.04], [-0.04, 0.04]])
    xy = xy + rng.normal(0, 0.005, xy.shape)
    p = np.c_[xy, np.ones(4)] @ H.T
    px = p[:, :2] / p[:, 2:]
    H_est = homography_dlt(xy, px)
    np.testing.assert_allclose(H_est / H_est[2, 2], H, rtol=1e-8, atol=1e-8)


def _motions(rng, n, noise_deg=0.0):
    X = T_from_Rt(random_rotation(rng), rng.normal(size=3) * 0.1)
    A, B = [], []
    for _ in range(n):
        Bk = T_from_Rt(random_rotation(rng, 1.0), rng.normal(size=3) * 0.2)
        Ak = X @ Bk @ inv_T(X)
        if noise_deg:
            Ak = T_from_Rt(random_rotation(rng, np.radians(noise_deg)), np.zeros(3)) @ Ak
            Ak[:3, 3] += rng.normal(size=3) * 1e-3
        A.append(Ak)
        B.append(Bk)
    return X, np.array(A), np.array(B)


def test_ax_xb_noise_free_and_noisy():
    method = ax_xb_park_martin
    rng = np.random.default_rng(1)
    X, A, B = _motions(rng, 6)
    Y = method(A, B)
    assert rotation_angle_deg(Y[:3, :3], X[:3, :3]) < 1e-8
    np.testing.assert_allclose(Y[:3, 3], X[:3, 3], atol=1e-10)
    # 0.05 deg and 1 mm on each of 30 motions: the rotation within a few times 0.05 / sqrt(30)
    X, A, B = _motions(rng, 30, noise_deg=0.05)
    Y = method(A, B)
    assert rotation_angle_deg(Y[:3, :3], X[:3, :3]) < 0.05
    assert np.linalg.norm(Y[:3, 3] - X[:3, 3]) < 3e-3


# -- classic sessions through the whole pipeline ------------------------------------------------
@pytest.mark.parametrize("eye_in_hand", [True, False], ids=["eye-in-hand", "eye-to-hand"])
def test_classic_session_noise_free(eye_in_hand):
    s = sc.classic(np.random.default_rng(3), 15, 0.0, 0.0, 0.0, eye_in_hand=eye_in_hand)
    assert len({round(float(np.trace(f.T_base_tool[:3, :3])), 6) for f in s.problem.frames}) == 15
    res = calibrate(s.problem)
    _check_truth(res, s)
    assert "T_tool_cam.t" not in res.unobservable and "T_base_cam.t" not in res.unobservable


@pytest.mark.parametrize("eye_in_hand", [True, False], ids=["eye-in-hand", "eye-to-hand"])
def test_classic_session_noisy_within_bound(eye_in_hand):
    """Pixel noise only: the reported std is the Cramer-Rao bound and covers the errors."""
    s = sc.classic(np.random.default_rng(4), 20, 0.15, 0.0, 0.0, eye_in_hand=eye_in_hand)
    res = calibrate(s.problem)
    bound = predicted_covariance(s.problem, s.truth, s.sigma_px)
    bound_rot = bound.std_rot_deg(res.hand_eye.name)
    # the reported std is s^2 (J'J)^-1 at the estimate: the bound within the spread of s (5 %)
    assert abs(res.hand_eye.std_rot_deg / bound_rot - 1) < 0.1
    assert abs(res.sigma_px / s.sigma_px - 1) < 0.1
    errs = _errors_in_std(res, s)
    assert max(errs.values()) < 4.0, errs


def test_classic_session_agrees_with_opencv_park():
    s = sc.classic(np.random.default_rng(5), 20, 0.15, 0.0, 0.0)
    res = calibrate(s.problem)
    K, dist = res.cameras["cam"].K, res.cameras["cam"].distortion
    Tg, Tc = [], []
    for f in s.problem.frames:
        d = f.detections["cam"]
        Tc.append(pnp_pose(K, dist, s.problem.target.points_m[d.ids], d.px))
        Tg.append(f.T_base_tool)
    Tg, Tc = np.array(Tg), np.array(Tc)
    R, t = cv2.calibrateHandEye(
        Tg[:, :3, :3], Tg[:, :3, 3], Tc[:, :3, :3], Tc[:, :3, 3], method=cv2.CALIB_HAND_EYE_PARK
    )
    # both estimate the same transform from the same images: they differ by about the
    # closed form's own error, of the order of the ML std (docs/results/HANDEYE.md: ~0.4 and ~1.2
    # std)
    assert rotation_angle_deg(R, res.hand_eye.R) < 3 * res.hand_eye.std_rot_deg
    assert 1000 * np.linalg.norm(t.ravel() - res.hand_eye.t_m) < 4 * res.hand_eye.std_t_mm


def test_mixed_session_uses_groups_and_single_frames():
    """Three orientations translated (groups) plus ten single-orientation frames."""
    rng = np.random.default_rng(6)
    groups = sc.classic(rng, 3, 0.0, 0.0, 0.0, per_orientation=4)
    singles = sc.classic(rng, 10, 0.0, 0.0, 0.0)
    frames = [
        replace(f, id=k) for k, f in enumerate(groups.problem.frames + singles.problem.frames)
    ]
    s = replace(groups, problem=replace(groups.problem, frames=tuple(frames)))
    res = calibrate(s.problem)
    _check_truth(res, s)
    assert len(res.residuals_px) == 22  # every frame entered the ML


def test_single_tag_four_corners_eye_to_hand_seven_orientations():
    """One AprilTag's 4 corners per image, eye-to-hand, 7 orientations of 5 frames."""
    tag = sc.square_tag(0.08)
    kw = dict(eye_in_hand=False, target=tag, per_orientation=5, distortion=np.zeros(5))
    s = sc.classic(np.random.default_rng(7), 7, 0.0, 0.0, 0.0, options=NO_DIST, **kw)
    assert {len(f.detections["cam"].ids) for f in s.problem.frames} == {4}
    _check_truth(calibrate(s.problem), s)
    s = sc.classic(np.random.default_rng(8), 7, 0.15, 0.0, 0.0, options=NO_DIST, **kw)
    res = calibrate(s.problem)
    errs = _errors_in_std(res, s)
    assert max(errs.values()) < 4.0, errs
    assert res.T_target.t_m is not None


def test_four_corner_tag_in_a_classic_session():
    tag = sc.square_tag(0.08)
    s = sc.classic(
        np.random.default_rng(9),
        12,
        0.0,
        0.0,
        0.0,
        target=tag,
        options=NO_DIST,
        distortion=np.zeros(5),
    )
    _check_truth(calibrate(s.problem), s)


def test_classic_session_too_few_frames_is_refused_with_the_count():
    s = sc.classic(np.random.default_rng(10), 2, 0.0, 0.0, 0.0, options=NO_DIST)
    with pytest.raises(DegenerateError, match="at least 3 orientations"):
        calibrate(s.problem)


# -- frames that saw nothing --------------------------------------------------------------------
def _blank(problem, which, keep=0):
    frames = list(problem.frames)
    for i in which:
        d = frames[i].detections["cam"]
        frames[i] = replace(frames[i], detections={"cam": Detection(d.ids[:keep], d.px[:keep])})
    return replace(problem, frames=tuple(frames))


@pytest.mark.parametrize("kind", ["classic", "groups", "images-only"])
def test_a_frame_that_saw_nothing_is_skipped_not_refused(kind):
    if kind == "classic":
        s = sc.classic(np.random.default_rng(11), 12, 0.0, 0.0, 0.0)
    else:
        s = sc.r1(np.random.default_rng(11), 0.0, 0.0, 0.0)
    problem = _blank(s.problem, [3])
    problem = _blank(problem, [7], keep=3)  # three points: too few for a pose
    if kind == "images-only":
        frames = tuple(Frame(f.id, f.detections) for f in problem.frames)
        problem = replace(problem, frames=frames, knowledge="none", mount="none")
    res = calibrate(problem)
    np.testing.assert_allclose(res.cameras["cam"].K, s.truth.K["cam"], rtol=1e-6)
    if kind != "images-only":
        assert rotation_angle_deg(res.hand_eye.R, s.T_hand_eye[:3, :3]) < 1e-6
    text = " ".join(res.messages)
    assert "frame 7" in text and "3 target points" in text and "skipped" in text
    assert "[3, 7]" in text or "[3]" in text
    assert (3, "cam") not in res.residuals_px and (7, "cam") not in res.residuals_px


def test_a_point_short_image_of_one_camera_leaves_the_frame_to_the_other():
    s = sc.r1(np.random.default_rng(12), 0.0, 0.0, 0.0)
    problem = _blank(s.problem, [4], keep=2)
    res = calibrate(problem)
    assert any("frame 4" in m and "2 target points" in m for m in res.messages)


def test_detections_that_failed_are_blamed_not_the_geometry():
    """One orientation group of 9 frames in which the detector found the board once."""
    s = sc.r1(np.random.default_rng(13), 0.0, 0.0, 0.0)
    one_group = replace(s.problem, frames=s.problem.frames[:5])
    problem = _blank(one_group, [1, 2, 3, 4])
    with pytest.raises(DegenerateError) as e:
        calibrate(problem)
    msg = str(e.value)
    assert "1 of 5 frames" in msg and "[1, 2, 3, 4]" in msg and "not" in msg
    assert "single frame" not in msg


def test_a_refusal_after_skipped_frames_says_frames_were_skipped():
    s = sc.r1(np.random.default_rng(14), 0.0, 0.0, 0.0)
    one_group = replace(s.problem, frames=s.problem.frames[:5])
    problem = _blank(one_group, [2, 3, 4])  # two frames left: one translation
    with pytest.raises(DegenerateError, match=r"3 of 5 frames.*target was not found"):
        calibrate(problem)


# -- no made-up numbers -------------------------------------------------------------------------
@pytest.mark.parametrize("eye_in_hand", [True, False], ids=["eye-in-hand", "eye-to-hand"])
def test_target_translation_is_none_when_the_hand_eye_translation_is_unobservable(eye_in_hand):
    s = sc.r1(np.random.default_rng(15), eye_in_hand=eye_in_hand)
    res = calibrate(replace(s.problem, frames=s.problem.frames[:5]))  # one tilt: translations
    he_name, tgt = ("T_tool_cam", "T_base_board")
    if not eye_in_hand:
        he_name, tgt = ("T_base_cam", "T_tool_board")
    assert res.hand_eye.t_m is None and f"{he_name}.t" in res.unobservable
    assert res.T_target.t_m is None and res.T_target.std_t_mm is None
    assert res.T_target.T is None
    assert f"{tgt}.t" in res.unobservable and he_name in res.unobservable[f"{tgt}.t"]
    assert not any(n.startswith(f"{tgt}.t") for n in res.parameter_names)
    assert not any(n.startswith(f"{he_name}.t") for n in res.parameter_names)
    assert {f"{tgt}.rx", f"{he_name}.rz"} <= set(res.parameter_names)
    assert res.covariance.shape == (len(res.parameter_names),) * 2
    # the rotation is observable and reported, with its std
    assert res.T_target.R is not None and res.T_target.std_rot_deg > 0
    assert rotation_angle_deg(res.T_target.R, s.T_target[:3, :3]) < 5 * res.T_target.std_rot_deg


def test_target_pose_is_reported_when_observable():
    s = sc.r1(np.random.default_rng(16), 0.0, 0.0, 0.0)
    res = calibrate(s.problem)
    assert not any(k.startswith("T_base_board") for k in res.unobservable)
    assert {f"T_base_board.{a}" for a in ("rx", "ry", "rz", "tx", "ty", "tz")} <= set(
        res.parameter_names
    )


# -- messages that name the cause ---------------------------------------------------------------
def test_poses_in_millimetres_are_named():
    s = sc.r1(np.random.default_rng(17), 0.0, 0.0, 0.0)
    frames = []
    for f in s.problem.frames:
        T = f.T_base_tool.copy()
        T[:3, 3] *= 1000.0
        frames.append(replace(f, T_base_tool=T))
    with pytest.raises(InputError, match="look like millimetres; give metres"):
        calibrate(replace(s.problem, frames=tuple(frames)))


_SESSION = {
    "format": "slidecal.session/1",
    "mount": "eye_in_hand",
    "target": {"kind": "chessboard", "squares_x": 9, "squares_y": 7, "square_size_m": 0.03},
    "cameras": [{"name": "left", "width": 1280, "height": 800}],
}


def _write(d: Path, **changes) -> None:
    data = {**_SESSION, **changes}
    d.mkdir(parents=True, exist_ok=True)
    (d / SESSION_FILE).write_text(yaml.safe_dump(data))


def test_rotations_in_degrees_are_named(tmp_path: Path):
    det = {"left": {"ids": [0, 1, 2, 3], "px": [[1, 2], [3, 4], [5, 6], [7, 9]]}}
    _write(tmp_path, frames=[{"id": 0, "T_base_tool": [0.4, 0, 0.3, 0, 180, 0], "detections": det}])
    with pytest.raises(InputError, match="look like degrees") as e:
        read_session(tmp_path)
    assert "frames[0].T_base_tool" in str(e.value)


def test_an_empty_frame_list_does_not_blame_the_knowledge(tmp_path: Path):
    _write(tmp_path, knowledge="robot", frames=[])
    with pytest.raises(InputError) as e:
        read_session(tmp_path)
    assert "remove" not in str(e.value) and "frames" in str(e.value)


def test_a_points_target_of_four_corners_loads(tmp_path: Path):
    """The session reader's 4-point target is what the solver now accepts."""
    tag = {
        "kind": "points",
        "points_m": [[-0.04, -0.04], [0.04, -0.04], [0.04, 0.04], [-0.04, 0.04]],
    }
    det = {"left": {"ids": [0, 1, 2, 3], "px": [[600, 400], [700, 400], [700, 500], [600, 500]]}}
    frames = [{"id": 0, "T_base_tool": [0.4, 0, 0.3, 0, 3.1, 0], "detections": det}]
    _write(tmp_path, target=tag, frames=frames)
    problem = read_session(tmp_path)
    assert problem.target.kind == "points" and len(problem.target.points_m) == 4
    assert isinstance(problem.target, Target)


# -- the benchmark ------------------------------------------------------------------------------
def test_benchmark_bounds_match_the_reported_std():
    """The bench's bounds (rotation, translation through the inverse, fx) are the solver's
    reported std at the same noise: both come from the same information matrix."""

    s = sc.classic(np.random.default_rng(18), 15, 0.15, 0.0, 0.0)
    res = calibrate(s.problem)
    rot, t, fx = hand_eye_bounds(s, s.sigma_px)
    assert abs(res.hand_eye.std_rot_deg / rot - 1) < 0.1
    assert abs(res.hand_eye.std_t_mm / t - 1) < 0.1
    assert abs(res.cameras["cam"].std["fx"] / fx - 1) < 0.1


@pytest.mark.slow
def test_benchmark_row_runs_and_stays_near_the_bound():
    # the classic study's eye-in-hand row (tests/bench/handeye.py): seeds 1000.. on one geometry
    board = Target.charuco(11, 8, 0.030, 0.022)
    geometry = sc.camera_board_poses(np.random.default_rng(15), 15, board)

    def make(seed: int) -> sc.Scenario:
        return sc.classic(np.random.default_rng(seed), 15, 0.15, 0.0, 0.0, T_cam_board=geometry)

    rot_bound_deg = hand_eye_bounds(make(999), 0.15)[0]
    rot_deg = []
    for seed in range(1000, 1004):
        s = make(seed)
        rot_deg.append(rotation_angle_deg(calibrate(s.problem).hand_eye.R, s.T_hand_eye[:3, :3]))
    # four trials: the rms of a 3-dof error lies within a factor 2.5 of its bound
    assert np.sqrt(np.mean(np.square(rot_deg))) < 2.5 * rot_bound_deg


# -- through the session files ------------------------------------------------------------------
@pytest.mark.parametrize("robot", [True, False], ids=["classic-hand-eye", "images-only"])
def test_solve_a_recorded_session_with_a_frame_that_saw_nothing(tmp_path: Path, robot):
    from slidecal.routines.solve import solve_session
    from tests.session_io import write_session

    s = sc.classic(np.random.default_rng(19), 12, 0.0, 0.0, 0.0)
    problem = _blank(s.problem, [5])
    if not robot:
        frames = tuple(Frame(f.id, f.detections) for f in problem.frames)
        problem = replace(problem, frames=frames, knowledge="none", mount="none")
    write_session(tmp_path / "session", problem)
    outcome = solve_session(tmp_path / "session")
    np.testing.assert_allclose(outcome.result.cameras["cam"].K, s.truth.K["cam"], rtol=1e-6)
    assert outcome.n_frames == 12  # the frame keeps its place in the session
    data = yaml.safe_load(outcome.result_path.read_text())
    assert any("frames [5]" in m and "skipped" in m for m in data["messages"])
    if robot:
        assert data["T_tool_cam"]["t_m"] is not None


# -- starts that the homographies alone cannot give ---------------------------------------------
def _small_tag_session(seed, tilt_deg):
    """A 4 cm tag 0.45-0.6 m away (about 70 px wide) with 1 px corner noise: the homographies
    barely fix a focal length; the robot poses do."""
    tag = sc.square_tag(0.04)
    rng = np.random.default_rng(seed)
    views = sc.camera_board_poses(rng, 15, tag, tilt_deg=tilt_deg, aim_spread_m=0.1)
    return sc.classic(
        rng,
        15,
        1.0,
        0.0,
        0.0,
        target=tag,
        options=NO_DIST,
        distortion=np.zeros(5),
        T_cam_board=views,
    )


@pytest.mark.parametrize(
    ("seed", "tilt_deg"),
    [(1, (5.0, 25.0)), (3, (5.0, 25.0)), (0, (0.0, 10.0))],
    ids=["zhang-not-positive-definite", "zhang-far-off", "zhang-start-does-not-converge"],
)
def test_noisy_small_tag_starts_from_the_robot_poses(seed, tilt_deg):
    s = _small_tag_session(seed, tilt_deg)
    res = calibrate(s.problem)
    assert res.converged
    errs = _errors_in_std(res, s)
    assert max(errs.values()) < 4.0, errs


def test_focal_from_homographies_noise_free():
    from slidecal.solver.homography import homography_dlt
    from slidecal.solver.linear import focal_from_homographies

    K = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 399.5], [0.0, 0.0, 1.0]])
    views = sc.camera_board_poses(np.random.default_rng(20), 5, Target.chessboard(9, 7, 0.03))
    pts = Target.chessboard(9, 7, 0.03).points_m
    Hs = []
    for T in views:
        P = pts @ T[:3, :3].T + T[:3, 3]
        px = P[:, :2] / P[:, 2:] * 900.0 + [639.5, 399.5]
        Hs.append(homography_dlt(pts[:, :2], px))
    np.testing.assert_allclose(focal_from_homographies(np.array(Hs), image_size=(1280, 800)), K)


def test_classic_session_of_a_two_camera_rig():
    """A stereo head on the tool, every frame at its own orientation: the rig's joint linear
    step takes the general-motion path (infinite homography) instead of refusing."""
    from slidecal.solver.geometry import R_from_rvec
    from slidecal.solver.problem import CameraSpec

    s = sc.classic(np.random.default_rng(21), 12, 0.0, 0.0, 0.0)
    T_right_cam = T_from_Rt(R_from_rvec(np.radians([0.0, 3.0, 0.0])), np.array([-0.075, 0, 0]))
    rng = np.random.default_rng(22)
    frames = []
    for f in s.problem.frames:
        T_cam_board = inv_T(f.T_base_tool @ sc.R1_T_TOOL_CAM) @ s.T_target
        right = sc.projected_detection(
            sc.R1_K,
            sc.R1_DIST,
            T_right_cam @ T_cam_board,
            s.problem.target,
            (1280, 800),
            0.0,
            rng,
            2.0,
        )
        frames.append(replace(f, detections={"cam": f.detections["cam"], "right": right}))
    cams = (*s.problem.cameras, CameraSpec("right", 1280, 800))
    res = calibrate(replace(s.problem, frames=tuple(frames), cameras=cams))
    assert not any("joint linear step" in m for m in res.messages)
    _check_truth(res, s)
    np.testing.assert_allclose(res.cameras["right"].K, sc.R1_K, rtol=1e-6)
    np.testing.assert_allclose(res.rig["T_right_cam"].T, T_right_cam, atol=1e-8)


def test_mixed_session_of_a_two_camera_rig():
    """Translation groups and single-orientation frames seen by both cameras of a head: the
    joint linear step uses the groups with a translation (it refused single-frame groups)."""
    from slidecal.solver.geometry import R_from_rvec
    from slidecal.solver.problem import CameraSpec

    rng = np.random.default_rng(23)
    groups = sc.classic(rng, 3, 0.0, 0.0, 0.0, per_orientation=4)
    singles = sc.classic(rng, 6, 0.0, 0.0, 0.0)
    T_right_cam = T_from_Rt(R_from_rvec(np.radians([0.0, 3.0, 0.0])), np.array([-0.075, 0, 0]))
    frames = []
    for k, f in enumerate(groups.problem.frames + singles.problem.frames):
        T_cam_board = inv_T(f.T_base_tool @ sc.R1_T_TOOL_CAM) @ groups.T_target
        right = sc.projected_detection(
            sc.R1_K,
            sc.R1_DIST,
            T_right_cam @ T_cam_board,
            groups.problem.target,
            (1280, 800),
            0.0,
            rng,
            2.0,
        )
        frames.append(replace(f, id=k, detections={"cam": f.detections["cam"], "right": right}))
    cams = (*groups.problem.cameras, CameraSpec("right", 1280, 800))
    s = replace(groups, problem=replace(groups.problem, frames=tuple(frames), cameras=cams))
    res = calibrate(s.problem)
    assert not any("joint linear step" in m for m in res.messages), res.messages
    _check_truth(res, s)
    np.testing.assert_allclose(res.rig["T_right_cam"].T, T_right_cam, atol=1e-8)


# -- a classic session's scale: the camera's lengths against the robot's -------------------------
def _aimed_session(rng, distances_m, board_scale=1.0, arm_mm=0.5):
    """Eye-in-hand, 20 frames each at its own orientation, every camera aimed at the board's
    centre from ``distances_m`` (per frame), the camera's view of the board ``board_scale``
    times as large as the robot's (a board described that much too large), the recorded tool
    positions off by ``arm_mm`` (per axis, independent). Returns the problem (no detections:
    only the poses matter here), the images-alone ``T_cam_board`` per frame index and
    ``R_board_base``."""
    T_base_board = T_from_Rt(np.eye(3), np.array([0.6, 0.0, 0.0]))
    centre = np.array([0.6, 0.0, 0.0]) + [0.15, 0.1, 0.0]
    T_tool_cam = T_from_Rt(random_rotation(rng, 0.3), np.array([0.03, -0.08, 0.06]))
    frames, poses = [], {}
    for k, d in enumerate(distances_m):
        u = np.array([*rng.uniform(-0.5, 0.5, 2), 1.0])
        c = centre + d * u / np.linalg.norm(u)
        R_cam_base = look_at_R_cam_world(c, centre, rng.normal(size=3))
        T_base_cam = T_from_Rt(R_cam_base.T, c)
        T_base_tool = T_base_cam @ inv_T(T_tool_cam)
        T_cam_board = inv_T(T_base_cam) @ T_base_board
        T_cam_board[:3, 3] *= board_scale
        measured = T_base_tool.copy()
        measured[:3, 3] += rng.normal(0.0, arm_mm / 1000.0, 3)
        frames.append(Frame(k, {}, T_base_tool=measured))
        poses[k] = T_cam_board
    target = Target.chessboard(9, 6, 0.03)
    problem = CalibrationProblem(target, (CameraSpec("cam", 1280, 800),), tuple(frames))
    return problem, poses, T_base_board[:3, :3].T


def test_a_classic_sessions_scale_is_read_only_where_its_geometry_pins_it():
    rng = np.random.default_rng(11)
    # 0.4-0.7 m from the board: the fit pins the ratio, and a board described 2 % too large
    # shows as the camera's lengths 2 % longer than the robot's
    far_near = rng.uniform(0.4, 0.7, 20)
    for scale in (1.0, 1.02):
        problem, poses, R = _aimed_session(np.random.default_rng(3), far_near, scale)
        ratio, se, _ = classic_scale_fit(problem, poses, R)
        assert se < MAX_CLASSIC_SCALE_SE and abs(ratio - scale) < 4 * se + 1e-4, (ratio, se)
        moves = scale_moves(problem, poses, R, frame_groups(problem), 0.001)
        assert len(moves) == 19
        assert abs(np.median([c / r for *_, r, c in moves]) - scale) < 0.003
    assert unchecked_scale_note(problem, poses, R, frame_groups(problem)) == ()
    # every frame 0.43 m from the point it is aimed at: a scale of the camera's view is a
    # shift of the hand-eye along the viewing direction, which the fit cannot tell apart; at
    # 0.41-0.46 m it barely can: no move is checked, and the result says so
    for distances in (np.full(20, 0.43), rng.uniform(0.41, 0.46, 20)):
        problem, poses, R = _aimed_session(np.random.default_rng(3), distances, 1.02)
        fit = classic_scale_fit(problem, poses, R)
        assert fit is None or fit[1] > MAX_CLASSIC_SCALE_SE, fit
        assert scale_moves(problem, poses, R, frame_groups(problem), 0.001) == []
        (note,) = unchecked_scale_note(problem, poses, R, frame_groups(problem))
        assert "scale" in note and "not checked" in note and "nearer to and farther" in note


@pytest.mark.parametrize("eye_in_hand", [True, False], ids=["eye-in-hand", "eye-to-hand"])
def test_a_classic_session_with_a_wrong_square_size_is_rejected_for_its_scale(eye_in_hand):
    # a classic session (28 frames, each at its own orientation) on a real arm, its board
    # described 2 % too small: eye-to-hand the solve took it as the arm's error (learned
    # accuracy 0.1-0.25 -> 0.7-0.8 mm) and put the camera 10 mm off, 14-16 times its reported
    # std, and the verdict accepted it (no move at one orientation to check the scale on)
    from slidecal.routines.ops.verdict import judge

    s = sc.classic_real_arm(np.random.default_rng(2001), eye_in_hand=eye_in_hand)
    t = s.problem.target
    for scale in (1.0, 0.98):
        board = replace(t, points_m=t.points_m * scale, square_size_m=t.square_size_m * scale)
        problem = replace(s.problem, target=board)
        res = calibrate(problem)
        ratios = [c.ratio for c in res.scale_checks]
        assert len(ratios) >= 20 and abs(np.median(ratios) - scale) < 0.005, ratios
        failed = {c.test: c.message for c in judge(res, problem=problem).checks if not c.passed}
        if scale == 1.0:
            assert "scale" not in failed, failed
        else:
            assert "target.square_size_m" in failed["scale"], failed


def test_a_classic_sessions_unexplained_scale_is_carried_in_its_covariance(monkeypatch):
    # an arm whose moves are 0.5 % longer than it reports (classic_real_arm(arm_scale=...),
    # seed 2002): the images alone read the camera/robot length ratio at 1.0037 +- 0.0012, a
    # scale the noise does not explain, which with every frame aimed at the board moves the
    # hand-eye along the viewing direction; the solve put T_tool_cam.tz 1.69 of its std off the
    # truth the session can know. The scale is now carried as the board's scale uncertainty
    import slidecal.solver.calibrate as cal

    def z_tz(res, s):  # noqa: ANN001, ANN202
        ra = res.robot_accuracy
        X, _ = sc.effective_truth(s, max(ra.rotation_deg, 1e-4), max(ra.translation_mm, 1e-3))
        return abs(res.hand_eye.t_m[2] - X[2, 3]) / res.named_covariance.std("T_tool_cam.tz")

    s = sc.classic_real_arm(np.random.default_rng(2002), arm_scale=0.005)
    kept = {}
    inner = cal.session_scale

    def keep(*a):  # noqa: ANN002, ANN202
        kept["scale"] = inner(*a)
        return kept["scale"]

    monkeypatch.setattr(cal, "session_scale", keep)
    res = calibrate(s.problem)
    assert 0.002 < kept["scale"] < 0.006 and res.board is None  # an exact board: no bow told
    monkeypatch.setattr(cal, "session_scale", lambda *a: 0.0)
    before = calibrate(s.problem)
    assert z_tz(before, s) > 1.5 and z_tz(res, s) < 1.0
    np.testing.assert_allclose(res.hand_eye.t_m, before.hand_eye.t_m, atol=1e-12)  # the same
    # an arm right to scale (seed 2000, the ratio 0.9985 +- 0.0018): nothing carried
    monkeypatch.setattr(cal, "session_scale", keep)
    calibrate(sc.classic_real_arm(np.random.default_rng(2000)).problem)
    assert kept["scale"] == 0.0
