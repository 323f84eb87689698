"""The reality benchmark's calibration expectations: what a calibrated Gaussian estimator gives
over as many trials, so a row's coverage and rms tell a miscalibration from sampling noise."""

from __future__ import annotations

import numpy as np
import pytest

from slidecal.routines.bench_reality import RealityRow, calibration, reality_table


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


def test_table_shows_expected_ranges_and_verdicts() -> None:
    rng = np.random.default_rng(8)
    row = RealityRow(
        "cell", {"fx": list(1.3 * rng.normal(size=200)), "cx": list(rng.normal(size=200))}
    )
    row.maha["rot"] = list(np.sum(rng.normal(size=(200, 3)) ** 2, axis=1))
    lines = reality_table([row])
    fx = next(line for line in lines if "| fx |" in line)
    assert "(91.5-99.0 %)" in fx and "std too small by" in fx
    cx = next(line for line in lines if "| cx |" in line)
    assert cx.endswith("| consistent |")
    rot = next(line for line in lines if "Mahalanobis" in line)
    assert "as a scalar" in rot


def test_the_rendered_tag_is_found_where_the_points_model_puts_its_corners() -> None:
    # the tag row's image model: the rendered tag's 4 corners, in square_tag's centred frame,
    # where R1's camera projects them (the same ids, well under a pixel)
    from slidecal.mocks import scenarios as sc
    from slidecal.routines.bench_reality import render_tag_detector
    from slidecal.solver.camera import project
    from slidecal.solver.geometry import R_from_rvec, T_from_Rt

    T = T_from_Rt(R_from_rvec(np.array([0.3, -0.2, 0.1])), np.array([0.05, -0.04, 0.6]))
    det = render_tag_detector(0.10)(T, np.random.default_rng(0), np.zeros(2))
    np.testing.assert_array_equal(det.ids, [0, 1, 2, 3])
    pts = sc.square_tag(0.10).points_m
    truth = project(sc.R1_K, sc.R1_DIST, pts @ T[:3, :3].T + T[:3, 3])
    assert np.abs(det.px - truth).max() < 0.3
