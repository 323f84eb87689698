"""Stereo head: infinite homography, joint linear calibration, relative rotation.

docs/METHOD.md Sec. 8.

Ground truth is the S5 set-up of docs/SETUPS.md (``slidecal.mocks.scenarios.s5_scene``).
"""

from __future__ import annotations

import numpy as np
import pytest

from slidecal.mocks.scenarios import PAPER_SIZE_PX, s5_scene
from slidecal.solver.errors import DegenerateError
from slidecal.solver.geometry import R_from_rvec, rotation_angle_deg
from slidecal.solver.stereo import (
    conic_transfer_matrix,
    infinite_homography,
    rig_linear_intrinsics,
)
from tests.helpers import relative_rotation
from tests.linear_scenes import estimate_homographies, params_of

SIZES = (PAPER_SIZE_PX, PAPER_SIZE_PX)


def w_from_K(K):
    """The conic vector (6,) of ``W = K^-T K^-1``, unit norm, ``w11 > 0``: the truth's."""
    Ki = np.linalg.inv(np.asarray(K, dtype=float))
    W = Ki.T @ Ki
    w = np.array([W[0, 0], W[0, 1], W[1, 1], W[0, 2], W[1, 2], W[2, 2]])
    return w / np.linalg.norm(w)


@pytest.fixture(scope="module")
def scene():
    return s5_scene()


def _true_H_inf(scene) -> np.ndarray:
    H = scene.K_left @ scene.R_left_right @ np.linalg.inv(scene.K_right)
    return H / np.cbrt(np.linalg.det(H))


@pytest.mark.parametrize("refine", [False, True])
def test_noise_free_recovers_everything(scene, refine):
    H_l, H_r = scene.homographies()
    rng = np.random.default_rng(0)
    # Arbitrary per-view scales and signs: mu must absorb them.
    s_l = rng.uniform(0.1, 10.0, 6) * rng.choice([-1.0, 1.0], 6)
    s_r = rng.uniform(0.1, 10.0, 6)
    H_l, H_r = H_l * s_l[:, None, None], H_r * s_r[:, None, None]
    H_inf, mu = infinite_homography(H_l, H_r, sizes=SIZES, refine=refine)
    assert np.abs(H_inf - _true_H_inf(scene)).max() < 1e-8 * np.abs(H_inf).max()
    for k in range(6):  # eqs. 58-59
        np.testing.assert_allclose(H_l[k][:, :2], mu[k] * H_inf @ H_r[k][:, :2], atol=1e-8 * abs(
            H_l[k]).max())
    K_l, K_r = rig_linear_intrinsics(H_l, H_r, H_inf, skew=True, sizes=SIZES)
    np.testing.assert_allclose(K_l, scene.K_left, atol=1e-8)
    np.testing.assert_allclose(K_r, scene.K_right, atol=1e-8)
    R = relative_rotation(K_l, K_r, H_inf)
    np.testing.assert_allclose(R, scene.R_left_right, atol=1e-8)
    # Any scale and sign of H_inf gives the same rotation (eq. 63).
    np.testing.assert_allclose(relative_rotation(K_l, K_r, -3.0 * H_inf), R, atol=1e-12)


def test_without_image_sizes_and_zero_skew(scene):
    H_l, H_r = scene.homographies()
    H_inf, _ = infinite_homography(H_l, H_r)
    assert np.abs(H_inf - _true_H_inf(scene)).max() < 1e-8 * np.abs(H_inf).max()
    for unit_aspect, pair in ((False, (H_l, H_r)), (True, (H_r, H_r))):
        K_a, K_b = rig_linear_intrinsics(
            *pair, None if unit_aspect else H_inf, unit_aspect=unit_aspect, sizes=SIZES
        )
        K_true_a = scene.K_right if unit_aspect else scene.K_left
        np.testing.assert_allclose(K_a, K_true_a, atol=1e-8)
        np.testing.assert_allclose(K_b, scene.K_right, atol=1e-8)


