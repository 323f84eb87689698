"""Maximum-likelihood refinement and its Cramer-Rao bound, against synthetic ground truth."""

import numpy as np
import pytest

from slidecal.mocks import scenarios as sc
from slidecal.mocks.truth import hand_eye_errors
from slidecal.solver.geometry import R_from_rvec, T_from_Rt, rotation_angle_deg
from slidecal.solver.model import (
    BundleModel,
    ModelState,
    _assemble,
    build_structure,
    fisher_covariance,
)
from slidecal.solver.problem import ModelOptions
from slidecal.solver.refine import refine


def _dense(nb):
    """``J' W J`` (P, P) and ``J' W r`` (P,) of normal blocks, global columns first."""
    return _assemble(nb.A_gg, nb.A_gE, nb.A_EE), np.concatenate([nb.g_g, nb.g_E.reshape(-1)])


def _normal_equations(model, state, w):
    """Residuals, ``J' W J`` and ``J' W r`` in the dense form of the model's blocks."""
    nb = model.normal_blocks(state, w)
    return (nb.r, *_dense(nb))


def _perturbed(
    truth: ModelState, rng, translate: bool = True, board: bool = True, k_px: float = 6.0
) -> ModelState:
    """A start near the truth; ``board=False`` keeps Y (fixed at identity in board-frame cases)."""
    dK = np.array([[1.0, 0, 0.7], [0, -0.8, -0.5], [0, 0, 0]]) * k_px
    K = {c: k + dK for c, k in truth.K.items()}
    X = np.stack(
        [
            T_from_Rt(
                R_from_rvec(rng.normal(0, 0.01, 3)) @ x[:3, :3],
                x[:3, 3] + (rng.normal(0, 0.003, 3) if translate else 0.0),
            )
            for x in truth.X
        ]
    )
    Y = (
        truth.Y
        if not board
        else T_from_Rt(
            R_from_rvec(rng.normal(0, 0.01, 3)) @ truth.Y[:3, :3],
            truth.Y[:3, 3] + rng.normal(0, 0.003, 3) * np.abs(truth.Y[:3, 3]).max(),
        )
    )
    return ModelState(
        K, {c: np.zeros(5) for c in truth.K}, dict(truth.T_cam_ref), X, Y, truth.s * 1.03
    )


def test_jacobian_matches_finite_differences():
    s = sc.r1(np.random.default_rng(0))
    st = build_structure(s.problem, s.truth.X[0][:3, :3])
    model = BundleModel(s.problem, st)
    state = _perturbed(s.truth, np.random.default_rng(1))
    r0, J = model.evaluate(state)
    h = 1e-7
    for j in range(len(model.names)):
        d = np.zeros(len(model.names))
        d[j] = h
        rp, _ = model.evaluate(model.apply(state, d), jacobian=False)
        rm, _ = model.evaluate(model.apply(state, -d), jacobian=False)
        num = (rp - rm) / (2 * h)
        scale = max(np.abs(num).max(), 1e-6)
        assert np.abs(J[:, j] - num).max() / scale < 1e-4, model.names[j]


@pytest.mark.parametrize("make", list(sc.NOISE_FREE.values()), ids=list(sc.NOISE_FREE))
def test_noise_free_recovery(make):
    rng = np.random.default_rng(2)
    s = make(rng)
    st = build_structure(s.problem, s.truth.X[0][:3, :3])
    # S1-S3 move along one direction only: their problems are exactly determined (docs/METHOD.md
    # Sec. 3 counts) and have further exact solutions a few pixels away, so start within 1 px
    paper = s.problem.cameras[0].width == 300
    init = _perturbed(
        s.truth, rng, st.X_t_basis.shape[1] > 0, st.Y_t_basis.shape[1] > 0, 1.0 if paper else 6.0
    )
    out = refine(s.problem, st, init)
    assert out.converged
    K, Kt = out.state.K["cam"], s.truth.K["cam"]
    np.testing.assert_allclose(K, Kt, rtol=1e-6, atol=1e-6 * Kt[0, 0])
    np.testing.assert_allclose(out.state.dist["cam"], s.truth.dist["cam"], atol=1e-7)
    assert out.sigma_px < 1e-6
    if st.Y_rot_basis.shape[1] == 3:  # hand-eye rotation observable
        assert rotation_angle_deg(out.state.X[0][:3, :3], s.truth.X[0][:3, :3]) < 1e-6


