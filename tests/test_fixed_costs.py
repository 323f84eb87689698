"""The solve's work outside the refinement, done once: the free-pose fit scores every image's
candidate poses together, the final fit serves the adequacy test and the scale checks, the hat
matrix reuses the refinement's inverse, and the start builds its structure once. Against
synthetic ground truth and the direct computation: the same answers."""

import importlib
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from slidecal.mocks import scenarios as sc
from slidecal.solver.calibrate import calibrate, frame_groups, image_poses, scale_checks
from slidecal.solver.camera import K_matrix, project
from slidecal.solver.free_pose import free_pose_fit
from slidecal.solver.geometry import R_from_rvec, T_from_Rt, transform_points

SIGMA_PX = 0.2
pipeline = importlib.import_module("slidecal.solver.calibrate")  # the module, not calibrate()


def _images(rng: np.random.Generator):
    """Two cameras (different intrinsics), 12 views each of the R1 target with SIGMA_PX noise,
    and one image of 3 points; the true ``T_cam_board`` per (frame, camera)."""
    target = sc.r1_target()
    K = {"a": sc.R1_K, "b": K_matrix(600.0, 610.0, 330.0, 250.0)}
    dist = {"a": sc.R1_DIST, "b": np.array([0.05, -0.02, 0.0, 0.0, 0.0])}
    size = {"a": (1280, 800), "b": (640, 480)}
    images, truth = [], {}
    for cam in K:
        for i, T in enumerate(sc.camera_board_poses(rng, 12, target)):
            det = sc.projected_detection(K[cam], dist[cam], T, target, size[cam], SIGMA_PX, rng)
            images.append((i, cam, target.points_m[det.ids], det.px))
            truth[(i, cam)] = T
    images.append((12, "a", target.points_m[:3], np.zeros((3, 2))))
    return images, K, dist, truth


def _flipped(T: np.ndarray) -> np.ndarray:
    """The board turned half a turn about its own x axis: a start in the wrong basin."""
    return T @ T_from_Rt(R_from_rvec([np.pi, 0.0, 0.0]), np.zeros(3))


def test_free_pose_fit_finds_each_images_minimum_whatever_the_start():
    images, K, dist, truth = _images(np.random.default_rng(5))
    fits = [
        free_pose_fit(images, K, dist),
        free_pose_fit(images, K, dist, truth),
        free_pose_fit(images, K, dist, {k: _flipped(T) for k, T in truth.items()}),
    ]
    ref = fits[1]
    assert set(ref.rss) == set(truth)  # the 3-point image is skipped
    for fi, cam, pts, px in images[:-1]:
        key = (fi, cam)
        T = ref.T_cam_board[key]
        # the score is the residual of the pose itself
        e = project(K[cam], dist[cam], transform_points(T, pts)) - px
        assert ref.rss[key] == pytest.approx(float(np.sum(e * e)), rel=1e-12)
        assert ref.rows[key] == 2 * len(pts)
        # near the truth: 70 points at 0.2 px put the board to well under a millimetre
        assert np.linalg.norm(T[:3, 3] - truth[key][:3, 3]) < 1e-3
        for other in (fits[0], fits[2]):  # the same minimum from IPPE or from a wrong start
            assert other.rss[key] == pytest.approx(ref.rss[key], rel=1e-6)
            assert np.allclose(other.T_cam_board[key], T, atol=1e-6)
    for cam in K:  # sqrt(rss / (rows - 6)) estimates the injected noise (1000+ rows: ~3 %)
        assert ref.sigma_px[cam] == pytest.approx(SIGMA_PX, rel=0.1)
        assert ref.sigma_px[cam] == pytest.approx(fits[0].sigma_px[cam], rel=1e-9)


def test_a_start_behind_the_camera_is_ignored():
    images, K, dist, truth = _images(np.random.default_rng(6))
    behind = {k: T_from_Rt(T[:3, :3], -T[:3, 3]) for k, T in truth.items()}
    a, b = free_pose_fit(images, K, dist, behind), free_pose_fit(images, K, dist)
    assert set(a.rss) == set(b.rss) == set(truth)
    for key in truth:
        assert a.rss[key] == pytest.approx(b.rss[key], rel=1e-9)