def test_eq62_identity(scene):
    """w_right ~ H_inf' w_left H_inf (eq. 62), in the conic-vector form used by the solver."""
    H_inf = _true_H_inf(scene)
    w_l, w_r = w_from_K(scene.K_left), w_from_K(scene.K_right)
    v = conic_transfer_matrix(H_inf) @ w_l
    scale = (v @ w_r) / (w_r @ w_r)
    assert scale > 0
    np.testing.assert_allclose(v, scale * w_r, atol=1e-12 * np.linalg.norm(v))
    # And with the matrices directly.
    Ki_l, Ki_r = np.linalg.inv(scene.K_left), np.linalg.inv(scene.K_right)
    W_l, W_r = Ki_l.T @ Ki_l, Ki_r.T @ Ki_r
    C = H_inf.T @ W_l @ H_inf
    np.testing.assert_allclose(C / C[2, 2], W_r / W_r[2, 2], rtol=1e-10, atol=1e-16)


def test_one_view_is_refused(scene):
    H_l, H_r = scene.homographies()
    with pytest.raises(DegenerateError, match="at least two stereo views"):
        infinite_homography(H_l[:1], H_r[:1], sizes=SIZES)
    with pytest.raises(DegenerateError):
        rig_linear_intrinsics(H_l[:1], H_r[:1], None, skew=True, sizes=SIZES)


def test_parallel_views_are_refused(scene):
    """Pure translations of the head: every view has one orientation (docs/METHOD.md Sec. 7)."""
    shifts_cam = np.array([[0, 0, 0], [10, 0, 0], [0, -8, 5], [3, 4, -12]], float)
    (H_l,), (H_r,) = scene.translated([3], -shifts_cam @ scene.R_right_board[3])
    with pytest.raises(DegenerateError, match="same board orientation"):
        infinite_homography(H_l, H_r, sizes=SIZES)
    with pytest.raises(DegenerateError):
        rig_linear_intrinsics(H_l, H_r, None, skew=True, sizes=SIZES)


def _noisy_trials(scene, sigma_l, sigma_r, trials, seed):
    rng = np.random.default_rng(seed)
    truth = {"l": params_of(scene.K_left), "r": params_of(scene.K_right)}
    err = {k: [] for k in ("sep_l", "sep_r", "joint_l", "joint_r")}
    rot_err_deg = []
    px_l0, px_r0 = scene.pixels()
    for _ in range(trials):
        H_l = estimate_homographies(scene.board_xy, px_l0 + rng.normal(0, sigma_l, px_l0.shape))
        H_r = estimate_homographies(scene.board_xy, px_r0 + rng.normal(0, sigma_r, px_r0.shape))
        H_inf, _ = infinite_homography(H_l, H_r, sizes=SIZES)
        for tag, Hi in (("sep", None), ("joint", H_inf)):
            K_l, K_r = rig_linear_intrinsics(H_l, H_r, Hi, skew=True, sizes=SIZES)
            err[f"{tag}_l"].append(np.abs(params_of(K_l) - truth["l"]) / truth["l"])
            err[f"{tag}_r"].append(np.abs(params_of(K_r) - truth["r"]) / truth["r"])
            if Hi is not None:
                R = relative_rotation(K_l, K_r, Hi)
                rot_err_deg.append(rotation_angle_deg(R, scene.R_left_right))
    return {k: np.mean(v, axis=0) for k, v in err.items()}, np.mean(rot_err_deg)


def test_joint_not_worse_than_separate_with_noise(scene):
    """20 paired trials, left camera at twice the right's noise (the paper's Fig. 9 case).

    Tolerances, measured over 20 seeds of this very test (20 trials each): the mean |relative
    error| of (fx, fy, cx, cy) was at most 2.2% per px of noise, so 3% per px bounds it. The
    comparison is paired (same data for both methods): the ratio joint / separate of the error
    averaged over both cameras ranged 0.89-1.01 (bound 1.05); for the noisier (left) camera
    0.85-0.97 (bound 1.0: joint is better there); for the better camera alone 0.86-1.14
    (bound 1.2: the paper's "hardly affects the right camera"). Mean rotation error at most
    0.33 deg (bound 1 deg).
    """
    sigma_r = 0.4
    err, rot_err_deg = _noisy_trials(scene, 2 * sigma_r, sigma_r, trials=20, seed=7)
    for cam, sigma in (("l", 2 * sigma_r), ("r", sigma_r)):
        assert np.all(err[f"sep_{cam}"] < 0.03 * sigma)
        assert np.all(err[f"joint_{cam}"] < 0.03 * sigma)
    joint = err["joint_l"].mean() + err["joint_r"].mean()
    sep = err["sep_l"].mean() + err["sep_r"].mean()
    assert joint <= 1.05 * sep
    assert err["joint_l"].mean() < err["sep_l"].mean()
    assert err["joint_r"].mean() <= 1.2 * err["sep_r"].mean()
    assert rot_err_deg < 1.0


