"""The model-adequacy test and the robot's accuracy learned from the data, against synthetic
ground truth: a wrong model must be marked unusable with its reason, a right one must not."""

from dataclasses import replace

import numpy as np
import pytest

from slidecal.mocks import scenarios as sc
from slidecal.solver.calibrate import calibrate
from slidecal.solver.errors import DegenerateError
from slidecal.solver.geometry import R_from_rvec, T_from_Rt, rvec_from_R
from slidecal.solver.problem import ModelOptions, Target

FIXED = ModelOptions(robot_noise_m=5e-5, robot_noise_deg=0.005, estimate_robot_noise=False)


def _z(res, s, name, a, b):
    return (res.cameras["cam"].K[a, b] - s.truth.K["cam"][a, b]) / res.cameras["cam"].std[name]


def test_clean_session_is_adequate_with_exact_poses_and_the_detector_noise_is_found():
    s = sc.r1(np.random.default_rng(11), 0.15, 0.0, 0.0)
    res = calibrate(s.problem)
    ad = res.adequacy
    assert ad.adequate and ad.reasons == ()
    # 2800 residual rows: the noise estimate's spread is 0.15 / sqrt(2 * 2680) = 1.4 %
    assert ad.detector_noise_px["cam"] == pytest.approx(0.15, rel=0.06)
    assert ad.normalised_rms["cam"] == pytest.approx(1.0, abs=0.08)
    assert res.robot_accuracy.translation_mm == 0.0 and res.robot_accuracy.rotation_deg == 0.0
    assert res.robot_accuracy.estimated


@pytest.mark.slow  # several seconds: the second CI tier
def test_rotations_in_degrees_are_marked_unusable():
    s = sc.r1(np.random.default_rng(12))
    frames = tuple(
        replace(
            f,
            T_base_tool=T_from_Rt(
                R_from_rvec(np.degrees(rvec_from_R(f.T_base_tool[:3, :3]))), f.T_base_tool[:3, 3]
            ),
        )
        for f in s.problem.frames
    )
    res = calibrate(replace(s.problem, frames=frames))
    assert not res.adequacy.adequate
    assert any("radians" in r for r in res.adequacy.reasons)


@pytest.mark.parametrize("scale", [1.24, 0.8])
def test_wrong_square_size_is_marked_unusable(scale):
    s = sc.r1(np.random.default_rng(13))
    target = Target.charuco(11, 8, 0.030 * scale, 0.022 * scale)
    res = calibrate(replace(s.problem, target=target))
    assert not res.adequacy.adequate
    reason = next(r for r in res.adequacy.reasons if "square_size_m" in r)
    seen = float(reason.split("moves ")[1].split(" %")[0])
    assert seen == pytest.approx(100 * (scale - 1), abs=1.0)


def test_robot_errors_beyond_the_prior_mark_a_fixed_prior_unusable_and_are_learned_by_default():
    # the poses err by 5 mm while the user's prior says 0.05 mm
    s = sc.r1(np.random.default_rng(14), 0.15, 5e-3, 0.005, options=FIXED)
    fixed = calibrate(s.problem)
    assert not fixed.adequacy.adequate
    assert fixed.adequacy.normalised_rms["cam"] > 3.0
    learned = calibrate(replace(s.problem, options=replace(FIXED, estimate_robot_noise=True)))
    assert learned.adequacy.adequate
    ra = learned.robot_accuracy
    assert ra.estimated
    # 20 frames x 3 axes: the estimate's relative spread is about 1 / sqrt(2 * 60) = 9 %
    assert ra.translation_mm == pytest.approx(5.0, rel=0.3)
    assert len(ra.worst_frames) == 5 and ra.worst_frames[0][1] > 5.0
    for name, a, b in (("fx", 0, 0), ("fy", 1, 1), ("cx", 0, 2), ("cy", 1, 2)):
        assert abs(_z(learned, s, name, a, b)) < 3.5