def test_noisy_r1_within_bound_and_covariance_matches_it():
    rng = np.random.default_rng(3)
    s = sc.r1(rng, sigma_px=0.15, robot_noise_m=0.0, robot_noise_deg=0.0)
    st = build_structure(s.problem, s.truth.X[0][:3, :3])
    out = refine(s.problem, st, _perturbed(s.truth, rng))
    names, crb = fisher_covariance(s.problem, st, s.truth, 0.15)
    assert names == out.names
    # the residual-based noise estimate is the injected noise (2800 residuals: +-3% is 2 sigma)
    assert abs(out.sigma_px / 0.15 - 1.0) < 0.06
    for n in ("cam.fx", "cam.fy", "cam.cx", "cam.cy", "cam.k1"):
        i = names.index(n)
        bound = np.sqrt(crb[i, i])
        # predicted std agrees with the bound (same model, noise estimated): within 10 %
        assert abs(np.sqrt(out.covariance[i, i]) / bound - 1.0) < 0.1
        truth = {"cam.fx": (0, 0), "cam.fy": (1, 1), "cam.cx": (0, 2), "cam.cy": (1, 2)}
        if n in truth:
            a, b = truth[n]
            assert abs(out.state.K["cam"][a, b] - s.truth.K["cam"][a, b]) < 4.0 * bound


def test_outliers_flagged_not_dropped_silently():
    rng = np.random.default_rng(4)
    s = sc.r1(rng, sigma_px=0.15, robot_noise_m=0.0, robot_noise_deg=0.0)
    frames = list(s.problem.frames)
    det = frames[3].detections["cam"]
    px = det.px.copy()
    px[[5, 17, 40]] += [[25.0, -10.0], [0.0, 30.0], [-15.0, -15.0]]
    frames[3] = type(frames[3])(
        frames[3].id, {"cam": type(det)(det.ids, px)}, frames[3].T_base_tool
    )
    problem = type(s.problem)(
        s.problem.target,
        s.problem.cameras,
        tuple(frames),
        s.problem.mount,
        s.problem.knowledge,
        s.problem.options,
    )
    st = build_structure(problem, s.truth.X[0][:3, :3])
    out = refine(problem, st, _perturbed(s.truth, rng))
    assert sorted(c for (_, _, c) in out.outliers) == sorted(det.ids[[5, 17, 40]].tolist())
    assert abs(out.sigma_px / 0.15 - 1.0) < 0.06
    assert abs(out.state.K["cam"][0, 0] - 880.0) < 1.5


def test_wrong_model_shows_high_residual():
    """Distortion ignored on distorted data: the fit cannot reach the noise level."""
    rng = np.random.default_rng(5)
    s = sc.r1(
        rng,
        sigma_px=0.15,
        robot_noise_m=0.0,
        robot_noise_deg=0.0,
        options=ModelOptions(distortion=(False,) * 5),
    )
    st = build_structure(s.problem, s.truth.X[0][:3, :3])
    out = refine(s.problem, st, _perturbed(s.truth, rng), robust=False)
    # 2800 residuals estimate sigma to +-1.3 %: 3 times the injected noise is far outside
    assert out.sigma_px > 3 * 0.15


def test_no_rotations_leaves_hand_eye_translation_unobservable():
    s = sc.s1(30.0, 0.5, np.random.default_rng(6))
    st = build_structure(s.problem)
    assert st.X_t_basis.shape[1] == 0 and "T_tool_cam.t" in st.unobservable
    # one translation direction: the hand-eye rotation about it is a gauge freedom
    assert st.Y_rot_basis.shape[1] == 2 and "T_tool_cam.R" in st.unobservable
    model = BundleModel(s.problem, st)
    _, J = model.evaluate(s.truth)
    sv = np.linalg.svd(J / np.linalg.norm(J, axis=0), compute_uv=False)
    assert sv[-1] / sv[0] > 1e-6  # no gauge freedom left in the parametrisation


# -- the robot's accuracy learned from the data (variance components) --------------------------
def _calibrate(problem):
    from slidecal.solver.calibrate import calibrate

    return calibrate(problem)


