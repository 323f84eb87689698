"""The paired drift test (solver/drift.py) against synthetic ground truth: a camera seeing a
board at the same poses twice, with the noise of a repeatable arm and a detector."""

from __future__ import annotations

import numpy as np
import pytest

from slidecal.mocks import scenarios as sc
from slidecal.routines.results_io import hand_eye_transforms
from slidecal.solver.calibrate import calibrate
from slidecal.solver.drift import (
    MIN_POSES,
    Z_LIMIT,
    chain_rms_px,
    common_corners,
    displacement_field,
    fit_target,
    hand_eye_T,
    match_poses,
)
from slidecal.solver.errors import DegenerateError
from slidecal.solver.geometry import R_from_rvec, T_from_Rt, inv_T
from slidecal.solver.problem import hand_eye_names

K = np.array([[880.0, 0.0, 640.0], [0.0, 880.0, 400.0], [0.0, 0.0, 1.0]])
REGION = (320.0, 200.0, 960.0, 600.0)  # the central half of a 1280 x 800 image
#: the simulated noise: per-corner detector noise and the per-pose shift that the arm's
#: repeatability (0.005 deg, 0.03 mm at 0.5 m) gives, one-sigma per axis, px
CORNER_PX = 0.06
POSE_PX = 0.1


def _board_views(rng: np.random.Generator, n_poses: int) -> list[np.ndarray]:
    """Board corners (11 x 8, 30 mm) in the camera frame at tilted poses about 0.5 m away."""
    g = np.stack(np.meshgrid(np.arange(10) * 0.03, np.arange(7) * 0.03), -1).reshape(-1, 2)
    P = np.hstack([g - g.mean(0), np.zeros((len(g), 1))])
    views = []
    for _ in range(n_poses):
        R = R_from_rvec(rng.normal(0.0, np.radians(15.0), 3))
        t = np.array([*rng.normal(0.0, 0.04, 2), 0.5 + rng.normal(0.0, 0.03)])
        views.append(P @ R.T + t)
    return views


def _project(Pc: np.ndarray, K_: np.ndarray = K) -> np.ndarray:
    uv = Pc[:, :2] / Pc[:, 2:3]
    return uv * [K_[0, 0], K_[1, 1]] + K_[:2, 2]


def _pairs(seed: int, n_poses: int = 6, K_new=K, R_cam=None):  # noqa: ANN001, ANN202
    """(old, new) pixels per pose: the new camera is ``K_new`` turned by ``R_cam``."""
    rng = np.random.default_rng(seed)
    olds, news = [], []
    for Pc in _board_views(rng, n_poses):
        Pn = Pc if R_cam is None else Pc @ R_cam  # the camera turned by R_cam: R_cam^T P
        o = _project(Pc) + rng.normal(0, CORNER_PX, (len(Pc), 2)) + rng.normal(0, POSE_PX, 2)
        n = _project(Pn, K_new) + rng.normal(0, CORNER_PX, (len(Pc), 2))
        olds.append(o)
        news.append(n + rng.normal(0, POSE_PX, 2))
    return olds, news


def test_unchanged_camera_is_not_drifted_over_many_seeds() -> None:
    zs, pxs = [], []
    for seed in range(300):
        f = displacement_field(*_pairs(seed), K, REGION)
        zs.append(f.max_z)
        pxs.append(f.max_px)
        assert not f.drifted(0.5), (seed, f.max_z, f.max_px)
    # the mean field of 6 poses: about POSE_PX * sqrt(2 / 6) per shift component
    assert np.median(pxs) < 4 * POSE_PX * np.sqrt(2 / 6)
    assert np.mean(np.array(zs) > Z_LIMIT) < 0.01


