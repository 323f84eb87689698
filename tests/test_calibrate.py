"""The whole pipeline (linear start, refinement, result) on synthetic sessions with truth."""

from dataclasses import replace

import cv2
import numpy as np
import pytest

import slidecal.solver.adequacy as adequacy
import slidecal.solver.calibrate as pipeline
from slidecal.mocks import scenarios as sc
from slidecal.solver.calibrate import calibrate
from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.geometry import inv_T, rotation_angle_deg
from slidecal.solver.problem import Frame, Target


@pytest.mark.parametrize("make", list(sc.NOISE_FREE.values()), ids=list(sc.NOISE_FREE))
def test_noise_free_pipeline_recovers_truth(make):
    s = make(np.random.default_rng(0))
    res = calibrate(s.problem)
    cam = res.cameras["cam"]
    Kt = s.truth.K["cam"]
    np.testing.assert_allclose(cam.K, Kt, rtol=1e-6, atol=1e-6 * Kt[0, 0])
    np.testing.assert_allclose(cam.distortion, s.truth.dist["cam"], atol=1e-7)
    assert res.converged and res.reproj_rms_px < 1e-6
    if s.problem.knowledge == "robot" and s.problem.cameras[0].width == 1280:
        assert rotation_angle_deg(res.hand_eye.R, s.T_hand_eye[:3, :3]) < 1e-6
        np.testing.assert_allclose(res.hand_eye.t_m, s.T_hand_eye[:3, 3], atol=1e-8)
        np.testing.assert_allclose(res.T_target.T, s.T_target, atol=1e-8)


def test_general_motion_zhang_without_robot():
    s = sc.r1(np.random.default_rng(1), 0.0, 0.0, 0.0)
    frames = tuple(Frame(f.id, f.detections) for f in s.problem.frames)
    problem = replace(s.problem, frames=frames, knowledge="none", mount="none")
    res = calibrate(problem)
    np.testing.assert_allclose(res.cameras["cam"].K, sc.R1_K, rtol=1e-6)
    assert res.hand_eye is None


def test_noisy_r1_errors_within_reported_uncertainty():
    s = sc.r1(np.random.default_rng(2))
    res = calibrate(s.problem)
    cam = res.cameras["cam"]
    for name, (a, b) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items():
        assert abs(cam.K[a, b] - sc.R1_K[a, b]) < 4.0 * cam.std[name], name
    # robot pose noise (0.05 mm, 0.005 deg) is not in the model: allow 4 sigma plus its size
    err = rotation_angle_deg(res.hand_eye.R, s.T_hand_eye[:3, :3])
    assert err < 4.0 * res.hand_eye.std_rot_deg + 0.005
    t_err_mm = 1000.0 * np.linalg.norm(res.hand_eye.t_m - s.T_hand_eye[:3, 3])
    assert t_err_mm < 4.0 * res.hand_eye.std_t_mm + 0.1
    assert {"cam.fx", "cam.k1", "T_tool_cam.rx", "T_base_board.tz"} <= set(res.parameter_names)
    assert not any(n.startswith(("X0.", "Y.", "pose")) for n in res.parameter_names)
    assert res.covariance.shape == (len(res.parameter_names),) * 2
    assert res.named_covariance.std("T_tool_cam.tx") is not None
    assert all(abs(c.ratio - 1.0) < 0.01 for c in res.scale_checks)


def test_hand_eye_agrees_with_opencv_park_martin():
    """A classic AX = XB method on the same data (per-frame PnP poses) as a cross-check."""
    s = sc.r1(np.random.default_rng(3), 0.0, 0.0, 0.0)
    res = calibrate(s.problem)
    K, dist = res.cameras["cam"].K, res.cameras["cam"].distortion
    R_g2b, t_g2b, R_t2c, t_t2c = [], [], [], []
    for f in s.problem.frames:
        det = f.detections["cam"]
        ok, rvec, tvec = cv2.solvePnP(s.problem.target.points_m[det.ids], det.px, K, dist)
        R_g2b.append(f.T_base_tool[:3, :3])
        t_g2b.append(f.T_base_tool[:3, 3])
        R_t2c.append(cv2.Rodrigues(rvec)[0])
        t_t2c.append(tvec)
    R, t = cv2.calibrateHandEye(R_g2b, t_g2b, R_t2c, t_t2c, method=cv2.CALIB_HAND_EYE_PARK)
    assert rotation_angle_deg(R, res.hand_eye.R) < 1e-4
    np.testing.assert_allclose(t.ravel(), res.hand_eye.t_m, atol=1e-5)


def test_translation_only_session_reports_hand_eye_translation_unobservable():
    s = sc.r1(np.random.default_rng(4))
    frames = tuple(f for f in s.problem.frames if f.id < 5)  # the first tilt group only
    res = calibrate(replace(s.problem, frames=frames))
    assert res.hand_eye.t_m is None and res.hand_eye.std_t_mm is None
    assert "T_tool_cam.t" in res.unobservable
    assert res.hand_eye.R is not None and res.hand_eye.std_rot_deg > 0
    assert (
        rotation_angle_deg(res.hand_eye.R, s.T_hand_eye[:3, :3])
        < 4 * res.hand_eye.std_rot_deg + 0.01
    )


def test_scale_check_catches_a_wrong_square_size():
    s = sc.r1(np.random.default_rng(5))
    t = s.problem.target
    wrong = Target.charuco(11, 8, 0.030 * 1.03, 0.022 * 1.03)
    res = calibrate(replace(s.problem, target=wrong))
    ratios = np.array([c.ratio for c in res.scale_checks])
    # a 3 % wrong board makes the whole model inconsistent: single moves scatter by +-3 %,
    # their median shows the 3 % (the right board gives 1 +- 0.002, see the test above)
    assert abs(np.median(ratios) - 1.03) < 0.01 and np.all(ratios > 1.005), ratios
    assert t.square_size_m == 0.030