def test_exact_poses_are_recognised_and_solved_as_before():
    s = sc.r1(np.random.default_rng(21), 0.15, 0.0, 0.0)
    learned = _calibrate(s.problem)
    fixed = _calibrate(
        sc.r1(
            np.random.default_rng(21), 0.15, 0.0, 0.0, ModelOptions(estimate_robot_noise=False)
        ).problem
    )
    assert learned.robot_accuracy.translation_mm == 0.0
    assert learned.robot_accuracy.rotation_deg == 0.0
    np.testing.assert_allclose(learned.cameras["cam"].K, fixed.cameras["cam"].K, atol=1e-9)
    np.testing.assert_allclose(learned.covariance, fixed.covariance, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize(
    ("noise_m", "noise_deg"),
    [(1e-3, 0.1), (2e-4, 0.02), (5e-5, 0.005)],
    ids=["1mm", "0.2mm", "50um"],
)
def test_robot_noise_levels_are_estimated(noise_m, noise_deg):
    # white pose noise of known size; the options say nothing: 20 frames x 3 axes per level,
    # relative spread of an rms from 60 values ~ 1 / sqrt(120) = 9 %: 30 % is over 3 of those
    s = sc.r1(np.random.default_rng(22), 0.15, noise_m, noise_deg)
    res = _calibrate(s.problem)
    ra = res.robot_accuracy
    assert ra.estimated
    assert ra.translation_mm == pytest.approx(1000 * noise_m, rel=0.3)
    assert ra.rotation_deg == pytest.approx(noise_deg, rel=0.3)
    assert res.sigma_px == pytest.approx(0.15, rel=0.05)
    for name, (a, b) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items():
        err = res.cameras["cam"].K[a, b] - s.truth.K["cam"][a, b]
        assert abs(err) < 3.5 * res.cameras["cam"].std[name], name


def test_user_prior_is_a_start_not_the_truth():
    # the options claim 0.05 mm, the arm errs by 1 mm: the estimate follows the data
    opts = ModelOptions(robot_noise_m=5e-5, robot_noise_deg=0.005)
    s = sc.r1(np.random.default_rng(23), 0.15, 1e-3, 0.05, options=opts)
    ra = _calibrate(s.problem).robot_accuracy
    assert ra.translation_mm == pytest.approx(1.0, rel=0.3)
    assert ra.rotation_deg == pytest.approx(0.05, rel=0.3)


def test_normal_equations_match_the_full_jacobian():
    opts = ModelOptions(robot_noise_m=1e-4, robot_noise_deg=0.01)
    s = sc.r1(np.random.default_rng(24), options=opts)
    model = BundleModel(s.problem, build_structure(s.problem, s.truth.X[0][:3, :3]))
    model.sigma_px = 0.15
    rng = np.random.default_rng(25)
    state = ModelState(
        s.truth.K, s.truth.dist, {}, s.truth.X, s.truth.Y, s.truth.s, rng.normal(0, 1e-4, (20, 6))
    )
    w = rng.uniform(0.5, 1.5, model.n_rows + 120)
    r, J = model.evaluate(state)
    r2, A, g = _normal_equations(model, state, w)
    np.testing.assert_allclose(r2, r, atol=0)
    np.testing.assert_allclose(A, J.T @ (J * w[:, None]), rtol=1e-12, atol=1e-9 * np.abs(A).max())
    np.testing.assert_allclose(g, J.T @ (w * r), rtol=1e-12, atol=1e-9 * np.abs(g).max())


def test_normal_equations_match_the_full_jacobian_with_what_the_groups_share():
    # the tag session's groups, offsets, trends and shared corrections (W): the blocks the solver
    # eliminates against the dense Jacobian, whose shared columns come from their map
    from dataclasses import replace

    from slidecal.solver import model as md
    from slidecal.solver import refine as rf

    s = sc.tag_real_arm(np.random.default_rng(28), n_frames=100)
    T = np.stack([f.T_base_tool for f in s.problem.frames])
    groups = md.orientation_groups(T)
    tg, tc, dims = rf.translation_trends(T, groups)
    common, rot, spread = rf.common_trend(T, tg, dims)
    assert common is not None and int(rot.sum()) == 9 and len(rot) == 27
    st = replace(
        build_structure(s.problem, s.truth.X[0][:3, :3]),
        T_meas=T,
        pose_sigma=(2e-4, 3e-4),
        pose_groups=groups,
        group_sigma=(3e-4, 4e-4),
        trend_groups=tg,
        trend_coords=tc,
        trend_dims=dims,
        trend_sigma=(1e-3, 2e-3),
        common_map=common,
        common_rotation=rot,
        common_sigma=(5e-4, 1e-3),
        common_spread=spread,
    )
    model = BundleModel(s.problem, st)
    model.sigma_px = 0.1
    rng = np.random.default_rng(29)
    F = len(s.problem.frames)
    state = model.with_corrections(
        ModelState(s.truth.K, s.truth.dist, {}, s.truth.X, s.truth.Y, s.truth.s)
    )
    assert state.U.shape == (len(np.unique(groups)), 6) and len(state.W) == len(rot)
    state = replace(state, E=rng.normal(0, 1e-4, (F, 6)), W=rng.normal(0, 1e-4, len(rot)))
    n_prior = sum(sl.stop - sl.start for k, sl in model.slices.items() if k in "UVWE")
    w = rng.uniform(0.5, 1.5, model.n_rows + n_prior)
    r, J = model.evaluate(state)
    r2, A, g = _normal_equations(model, state, w)
    np.testing.assert_allclose(r2, r, atol=0)
    np.testing.assert_allclose(A, J.T @ (J * w[:, None]), rtol=1e-10, atol=1e-9 * np.abs(A).max())
    np.testing.assert_allclose(g, J.T @ (w * r), rtol=1e-10, atol=1e-9 * np.abs(g).max())


def test_orientation_groups_get_a_shared_correction_with_its_own_level():
    # a real arm: R1's four tilt groups see different constant orientation errors; the
    # between-group level is estimated apart from the within-group scatter
    from slidecal.solver import refine as rf

    s = sc.r1_real_arm(np.random.default_rng(26))
    st = build_structure(s.problem, s.truth.X[0][:3, :3])
    out = rf.refine(s.problem, st, _perturbed(s.truth, np.random.default_rng(27), k_px=2.0))
    assert (
        "U" in out.model.slices and out.model.slices["U"].stop - out.model.slices["U"].start == 24
    )
    within, between = out.model.pose_sigma, out.model.group_sigma
    # wrists 25 deg apart err differently: a between-group level of the arm's size, not the floor
    assert np.degrees(between[0]) > 0.005
    assert np.degrees(np.hypot(within[0], between[0])) < 0.2
    # the reported accuracy: the three parts (frames, groups, trends along the moves) together,
    # the groups' as their corrections say it (their level's prior pulls it toward the
    # frames' own); 20 frames are too few for corrections the groups share (common_trend)
    assert "W" not in out.model.slices
    c = out.model.st.trend_coords
    trend = np.sqrt(np.mean(np.sum(c**2, axis=1))) * np.asarray(out.model.trend_sigma)
    data = np.asarray(out.model.group_sigma_data)
    np.testing.assert_allclose(
        out.robot_sigma, np.sqrt(np.square(within) + np.square(data) + trend**2), rtol=1e-12
    )


def test_groups_level_does_not_fall_to_zero_where_few_dof_see_it():
    # R1 on a real arm, seed 2010: four groups tell their offsets from the hand-eye on about
    # four degrees of freedom per kind; alone the groups' level fell to zero and stayed there
    # (redundancy 0), the frames' corrections taken as independent, and the hand-eye's z came
    # out 5.5 std off the effective truth (fx 3.5). Under its prior at the frames' own level
    # it stays of the arm's size and z is 3.2 std off: 4 is beyond that, below the collapse
    from slidecal.solver import model as md

    models = []
    orig = md.BundleModel.__init__

    def spy(self, *a, **k):  # noqa: ANN001, ANN002, ANN003, ANN202
        orig(self, *a, **k)
        models.append(self)

    s = sc.r1_real_arm(np.random.default_rng(2010), sigma_px=0.15, arm_mm=1.0, arm_deg=0.1)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(md.BundleModel, "__init__", spy)
        res = _calibrate(s.problem)
    m = models[-1]
    assert m.level_redundancy["U"][1] > 1.0
    assert m.group_sigma[1] > 0.3 * m.pose_sigma[1]
    ra = res.robot_accuracy
    gone = {f for f, _, _ in ra.left_out}
    used = [i for i, f in enumerate(s.problem.frames) if f.id not in gone]
    T_eff, _ = sc.effective_truth(s, ra.rotation_deg, ra.translation_mm, used)
    d, C = hand_eye_errors(res, T_eff)["t"]
    assert abs(d[2]) < 4.0 * np.sqrt(C[2, 2])


def test_no_group_correction_without_groups_of_several_frames():
    from slidecal.solver.refine import _shared_groups

    assert _shared_groups(np.array([0, 0, 1, 1, 1]))
    assert not _shared_groups(np.array([0, 0, 0]))  # one group: the hand-eye's gauge
    assert not _shared_groups(np.arange(6))  # classic hand-eye: every orientation differs
    assert not _shared_groups(np.array([0, 0, 1, 2, 2]))


def _trend_model(s, pose_sigma=(1e-4, 1e-4)):  # noqa: ANN001, ANN202 - a scenario
    """The model of a real-arm structure with frame, group and trend corrections."""
    from dataclasses import replace

    from slidecal.solver import model as md
    from slidecal.solver import refine as rf

    T = np.stack([f.T_base_tool for f in s.problem.frames])
    groups = md.orientation_groups(T)
    trend_groups, coords, dims = rf.translation_trends(T, groups)
    st = replace(
        build_structure(s.problem, s.truth.X[0][:3, :3]),
        T_meas=T,
        pose_sigma=pose_sigma,
        pose_groups=groups if rf._shared_groups(groups) else None,
        group_sigma=pose_sigma,
        trend_groups=trend_groups,
        trend_coords=coords,
        trend_dims=dims,
        trend_sigma=(1e-2, 1e-3),
    )
    model = BundleModel(s.problem, st)
    model.sigma_px = 0.15
    return model


def _truth_with_corrections(s, model, rng, sigma, sigma_trend):  # noqa: ANN001, ANN202
    """The scenario's true state with random pose corrections of ``sigma`` (frames, groups)
    and ``sigma_trend`` (trends) in ``model``'s blocks; and the number of groups."""
    su = model.slices.get("U", slice(0, 0))
    n_u = (su.stop - su.start) // 6
    sv = model.slices["V"]
    state = ModelState(
        s.truth.K,
        s.truth.dist,
        {},
        s.truth.X,
        s.truth.Y,
        s.truth.s,
        rng.normal(0, sigma, (len(s.problem.frames), 6)),
        rng.normal(0, sigma, (n_u, 6)) if n_u else None,
        rng.normal(0, sigma_trend, sv.stop - sv.start),
    )
    return state, n_u


@pytest.mark.parametrize("translations_only", [False, True])
def test_trend_columns_match_finite_differences(translations_only: bool):
    # the trend block V sits before E; its columns are the pose block times the frame's offset
    s = sc.r1_real_arm(np.random.default_rng(31), translations_only=translations_only)
    model = _trend_model(s)
    assert list(model.slices)[-2:] == ["V", "E"]
    assert model.st.trend_dims == ((3,) if translations_only else (3, 3, 3, 3))
    rng = np.random.default_rng(32)
    sl = model.slices["V"]
    state, n_u = _truth_with_corrections(s, model, rng, 1e-7, 1e-6)
    r, J = model.evaluate(state)
    h = 1e-6
    for i in range(sl.start, sl.stop):
        d = np.zeros(len(model.names))
        d[i] = h
        rp = model.evaluate(model.apply(state, d), jacobian=False)[0]
        rm = model.evaluate(model.apply(state, -d), jacobian=False)[0]
        # the pose block is the derivative at zero correction: exact up to ~1e-7 relative here
        np.testing.assert_allclose(J[:, i], (rp - rm) / (2 * h), atol=1e-5 * np.abs(J[:, i]).max())
    w = rng.uniform(0.5, 1.5, len(r))
    r2, A, g = _normal_equations(model, state, w)
    np.testing.assert_allclose(r2, r, atol=0)
    np.testing.assert_allclose(A, J.T @ (J * w[:, None]), rtol=1e-12, atol=1e-9 * np.abs(A).max())
    np.testing.assert_allclose(g, J.T @ (w * r), rtol=1e-12, atol=1e-9 * np.abs(g).max())
    # the frames' whole corrections: their own, their group's and the trend at their offset
    E = model.pose_corrections(state)
    k = 3
    o = model.trend_offsets[model.st.trend_groups[k]]
    D = state.V[o : o + 18].reshape(6, 3)
    want = state.E[k] + D @ model.st.trend_coords[k]
    if n_u:
        want = want + state.U[model.st.pose_groups[k]]
    np.testing.assert_allclose(E[k], want, rtol=1e-12)


@pytest.mark.parametrize("translations_only", [False, True])
def test_pixel_step_is_the_jacobian_times_the_step(translations_only: bool):
    # the variance-component steps read the pixel residuals of a step to first order from the
    # kept split Jacobian (global columns, the groups' and the trends' corrections through the
    # frames' pose blocks): equal to the whole Jacobian's product
    s = sc.r1_real_arm(np.random.default_rng(33), translations_only=translations_only)
    model = _trend_model(s)
    rng = np.random.default_rng(34)
    state, n_u = _truth_with_corrections(s, model, rng, 1e-5, 1e-5)
    assert ("U" in model.slices) != translations_only
    J = model.evaluate(state)[1][: model.n_rows]
    delta = rng.normal(0, 1e-4, len(model.names)) * np.abs(np.diag(J.T @ J)) ** -0.5
    want = J @ delta
    got = model.pixel_step(state, delta)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())
    # a step along the trends alone is seen (the comparison can fail)
    dv = np.zeros_like(delta)
    dv[model.slices["V"]] = delta[model.slices["V"]]
    assert np.abs(model.pixel_step(state, dv)).max() > 1e-3 * np.abs(want).max()


