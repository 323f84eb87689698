"""Closed-form intrinsics (docs/METHOD.md Secs. 2-3): every knowledge row, assumptions, groups,
noise."""

import sys
from pathlib import Path

import numpy as np
import pytest

from slidecal.mocks import scenarios as sl
from slidecal.solver.errors import DegenerateError
from slidecal.solver.homography import group_homographies
from slidecal.solver.linear import (
    K_from_w,
    LinearGroup,
    _common_h12,
    image_normalisation,
    linear_intrinsics,
    linear_system,
    solve_null,
    zhang_intrinsics,
    zhang_rows,
)
from tests.helpers import random_rotation

sys.path.insert(0, str(Path(__file__).parent))
import linear_scenes as lg  # noqa: E402

SIZE = sl.PAPER_SIZE_PX


def w_from_K(K):
    """The conic vector (6,) of ``W = K^-T K^-1``, unit norm, ``w11 > 0``: the truth's."""
    Ki = np.linalg.inv(np.asarray(K, dtype=float))
    W = Ki.T @ Ki
    w = np.array([W[0, 0], W[0, 1], W[1, 1], W[0, 2], W[1, 2], W[2, 2]])
    return w / np.linalg.norm(w)


def _rel(K, K_true):
    return np.abs(K - K_true).max() / K_true[0, 0]


def _normal_dirs(n):
    d = np.tile([0.0, 0.0, -1.0], (n, 1))
    d[0] = 0.0
    return d


def signed_lengths(K, H, directions):
    """Case 2 step lengths (n,) given ``K``: the camera displacement ``K^-1 Delta / lambda``
    along ``R n`` (eqs. 12-13)."""
    H = _common_h12(H)
    Ki = np.linalg.inv(K)
    m1, m2 = Ki @ H[0][:, 0], Ki @ H[0][:, 1]
    lam = np.sqrt(0.5 * (m1 @ m1 + m2 @ m2))
    R = np.column_stack([m1 / lam, m2 / lam, np.cross(m1, m2) / lam**2])
    out = np.zeros(len(H))
    for k in range(1, len(H)):
        n = directions[k] / np.linalg.norm(directions[k])
        out[k] = (R @ n) @ (Ki @ (H[0][:, 2] - H[k][:, 2])) / lam
    return out


def group_scales(groups, knowledge, **options):
    """Each group's ``c = lambda^2`` (``H = lambda K [r1 r2 t]``, the caller's units) from the
    null vector of the linear system, ``w`` taken at the scale of ``K^-T K^-1``."""
    system = linear_system(groups, knowledge, **options)
    x, _ = solve_null(system.A, system.col_scale, system.unknowns)
    m = system.basis.shape[1]
    w = system.basis @ x[:m]
    Kni = np.linalg.inv(K_from_w(w))
    Wt = Kni.T @ Kni
    w_true = np.array([Wt[0, 0], Wt[0, 1], Wt[1, 1], Wt[0, 2], Wt[1, 2], Wt[2, 2]])
    alpha = (w_true @ w) / (w @ w)
    scales = zip(x[m:], system.h_scale, strict=True)
    return [float(alpha * c * s**2 / system.sigma**2) for c, s in scales]


def test_conic_helpers():
    K = lg.K_SKEW
    w = w_from_K(K)
    assert abs(np.linalg.norm(w) - 1) < 1e-12 and w[0] > 0
    assert _rel(K_from_w(w), K) < 1e-12
    assert _rel(K_from_w(-7.0 * w), K) < 1e-12  # sign and scale free
    g = lg.s2_group(1, np.random.default_rng(0), K=K)
    assert np.abs(zhang_rows(g.H[0] / np.linalg.norm(g.H[0])) @ w).max() < 1e-14
    with pytest.raises(DegenerateError, match="not positive definite"):
        K_from_w(np.array([1.0, 0.0, -1.0, 0.0, 0.0, 1.0]))
    N = image_normalisation(300, 240)
    corners = N @ np.array([[0, 299, 0, 299], [0, 0, 239, 239], [1, 1, 1, 1.0]])
    assert np.allclose(np.abs(corners[:2]), [[149.5 / 270] * 4, [119.5 / 270] * 4])