def test_principal_point_shift_is_found_and_named() -> None:
    K1 = K.copy()
    K1[0, 2] += 1.0
    for seed in range(20):
        f = displacement_field(*_pairs(seed, K_new=K1), K, REGION)
        tol = 5 * POSE_PX * np.sqrt(2 / 6)  # five one-sigmas of the mean shift
        assert f.equivalent["cx_px"] == pytest.approx(1.0, abs=tol)
        assert f.equivalent["cy_px"] == pytest.approx(0.0, abs=tol)
        assert f.drifted(0.5) and f.max_z > 10


def test_focal_length_change_is_a_scale() -> None:
    K1 = K.copy()
    K1[:2, :2] *= 1.003
    for seed in range(20):
        f = displacement_field(*_pairs(seed, K_new=K1), K, REGION)
        # the scale at the corners' rms radius (~220 px) carries the per-pose noise too
        assert f.equivalent["f_rel"] == pytest.approx(0.003, abs=5 * f.std_px[2] / f.radius_px)
        assert f.drifted(0.5)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_camera_rotation_is_named_about_its_axis(axis: int) -> None:
    w = np.zeros(3)
    w[axis] = np.radians(0.1)
    name = ("rx_deg", "ry_deg", "rz_deg")[axis]
    f = displacement_field(*_pairs(7, R_cam=R_from_rvec(w)), K, REGION)
    tol = np.degrees(5 * np.sqrt(2 / 6) * POSE_PX / 880.0) + (0.02 if axis == 2 else 0.0)
    assert f.equivalent[name] == pytest.approx(0.1, abs=tol)
    assert f.drifted(0.5)


def test_outlier_corner_is_dropped() -> None:
    olds, news = _pairs(3)
    clean = displacement_field(olds, news, K, REGION)
    news[2] = news[2].copy()
    news[2][5] += [8.0, -6.0]
    f = displacement_field(olds, news, K, REGION)
    assert np.allclose(f.mean_px, clean.mean_px, atol=0.02)


def test_too_few_poses_is_degenerate() -> None:
    olds, news = _pairs(1, n_poses=MIN_POSES - 1)
    with pytest.raises(DegenerateError, match="paired test needs"):
        displacement_field(olds, news, K, REGION)


def test_match_poses_and_common_corners() -> None:
    T = T_from_Rt(R_from_rvec([3.1, 0.0, 0.0]), [-0.4, 0.0, 0.5])
    near = T @ T_from_Rt(R_from_rvec(np.radians([0.02, 0, 0])), [0.0003, 0.0, 0.0])
    far = T @ T_from_Rt(np.eye(3), [0.005, 0.0, 0.0])
    turned = T @ T_from_Rt(R_from_rvec(np.radians([0.5, 0, 0])), [0.0, 0.0, 0.0])
    assert match_poses([near, far, None, turned], [inv_T(T), T]) == [(0, 1)]
    a, b = common_corners(
        np.array([3, 1, 7]), np.eye(3)[:, :2], np.array([7, 3, 9]), np.ones((3, 2))
    )
    assert len(a) == 2 and np.allclose(b, [[1, 0], [0, 0]]) and np.allclose(a, 1.0)


def test_fit_target_explains_the_session_the_calibration_was_made_from():
    # the unpaired check on the installed session itself: the target pose comes back and the
    # residuals stay near the solve's own (the arm's noise adds a little); a rig's cameras
    # take the hand-eye the result file names for them (T_tool_<name>)
    s = sc.r1(np.random.default_rng(3))
    res = calibrate(s.problem)
    Y, per = fit_target(s.problem, res)
    assert np.abs(Y - res.T_target.T).max() < 1e-4
    assert len(per["cam"]) == sum(len(f.detections["cam"].ids) for f in s.problem.frames)
    assert res.reproj_rms_px < chain_rms_px(res, s.problem)["cam"] < 2.0 * res.reproj_rms_px
    rig = calibrate(sc.oak_rig(np.random.default_rng(6)).problem)
    names, he = hand_eye_names(rig.mount, list(rig.cameras)), hand_eye_transforms(rig)
    for c in rig.cameras:
        np.testing.assert_allclose(hand_eye_T(rig, c), he[names[c]].T, atol=1e-15)
