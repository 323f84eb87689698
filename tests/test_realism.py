"""Simulated cells as hard as reality: the photo key, the arm's true poses in the session, and
results judged against the truth a session can know (the effective hand-eye and target)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slidecal.drivers.ur_pose import ur_pose_from_T
from slidecal.mocks import scenarios as sc
from slidecal.mocks.render import Photo
from slidecal.mocks.scenarios import drifting_arm
from slidecal.mocks.truth import hand_eye_errors
from slidecal.routines.config import load_config
from slidecal.routines.results_io import errors_against_truth, summary_text
from slidecal.routines.session import SessionWriter, load_session
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import R_from_rvec, T_from_Rt
from slidecal.solver.problem import CameraSpec, Detection, Target
from slidecal.solver.result import CalibrationResult, CameraEstimate, TransformEstimate
from slidecal.solver.robot_error import effective_truth

K = np.array([[880.0, 0.0, 640.0], [0.0, 880.0, 400.0], [0.0, 0.0, 1.0]])


_IJ = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}


def _assert_within_3_std(cam: CameraEstimate, s: sc.Scenario) -> None:
    """Every intrinsic of the scenario's camera ``cam`` within 3 of its reported std."""
    for name, (a, b) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items():
        assert abs(cam.K[a, b] - s.truth.K["cam"][a, b]) < 3.0 * cam.std[name], name


def _T(rng: np.random.Generator, rot_deg: float, mm: float) -> np.ndarray:
    return T_from_Rt(
        R_from_rvec(rng.normal(0.0, np.radians(rot_deg), 3)), rng.normal(0.0, mm / 1000.0, 3)
    )


def _arm(rng: np.random.Generator, n: int = 12):
    """Measured poses spread over a workspace, and true ones off by a constant tool-frame error
    ``D`` (the arm's constant error) plus a small varying one."""
    D = _T(rng, 0.1, 1.0)
    meas, true = [], []
    for _ in range(n):
        Tm = T_from_Rt(
            R_from_rvec(np.r_[np.pi, 0.0, 0.0] + rng.normal(0, 0.4, 3)),
            np.r_[-0.4, 0.0, 0.5] + rng.normal(0, 0.1, 3),
        )
        meas.append(Tm)
        true.append(Tm @ D @ _T(rng, 0.005, 0.03))
    return D, meas, true


def _result(T_he: np.ndarray, T_tg: np.ndarray, mount: str, frames: int) -> CalibrationResult:
    he_key, tg_key = (
        ("T_tool_cam", "T_base_board")
        if mount == "eye_in_hand"
        else (
            "T_base_cam",
            "T_tool_board",
        )
    )
    return CalibrationResult(
        cameras={"cam": CameraEstimate("cam", 1280, 800, K, np.zeros(5), {"fx": 0.2}, 0.05)},
        hand_eye=TransformEstimate(he_key, T_he[:3, :3], T_he[:3, 3], 0.05, 0.5),
        rig={},
        T_target=TransformEstimate(tg_key, T_tg[:3, :3], T_tg[:3, 3], 0.05, 0.5),
        converged=True,
        iterations=5,
        reproj_rms_px=0.05,
        sigma_px=0.05,
        parameter_names=("fx",),
        covariance=np.array([[0.04]]),
        residuals_px={(i, "cam"): 0.05 for i in range(frames)},
        outliers=(),
        unobservable={},
        messages=(),
        mount=mount,
        reference_camera="cam",
    )


def _truth(T_he, T_tg, mount, meas, true) -> dict:
    he_key, tg_key = (
        ("T_tool_cam", "T_base_board")
        if mount == "eye_in_hand"
        else (
            "T_base_cam",
            "T_tool_board",
        )
    )

    def d(T):
        return {"R": T[:3, :3].tolist(), "t_m": T[:3, 3].tolist()}

    return {
        "cameras": {"cam": {"K": K.tolist(), "distortion": [0.0] * 5}},
        he_key: d(T_he),
        tg_key: d(T_tg),
        "noise": {"robot_mm": 0.05, "robot_deg": 0.005},
        "frames": [
            {"id": i, "T_base_tool": ur_pose_from_T(Tt), "T_base_tool_measured": ur_pose_from_T(Tm)}
            for i, (Tt, Tm) in enumerate(zip(true, meas, strict=True))
        ],
    }