def test_case1_lengths_noise_free():
    rng = np.random.default_rng(1)
    for theta in (10.0, 30.0, 60.0):
        g = lg.s1_group(theta, 5, rng)
        grp = LinearGroup(group_homographies(g.observations), g.T_board)
        sol = linear_intrinsics([grp], "lengths", unit_aspect=True, image_size=SIZE)
        assert _rel(sol.K, sl.K_S1) < 1e-6
    # fx != fy (zero skew only): one direction gives 3 constraints for 4 unknowns, two suffice.
    R = sl.tilt_R(30, 30)
    T = np.array([[0, 0, 0], [0, 0, -5], [0, 0, -10], [4, 0, -3], [8, 0, -6.0]])
    g = lg.make_group(sl.K_S2, R, sl.centre_on_axis(R), T, rng)
    grp = LinearGroup(group_homographies(g.observations), T)
    assert _rel(linear_intrinsics([grp], "lengths", image_size=SIZE).K, sl.K_S2) < 1e-6


def test_case2_direction_noise_free_recovers_lengths_and_scale():
    rng = np.random.default_rng(2)
    g = lg.s2_group(5, rng)
    Hs = group_homographies(g.observations)
    sol = linear_intrinsics([LinearGroup(Hs, _normal_dirs(5))], "board_direction", image_size=SIZE)
    assert _rel(sol.K, sl.K_S2) < 1e-6
    lengths = signed_lengths(sol.K, Hs, _normal_dirs(5))
    assert np.allclose(lengths, np.arange(5) * 5.0, rtol=1e-6, atol=1e-6)
    lam = 1.0 / np.linalg.norm(g.H[0])  # Hs = g.H * lam and g.H = K [r1 r2 t]
    scale = group_scales([LinearGroup(Hs, _normal_dirs(5))], "board_direction", image_size=SIZE)
    assert abs(scale[0] / lam**2 - 1) < 1e-6
    # A direction with in-plane components (rows with n_x, n_y != 0) and unit aspect.
    R = sl.tilt_R(30, 30)
    d = np.array([0.3, -0.2, -1.0])
    g = lg.make_group(sl.K_S1, R, sl.centre_on_axis(R), lg.line_steps(d, 4), rng)
    dirs = np.tile(d / np.linalg.norm(d), (4, 1))
    dirs[0] = 0
    Hs = group_homographies(g.observations)
    sol = linear_intrinsics(
        [LinearGroup(Hs, dirs)], "board_direction", unit_aspect=True, image_size=SIZE
    )
    assert _rel(sol.K, sl.K_S1) < 1e-6
    assert np.allclose(signed_lengths(sol.K, Hs, dirs), np.arange(4) * 5.0, atol=1e-6)


def test_case3_full_translation_all_five_intrinsics():
    rng = np.random.default_rng(3)
    g = lg.s2_group(5, rng, K=lg.K_SKEW)
    grp = LinearGroup(group_homographies(g.observations), g.T_board)
    sol = linear_intrinsics([grp], "board_translation", skew=True, image_size=SIZE)
    assert _rel(sol.K, lg.K_SKEW) < 1e-6
    assert sol.unknowns[:6] == ("w11", "w12", "w22", "w13", "w23", "w33")


def test_robot_frame_single_tilt_three_directions():
    rng = np.random.default_rng(4)
    R = sl.tilt_R(30, 30)
    T = np.array([[0, 0, 0], [0, 0, -10], [8, 0, -6], [0, 8, -6], [5, 5, -5.0]])
    g = lg.make_group(lg.K_SKEW, R, sl.centre_on_axis(R), T, rng)
    R_robot_board = random_rotation(rng)
    grp = LinearGroup(group_homographies(g.observations), T @ R_robot_board.T)
    sol = linear_intrinsics([grp], "robot", skew=True, image_size=SIZE)
    assert _rel(sol.K, lg.K_SKEW) < 1e-6
    # Fronto-parallel board: still fine with three non-coplanar directions.
    g = lg.make_group(lg.K_SKEW, sl.D0, sl.centre_on_axis(sl.D0), T, rng)
    grp = LinearGroup(group_homographies(g.observations), T @ R_robot_board.T)
    assert _rel(linear_intrinsics([grp], "robot", skew=True, image_size=SIZE).K, lg.K_SKEW) < 1e-6