def test_error_scales_with_noise(scene):
    """Ten times less noise, about ten times less error (linear regime): within a factor 2."""
    hi, _ = _noisy_trials(scene, 0.5, 0.5, trials=8, seed=11)
    lo, _ = _noisy_trials(scene, 0.05, 0.05, trials=8, seed=11)
    ratio = hi["joint_l"].mean() / lo["joint_l"].mean()
    assert 5.0 < ratio < 20.0


def test_relative_rotation_projects_onto_SO3(scene):
    R_true = R_from_rvec(np.radians([3.0, -7.0, 2.0]))
    H = scene.K_left @ R_true @ np.linalg.inv(scene.K_right)
    H_noisy = H * (1.0 + 1e-4 * np.random.default_rng(3).normal(size=(3, 3)))
    R = relative_rotation(scene.K_left, scene.K_right, H_noisy)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    assert rotation_angle_deg(R, R_true) < 0.1


def _translated_groups(scene, views, steps_board, R_robot_board):
    """Groups (one per view) of the head translated by ``steps_board`` (n, 3) board frame, l.u.

    Returns groups of the left camera, of the right camera, and the motions by knowledge.
    """
    gl, gr = scene.translated(views, steps_board)
    norms = np.linalg.norm(steps_board, axis=1, keepdims=True)
    motion = {
        "board_translation": steps_board,
        "board_direction": np.divide(steps_board, norms, out=np.zeros_like(steps_board),
                                     where=norms > 0),
        "lengths": steps_board,
        "robot": steps_board @ R_robot_board,  # T_robot = R_robot_board' ... any fixed rotation
    }
    return gl, gr, motion


@pytest.mark.parametrize(
    ("knowledge", "views", "skew"),
    [
        ("board_translation", [3], True),
        ("robot", [3], True),
        ("lengths", [3], False),
        ("board_direction", [3], False),
        ("robot", [3, 4], True),
        ("lengths", [0, 1, 5], True),
    ],
)
def test_translation_rig_noise_free(scene, knowledge, views, skew):
    from slidecal.solver.linear import LinearGroup
    from slidecal.solver.stereo import rig_linear_intrinsics_translation

    steps = np.array([[0, 0, 0], [0, 0, 5.0], [0, 0, 10.0], [4.0, 0, 8.0], [0, -3.0, 6.0]])
    R_rb = R_from_rvec(np.radians([10.0, -40.0, 70.0]))
    gl, gr, motion = _translated_groups(scene, views, steps, R_rb)
    rng = np.random.default_rng(5)
    groups_l = [LinearGroup(H * rng.uniform(0.5, 2.0), motion[knowledge]) for H in gl]
    groups_r = [LinearGroup(H * rng.uniform(0.5, 2.0)) for H in gr]
    K_l, K_r = rig_linear_intrinsics_translation(
        groups_l, groups_r, knowledge, skew=skew, sizes=SIZES
    )
    np.testing.assert_allclose(K_l, scene.K_left, atol=1e-8)
    np.testing.assert_allclose(K_r, scene.K_right, atol=1e-8)


def test_translation_rig_parallel_to_board_is_refused(scene):
    """Translations parallel to the board plane only add points on it (docs/METHOD.md Sec. 7)."""
    from slidecal.solver.linear import LinearGroup
    from slidecal.solver.stereo import rig_linear_intrinsics_translation

    steps = np.array([[0, 0, 0], [5.0, 0, 0], [0, 5.0, 0], [5.0, 5.0, 0]])
    gl, gr, motion = _translated_groups(scene, [3], steps, np.eye(3))
    with pytest.raises(DegenerateError):
        rig_linear_intrinsics_translation(
            [LinearGroup(gl[0], motion["lengths"])], [LinearGroup(gr[0])], "lengths",
            skew=True, sizes=SIZES,
        )