@pytest.mark.slow
def test_real_arm_with_poses_taken_as_exact_is_unusable_and_honest_by_default():
    s = sc.r1_real_arm(
        np.random.default_rng(15), options=replace(FIXED, robot_noise_m=0.0, robot_noise_deg=0.0)
    )
    exact = calibrate(s.problem)
    assert not exact.adequacy.adequate
    res = calibrate(replace(s.problem, options=ModelOptions()))
    assert res.adequacy.adequate
    # the per-frame and per-orientation-group corrections are marginalised out of the result
    assert not any(n.startswith("pose") for n in res.parameter_names)
    assert 0.0 < res.robot_accuracy.translation_mm < 2.0
    assert 0.001 < res.robot_accuracy.rotation_deg < 0.2
    for name, a, b in (("fx", 0, 0), ("fy", 1, 1), ("cx", 0, 2), ("cy", 1, 2)):
        assert abs(_z(res, s, name, a, b)) < 3.0


@pytest.mark.parametrize("robot_noise_mm", [0.0, 0.8])
def test_a_four_point_target_is_judged_by_its_own_redundancy(robot_noise_mm):
    """A single tag (4 corners, 2 redundant rows per image after a free pose): the robot model's
    noise estimate and the free-pose floor agree when the model is right, with exact poses and
    with a noisy arm learned from the data (the raw rms ratio would be up to 2 here)."""
    from slidecal.mocks.scenarios import classic, square_tag

    s = classic(
        np.random.default_rng(3), n_frames=7, per_orientation=8, eye_in_hand=False,
        target=square_tag(0.12), sigma_px=0.25,
        robot_noise_m=robot_noise_mm / 1000.0 / np.sqrt(3), robot_noise_deg=0.03 * bool(
            robot_noise_mm),
    )
    r = calibrate(s.problem)
    assert r.adequacy is not None and r.adequacy.adequate, r.adequacy
    # 56 images x 2 redundant rows: the ratio of two noise estimates is within ~15 % (2 sigma)
    assert 0.8 < r.adequacy.normalised_rms["cam"] < 1.25


@pytest.mark.parametrize("seed", [2, 40])
def test_noise_levels_that_keep_creeping_still_give_a_converged_solve(seed):
    """The default simulated cell, seeds 2 and 40 (recorded sessions): the robot's noise levels
    were still moving after the last variance-component update, and the solve used to stop part
    way (not converged, verdict rejected). The last levels are kept and the parameters
    converged. Seed 40: the damping the level steps had reached (1e10) took only round-off
    steps, and Levenberg-Marquardt gave up; it starts again from a light damping."""
    from pathlib import Path

    from slidecal.routines.session import load_session

    s = load_session(Path(__file__).parent / "data" / f"default_cell_seed{seed}")
    r = calibrate(s.problem)
    assert r.converged and r.adequacy is not None and r.adequacy.adequate
    K_true = np.asarray(s.simulation["cameras"]["cam"]["K"])
    K = r.cameras["cam"].K
    for name, (i, j) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items():
        assert abs(K[i, j] - K_true[i, j]) < 3 * r.cameras["cam"].std[name], name


def _glitched(problem, k, dt_m=(0.0, 0.0, 0.0), drot_deg=0.0):
    """``problem`` with frame ``k``'s recorded pose off by ``dt_m`` and ``drot_deg`` about the
    tool's y axis: a pose read before the arm settled."""
    frames = list(problem.frames)
    T = frames[k].T_base_tool.copy()
    T[:3, 3] += dt_m
    T[:3, :3] = T[:3, :3] @ R_from_rvec(np.radians([0.0, drot_deg, 0.0]))
    frames[k] = replace(frames[k], T_base_tool=T)
    return replace(problem, frames=tuple(frames))


def _left_out(res) -> list[int]:
    return [int(m.split(":")[0].split()[1]) for m in res.messages if "left out of the solve" in m]


@pytest.mark.parametrize(("dt_m", "drot_deg"), [((0.006, 0.0, 0.0), 0.0), ((0.0, 0.0, 0.0), 1.0)])
def test_a_pose_glitch_is_left_out_and_named(dt_m, drot_deg):
    # R1 on a real arm (about 1 mm, 0.1 deg, 20 frames): one recorded pose 6 mm or 1 deg off
    # its frame is 7-15 times a typical frame's correction (clean frames: below 4); it is left
    # out, named with its misfit, and the intrinsics stay within 3 std of the truth
    s = sc.r1_real_arm(np.random.default_rng(1))
    assert _left_out(calibrate(s.problem)) == []
    res = calibrate(_glitched(s.problem, 7, dt_m, drot_deg))
    assert _left_out(res) == [s.problem.frames[7].id]
    assert res.adequacy.adequate
    for name, (a, b) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items():
        assert abs(_z(res, s, name, a, b)) < 3.0, name