def test_trend_directions_are_the_ones_a_group_spans():
    from slidecal.solver.refine import translation_trends

    def pose(t):  # noqa: ANN001, ANN202
        return T_from_Rt(np.eye(3), np.asarray(t, float))

    line = [pose([0.1 * k, 0.0, 0.5]) for k in range(4)]  # a line: one direction
    plane = [pose([0.05 * (k % 2), 0.05 * (k // 2), 0.5]) for k in range(4)]  # a plane: two
    pair = [pose([0.0, 0.0, 0.4]), pose([0.05, 0.0, 0.4])]  # two frames: no trend
    still = [pose([0.3, 0.3, 0.3])] * 3  # no spread: no trend
    T = np.stack(line + plane + pair + still)
    groups = np.repeat([0, 1, 2, 3], [4, 4, 2, 3])
    trend_groups, coords, dims = translation_trends(T, groups)
    assert dims == (1, 2)
    np.testing.assert_array_equal(trend_groups, np.repeat([0, 1, -1, -1], [4, 4, 2, 3]))
    # the coordinates are the offsets from the group's mean, in an orthonormal basis
    np.testing.assert_allclose(np.abs(coords[:4, 0]), np.abs([-0.15, -0.05, 0.05, 0.15]))
    np.testing.assert_allclose(np.linalg.norm(coords[4:8], axis=1), np.full(4, 0.025 * np.sqrt(2)))
    assert not np.any(coords[:4, 1:]) and not np.any(coords[8:])
    # a classic hand-eye session (every orientation differs) has no trend
    assert translation_trends(T, np.arange(len(T)))[2] == ()


def test_exact_poses_get_no_trend():
    # a clean cell: the F test keeps the poses exact, no correction of any kind is added
    s = sc.r1(np.random.default_rng(33), 0.15, 0.0, 0.0)
    st = build_structure(s.problem, s.truth.X[0][:3, :3])
    out = refine(s.problem, st, _perturbed(s.truth, np.random.default_rng(34), k_px=2.0))
    assert out.robot_sigma == (0.0, 0.0)
    assert not {"E", "U", "V"} & set(out.model.slices)


def _noisy_model_and_blocks(seed: int, groups: bool):
    """R1 with per-frame pose corrections (and, with ``groups``, the tilt groups' shared ones)
    at a perturbed state: the blocked normal equations and the model."""
    from dataclasses import replace

    from slidecal.solver.model import orientation_groups

    opts = ModelOptions(robot_noise_m=1e-4, robot_noise_deg=0.01)
    s = sc.r1(np.random.default_rng(seed), options=opts)
    st = build_structure(s.problem, s.truth.X[0][:3, :3])
    if groups:
        pg = orientation_groups(np.stack([f.T_base_tool for f in s.problem.frames]))
        st = replace(st, pose_groups=pg, group_sigma=(2e-4, 3e-4))
    model = BundleModel(s.problem, st)
    model.sigma_px = 0.15
    rng = np.random.default_rng(seed + 1)
    n_g = int(st.pose_groups.max()) + 1 if groups else 0
    state = model.with_corrections(_perturbed(s.truth, rng, k_px=2.0))
    assert len(state.E) == 20 and (state.U is None if not n_g else len(state.U) == n_g)
    state = ModelState(
        state.K,
        state.dist,
        {},
        state.X,
        state.Y,
        state.s,
        rng.normal(0, 1e-4, (20, 6)),
        None if state.U is None else rng.normal(0, 1e-4, (n_g, 6)),
    )
    n_rows = len(model.evaluate(state, jacobian=False)[0])
    w = rng.uniform(0.5, 1.5, n_rows)
    return model, state, w


@pytest.mark.parametrize("groups", [False, True], ids=["frames", "frames+groups"])
def test_schur_solve_and_inverse_equal_the_dense_ones(groups):
    # the per-frame correction blocks eliminated by the Schur complement: the damped step, the
    # inverse's blocks VCE and the covariance use, and the hat-matrix traces equal the dense
    # algebra's to round-off (the dense normal matrix is checked against J' W J above)
    model, state, w = _noisy_model_and_blocks(31, groups)
    nb = model.normal_blocks(state, w)
    A, g = _dense(nb)
    P0 = model.slices["E"].start
    assert A.shape == (P0 + 120,) * 2 and ("U" in model.slices) == groups
    for lam in (0.0, 1e-3, 10.0):
        D = np.diag(np.where(np.diag(A) > 0, np.diag(A), 1.0))
        dense = np.linalg.solve(A + lam * D, -g)
        np.testing.assert_allclose(nb.solve(lam), dense, rtol=1e-7, atol=1e-9 * np.abs(dense).max())
    Ni = np.linalg.inv(A)
    inv = nb.inverse()
    tol = dict(rtol=1e-6, atol=1e-8 * np.abs(Ni).max())
    np.testing.assert_allclose(inv.gg, Ni[:P0, :P0], **tol)
    np.testing.assert_allclose(inv.gE.reshape(P0, -1), Ni[:P0, P0:], **tol)
    for k in range(20):
        c = P0 + 6 * k
        np.testing.assert_allclose(inv.EE[k], Ni[c : c + 6, c : c + 6], **tol)
    np.testing.assert_allclose(inv.dense(), Ni, **tol)
    # any rows against any columns (global and frames mixed, a frame's own block included),
    # scaled as a covariance, without the dense matrix
    rng = np.random.default_rng(5)
    rows = np.concatenate([rng.choice(P0, 7, replace=False), P0 + np.array([0, 5, 13, 119])])
    cols = np.concatenate([P0 + np.array([1, 5, 12, 17, 118]), rng.choice(P0, 4, replace=False)])
    np.testing.assert_allclose(
        inv.scaled(0.04).submatrix(rows, cols), 0.04 * Ni[np.ix_(rows, cols)], **tol
    )
    # the inverse times a vector (the variance-component steps' Gauss-Newton step)
    want = Ni @ g
    np.testing.assert_allclose(
        inv.times(nb.g_g, nb.g_E), want, rtol=1e-6, atol=1e-8 * np.abs(want).max()
    )
    # the hat matrix's trace over one camera's rows (here: the pixel rows)
    wc = w.copy()
    wc[model.n_rows :] = 0.0
    Ac = _dense(model.normal_blocks(state, wc))[0]
    assert inv.trace_with(model.normal_blocks(state, wc)) == pytest.approx(
        float(np.sum(Ni * Ac)), rel=1e-8
    )
    # a wrong block (frame 3's coupling altered) is seen: the comparison can fail
    bad = np.array(inv.gE)
    bad[:, 3] *= 1.01
    assert not np.allclose(bad.reshape(P0, -1), Ni[:P0, P0:], **tol)


def test_orientation_groups_match_the_first_founder_rule():
    # the vectorised grouping against the rule it implements, on clusters whose spread
    # straddles the tolerance (0.5 deg): a frame joins the first group whose founding frame
    # it agrees with, else founds a new one
    from slidecal.solver.model import orientation_groups

    rng = np.random.default_rng(41)
    centres = [R_from_rvec(rng.normal(0, 1.0, 3)) for _ in range(5)]
    T = np.tile(np.eye(4), (300, 1, 1))
    for k in range(300):
        T[k, :3, :3] = R_from_rvec(rng.normal(0, np.radians(0.3), 3)) @ centres[k % 5]
    founders, expected = [], []
    for t in T:
        for g, R in enumerate(founders):
            if rotation_angle_deg(t[:3, :3], R) < 0.5:
                expected.append(g)
                break
        else:
            founders.append(t[:3, :3])
            expected.append(len(founders) - 1)
    got = orientation_groups(T)
    assert len(founders) > 5  # the spread made extra groups: the rule is exercised
    np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("noisy", [False, True], ids=["exact poses", "pose corrections"])
def test_rig_normal_equations_match_the_full_jacobian(noisy):
    # three cameras (their Jacobian columns written camera by camera), with and without the
    # per-frame pose corrections accumulated frame by frame: the whole J' W J
    from slidecal.mocks.scenarios import oak_rig
    opts = ModelOptions(robot_noise_m=1e-4, robot_noise_deg=0.01) if noisy else None
    s = oak_rig(np.random.default_rng(42), cameras=("left", "right", "rgb"), options=opts)
    model = BundleModel(s.problem, build_structure(s.problem, s.truth.X[0][:3, :3]))
    model.sigma_px = 0.15
    state = s.truth
    if noisy:
        state = model.with_corrections(state)
    rng = np.random.default_rng(43)
    r, J = model.evaluate(state)
    w = rng.uniform(0.5, 1.5, len(r))
    r2, A, g = _normal_equations(model, state, w)
    assert len(model.cams) == 3 and ("E" in model.slices) == noisy
    np.testing.assert_allclose(r2, r, atol=0)
    np.testing.assert_allclose(A, J.T @ (J * w[:, None]), rtol=1e-12, atol=1e-9 * np.abs(A).max())
    np.testing.assert_allclose(g, J.T @ (w * r), rtol=1e-12, atol=1e-9 * np.abs(g).max())


def test_one_cameras_normal_equations_leave_the_other_rows_out():
    # a camera's share of J' W J (the hat-matrix traces per camera): the rows of the other
    # cameras have zero weight and are left out of the product; the result is the full one's
    from slidecal.mocks.scenarios import oak_rig

    s = oak_rig(np.random.default_rng(44), cameras=("left", "right", "rgb"))
    model = BundleModel(s.problem, build_structure(s.problem, s.truth.X[0][:3, :3]))
    r, J = model.evaluate(s.truth)
    w = np.random.default_rng(45).uniform(0.5, 1.5, len(r))
    w[np.repeat(model.o_cam != 1, 2)] = 0.0  # only the second camera's rows
    assert 0.2 < np.mean(w > 0) < 0.5
    _, A, g = _normal_equations(model, s.truth, w)
    np.testing.assert_allclose(A, J.T @ (J * w[:, None]), rtol=1e-12, atol=1e-9 * np.abs(A).max())
    np.testing.assert_allclose(g, J.T @ (w * r), rtol=1e-12, atol=1e-9 * np.abs(g).max())
    assert np.abs(A[model.slices["intr:left"]]).max() == 0.0  # the first camera: no rows


def test_unit_weights_give_the_weighted_products_exactly():
    # the normal matrix of rows all weighing one skips the weighted copy: the same numbers
    rng = np.random.default_rng(2)
    JT, r = rng.standard_normal((7, 300)), rng.standard_normal(300)
    A, g = BundleModel._weighted_gram(JT, np.ones(300), r)
    Js = JT * np.sqrt(np.ones(300))
    np.testing.assert_array_equal(A, Js @ Js.T)
    np.testing.assert_array_equal(g, Js @ r)
    for step in (3, 10):  # a third of the rows left out (dropped), a tenth (weighed zero)
        w = np.ones(300)
        w[::step] = 0.0
        A, g = BundleModel._weighted_gram(JT, w, r)
        keep = w != 0 if step == 3 else slice(None)
        Js = JT[:, keep] * np.sqrt(w[keep])
        np.testing.assert_array_equal(A, Js @ Js.T)
        np.testing.assert_array_equal(g, Js @ (np.sqrt(w[keep]) * r[keep]))