def test_scale_checks_of_a_learned_arm_take_the_final_fit(monkeypatch):
    # the arm's accuracy learned (R1's default): the adequacy test's free-pose fit at the final
    # intrinsics gives the scale checks their poses; no PnP of the reference camera again
    s = sc.r1(np.random.default_rng(7))
    outs, pnp_runs = [], []
    real_refine, real_poses = pipeline.refine, pipeline._frame_poses

    def spy_refine(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        outs.append(real_refine(*args, **kwargs))
        return outs[-1]

    def spy_poses(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        pnp_runs.append(kwargs.get("only"))
        return real_poses(*args, **kwargs)

    monkeypatch.setattr(pipeline, "refine", spy_refine)
    monkeypatch.setattr(pipeline, "_frame_poses", spy_poses)
    res = calibrate(s.problem)
    out = outs[-1]
    assert res.robot_accuracy.translation_mm > 0.0 and out.free_pose is None
    assert pnp_runs == [None]  # the start's poses only
    monkeypatch.setattr(pipeline, "_frame_poses", real_poses)
    guesses = {i: out.model.T_ref_board(out.state, i) for i in range(len(s.problem.frames))}
    poses = image_poses(s.problem, out.state, guesses)
    fresh = scale_checks(s.problem, out.state, frame_groups(s.problem), poses)
    assert len(fresh) == len(res.scale_checks) > 10
    for a, b in zip(res.scale_checks, fresh, strict=True):
        assert (a.frame_a, a.frame_b, a.robot_mm) == (b.frame_a, b.frame_b, b.robot_mm)
        assert a.camera_mm == pytest.approx(b.camera_mm, abs=1e-6)


def test_the_final_fit_of_a_learned_arm_starts_from_the_robot_tests(monkeypatch):
    # the robot test's fit (exact-pose intrinsics) starts the final fit at the learned-arm
    # intrinsics without the closed form: the same poses and scores as the guarded fit
    from slidecal.solver.adequacy import final_free_pose_fit
    from slidecal.solver.free_pose import model_starts, session_images

    s = sc.r1_real_arm(np.random.default_rng(2001))
    outs = []
    real_refine = pipeline.refine

    def spy_refine(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        outs.append(real_refine(*args, **kwargs))
        return outs[-1]

    monkeypatch.setattr(pipeline, "refine", spy_refine)
    calibrate(s.problem)
    out = outs[-1]
    assert out.free_pose is None and out.test_fit is not None
    ippe = []
    real_pnp = cv2.solvePnP

    def spy_pnp(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        ippe.append(kwargs.get("flags") == cv2.SOLVEPNP_IPPE)
        return real_pnp(*args, **kwargs)

    monkeypatch.setattr(cv2, "solvePnP", spy_pnp)
    fit = final_free_pose_fit(out)
    assert fit.rss and not ippe  # no closed form, nor any PnP: the test's poses refined at once
    monkeypatch.setattr(cv2, "solvePnP", real_pnp)
    images = session_images(out.model, out.inlier_rows)
    guarded = free_pose_fit(images, out.state.K, out.state.dist, model_starts(out.model, out.state))
    assert fit.rss.keys() == guarded.rss.keys()
    for key, rss in guarded.rss.items():
        assert fit.rss[key] == pytest.approx(rss, rel=1e-9)
        np.testing.assert_allclose(fit.T_cam_board[key], guarded.T_cam_board[key], atol=1e-8)


def _spy(monkeypatch, name: str) -> list:
    """Record the positional arguments of every call of the pipeline's ``name``."""
    calls, real = [], getattr(pipeline, name)

    def spy(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        calls.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline, name, spy)
    return calls


def test_the_structure_is_built_once_when_the_hand_eye_rotation_does_not_enter_it(monkeypatch):
    built = _spy(monkeypatch, "build_structure")
    calibrate(sc.r1(np.random.default_rng(7), 0.15, 0.0, 0.0).problem)
    assert len(built) == 1 and len(built[0]) == 1  # rotations about several axes: no R_X


def test_rotations_about_one_axis_get_the_hand_eye_translation_basis_of_the_start():
    # R1's first two tilt groups: every rotation is about one axis, the hand-eye translation
    # along it is unobservable; the refinement's free directions are perpendicular to that axis
    # as the camera sees it (X's rotation of the start), not as the tool sees it
    from dataclasses import replace

    from slidecal.solver.geometry import rvec_from_R

    s = sc.r1(np.random.default_rng(21), 0.15, 0.0, 0.0)
    problem = replace(s.problem, frames=s.problem.frames[:10])
    with pytest.MonkeyPatch.context() as mp:
        refined = _spy(mp, "refine")
        res = calibrate(problem)
    _, structure, init = refined[0]
    T = [f.T_base_tool for f in problem.frames]
    axis = rvec_from_R(T[0][:3, :3].T @ T[9][:3, :3])
    axis_cam = init.X[0][:3, :3] @ (axis / np.linalg.norm(axis))
    assert structure.X_t_basis.shape == (3, 2)
    assert np.abs(structure.X_t_basis.T @ axis_cam).max() < 1e-9
    assert "T_tool_cam.t_along_rotation_axis" in res.unobservable


@pytest.mark.parametrize(
    "make",
    [
        lambda: sc.r1(np.random.default_rng(7)),  # the arm's accuracy learned: priors
        lambda: sc.r1(np.random.default_rng(7), 0.15, 0.0, 0.0),  # exact poses: no priors
        lambda: sc.oak_rig(np.random.default_rng(3), robot_noise_m=3e-4, robot_noise_deg=0.02),
    ],
)
def test_the_hat_matrix_counts_every_row_of_the_model(make, monkeypatch):
    from slidecal.solver import adequacy

    outs = _spy(monkeypatch, "assess")
    res = calibrate(make().problem)
    out = outs[0][1]
    n_all = len(out.model.evaluate(out.state, jacobian=False)[0])  # pixels, then the priors
    sizes = []
    real = out.model.normal_blocks

    def count(state, weights):  # noqa: ANN001, ANN202
        sizes.append(len(weights))
        return real(state, weights)

    monkeypatch.setattr(out.model, "normal_blocks", count)
    used = adequacy._parameters_used(out)
    assert set(sizes) == {n_all}
    assert set(used) == set(res.cameras)
    # the pixels pay for at most every parameter, and for the intrinsics at least
    assert all(9 < u < len(out.names) + 1e-6 for u in used.values())


def _corrupt(problem, rng: np.random.Generator, knowledge_robot: bool = True):
    """``problem`` with 1-3 frames spoilt, each in one of the ways check_problem refuses."""
    from dataclasses import replace

    from slidecal.solver.problem import Detection, Frame

    frames = list(problem.frames)
    for i in rng.choice(len(frames), rng.integers(1, 4), replace=False):
        f = frames[i]
        det = f.detections["cam"]
        ids, px = det.ids.copy(), det.px.copy()
        kind = rng.integers(7 if knowledge_robot else 5)
        dets = dict(f.detections)
        T = f.T_base_tool
        if kind == 0:
            ids[rng.integers(len(ids))] = 10_000
        elif kind == 1:
            ids[rng.integers(len(ids))] = -1
        elif kind == 2:
            px[rng.integers(len(px)), rng.integers(2)] = np.nan
        elif kind == 3:
            ids[1] = ids[0]
        elif kind == 4:
            dets["ghost"] = det
        elif kind == 5:
            T = None
        else:
            T = T.copy()
            T[:3, :3] *= 1.01
        dets["cam"] = Detection(ids, px)
        frames[i] = Frame(f.id, dets, T_base_tool=T)
    return replace(problem, frames=tuple(frames))


def test_a_spoilt_session_is_refused_at_its_first_bad_frame():
    from slidecal.solver.errors import InputError

    base = sc.r1(np.random.default_rng(7)).problem
    rng = np.random.default_rng(0)
    for _ in range(60):
        problem = _corrupt(base, rng)
        pairs = zip(problem.frames, base.frames, strict=True)
        first = min(i for i, (f, g) in enumerate(pairs) if f is not g)
        with pytest.raises(InputError) as got:
            pipeline.check_problem(problem)
        assert f"frames[{first}]" in str(got.value)


def _used_afresh(out) -> dict[str, float]:
    """The hat matrix's trace per camera with the inverse computed from the inlier rows."""
    m = out.model
    n_px = len(out.inlier_rows)
    w = np.ones(n_px + (len(m.names) - m.shared_start if "E" in m.slices else 0))
    w[:n_px] = out.inlier_rows
    Ni = m.normal_blocks(out.state, w).inverse()
    used = {}
    for c in m.cams:
        wc = np.zeros(len(w))
        for ch in m.chunks:
            if ch.camera == c:
                wc[ch.rows] = w[ch.rows]
        used[c] = Ni.trace_with(m.normal_blocks(out.state, wc))
    return used


@pytest.mark.parametrize(
    ("make", "inverted"),
    [
        (lambda: sc.r1(np.random.default_rng(7)), 0),  # one camera, the arm learned
        (lambda: sc.r1(np.random.default_rng(7), 0.15, 0.0, 0.0), 0),  # one camera, exact
        # a rig whose cameras differ in noise: the refinement weighed them, the hat matrix not
        (lambda: sc.oak_rig(np.random.default_rng(3), sigma_px={"left": 0.1, "right": 0.3}), 1),
    ],
)
def test_the_hat_matrix_reuses_the_refinements_inverse_when_the_weights_agree(
    make, inverted, monkeypatch
):
    from slidecal.solver import adequacy
    from slidecal.solver.model import NormalBlocks

    outs = _spy(monkeypatch, "assess")
    calibrate(make().problem)
    out = outs[0][1]
    expected = _used_afresh(out)
    calls = []
    real = NormalBlocks.inverse

    def count(self, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        calls.append(1)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(NormalBlocks, "inverse", count)
    used = adequacy._parameters_used(out)
    assert len(calls) == inverted
    for c, u in expected.items():
        assert used[c] == pytest.approx(u, rel=1e-9)


def test_the_focal_sweep_shares_one_structure_between_its_candidates(monkeypatch):
    # a 4 cm tag with 1 px noise (Zhang's closed form fails): 18 focal lengths compete through
    # the robot poses, each with its own PnP poses and hand-eye start but the same structure
    sys.path.insert(0, str(Path(__file__).parent))
    from test_classic_handeye import _small_tag_session

    s = _small_tag_session(1, (5.0, 25.0))
    built = _spy(monkeypatch, "build_structure")
    res = calibrate(s.problem)
    assert any("focal length that fits the images best" in m for m in res.messages)
    assert len(built) == 2  # the sweep's (poses taken as exact) and the solve's
    assert res.converged
    assert res.cameras["cam"].K[0, 0] == pytest.approx(s.truth.K["cam"][0, 0], rel=0.05)