def test_no_more_than_one_frame_in_ten_is_left_out():
    # three glitches in 20 frames: the two worst are left out (one in ten), the third is named
    # with what to check; the median-based typical size keeps them from hiding each other
    s = sc.r1_real_arm(np.random.default_rng(0))
    p = _glitched(s.problem, 7, (0.006, 0.0, 0.0))
    p = _glitched(p, 12, drot_deg=1.0)
    p = _glitched(p, 3, (0.0, -0.005, 0.003))
    res = calibrate(p)
    assert sorted(_left_out(res)) == [3, 12]
    kept = [m for m in res.messages if m.startswith("frame 7:")]
    assert len(kept) == 1 and "no more than 2 of 20 frames" in kept[0]


def _poses_reassigned(problem, order):
    """``problem`` with frame k given the recorded pose of frame ``order[k]``."""
    frames = tuple(
        replace(f, T_base_tool=problem.frames[o].T_base_tool)
        for f, o in zip(problem.frames, order, strict=True)
    )
    return replace(problem, frames=frames)


def test_pairing_check_is_silent_on_a_right_session_and_names_the_wrong_pairing():
    from slidecal.solver.adequacy import record_check

    s = sc.classic_real_arm(np.random.default_rng(4))  # 28 frames, every orientation different
    n = len(s.problem.frames)
    assert record_check(s.problem) is None
    # the logger one frame behind: image k carries the pose of frame k - 1
    late = record_check(_poses_reassigned(s.problem, [0, *range(n - 1)]))
    assert late is not None and "the pose recorded 1 frame(s) later" in late
    # two images swapped: those two frames are named
    order = list(range(n))
    order[5], order[17] = 17, 5
    swapped = record_check(_poses_reassigned(s.problem, order))
    assert swapped is not None and swapped.startswith("frames [5, 17]:")
    # the same session with the poses in a random order
    shuffled = _poses_reassigned(s.problem, np.random.default_rng(0).permutation(n))
    assert "not paired as recorded" in record_check(shuffled)


def _misread(problem, kind: str):
    """``problem`` with every recorded pose as slidecal would read it after the mistake
    ``kind`` in the records (made with scipy's conventions, not the solver's helpers)."""
    from scipy.spatial.transform import Rotation

    from slidecal.solver.geometry import R_from_quat_wxyz, inv_T

    def read(T):
        R, t = T[:3, :3], T[:3, 3]
        if kind == "inverted":  # T_tool_base given for T_base_tool
            return inv_T(T)
        if kind == "transposed":
            return T_from_Rt(R.T, t)
        if kind == "quaternion":  # ROS's [x, y, z, w] given as q_wxyz
            return T_from_Rt(R_from_quat_wxyz(Rotation.from_matrix(R).as_quat()), t)
        if kind == "abc":  # KUKA's [A, B, C] given as rpy_deg [roll, pitch, yaw]
            a, b, c = Rotation.from_matrix(R).as_euler("ZYX")
            return T_from_Rt(Rotation.from_euler("ZYX", [c, b, a]).as_matrix(), t)
        assert kind == "intrinsic"  # angles of R = Rx(a) Ry(b) Rz(c) given as rpy_deg
        a, b, c = Rotation.from_matrix(R).as_euler("XYZ")
        return T_from_Rt(Rotation.from_euler("ZYX", [c, b, a]).as_matrix(), t)

    frames = tuple(replace(f, T_base_tool=read(f.T_base_tool)) for f in problem.frames)
    return replace(problem, frames=frames)