@pytest.mark.parametrize("mount", ["eye_in_hand", "eye_to_hand"])
def test_constant_arm_error_moves_the_judged_hand_eye_or_target(mount: str) -> None:
    """A constant tool-frame error D is a hand-eye change (eye-in-hand: T_tool_cam' = D
    T_tool_cam) or a target change (eye-to-hand: T_tool_board' = D T_tool_board); a result
    equal to that is judged right, within the arm's varying error, and the physical truth is
    1 mm / 0.1 deg away (the old judge)."""
    rng = np.random.default_rng(5)
    D, meas, true = _arm(rng)
    T_he = T_from_Rt(R_from_rvec([0.01, -0.02, 1.57]), [0.032, -0.061, 0.045])
    T_tg = T_from_Rt(R_from_rvec([np.pi, 0.0, 0.03]), [-0.56, 0.12, 0.0])
    if mount == "eye_in_hand":
        he_eff, tg_eff = effective_truth(mount, true, meas, T_he, T_tg, 0.1, 1.0)
        np.testing.assert_allclose(he_eff, D @ T_he, atol=2e-4)
        np.testing.assert_allclose(tg_eff, T_tg, atol=2e-4)
        est_he, est_tg = D @ T_he, T_tg
        moved = "T_tool_cam"
    else:
        T_he = T_from_Rt(R_from_rvec([np.pi, 0.0, 0.02]), [-0.40, 0.0, 1.05])
        T_tg = T_from_Rt(R_from_rvec([0.01, 0.0, 0.0]), [-0.165, -0.12, 0.05])
        he_eff, tg_eff = effective_truth(mount, true, meas, T_he, T_tg, 0.1, 1.0)
        np.testing.assert_allclose(he_eff, T_he, atol=2e-4)
        np.testing.assert_allclose(tg_eff, D @ T_tg, atol=2e-4)
        est_he, est_tg = T_he, D @ T_tg
        moved = "T_tool_board"
    truth = _truth(T_he, T_tg, mount, meas, true)
    r = _result(est_he, est_tg, mount, len(meas))
    e = errors_against_truth(r, truth)
    for k in ("rot_deg", "t_mm"):
        assert e[f"{moved}.{k}"] < (0.01 if k == "rot_deg" else 0.1)
    # without the arm's poses the block only knows the physical truth: D's size shows
    physical = errors_against_truth(r, {k: v for k, v in truth.items() if k != "frames"})
    assert physical[f"{moved}.t_mm"] > 0.3
    assert "effective truth over 12 frames" in summary_text(r, truth)
    no_frames = {k: v for k, v in truth.items() if k != "frames"}
    assert "the physical truth" in summary_text(r, no_frames)


def test_only_the_frames_the_solve_used_are_judged() -> None:
    """Frames without residuals (the camera saw nothing) do not move the effective truth."""
    rng = np.random.default_rng(6)
    D, meas, true = _arm(rng, 10)
    T_he = T_from_Rt(R_from_rvec([0.0, 0.0, 1.57]), [0.03, -0.06, 0.04])
    T_tg = T_from_Rt(R_from_rvec([np.pi, 0.0, 0.0]), [-0.56, 0.12, 0.0])
    true[9] = meas[9] @ _T(rng, 2.0, 20.0)  # a wild pose the solve never saw
    truth = _truth(T_he, T_tg, "eye_in_hand", meas, true)
    r = _result(D @ T_he, T_tg, "eye_in_hand", 9)
    assert errors_against_truth(r, truth)["T_tool_cam.t_mm"] < 0.1


