"""The named model (solver/uncertainty.py): the reported quantities' covariance, checked against
finite differences of the transforms as reported, a calibration and results of earlier versions."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from slidecal.mocks import scenarios as sc
from slidecal.mocks.scenarios import drifting_arm
from slidecal.mocks.truth import calibration, hand_eye_errors
from slidecal.routines.results_io import hand_eye_transforms, read_result, write_result
from slidecal.solver.calibrate import calibrate
from slidecal.solver.geometry import R_from_rvec, T_from_Rt, inv_T, rvec_from_R
from slidecal.solver.model import build_structure, complement_basis, fisher_covariance
from slidecal.solver.problem import MOUNTS, hand_eye_names
from slidecal.solver.result import TransformEstimate
from slidecal.solver.uncertainty import (
    Layout,
    is_legacy,
    predicted_covariance,
    propagate,
)
from tests.helpers import linearised_estimator, random_rotation

ROT = ("rx", "ry", "rz")
SIX = ROT + ("tx", "ty", "tz")


def _random_T(rng: np.random.Generator) -> np.ndarray:
    return T_from_Rt(random_rotation(rng), rng.normal(0, 0.3, 3))


def _step(T: np.ndarray, d: np.ndarray, Br: np.ndarray, Bt: np.ndarray) -> np.ndarray:
    """The optimiser's update: rotation on the left in the basis, translation added."""
    mr = Br.shape[1]
    return T_from_Rt(R_from_rvec(Br @ d[:mr]) @ T[:3, :3], T[:3, 3] + Bt @ d[mr:])


def _reported(layout: Layout, internal: tuple[str, ...], d: np.ndarray) -> dict[str, float]:
    """Every reported quantity after the optimiser's step ``d``, computed from the transforms
    themselves (inverse, composition): the oracle for the propagation's Jacobian."""
    v = dict(zip(internal, d, strict=True))
    out = {}
    for c in layout.cameras:
        f = v.get(f"{c}.f", 0.0)
        out[f"{c}.fx"] = v.get(f"{c}.fx", f)
        out[f"{c}.fy"] = v.get(f"{c}.fy", f)
        out[f"{c}.cx"] = v[f"{c}.cx"]
    ref = layout.reference
    Xr, Xt, Yr, Yt = layout.X_rot_basis, layout.X_t_basis, layout.Y_rot_basis, layout.Y_t_basis
    dx = [v[f"X0.r{k}"] for k in range(Xr.shape[1])] + [v[f"X0.t{k}"] for k in range(Xt.shape[1])]
    dy = [v[f"Y.r{k}"] for k in range(Yr.shape[1])] + [v[f"Y.t{k}"] for k in range(Yt.shape[1])]
    X = _step(layout.X, np.array(dx), Xr, Xt)
    Y = _step(layout.Y, np.array(dy), Yr, Yt)
    he = hand_eye_names(layout.mount, list(layout.cameras))
    pairs = {he[ref]: (inv_T(X), inv_T(layout.X)), MOUNTS[layout.mount].target: (Y, layout.Y)}
    for c, T0 in layout.T_cam_ref.items():
        T = _step(T0, np.array([v[f"T_{c}_{ref}.{a}"] for a in SIX]), np.eye(3), np.eye(3))
        pairs[f"T_{c}_{ref}"] = (T, T0)
        pairs[he[c]] = (inv_T(T @ X), inv_T(T0 @ layout.X))
    for name, (T, T0) in pairs.items():
        r = rvec_from_R(T[:3, :3] @ T0[:3, :3].T)  # left perturbation of the reported transform
        for k, a in enumerate(ROT):
            out[f"{name}.{a}"] = r[k]
        for k, a in enumerate(("tx", "ty", "tz")):
            out[f"{name}.{a}"] = (T[:3, 3] - T0[:3, 3])[k]
    return out


def _layout(rng, mount: str, rig: bool, Xt: np.ndarray) -> tuple[Layout, tuple[str, ...]]:
    cams = ("left", "right") if rig else ("cam",)
    internal = []
    for c in cams:
        internal += [f"{c}.f", f"{c}.cx"] if c == "cam" else [f"{c}.fx", f"{c}.fy", f"{c}.cx"]
    T_cam_ref = {"right": _random_T(rng)} if rig else {}
    internal += [f"T_right_left.{a}" for a in SIX] if rig else []
    internal += [f"X0.r{k}" for k in range(3)] + [f"X0.t{k}" for k in range(Xt.shape[1])]
    internal += [f"Y.r{k}" for k in range(3)] + [f"Y.t{k}" for k in range(3)]
    internal += [f"pose{k}.{a}" for k in range(2) for a in SIX]  # nuisance: marginalised
    I3 = np.eye(3)
    layout = Layout(cams, cams[0], mount, _random_T(rng), _random_T(rng), T_cam_ref, I3, Xt, I3, I3)
    return layout, tuple(internal)