@pytest.mark.parametrize("eye_in_hand", [True, False])
def test_convention_check_names_how_the_records_were_misread(eye_in_hand):
    from slidecal.solver.adequacy import convention_check, record_check

    # a classic session on a real arm (28 frames, every orientation different): silent as read
    s = sc.classic_real_arm(np.random.default_rng(4), eye_in_hand=eye_in_hand)
    assert convention_check(s.problem) is None
    other = "eye_to_hand" if eye_in_hand else "eye_in_hand"
    expected = {
        "inverted": f"not T_base_tool, or the camera is mounted the other way ({other})",
        "transposed": "the rotation matrices are transposed",
        "quaternion": "the quaternions are [x, y, z, w]",
        "abc": "the angles are [yaw, pitch, roll] (KUKA's A, B, C)",
        "intrinsic": "the angles compose as Rx(roll) Ry(pitch) Rz(yaw)",
    }
    for kind, meaning in expected.items():
        said = convention_check(_misread(s.problem, kind))
        assert said is not None and meaning in said, (kind, said)
        assert said.startswith("the robot poses as read do not fit")
    # the whole solve: rejected with the reading named first, without learning an arm's
    # accuracy for records no arm explains (that ran its full budget: minutes on real sessions)
    res = calibrate(_misread(s.problem, "quaternion"))
    assert not res.adequacy.adequate and expected["quaternion"] in res.adequacy.reasons[0]
    assert res.robot_accuracy is None or not res.robot_accuracy.estimated
    # poses paired with the wrong images are not a convention: that test says nothing
    n = len(s.problem.frames)
    shuffled = _poses_reassigned(s.problem, np.random.default_rng(0).permutation(n))
    assert convention_check(shuffled) is None and record_check(shuffled) is not None


def test_convention_check_reads_a_lone_tag_session():
    from slidecal.solver.adequacy import convention_check

    # a fixed camera, one tag's 4 corners per image, 205 frames in 7 orientations: the
    # images-alone poses are rougher, a wrong reading still spreads by degrees and decimetres
    s = sc.tag_real_arm(np.random.default_rng(2000), sigma_px=0.15, arm_mm=1.0, arm_deg=0.1)
    assert convention_check(s.problem) is None
    said = convention_check(_misread(s.problem, "abc"))
    assert said is not None and "KUKA's A, B, C" in said and "target's pose on the tool" in said


def test_a_shuffled_session_is_refused_for_its_pairing_first():
    # R1's translation groups: the linear start fails, and says why
    s = sc.r1_real_arm(np.random.default_rng(2))
    order = np.random.default_rng(1).permutation(len(s.problem.frames))
    with pytest.raises(DegenerateError, match="not paired as recorded"):
        calibrate(_poses_reassigned(s.problem, order))


@pytest.mark.slow  # a solve that does not converge: seconds
def test_a_shuffled_classic_session_is_unusable_for_its_pairing_first():
    s = sc.classic_real_arm(np.random.default_rng(5))
    order = np.random.default_rng(1).permutation(len(s.problem.frames))
    res = calibrate(_poses_reassigned(s.problem, order))
    assert not res.adequacy.adequate
    assert "not paired as recorded" in res.adequacy.reasons[0]


def test_frames_left_out_are_recorded_in_the_result_file(tmp_path):
    from slidecal.routines.results_io import read_result, write_result

    s = sc.r1_real_arm(np.random.default_rng(1))
    res = calibrate(_glitched(s.problem, 7, (0.006, 0.0, 0.0)))
    ((frame, t_mm, _),) = res.robot_accuracy.left_out
    assert frame == 7 and 3.0 < t_mm < 7.0
    write_result(res, tmp_path / "result.yaml")
    back = read_result(tmp_path / "result.yaml").robot_accuracy.left_out
    assert np.allclose(back, res.robot_accuracy.left_out)


def test_a_run_of_frames_on_another_joint_configuration_is_not_a_glitch():
    # the eye-to-hand tag session (205 frames, 7 orientations, a UR5e erring by about 1 mm):
    # seed 2008's controller reaches frames 102-111 with the wrist turned over (each pose's
    # joints the solution nearest the last), and that run errs 0.7-1.0 mm off the rest of its
    # group, 5 times a typical frame's correction: the arm, not ten glitches. None is left out
    # (five were, one at a time), and the intrinsics stay within 3 std of the truth. A pose
    # 6 mm off in the same session still is left out.
    s = sc.tag_real_arm(np.random.default_rng(2008), sigma_px=0.15, arm_mm=1.0, arm_deg=0.1)
    res = calibrate(s.problem)
    assert _left_out(res) == []
    for name, (a, b) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items():
        assert abs(_z(res, s, name, a, b)) < 3.0, name
    res = calibrate(_glitched(s.problem, 40, (0.006, 0.0, 0.0)))
    assert _left_out(res) == [s.problem.frames[40].id]