def test_translations_parallel_to_the_board_are_refused():
    s = sc.r1(np.random.default_rng(6), 0.1, 0.0, 0.0)
    T_base_board = s.T_target
    frames = []
    rng = np.random.default_rng(7)
    for k in range(5):
        T_base_tool = s.problem.frames[0].T_base_tool.copy()
        # move within the board plane (board x, y axes in the base frame)
        T_base_tool[:3, 3] += T_base_board[:3, :3] @ np.array([0.02 * k, 0.015 * (k % 2), 0.0])
        T_cam_board = inv_T(T_base_tool @ sc.R1_T_TOOL_CAM) @ T_base_board
        det = sc.projected_detection(
            sc.R1_K, sc.R1_DIST, T_cam_board, s.problem.target, (1280, 800), 0.1, rng
        )
        frames.append(Frame(k, {"cam": det}, T_base_tool=T_base_tool))
    with pytest.raises(DegenerateError, match="parallel to the board"):
        calibrate(replace(s.problem, frames=tuple(frames)))


def test_bad_input_is_named():
    s = sc.r1(np.random.default_rng(8))
    frames = list(s.problem.frames)
    frames[2] = Frame(2, frames[2].detections, T_base_tool=None)
    with pytest.raises(InputError, match=r"frames\[2\].T_base_tool"):
        calibrate(replace(s.problem, frames=tuple(frames)))


def test_a_solve_limits_the_blas_threads_once(monkeypatch):
    # the solve runs with one BLAS thread, set once: the refinement inside it keeps the limit
    # (setting and restoring it again restarts the BLAS's threads)
    import slidecal.solver.model as model

    ctl = model._blas_controller()
    limits = []
    real = ctl.limit

    def spy(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        limits.append(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(ctl, "limit", spy)
    calibrate(sc.r1(np.random.default_rng(3)).problem)
    assert limits == [{"limits": 1, "user_api": "blas"}]


def test_scale_checks_reuse_the_robot_tests_free_poses(monkeypatch):
    # poses kept exact: the robot test's free-pose fit already holds each image's PnP minimum
    # at the final intrinsics; the scale checks take it (images with a flagged detection
    # excepted) and equal the ones computed afresh from the model's guesses
    import importlib

    from slidecal.solver.calibrate import _fitted_poses, frame_groups, image_poses, scale_checks

    pipeline = importlib.import_module("slidecal.solver.calibrate")  # the module, not calibrate()
    s = sc.r1(np.random.default_rng(3), 0.15, 0.0, 0.0)
    outs = []
    real = pipeline.refine

    def spy(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        outs.append(real(*args, **kwargs))
        return outs[-1]

    monkeypatch.setattr(pipeline, "refine", spy)
    res = calibrate(s.problem)
    out = outs[-1]
    assert res.robot_accuracy.translation_mm == 0.0 and out.free_pose is not None
    known = _fitted_poses(out, out.free_pose)
    assert len(known) == sum(bool(out.inlier_rows[ch.rows].all()) for ch in out.model.chunks) > 10
    guesses = {i: out.model.T_ref_board(out.state, i) for i in range(len(s.problem.frames))}
    poses = image_poses(s.problem, out.state, guesses)
    fresh = scale_checks(s.problem, out.state, frame_groups(s.problem), poses)
    assert len(fresh) == len(res.scale_checks) > 10
    for a, b in zip(res.scale_checks, fresh, strict=True):
        assert (a.frame_a, a.frame_b) == (b.frame_a, b.frame_b)
        assert a.camera_mm == pytest.approx(b.camera_mm, abs=1e-6)


def test_the_outlier_loop_keeps_a_frame_whose_leaving_out_fails(monkeypatch):
    # every frame beyond the typical one's pose error is an outlier here: the loop leaves frames
    # out one at a time (at most 2 of 20). When the solve without the second fails, the pass that
    # left the second out is finished with it kept (a line says why); when that pass's own
    # finish fails too, the first pass's result stands
    p = sc.r1_real_arm(np.random.default_rng(21)).problem
    n = len(p.frames)
    monkeypatch.setattr(adequacy, "POSE_OUTLIER_RATIO", 1.0)
    res = calibrate(p)
    assert len(res.robot_accuracy.left_out) == 2
    assert sum("left out of the solve" in m for m in res.messages) == 2
    real_motion, real_scale = pipeline.init_motion, pipeline.session_scale

    def init_motion(problem, *a, **k):  # noqa: ANN001, ANN002, ANN003, ANN202
        if len(problem.frames) == n - 2:
            raise DegenerateError("forced")
        return real_motion(problem, *a, **k)

    monkeypatch.setattr(pipeline, "init_motion", init_motion)
    res = calibrate(p)
    assert len(res.robot_accuracy.left_out) == 1
    assert "left out of the solve" in res.messages[0]
    assert "it stays in the solve: without it, forced" in res.messages[1]

    def session_scale(problem, *a, **k):  # noqa: ANN001, ANN002, ANN003, ANN202
        if len(problem.frames) == n - 1:
            raise DegenerateError("forced too")
        return real_scale(problem, *a, **k)

    monkeypatch.setattr(pipeline, "session_scale", session_scale)
    res = calibrate(p)
    assert res.robot_accuracy.left_out == ()
    assert res.messages[0].endswith("it stays in the solve: without it, forced too")