@pytest.mark.parametrize("knowledge", ["robot", "lengths", "board_direction", "board_translation"])
def test_multi_group_noise_free(knowledge):
    rng = np.random.default_rng(5)
    groups = []
    for ax, ay, d in ((30, 30, [0, 0, -1.0]), (-25, 10, [0.2, 0.1, -1]), (5, -35, [0, -0.3, -1])):
        R = sl.tilt_R(ax, ay)
        g = lg.make_group(lg.K_SKEW, R, sl.centre_on_axis(R), lg.line_steps(d, 3), rng)
        motion = g.T_board.copy()
        if knowledge == "robot":
            motion = motion @ random_rotation(rng).T  # each group its own robot-board rotation
        if knowledge == "board_direction":
            motion[1:] /= np.linalg.norm(motion[1:], axis=1, keepdims=True)
        groups.append(LinearGroup(group_homographies(g.observations), motion))
    sol = linear_intrinsics(groups, knowledge, skew=True, image_size=SIZE)
    assert _rel(sol.K, lg.K_SKEW) < 1e-6
    assert sum(n.startswith("c") for n in sol.unknowns) == 3  # one scale per group


def test_zhang_alone():
    rng = np.random.default_rng(6)
    Hs = []
    for ax, ay in ((30, 0), (0, 30), (20, -25)):
        R = sl.tilt_R(ax, ay)
        g = lg.make_group(lg.K_SKEW, R, sl.centre_on_axis(R), np.zeros((1, 3)), rng)
        Hs.append(group_homographies(g.observations)[0])
    assert _rel(zhang_intrinsics(np.array(Hs), skew=True, image_size=SIZE), lg.K_SKEW) < 1e-6
    assert _rel(zhang_intrinsics(np.array(Hs[:2]), image_size=SIZE)[:, 1:], lg.K_SKEW[:, 1:]) > 0
    K0 = sl.K_S2
    Hs2 = [
        lg.H_true(K0, sl.tilt_R(a, b), sl.centre_on_axis(sl.tilt_R(a, b)))
        for a, b in ((30, 0), (0, 30))
    ]
    assert _rel(zhang_intrinsics(np.array(Hs2), image_size=SIZE), K0) < 1e-6
    with pytest.raises(DegenerateError):
        zhang_intrinsics(np.array(Hs[:1]), skew=True, image_size=SIZE)


def _s2_fx_errors(trials, sigma, n, rng, condition=True):
    err = []
    for _ in range(trials):
        g = lg.s2_group(n, rng, sigma)
        grp = LinearGroup(group_homographies(g.observations), _normal_dirs(n))
        sol = linear_intrinsics([grp], "board_direction", image_size=SIZE, condition=condition)
        err.append(sol.K[0, 0] - sl.K_S2[0, 0])
    return np.array(err)


def test_s2_monte_carlo_against_reference():
    # docs/SETUPS.md: linear fx bias +3.5, std 5.6 px (5 images, sigma 0.5); Cramer-Rao 2.3 px.
    e = _s2_fx_errors(40, 0.5, 5, np.random.default_rng(7))
    std = e.std(ddof=1)
    assert 2.3 * 0.9 < std < 5.6 * 1.5
    assert abs(e.mean()) < 5.0


def test_conditioning_matters():
    # docs/METHOD.md "Numerical conditioning": the naive solve (pixels, board units, raw rows) is an
    # order of magnitude worse than the conditioned one (S3, all five intrinsics, 0.01 px).
    errs = {}
    for condition in (True, False):
        rng = np.random.default_rng(8)
        e = []
        for _ in range(5):
            g = lg.s2_group(5, rng, 0.01, K=lg.K_SKEW)
            grp = LinearGroup(group_homographies(g.observations), g.T_board)
            K = linear_intrinsics(
                [grp], "board_translation", skew=True, image_size=SIZE, condition=condition
            ).K
            e.append(_rel(K, lg.K_SKEW))
        errs[condition] = max(e)
    assert errs[True] < 1e-3
    assert errs[False] > 5 * errs[True]