def _noisier(problem, k, factor, rng, camera=None):
    """``problem`` with frame ``k``'s detections (of ``camera`` only, when given) given
    ``factor`` times more noise (0.15 px is the scenarios' noise): a blurred or badly lit
    image."""
    frames = list(problem.frames)
    dets = {
        c: replace(d, px=d.px + rng.normal(0.0, 0.15 * factor, d.px.shape))
        if camera in (None, c)
        else d
        for c, d in frames[k].detections.items()
    }
    frames[k] = replace(frames[k], detections=dets)
    return replace(problem, frames=tuple(frames))


def test_a_noisy_image_is_left_out_and_one_beyond_the_budget_weighs():
    # R1 (20 images of 88 corners, exact poses): one image with 10 times the detector's noise
    # is half of the session's squares; it is left out (named) and the result is adequate
    s = sc.r1(np.random.default_rng(11), 0.15, 0.0, 0.0)
    res = calibrate(_noisier(s.problem, 7, 10.0, np.random.default_rng(0)))
    assert _left_out(res) == [s.problem.frames[7].id] and res.adequacy.adequate
    (note,) = [m for m in res.messages if "left out of the solve" in m]
    assert "its image of 'cam' has residuals" in note
    assert [f for f, _, _ in res.robot_accuracy.left_out] == [s.problem.frames[7].id]


def test_a_noisy_image_among_many_is_left_out_the_result_within_its_std():
    # the eye-to-hand tag session (205 images of 4 corners, a real arm): one image with 10
    # times the detector's noise is left out; the intrinsics stay within 3 std of the truth
    s = sc.tag_real_arm(np.random.default_rng(2002), sigma_px=0.15, arm_mm=1.0, arm_deg=0.1)
    res = calibrate(_noisier(s.problem, 60, 10.0, np.random.default_rng(0)))
    assert _left_out(res) == [s.problem.frames[60].id] and res.adequacy.adequate
    for name, (a, b) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items():
        assert abs(_z(res, s, name, a, b)) < 3.0, name


def test_a_rigs_noisy_image_is_left_out_and_its_frame_keeps_the_other():
    # the OAK-D-like head eye-in-hand on R1 (robot poses with 0.05 mm / 0.005 deg noise): the
    # right camera's image of frame 7 has 10 times the detector's noise. That image is left out
    # (named); the frame stays in the solve with its left image, so no frame is recorded as
    # left out and the result is adequate
    s = sc.oak_rig(np.random.default_rng(3), robot_noise_m=5e-5, robot_noise_deg=0.005)
    res = calibrate(_noisier(s.problem, 7, 10.0, np.random.default_rng(0), camera="right"))
    (note,) = [m for m in res.messages if "left out of the solve" in m]
    frame = s.problem.frames[7].id
    assert f"frame {frame}: its image of 'right' has residuals" in note
    assert "the frame's other images stay in it" in note
    assert res.robot_accuracy.left_out == () and res.adequacy.adequate
    assert all(c != "right" or f != frame for f, c, _ in res.adequacy.worst_frames)


def test_images_beyond_the_ratio_that_do_not_weigh_are_named():
    from slidecal.solver.adequacy import bad_images_note
    from slidecal.solver.result import ModelAdequacy

    worst = ((12, "cam", 5.2), (3, "cam", 4.4), (9, "cam", 2.0))
    ok = ModelAdequacy({"cam": 0.05}, {"cam": 1.02}, worst, adequate=True)
    (note,) = bad_images_note(ok)
    assert note.startswith("image(s) of frame 12 'cam' (5.2), 3 'cam' (4.4) above 4.0 times")
    assert "10 % of the session's squares" in note
    assert bad_images_note(replace(ok, adequate=False, reasons=("x",))) == ()
    assert bad_images_note(replace(ok, worst_frames=worst[2:])) == ()