def test_photo_key_in_the_cell(tmp_path: Path) -> None:
    cam = load_config(None, {"simulation": {"cameras": {"cam": {"photo": True}}}}).simulation
    assert cam.cameras[0].photo == Photo()
    cfg = load_config(
        None,
        {"simulation": {"cameras": {"cam": {"photo": {"jpeg_quality": 70, "bayer": False}}}}},
    )
    assert cfg.simulation.cameras[0].photo == Photo(jpeg_quality=70, bayer=False)
    off = load_config(None, {"simulation": {"cameras": {"cam": {"photo": False}}}})
    assert off.simulation.cameras[0].photo is None
    with pytest.raises(InputError, match=r"simulation\.cameras\.cam\.photo\.jpeg_qualty"):
        load_config(None, {"simulation": {"cameras": {"cam": {"photo": {"jpeg_qualty": 70}}}}})
    with pytest.raises(InputError, match=r"photo.*true, false or a mapping"):
        load_config(None, {"simulation": {"cameras": {"cam": {"photo": "yes"}}}})
    with pytest.raises(InputError, match=r"photo\.jpeg_quality"):
        load_config(None, {"simulation": {"cameras": {"cam": {"photo": {"jpeg_quality": 101}}}}})


def test_shipped_cells_are_as_hard_as_reality() -> None:
    from importlib import resources

    for name in ("default_cell.yaml", "eye_to_hand_cell.yaml"):
        cfg = load_config(str(resources.files("slidecal.mocks").joinpath(name)))
        assert cfg.simulation.kinematic_error is not None, name
        assert all(c.photo is not None for c in cfg.simulation.cameras), name


def _writer(tmp_path: Path, simulation: dict | None) -> SessionWriter:
    target = Target.chessboard(9, 6, 0.03)
    return SessionWriter(
        tmp_path / "s", target, [CameraSpec("cam", 1280, 800)], simulation=simulation
    )