@pytest.mark.parametrize("row_weighting", ["noise", "unit"])
def test_rig_rows_are_the_linear_methods(scene, row_weighting):
    """Each camera alone is ``linear.zhang_intrinsics`` to the last digit: the rig's rows are
    linear.py's (one basis, normalisation and row weighting)."""
    from slidecal.solver.linear import zhang_intrinsics

    rng = np.random.default_rng(4)
    px_l, px_r = scene.pixels()
    H_l = estimate_homographies(scene.board_xy, px_l + rng.normal(0, 0.5, px_l.shape))
    H_r = estimate_homographies(scene.board_xy, px_r + rng.normal(0, 0.5, px_r.shape))
    K_l, K_r = rig_linear_intrinsics(
        H_l, H_r, None, skew=True, sizes=SIZES, row_weighting=row_weighting
    )
    for K, H in ((K_l, H_l), (K_r, H_r)):
        K1 = zhang_intrinsics(H, skew=True, image_size=PAPER_SIZE_PX, row_weighting=row_weighting)
        np.testing.assert_allclose(K, K1, rtol=1e-12)


def test_translation_rig_noisy_not_worse_than_each_camera_alone(scene):
    """S5's head translated in three orientations, 0.3 px, knowledge "lengths", 20 trials.

    The joint system holds each camera's own rows (``linear.linear_intrinsics``) plus the
    shared translations and eq. 62, so it must not do worse than either camera alone. Measured
    over 8 seeds (paired, same data): joint / alone rms of (fx, fy) 0.85-0.96 per camera; the
    former rig rows (unit-norm, their own conditioning) gave 1.07-1.51. Bound: 1.0.
    """
    from slidecal.solver.homography import group_homographies
    from slidecal.solver.linear import LinearGroup, linear_intrinsics
    from slidecal.solver.stereo import rig_linear_intrinsics_translation

    steps = np.array([[0, 0, 0], [0, 0, 5.0], [0, 0, 10.0], [4.0, 0, 8.0], [0, -3.0, 6.0]])
    gl, gr, motion = _translated_groups(scene, [0, 1, 5], steps, np.eye(3))
    X = np.column_stack([scene.board_xy, np.ones(len(scene.board_xy))])

    def noisy(H, rng):
        u = X @ H.T
        return scene.board_xy, u[:, :2] / u[:, 2:] + rng.normal(0, 0.3, (len(X), 2))

    rng = np.random.default_rng(3)
    err = {"joint": [], "alone": []}
    truth = np.array([np.diag(scene.K_left)[:2], np.diag(scene.K_right)[:2]])
    for _ in range(20):
        groups = [
            [LinearGroup(group_homographies([noisy(H, rng) for H in Hs]), motion["lengths"])
             for Hs in cam]
            for cam in (gl, gr)
        ]
        K_l, K_r = rig_linear_intrinsics_translation(*groups, "lengths", sizes=SIZES)
        err["joint"].append([np.diag(K_l)[:2], np.diag(K_r)[:2]] - truth)
        alone = [linear_intrinsics(g, "lengths", image_size=PAPER_SIZE_PX).K for g in groups]
        err["alone"].append([np.diag(K)[:2] for K in alone] - truth)
    rms = {k: np.sqrt(np.mean(np.square(v), axis=(0, 2))) for k, v in err.items()}
    assert np.all(rms["joint"] <= rms["alone"]), rms


def test_shared_translation_rows_are_every_pair_of_translations():
    # the coupling rows (eqs. 33-42), vectorised over a group's n^2 / 2 pairs, against their
    # definition written pair by pair: h1' W D_k, h2' W D_k, then D_i' W D_k for i <= k
    from slidecal.solver.linear import conic_row
    from slidecal.solver.stereo import _shared_translation_rows

    rng = np.random.default_rng(5)
    Ha, Hb = rng.normal(size=(6, 3, 3)), rng.normal(size=(6, 3, 3))
    f1, f2 = 1.3, 0.7
    rows, noises = _shared_translation_rows(Ha, Hb, f1, f2)
    D = [(Ha[0][:, 2] - Ha[k][:, 2], Hb[0][:, 2] - Hb[k][:, 2]) for k in range(6)]
    want, want_noise = [], []
    for k in range(1, 6):
        pairs = [(Ha[0][:, c], D[k][0], Hb[0][:, c], D[k][1], f1) for c in (0, 1)]
        pairs += [(D[i][0], D[k][0], D[i][1], D[k][1], f2) for i in range(1, k + 1)]
        for a1, b1, a2, b2, fb in pairs:
            want.append(np.concatenate([conic_row(a1, b1), -fb * conic_row(a2, b2)]))
            n = np.linalg.norm
            want_noise.append(n(a1) + n(b1) + fb * (n(a2) + n(b2)))
    assert rows.shape == (5 * 2 + 15, 12)
    np.testing.assert_allclose(rows, want, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(noises, want_noise, rtol=1e-14)