def test_row_weighting_noise_beats_unit_rows():
    # Rows divided by their noise scale (default) against unit-norm rows: same data, S2.
    std = {}
    for rw in ("noise", "unit"):
        rng = np.random.default_rng(9)
        e = []
        for _ in range(30):
            g = lg.s2_group(5, rng, 0.5)
            grp = LinearGroup(group_homographies(g.observations), _normal_dirs(5))
            sol = linear_intrinsics([grp], "board_direction", image_size=SIZE, row_weighting=rw)
            e.append(sol.K[0, 0] - 400.0)
        std[rw] = np.std(e)
    assert std["noise"] < std["unit"]


@pytest.mark.parametrize("knowledge", ["robot", "board_translation"])
@pytest.mark.parametrize(
    ("skew", "unit_aspect", "K_true"),
    [
        (True, False, lg.K_SKEW),
        (False, False, sl.K_S2),
        (False, True, sl.K_S1),
        (True, True, sl.K_S1),
    ],
)
def test_assumption_options_noise_free(knowledge, skew, unit_aspect, K_true):
    rng = np.random.default_rng(10)
    R = sl.tilt_R(25, -20)
    T = np.array([[0, 0, 0], [0, 0, -10], [8, 0, -6], [0, 8, -6], [5, 5, -5.0]])
    g = lg.make_group(K_true, R, sl.centre_on_axis(R), T, rng)
    motion = T @ random_rotation(rng).T if knowledge == "robot" else T
    grp = LinearGroup(group_homographies(g.observations), motion)
    sol = linear_intrinsics([grp], knowledge, skew=skew, unit_aspect=unit_aspect, image_size=SIZE)
    assert _rel(sol.K, K_true) < 1e-6
    assert len(sol.unknowns) == sol.singular_values.size


def _big_robot_group(n, rel_noise, rng):
    """One orientation, ``n`` random translations; the true homographies with relative noise
    ``rel_noise`` on every entry (fast; the pairing is compared on the same data)."""
    R = sl.tilt_R(30, 30)
    T = np.concatenate([np.zeros((1, 3)), rng.uniform(-8, 8, (n - 1, 3)) + [0, 0, -6]])
    g = lg.make_group(sl.K_S2, R, sl.centre_on_axis(R), T, rng, xy=sl.board_xy(2, 2))
    return LinearGroup(g.H * (1.0 + rel_noise * rng.normal(size=g.H.shape)), T)


def test_robot_pairs_grow_like_the_frames_and_keep_the_accuracy(monkeypatch):
    from slidecal.solver import linear

    k, j = linear.robot_pairs(10)  # small groups: every pair, as before
    assert len(k) == 55 and np.all(j <= k)
    k, j = linear.robot_pairs(400)
    assert len(k) <= 21 * 400 and np.all(j <= k) and np.all(np.isin(np.arange(400), k[k == j]))
    assert len(set(zip(k.tolist(), j.tolist(), strict=True))) == len(k)  # no pair twice
    rng = np.random.default_rng(40)
    grp = _big_robot_group(60, 0.0, rng)
    assert _rel(linear_intrinsics([grp], "robot", image_size=SIZE).K, sl.K_S2) < 1e-6
    # 100 translations, 1e-3 relative noise, 40 trials: the partners' fx error against every
    # pair's (same data); the rms of 40 errors spreads ~11 %, so 1.3 is a real loss
    errs = {"partners": [], "all": []}
    for _ in range(40):
        grp = _big_robot_group(100, 1e-3, rng)
        for name in errs:
            if name == "all":
                monkeypatch.setattr(linear, "robot_pairs", np.tril_indices)
            K = linear_intrinsics([grp], "robot", image_size=SIZE).K
            monkeypatch.undo()
            errs[name].append(K[0, 0] - sl.K_S2[0, 0])
    rms = {n: float(np.sqrt(np.mean(np.square(e)))) for n, e in errs.items()}
    assert rms["partners"] < 1.3 * rms["all"], rms