def test_session_records_and_checks_the_true_poses(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    _, meas, true = _arm(rng, 3)
    sim = {"cameras": {"cam": {"K": K.tolist(), "distortion": [0.0] * 5}}}
    w = _writer(tmp_path, sim)
    empty = Detection(np.zeros(0, int), np.zeros((0, 2)))
    for Tm, Tt in zip(meas, true, strict=True):
        w.append_frame(Tm, detections={"cam": empty}, T_base_tool_true=Tt)
    w.finish()
    s = load_session(tmp_path / "s", detect_images=False)
    frames = s.simulation["frames"]
    assert [f["id"] for f in frames] == [0, 1, 2]
    np.testing.assert_allclose(frames[1]["T_base_tool"], ur_pose_from_T(true[1]), atol=1e-9)
    np.testing.assert_allclose(frames[1]["T_base_tool_measured"], ur_pose_from_T(meas[1]))
    # a real run (no simulation block) records nothing
    w2 = _writer(tmp_path / "real", None)
    w2.append_frame(meas[0], detections={"cam": empty}, T_base_tool_true=true[0])
    assert "simulation" not in w2.data
    # a pose that is not a UR pose, a frame listed twice: refused with the field
    import yaml

    path = tmp_path / "s" / "session.yaml"
    doc = yaml.safe_load(path.read_text())
    doc["simulation"]["frames"][2]["id"] = 1
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(InputError, match=r"simulation\.frames\[2\]\.id.*twice"):
        load_session(tmp_path / "s", detect_images=False)
    doc["simulation"]["frames"][2]["id"] = 2
    doc["simulation"]["frames"][0]["T_base_tool"] = [0.1, 0.2]
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(InputError, match=r"simulation\.frames\[0\]\.T_base_tool.*UR pose"):
        load_session(tmp_path / "s", detect_images=False)


@pytest.mark.slow
def test_default_cell_run_judged_against_the_effective_truth(tmp_path: Path) -> None:
    """The realistic default cell end to end: the session holds the arm's true poses, every
    error lies within 4 reported std of the truth the session can know."""
    from slidecal.routines.run import RunRequest, run_calibration

    o = run_calibration(RunRequest(out_dir=tmp_path / "s", progress=False, recording=False, seed=4))
    s = load_session(o.session_dir, detect_images=False)
    assert len(s.simulation["frames"]) == o.n_frames
    T_true = [np.asarray(f["T_base_tool"]) for f in s.simulation["frames"]]
    T_meas = [np.asarray(f["T_base_tool_measured"]) for f in s.simulation["frames"]]
    # the arm really errs (about 1 mm): the reported poses are not the reached ones
    dt = [np.linalg.norm(a[:3] - b[:3]) for a, b in zip(T_true, T_meas, strict=True)]
    assert np.mean(dt) > 2e-4
    r = o.result
    assert r.adequacy is not None and r.adequacy.adequate
    cam = r.cameras["cam"]
    for p in ("fx", "fy", "cx", "cy"):
        assert o.errors[f"cam.{p}_px"] <= 4.0 * cam.std[p], p
    for key, t in (("T_tool_cam", r.hand_eye), ("T_base_board", r.T_target)):
        assert o.errors[f"{key}.rot_deg"] <= 3.0 * t.std_rot_deg, key
        assert o.errors[f"{key}.t_mm"] <= 3.0 * t.std_t_mm, key
    assert "effective truth" in o.summary


@pytest.mark.parametrize("seed", [7, 17, 26])
def test_drift_along_the_moves_is_learned_and_covers_the_principal_point(seed: int) -> None:
    # one orientation, 13 frames, the arm's orientation drifting 0.06 deg over 60 mm: the drift
    # shifts the focus of expansion, i.e. the principal point. With independent per-frame
    # corrections the principal point came out 3.6-5.2 reported std off on these seeds; the trend
    # of the correction along the moves carries it (within 3 std)
    from slidecal.solver.calibrate import calibrate
    from slidecal.solver.model import build_structure
    from slidecal.solver.refine import refine

    s, D = drifting_arm(np.random.default_rng(seed))
    res = calibrate(s.problem)
    cam = res.cameras["cam"]
    _assert_within_3_std(cam, s)
    # the trend's level is learned from the images: the injected one's rms per element,
    # within the spread of an estimate from 9 numbers
    out = refine(s.problem, build_structure(s.problem), s.truth)
    assert "V" in out.model.slices and out.model.st.trend_dims == (3,)
    true_rms = np.sqrt(np.mean(D**2))
    assert 0.5 * true_rms < out.model.trend_sigma[0] < 2.0 * true_rms


def test_a_classic_session_on_a_real_arm_learns_one_trend_over_its_positions() -> None:
    # 28 frames, each at its own orientation, on a UR5e whose kinematics err by about 1 mm and
    # 0.1 deg: no orientation group has a trend of its own, so the session gets one over the
    # tool's positions (eye-in-hand). Without it this seed's fx, fy and hand-eye z came out 4.5,
    # 3.7 and 6.7 reported std off: the arm's error is smooth over the workspace, and its linear
    # part scales the positions, which the focal lengths follow
    from slidecal.solver.calibrate import calibrate
    from slidecal.solver.model import build_structure
    from slidecal.solver.refine import refine

    s = sc.classic_real_arm(np.random.default_rng(3129))
    res = calibrate(s.problem)
    cam = res.cameras["cam"]
    _assert_within_3_std(cam, s)
    ra = res.robot_accuracy
    T_eff, _ = sc.effective_truth(s, ra.rotation_deg, ra.translation_mm)
    for key, (d, C) in hand_eye_errors(res, T_eff).items():
        assert np.all(np.abs(d) < 3.0 * np.sqrt(np.diag(C))), key
    out = refine(s.problem, build_structure(s.problem), s.truth)
    assert "V" in out.model.slices and out.model.st.trend_dims == (3,)
    assert np.all(out.model.st.trend_groups == 0)
    # eye-to-hand keeps independent corrections: there a linear field's rotation is the
    # camera's own (the reported T_base_cam), not the arm's
    e2h = sc.classic_real_arm(np.random.default_rng(3129), eye_in_hand=False)
    out = refine(e2h.problem, build_structure(e2h.problem), e2h.truth)
    assert "V" not in out.model.slices


def test_a_tag_session_on_a_real_arm_shares_a_field_across_its_groups() -> None:
    # a fixed camera, one tag's 4 corners on the tool, 205 frames in 7 orientations over a large
    # part of the workspace, a UR5e whose kinematics err by about 0.8 mm and 0.08 deg: the arm's
    # error is correlated from frame to frame and the groups share much of it (its sag under
    # gravity grows with the reach whatever the orientation). With each group's offset and
    # trend alone this seed's cy came out 7.0 reported std off (1.9 px)
    from slidecal.solver.calibrate import calibrate
    from slidecal.solver.model import build_structure
    from slidecal.solver.refine import refine

    s = sc.tag_real_arm(np.random.default_rng(6))
    res = calibrate(s.problem)
    cam = res.cameras["cam"]
    _assert_within_3_std(cam, s)
    out = refine(s.problem, build_structure(s.problem), s.truth)
    m = out.model
    # the shared rotation trend (3 x 3) and quadratic translation field (3 x 6)
    assert "W" in m.slices and m.slices["W"].stop - m.slices["W"].start == 27
    assert int(m.st.common_rotation.sum()) == 9


def test_a_tag_sessions_shared_linear_field_is_carried_at_its_quadratic_level(monkeypatch):
    # the groups' translation trends share a linear field no image measures (it is the focal
    # lengths and the principal point again); its level learned from the trends is only how
    # they differ. On this arm (seed 2098 of the reality benchmark) the trends' level came out
    # 0.35 mm/m where the arm's trends are about 0.75 mm/m, and the fixed camera's position was
    # 4.1 std off (1.1 mm) against what the session can know. The quadratic field the groups
    # share is learned at about the trends' true size: carried at that level, within 3 std
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from test_named import _solve_keeping_the_refinement


    s = sc.tag_real_arm(np.random.default_rng(2098), sigma_px=0.15, arm_mm=1.0, arm_deg=0.1)
    res, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
    m = out.model
    assert "W" in m.slices and m.common_sigma[1] > 1.5 * m.trend_sigma[1]
    ra = res.robot_accuracy
    assert not ra.left_out
    T_eff, _ = sc.effective_truth(s, ra.rotation_deg, ra.translation_mm)
    d, C = hand_eye_errors(res, T_eff)["t"]
    assert np.all(np.abs(d) / np.sqrt(np.diag(C)) < 3.0)
    assert float(d @ np.linalg.solve(C, d)) < 14.16  # chi-square(3) at 3 sigma's tail
    _assert_within_3_std(res.cameras["cam"], s)


def test_a_short_tag_session_shares_the_rotation_trend_only(monkeypatch) -> None:
    # 35 frames, 5 per orientation: three frames per coordinate hold the shared rotation trend
    # (9 coordinates), too few for the quadratic field (18). The trend brings this seed's cy
    # from 3.77 to 3.39 reported std off: a short eye-to-hand tag session's cy is its weak
    # point (rms error/std 1.31 over 20 seeds; docs/ROBOT_ACCURACY.md, "Where the model of the
    # arm is still too simple"); fx, fy and cx are within 3 std
    import slidecal.solver.refine as rf
    from slidecal.solver.calibrate import calibrate
    from slidecal.solver.model import build_structure
    from slidecal.solver.refine import refine

    s = sc.tag_real_arm(np.random.default_rng(19), n_frames=35)
    cam = calibrate(s.problem).cameras["cam"]
    z = {p: (cam.K[a, b] - s.truth.K["cam"][a, b]) / cam.std[p] for p, (a, b) in _IJ.items()}
    assert all(abs(z[p]) < 3.0 for p in ("fx", "fy", "cx")), z
    m = refine(s.problem, build_structure(s.problem), s.truth).model
    assert "W" in m.slices and m.st.common_rotation.all() and len(m.st.common_rotation) == 9
    monkeypatch.setattr(rf, "COMMON_FIELD_FRAMES_PER_COORD", 1000)  # no shared trend
    alone = calibrate(s.problem).cameras["cam"]
    assert abs(z["cy"]) < abs((alone.K[1, 2] - s.truth.K["cam"][1, 2]) / alone.std["cy"])


def test_a_bowed_board_is_estimated_where_a_flat_one_misses() -> None:
    # R1 on a real arm in front of a real board (bowed by a draw of a real board's flatness,
    # described as a file describes it): solved as flat, fx is 4.7 std off (seed 2010); with the
    # bow estimated (its two readings carried) every intrinsic is within 3 std
    from dataclasses import replace

    from slidecal.solver.calibrate import calibrate

    s = sc.r1_real_arm(np.random.default_rng(2010), real_board=True)
    flat = replace(s.problem, target=replace(s.problem.target, flatness_m=0.0, print_tolerance=0.0))
    res = calibrate(s.problem)
    _assert_within_3_std(res.cameras["cam"], s)
    with pytest.raises(AssertionError):
        _assert_within_3_std(calibrate(flat).cameras["cam"], s)
    assert res.board is not None and max(res.board.bow_std_mm) < 0.1