@pytest.mark.parametrize(
    "mount, rig, t_rank",
    [("eye_in_hand", True, 3), ("eye_to_hand", False, 3), ("eye_in_hand", False, 2)],
    ids=["eye-in-hand-rig", "eye-to-hand", "translation-along-axis-unobservable"],
)
def test_propagation_is_that_of_the_transforms_as_reported(mount, rig, t_rank):
    rng = np.random.default_rng(11)
    Xt = np.eye(3) if t_rank == 3 else complement_basis(rng.normal(size=3))
    layout, internal = _layout(rng, mount, rig, Xt)
    A = rng.normal(size=(len(internal), len(internal)))
    cov = 1e-4 * (A @ A.T + np.eye(len(internal)))
    named = propagate(layout, internal, cov)
    # central differences of the reported quantities through inverse and composition
    h = 1e-6
    base = _reported(layout, internal, np.zeros(len(internal)))
    J = np.zeros((len(named.names), len(internal)))
    for k in range(len(internal)):
        e = np.zeros(len(internal))
        e[k] = h
        plus, minus = _reported(layout, internal, e), _reported(layout, internal, -e)
        J[:, k] = [(plus[n] - minus[n]) / (2 * h) for n in named.names]
    assert set(named.names) <= set(base)
    np.testing.assert_allclose(named.matrix, J @ cov @ J.T, rtol=1e-6, atol=1e-12)
    he = MOUNTS[mount].hand_eye if not rig else "T_tool_left"
    assert f"{he}.rx" in named.names and named.std_rot_deg(he) > 0
    # what the data cannot determine is absent, not zero
    assert (named.std_t_mm(he) is None) == (t_rank < 3)
    assert not any(n.startswith(("X0.", "Y.", "pose")) for n in named.names)
    if rig:
        assert named.std_t_mm("T_tool_right") > 0  # composed, with the correlations


def test_rig_hand_eye_std_comes_from_the_joint_covariance(tmp_path: Path):
    s = sc.oak_rig(np.random.default_rng(4), 0.15)
    res = calibrate(s.problem)
    assert {f"T_tool_right.{a}" for a in SIX} <= set(res.parameter_names)
    composed = hand_eye_transforms(res)["T_tool_right"]
    named = res.named_covariance
    assert composed.std_rot_deg == pytest.approx(named.std_rot_deg("T_tool_right"))
    assert composed.std_t_mm == pytest.approx(named.std_t_mm("T_tool_right"))
    # the reported std is the bound at the truth within the spread of the estimated noise
    bound = predicted_covariance(s.problem, s.truth, s.sigma_px)
    assert composed.std_t_mm / bound.std_t_mm("T_tool_right") == pytest.approx(1.0, abs=0.15)
    # and the composed estimate's error is within it
    T_true = s.T_hand_eye @ inv_T(s.truth.T_cam_ref["right"])
    err_mm = 1000.0 * np.linalg.norm(composed.t_m - T_true[:3, 3])
    assert err_mm < 4.0 * composed.std_t_mm
    q = read_result(write_result(res, tmp_path / "result.yaml"))
    assert q.parameter_names == res.parameter_names
    assert hand_eye_transforms(q)["T_tool_right"].std_t_mm == pytest.approx(composed.std_t_mm)


def test_result_of_an_earlier_version_is_read_in_the_named_quantities(tmp_path: Path):
    """A covariance written with the optimiser's names (X0.r0 .. Y.t2, cam.f) is converted on
    reading: it equals the named layer's own propagation of the same covariance."""
    s = sc.r1(np.random.default_rng(5), 0.15, 0.0, 0.0)
    problem = replace(s.problem, options=replace(s.problem.options, unit_aspect=True))
    st = build_structure(problem, s.truth.X[0][:3, :3])
    internal, cov = fisher_covariance(problem, st, s.truth, 0.15)
    assert is_legacy(internal)
    res = calibrate(s.problem)
    he = inv_T(s.truth.X[0])
    old = replace(
        res,
        hand_eye=TransformEstimate("T_tool_cam", he[:3, :3], he[:3, 3]),
        T_target=TransformEstimate("T_base_board", s.truth.Y[:3, :3], s.truth.Y[:3, 3]),
        parameter_names=internal,
        covariance=cov,
    )
    q = read_result(write_result(old, tmp_path / "result.yaml"))
    bound = predicted_covariance(problem, s.truth, 0.15, structure=st)
    assert q.parameter_names == bound.names and not is_legacy(q.parameter_names)
    np.testing.assert_allclose(q.covariance, bound.matrix, rtol=1e-6, atol=1e-15)
    named = q.named_covariance
    assert named.std("cam.fx") == named.std("cam.fy") == pytest.approx(bound.std("cam.fx"))


