"""mocks/truth.py: what a calibrated Gaussian estimator gives over as many trials (so a study's
coverage and rms tell a miscalibration from sampling noise), the split-half statistics, and the
scenes the studies share (mocks/scenarios.py)."""

from __future__ import annotations

import numpy as np
import pytest

from slidecal.mocks import scenarios as sc
from slidecal.mocks.scenarios import scale_session
from slidecal.mocks.truth import calibration, halves_z, rms, split_halves
from slidecal.solver.camera import project
from slidecal.solver.geometry import R_from_rvec, T_from_Rt


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_calibrated_scalar_errors_are_consistent(seed: int) -> None:
    z = np.random.default_rng(seed).normal(size=400)
    c = calibration(z, 1)
    assert c.verdict == "consistent"
    # the interval is +-9 % at 400 trials: it holds 1 in 99 % of the draws
    assert c.scale_range[0] < 1.05 and c.scale_range[1] > 0.95
    assert c.inside_2_range[0] <= c.inside_2 <= c.inside_2_range[1]
    # 400 x 0.27 % beyond 3 sigma: about one expected, 0 to 4 in 99 % of draws
    assert c.beyond_3_range == (0, 4)


def test_a_std_too_small_by_a_fifth_is_found_and_sized() -> None:
    # reported std 1 / 1.2 of the spread: the verdict says so, the interval holds 1.2
    z = 1.2 * np.random.default_rng(4).normal(size=400)
    c = calibration(z, 1)
    assert c.verdict.startswith("std too small by 1.")
    assert c.scale_range[0] < 1.2 < c.scale_range[1]
    assert c.scale_range[0] > 1.0
    # and a too large one (0.7)
    c = calibration(0.7 * np.random.default_rng(5).normal(size=400), 1)
    assert c.verdict.startswith("std too large by 1.")


def test_thirty_trials_cannot_tell_a_fifth() -> None:
    # the question: 30 trials with rms 1.2 are within sampling noise of 1 (the sum of
    # 30 squares is chi-square(30); its 95 % interval for the scale spans 1)
    z = np.random.default_rng(6).normal(size=30)
    z *= 1.2 / np.sqrt(np.mean(z**2))
    c = calibration(z, 1)
    assert c.verdict == "consistent"
    assert c.scale_range[0] < 1.0


def test_mahalanobis_rows_use_the_chi_square_3_law() -> None:
    rng = np.random.default_rng(7)
    m = np.sum(rng.normal(size=(400, 3)) ** 2, axis=1)  # calibrated 3-vectors
    c = calibration(m, 3)
    assert c.verdict == "consistent"
    assert abs(c.inside_2 / 400 - 0.9545) < 0.03
    # a squared distance of 11.0 (3.32 "sigmas") has the tail of a scalar at 2.52 sigma
    assert calibration([1.0, 11.0, 2.0], 3).worst_z == pytest.approx(2.52, abs=0.01)
    # a 3-vector whose covariance is too small by 1.3 per axis
    big = calibration(1.3**2 * m, 3)
    assert big.verdict.startswith("std too small by")
    assert big.scale == pytest.approx(1.3 * c.scale)


def test_the_rendered_tag_is_found_where_the_points_model_puts_its_corners() -> None:
    # the tag row's image model: the rendered tag's 4 corners, in square_tag's centred frame,
    # where R1's camera projects them (the same ids, well under a pixel)
    T = T_from_Rt(R_from_rvec(np.array([0.3, -0.2, 0.1])), np.array([0.05, -0.04, 0.6]))
    det = sc.render_detector(0.10)(T, np.random.default_rng(0), np.zeros(2))
    np.testing.assert_array_equal(det.ids, [0, 1, 2, 3])
    pts = sc.square_tag(0.10).points_m
    truth = project(sc.R1_K, sc.R1_DIST, pts @ T[:3, :3].T + T[:3, 3])
    assert np.abs(det.px - truth).max() < 0.3


def test_scale_session_has_the_requested_frames_and_cameras():
    p = scale_session(45, 2)
    assert len(p.frames) == 45 and [f.id for f in p.frames] == list(range(45))
    assert {c.name for c in p.cameras} == {"left", "right"}


def test_scale_arm_session_carries_the_arms_error():
    exact, arm = scale_session(25, 1), scale_session(25, 1, arm_error=True)
    assert len(arm.frames) == 25
    assert arm.options.robot_noise_m == 0.0  # the solve is told nothing: it learns the arm
    moved = [
        np.linalg.norm(a.T_base_tool[:3, 3] - e.T_base_tool[:3, 3])
        for a, e in zip(arm.frames, exact.frames, strict=True)
    ]
    assert 0 < np.median(moved) < 0.01  # the measured poses carry the arm's error


def test_split_halves_within_and_by_groups():
    groups = [0] * 5 + [1] * 4 + [2] * 6
    rng = np.random.default_rng(3)
    for _ in range(20):
        a = split_halves(groups, rng)
        for g, n in ((0, 5), (1, 4), (2, 6)):
            k = int(a[np.asarray(groups) == g].sum())
            assert k in (n // 2, n - n // 2)  # half of every group, the odd frame either side
        b = split_halves(groups, rng, by_group=True)
        for g in (0, 1, 2):
            assert len(set(b[np.asarray(groups) == g])) == 1  # whole groups
        assert 0 < b.sum() < len(groups)


def test_halves_z_of_an_honest_std_is_about_one():
    # two independent estimates of one value, each with its std: the rms z over draws is 1
    rng = np.random.default_rng(4)
    std_a, std_b = 0.3, 0.5
    z = [halves_z(rng.normal(0, std_a), std_a, rng.normal(0, std_b), std_b) for _ in range(4000)]
    assert abs(rms(z) - 1.0) < 0.05
    assert halves_z(1.0, 3.0, -3.0, 4.0) == pytest.approx(0.8)