def test_public_api_is_declared_and_light():
    import subprocess
    import sys

    code = (
        "import sys, slidecal.solver as s; assert 'slidecal.solver.refine' not in sys.modules; "
        "[getattr(s, n) for n in s.__all__]; print(len(s.__all__))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert int(out.stdout) >= 20
    import slidecal.solver as solver

    assert solver.predicted_covariance is predicted_covariance
    assert solver.MOUNTS["eye_to_hand"].hand_eye == "T_base_cam"
    with pytest.raises(AttributeError):
        _ = solver.BundleModel  # the optimiser's model is private


def test_named_convention_matches_the_solvers_actual_errors():
    """The linearised estimator in the named quantities predicts the errors ``calibrate`` makes
    on the same noise draw (rotation vector on the left of the reported T_tool_cam, its
    translation, the intrinsics): one convention from the optimiser to the result."""
    s = sc.r1(np.random.default_rng(3), 0.15, 0.0, 0.0)
    lin = linearised_estimator(s.problem, s.truth)
    predicted = lin.errors(s.problem)
    res = calibrate(s.problem)
    bound = predicted_covariance(s.problem, s.truth, s.sigma_px)
    assert set(predicted) == set(bound.names) == set(res.parameter_names)
    K, Kt = res.cameras["cam"].K, s.truth.K["cam"]
    actual = {"cam.fx": K[0, 0] - Kt[0, 0], "cam.fy": K[1, 1] - Kt[1, 1]}
    actual |= {"cam.cx": K[0, 2] - Kt[0, 2], "cam.cy": K[1, 2] - Kt[1, 2]}
    for name, T, T_true in (
        ("T_tool_cam", res.hand_eye.T, s.T_hand_eye),
        ("T_base_board", res.T_target.T, s.T_target),
    ):
        r = rvec_from_R(T[:3, :3] @ T_true[:3, :3].T)
        dt = T[:3, 3] - T_true[:3, 3]
        actual |= {f"{name}.{a}": v for a, v in zip(SIX, np.r_[r, dt], strict=True)}
    for n, v in actual.items():
        assert abs(predicted[n] - v) < 0.05 * bound.std(n), n
    # noise-free detections: no error at all
    s0 = sc.r1(np.random.default_rng(3), 0.0, 0.0, 0.0)
    assert max(abs(v) for v in lin.errors(s0.problem).values()) < 1e-9


def test_rig_result_of_an_earlier_version_gets_the_composed_hand_eye_std(tmp_path: Path):
    s = sc.oak_rig(np.random.default_rng(6), 0.15)
    st = build_structure(s.problem, s.truth.X[0][:3, :3])
    internal, cov = fisher_covariance(s.problem, st, s.truth, 0.15)
    res = calibrate(s.problem)
    he = inv_T(s.truth.X[0])
    T_rl = s.truth.T_cam_ref["right"]
    old = replace(
        res,
        hand_eye=TransformEstimate("T_tool_cam", he[:3, :3], he[:3, 3]),
        T_target=TransformEstimate("T_base_board", s.truth.Y[:3, :3], s.truth.Y[:3, 3]),
        rig={"T_right_left": TransformEstimate("T_right_left", T_rl[:3, :3], T_rl[:3, 3])},
        parameter_names=internal,
        covariance=cov,
    )
    q = read_result(write_result(old, tmp_path / "result.yaml"))
    bound = predicted_covariance(s.problem, s.truth, 0.15, structure=st)
    assert q.parameter_names == bound.names
    composed = hand_eye_transforms(q)["T_tool_right"]
    assert composed.std_t_mm == pytest.approx(bound.std_t_mm("T_tool_right"), rel=1e-6)
    assert composed.std_rot_deg == pytest.approx(bound.std_rot_deg("T_tool_right"), rel=1e-6)


@pytest.mark.slow
def test_composed_rig_hand_eye_std_matches_monte_carlo():
    """40 noise draws of the OAK rig: the rms error of T_tool_right (3-vectors, 120 squared
    components: relative spread of the rms about 6.5 %, so 3 of them: 20 %) is its reported
    std; the root sum of squares of its two parts, which ignored their correlation, is not."""
    err_t, err_r, sd_t, sd_r, rss_t = [], [], [], [], []
    for seed in range(100, 140):
        s = sc.oak_rig(np.random.default_rng(seed), 0.15)
        res = calibrate(s.problem)
        c = hand_eye_transforms(res)["T_tool_right"]
        T = s.T_hand_eye @ inv_T(s.truth.T_cam_ref["right"])
        err_t.append(1000.0 * np.linalg.norm(c.t_m - T[:3, 3]))
        err_r.append(np.degrees(np.linalg.norm(rvec_from_R(c.R @ T[:3, :3].T))))
        sd_t.append(c.std_t_mm)
        sd_r.append(c.std_rot_deg)
        rss_t.append(np.hypot(res.hand_eye.std_t_mm, res.rig["T_right_left"].std_t_mm))
    rms_t, rms_r = np.sqrt(np.mean(np.square(err_t))), np.sqrt(np.mean(np.square(err_r)))
    assert rms_t / np.median(sd_t) == pytest.approx(1.0, abs=0.2)
    assert rms_r / np.median(sd_r) == pytest.approx(1.0, abs=0.2)
    assert np.median(rss_t) > 1.3 * rms_t


def _solve_keeping_the_refinement(problem, monkeypatch):  # noqa: ANN001, ANN202
    """``calibrate`` of ``problem`` and the refinement behind its result."""
    import slidecal.solver.calibrate as cal
    import slidecal.solver.uncertainty as unc

    kept = {}
    inner = unc.result_covariance

    def keep(p, out, *rest):  # noqa: ANN001, ANN002, ANN202
        kept["out"] = out
        return inner(p, out, *rest)

    monkeypatch.setattr(unc, "result_covariance", keep)
    return cal.calibrate(problem), kept["out"]


def test_a_classic_sessions_linear_field_is_read_both_ways(monkeypatch):
    # a classic eye-in-hand session (28 frames, each at its own orientation) on an arm whose
    # moves are 0.5 % long as well as its kinematics' error: the session's one trend over its
    # positions takes part of that scale, the images cannot tell the rest from the hand-eye's
    # translation along the viewing direction, and the trend's level, learned from the same
    # frames, understates it. The old result (the field's reading alone) put T_tool_cam.tz
    # 9.97 reported std off the effective truth here. The reading without the field is the
    # solve with the trend held at zero (levels as learned); the step to it, to first order,
    # is what that re-solve gives; the result is halfway, the spread in its covariance
    from scipy.spatial.transform import Rotation

    from slidecal.solver.geometry import inv_T
    from slidecal.solver.refine import _Solve
    from slidecal.solver.robot_error import session_field_step
    from slidecal.solver.target_shape import READING_WEIGHT
    from slidecal.solver.uncertainty import layout_of, named_step

    s = sc.classic_real_arm(np.random.default_rng(2006), arm_scale=0.005)
    res, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
    m = out.model
    step = session_field_step(out)
    assert step is not None
    d = named_step(layout_of(s.problem, m.st, out.state), tuple(out.names), step)
    held = replace(
        m.st,
        trend_groups=None,
        trend_coords=None,
        trend_dims=(),
        trend_sigma=None,
        pose_sigma=m.pose_sigma,
        group_sigma=m.group_sigma,
    )
    r = _Solve(s.problem, held, replace(out.state, V=None), False).iterate(100, False).output()
    X0, X1 = inv_T(out.state.X[0]), inv_T(r.state.X[0])
    moved_t = X1[:3, 3] - X0[:3, 3]
    moved_r = Rotation.from_matrix(X1[:3, :3] @ X0[:3, :3].T).as_rotvec()
    step_t = np.array([d[f"T_tool_cam.t{a}"] for a in "xyz"])
    step_r = np.array([d[f"T_tool_cam.r{a}"] for a in "xyz"])
    assert np.linalg.norm(moved_t) > 1e-3  # the readings are 1.9 mm apart here
    np.testing.assert_allclose(step_t, moved_t, rtol=0.05, atol=2e-5)
    np.testing.assert_allclose(step_r, moved_r, rtol=0.05, atol=2e-5)
    # reported halfway, the spread in the covariance, and said
    np.testing.assert_allclose(res.hand_eye.t_m, X0[:3, 3] + READING_WEIGHT * step_t, atol=2e-5)
    tz = res.parameter_names.index("T_tool_cam.tz")
    assert res.covariance[tz, tz] >= 0.25 * step_t[2] ** 2
    assert any("read without that field" in line for line in res.messages)
    ra = res.robot_accuracy
    T_eff, _ = sc.effective_truth(s, ra.rotation_deg, ra.translation_mm)
    for key, (e, C) in hand_eye_errors(res, T_eff).items():
        assert np.all(np.abs(e) < 3.0 * np.sqrt(np.diag(C))), key
    # R1's groups have trends of their own: one reading
    _, o = _solve_keeping_the_refinement(
        sc.r1_real_arm(np.random.default_rng(2000)).problem, monkeypatch
    )
    assert session_field_step(o) is None


def test_smooth_arm_cover_widens_what_the_groups_cannot_tell(monkeypatch):
    # R1 on a real arm: groups of five frames cannot tell a trend of the pose error along the
    # moves from the frames' scatter (the trend's level goes to the floor); the reported
    # covariance covers the estimator's spread under both readings: never below the model's
    # own, the focal lengths (a trend of the translation is a scale error of the moves) wider
    from slidecal.solver.robot_error import smooth_field_excess
    from slidecal.solver.uncertainty import layout_of, propagate

    s = sc.r1_real_arm(np.random.default_rng(2000))
    res, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
    assert smooth_field_excess(out, ways=("groups",)) is not None
    own = propagate(layout_of(s.problem, out.model.st, out.state), out.names, out.covariance)
    reported = res.named_covariance
    assert reported.names == own.names
    assert np.all(np.linalg.eigvalsh(reported.matrix - own.matrix) > -1e-12 * own.matrix.max())
    assert reported.std("cam.fx") > 1.05 * own.std("cam.fx")
    assert reported.std("cam.fy") > 1.05 * own.std("cam.fy")


def test_smooth_arm_cover_leaves_exact_poses_alone_and_carries_one_orientations_scale(
    monkeypatch,
):
    # exact poses carry no correction at all: nothing is added. Thirteen frames of one
    # orientation learn their rotation trend, but the translation trend's scale along the moves
    # is the focal length's: its level stays at the floor and the reading that the frames'
    # translation error is all trend is carried, on the translation axes only (the drifting
    # arm's rotation trend is learned, not carried)
    from slidecal.solver.refine import SIGMA_FLOOR
    from slidecal.solver.robot_error import smooth_field_excess

    _, out = _solve_keeping_the_refinement(
        sc.r1(np.random.default_rng(7), 0.15, 0.0, 0.0).problem, monkeypatch
    )
    assert smooth_field_excess(out, ways=("groups",)) is None
    for s, drifts in (
        (drifting_arm(np.random.default_rng(7))[0], True),
        (sc.r1_real_arm(np.random.default_rng(2000), translations_only=True), False),
    ):
        _, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
        m = out.model
        assert m.st.trend_scale_fixed and m.trend_sigma[1] == SIGMA_FLOOR[1]
        if drifts:  # the drifting arm's rotation trend is learned
            assert m.trend_sigma[0] * m.trend_spread > 0.1 * m.pose_sigma[0]
        extra = smooth_field_excess(out, ways=("groups",))
        assert extra is not None and np.trace(extra) > 0.0


@pytest.mark.slow
def test_focal_lengths_on_a_real_arm_are_covered(monkeypatch):
    # 40 simulated arms (seeds 2000-2039), R1 eye-in-hand: with the frames' corrections read as
    # independent only, fx and fy are 1.33 and 1.37 times their std off in rms (beyond the 99 %
    # chi-square(40) interval of a calibrated estimator); with the cover, consistent with it
    from slidecal.solver.uncertainty import layout_of, propagate

    z_own, z_reported = [], []
    for seed in range(2000, 2040):
        s = sc.r1_real_arm(np.random.default_rng(seed))
        res, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
        own = propagate(layout_of(s.problem, out.model.st, out.state), out.names, out.covariance)
        cam = res.cameras["cam"]
        err = {
            "fx": cam.K[0, 0] - s.truth.K["cam"][0, 0],
            "fy": cam.K[1, 1] - s.truth.K["cam"][1, 1],
        }
        z_own.append([err[p] / own.std(f"cam.{p}") for p in err])
        z_reported.append([err[p] / cam.std[p] for p in err])
    for i in range(2):
        assert calibration(np.array(z_own)[:, i], 1).verdict.startswith("std too small")
        assert calibration(np.array(z_reported)[:, i], 1).verdict == "consistent"


def test_estimated_levels_carry_their_own_uncertainty(monkeypatch):
    # the drifting arm's 13 frames: the frames' and the trends' levels rest on a few degrees of
    # freedom each (5-15); the reported covariance adds, per level, nu / (nu - 2) - 1 times its
    # share, never less than the model's own, and nothing for exact poses
    from slidecal.solver.robot_error import MIN_LEVEL_DOF, level_excess
    from slidecal.solver.uncertainty import layout_of, propagate

    s = drifting_arm(np.random.default_rng(2001))[0]
    _, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
    red = out.model.level_redundancy
    assert set(red) >= {"E", "V"} and all(v >= 0 for nu in red.values() for v in nu)
    extra = level_excess(out)
    assert extra is not None
    assert np.all(np.linalg.eigvalsh(extra) > -1e-12 * np.abs(extra).max())
    # the frames' rotation level alone: its share of the covariance, times nu / (nu - 2) - 1
    m, cov = out.model, np.asarray(out.covariance)
    nu = red["E"][0]
    assert nu >= MIN_LEVEL_DOF
    rot = np.tile([True, True, True, False, False, False], len(s.problem.frames))
    C = cov[:, m.slices["E"]][:, rot]
    share = (nu / (nu - 2.0) - 1.0) * (C @ C.T) / m.pose_sigma[0] ** 2
    assert np.all(np.linalg.eigvalsh(extra - share) > -1e-9 * np.abs(extra).max())
    layout = layout_of(s.problem, m.st, out.state)
    more = propagate(layout, out.names, extra)
    assert more.std("cam.fy") > 0
    _, exact = _solve_keeping_the_refinement(
        sc.r1(np.random.default_rng(7), 0.15, 0.0, 0.0).problem, monkeypatch
    )
    assert level_excess(exact) is None


def test_unobserved_tool_offset_gain_is_the_response_of_a_solve(monkeypatch):
    # one orientation: the camera's offset from the flange is not observed and taken as zero;
    # with the arm's rotation learned per frame, holding it at another value moves the focal
    # lengths. The gain the covariance carries is that response, to first order: re-solving
    # with the offset held 5 mm off along each axis moves the intrinsics by the gain times it
    from slidecal.solver.refine import _Solve
    from slidecal.solver.robot_error import tool_offset_gain
    from slidecal.solver.uncertainty import _jacobian, layout_of

    s = drifting_arm(np.random.default_rng(2001))[0]
    _, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
    m = out.model
    assert m.st.X_t_basis.shape[1] == 0 and "E" in m.slices
    names, J = _jacobian(layout_of(s.problem, m.st, out.state), tuple(out.names))
    used = np.flatnonzero(np.any(J != 0, axis=0))
    G = tool_offset_gain(s.problem, out, (J[:, used], used))
    assert G.shape == (len(names), 3)
    levels = {"pose_sigma": m.pose_sigma, "group_sigma": m.group_sigma}
    st = replace(m.st, trend_sigma=m.trend_sigma, **levels)

    def solve(t: np.ndarray) -> np.ndarray:
        X = out.state.X.copy()
        X[0, :3, 3] = t
        init = replace(out.state, X=X)
        res = _Solve(s.problem, st, init, False).iterate(100, False).output()
        return np.array([res.state.K["cam"][i, j] for i, j in ((0, 0), (1, 1), (0, 2), (1, 2))])

    h = 0.002
    response = np.array([(solve(h * e) - solve(-h * e)) / (2 * h) for e in np.eye(3)]).T
    rows = [names.index(f"cam.{p}") for p in ("fx", "fy", "cx", "cy")]
    # the gain's directions are an orthonormal basis of the unobserved ones: compare the
    # spread per parameter, sqrt(diag(G G')) (px per m); cy barely moves (under 1 px per m,
    # where second-order terms the gain leaves out are of its size)
    want = np.sqrt(np.diag(response @ response.T))
    got = np.sqrt(np.diag(G[rows] @ G[rows].T))
    assert want[:3].min() > 5.0  # the offset matters here: fx, fy and cx move
    np.testing.assert_allclose(got, want, rtol=0.15, atol=1.0)
    # poses taken as exact: the offset only moves the target, nothing to carry
    p = replace(s.problem, options=replace(s.problem.options, estimate_robot_noise=False))
    res, exact = _solve_keeping_the_refinement(p, monkeypatch)
    assert "E" not in exact.model.slices
    names, J = _jacobian(layout_of(p, exact.model.st, exact.state), tuple(exact.names))
    used = np.flatnonzero(np.any(J != 0, axis=0))
    assert tool_offset_gain(p, exact, (J[:, used], used)) is None


def test_a_trend_moves_the_result_as_the_corrections_it_adds_to(monkeypatch):
    # a trend adds V c_k to frame k's correction E_k, so shifting its prior mean by one unit
    # moves the reported quantities as shifting every frame's correction by c_k does: the
    # field way of smooth_field_excess reads every trend through the frames' corrections
    from slidecal.solver.model import TREND_AXES
    from slidecal.solver.robot_error import _columns
    from slidecal.solver.uncertainty import _jacobian, _used, layout_of

    s = sc.tag_real_arm(np.random.default_rng(10), n_frames=70)
    _, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
    m, st = out.model, out.model.st
    assert "V" in m.slices and len(st.trend_dims) >= 2
    project = _used(_jacobian(layout_of(s.problem, st, out.state), tuple(out.names))[1])
    e, v = m.slices["E"], m.slices["V"]
    sig, tau = np.asarray(m.pose_sigma, float), np.asarray(m.trend_sigma, float)
    A_E = _columns(out, project, np.arange(e.start, e.stop))
    A_E = A_E / np.tile(np.repeat(sig**2, 3), (e.stop - e.start) // 6)
    A_V = _columns(out, project, np.arange(v.start, v.stop))
    for g, dims in enumerate(st.trend_dims):
        k = np.flatnonzero(st.trend_groups == g)
        for ai, a in enumerate(TREND_AXES):
            o = m.trend_offsets[g] + ai * dims
            via_v = A_V[:, o : o + dims] / tau[a // 3] ** 2
            via_e = A_E[:, 6 * k + a] @ st.trend_coords[k, :dims]
            np.testing.assert_allclose(via_e, via_v, rtol=1e-6, atol=1e-9 * np.abs(via_v).max())


def test_untold_field_gain_is_the_response_of_a_solve(monkeypatch):
    # a classic eye-to-hand session (28 frames, each at its own orientation) keeps independent
    # pose corrections: no trend over the tool's positions. The covariance carries a linear
    # field of the arm's translation error over them at an arm's scale error (0.1 %) through
    # the estimate's response to it; that response, to first order, is what re-solving with the
    # measured positions moved by the field gives (the levels held at the learned ones)
    from slidecal.solver.refine import _Solve
    from slidecal.solver.robot_error import MOVE_SCALE_SIGMA, _session_trend, smooth_field_excess
    from slidecal.solver.uncertainty import _jacobian, _used, layout_of

    s = sc.classic_real_arm(np.random.default_rng(2005), eye_in_hand=False)
    res, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
    m = out.model
    assert "E" in m.slices and "V" not in m.slices
    names, J = _jacobian(layout_of(s.problem, m.st, out.state), tuple(out.names))
    project = _used(J)
    extra = smooth_field_excess(out, project, ("field",))
    assert extra is not None
    assert np.all(np.linalg.eigvalsh(extra) > -1e-12 * np.abs(extra).max())
    rows = [names.index(f"cam.{p}") for p in ("fx", "fy", "cx", "cy")]
    T_meas = m.st.T_meas
    D = T_meas[:, :3, 3] - T_meas[:, :3, 3].mean(axis=0)
    levels = {"pose_sigma": m.pose_sigma, "group_sigma": m.group_sigma}

    def solve(M: np.ndarray) -> np.ndarray:
        moved = T_meas.copy()
        moved[:, :3, 3] += D @ M.T
        st = replace(m.st, T_meas=moved, **levels)
        r = _Solve(s.problem, st, out.state, False).iterate(100, False).output()
        return np.array([r.state.K["cam"][i, j] for i, j in ((0, 0), (1, 1), (0, 2), (1, 2))])

    h = 2e-3
    response = []
    for a in range(3):
        for j in range(3):
            M = np.zeros((3, 3))
            M[a, j] = h
            response.append((solve(M) - solve(-M)) / (2 * h))
    response = np.array(response).T  # (4, 9): px per unit of each coefficient
    want = MOVE_SCALE_SIGMA * np.sqrt(np.diag(response @ response.T))
    got = np.sqrt(np.diag(extra)[rows])
    assert want[:2].min() > 0.2 * res.cameras["cam"].std["fx"]  # the field matters to fx, fy
    np.testing.assert_allclose(got, want, rtol=0.15, atol=0.02)
    # the trend an eye-in-hand classic session learns is carried at no less than 0.1 %

    e = sc.classic_real_arm(np.random.default_rng(2135))
    res_e, out_e = _solve_keeping_the_refinement(e.problem, monkeypatch)
    assert "V" in out_e.model.slices and out_e.model.trend_sigma[1] < MOVE_SCALE_SIGMA
    names_e, J_e = _jacobian(layout_of(e.problem, out_e.model.st, out_e.state), out_e.names)
    more = smooth_field_excess(out_e, _used(J_e), ("field",))  # the trend's, not one untold
    assert more is not None and _session_trend(out_e) and "V" in out_e.model.slices
    assert np.all(np.linalg.eigvalsh(more) > -1e-12 * np.abs(more).max())
    assert more[names_e.index("cam.fx"), names_e.index("cam.fx")] > 0.0
    # R1's groups have trends of their own, and exact poses carry no correction: neither adds
    for scen in (sc.r1_real_arm(np.random.default_rng(2000)), sc.r1(np.random.default_rng(7))):
        _, o = _solve_keeping_the_refinement(scen.problem, monkeypatch)
        assert not _session_trend(o) and ("V" in o.model.slices or "E" not in o.model.slices)


def test_a_classic_sessions_board_reaches_the_result_between_its_two_readings(monkeypatch):
    # the result of a classic session is reported halfway between its readings with and
    # without the arm's linear field; a board printed at another scale moves the two readings
    # differently (without the field, the hand-eye takes the whole scale as a shift along the
    # view; with it, the field takes part as the arm's scale). The board's modes reach the
    # reported value by the response of that halfway reading (reported_response): checked
    # against re-solves with the board 0.2 % larger, the levels held. With the response of the
    # field's reading alone, T_tool_cam.tz's share of the board's scale was understated
    from dataclasses import replace as dc_replace

    from slidecal.solver.geometry import inv_T
    from slidecal.solver.refine import _Solve
    from slidecal.solver.robot_error import reported_response, session_field_step
    from slidecal.solver.target_shape import READING_WEIGHT, fit_board
    from slidecal.solver.uncertainty import layout_of, named_step

    s = sc.classic_real_arm(np.random.default_rng(2006), arm_scale=0.005)
    _, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
    p = s.problem
    tol = dc_replace(p, target=dc_replace(p.target, print_tolerance=1e-3, flatness_m=0.0))
    G = fit_board(tol, out).response[:, :1]  # per unit of the board's scale
    eps = 2e-3
    big = dc_replace(p, target=dc_replace(p.target, points_m=p.target.points_m * (1.0 + eps)))
    m = out.model
    held = dc_replace(  # the levels as learned
        m.st, pose_sigma=m.pose_sigma, group_sigma=m.group_sigma, trend_sigma=m.trend_sigma
    )
    base = _Solve(p, held, out.state, False).iterate(100, False).output()
    r = _Solve(big, held, out.state, False).iterate(100, False).output()
    layout = layout_of(p, m.st, out.state)

    def tz(o, step=None):  # noqa: ANN001, ANN202 - the reading (with a step of the field)
        state = o.state if step is None else o.model.apply(o.state, step)
        return inv_T(state.X[0])[2, 3]

    def predicted(response):  # noqa: ANN001, ANN202
        return named_step(layout, tuple(out.names), eps * response[:, 0])["T_tool_cam.tz"]

    moved_with = tz(r) - tz(base)
    moved_reported = tz(r, READING_WEIGHT * session_field_step(r)) - tz(
        base, READING_WEIGHT * session_field_step(base)
    )
    rep = reported_response(out, G)
    # the readings take the scale unlike: here the field's moves tz by +0.12 mm, the reported
    # value by -0.18 mm (without the field, -0.49 mm)
    assert abs(moved_reported - moved_with) > 2.0 * abs(moved_with)
    np.testing.assert_allclose(predicted(G), moved_with, rtol=0.05)
    np.testing.assert_allclose(predicted(rep), moved_reported, rtol=0.05)
