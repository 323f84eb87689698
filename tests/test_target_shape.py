"""The board's tolerance (solver/target_shape.py): a bowed board's bow estimated and its two
readings carried, what the print leaves uncertain carried, an exact board left alone. Seeded;
tolerances from the noise."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from slidecal.mocks import scenarios as sc
from slidecal.solver.calibrate import calibrate
from slidecal.solver.problem import CalibrationProblem, CameraSpec, Frame, Target
from slidecal.solver.target_shape import default_flatness_m, shape_modes

TARGET = Target.chessboard(12, 9, 0.04)  # a pattern of 0.44 x 0.32 m
SIGMA_PX = 0.1


def _bowed(target: Target, bow_m: tuple[float, float]) -> Target:
    """``target`` with its points bowed (``shape_modes``' two bows, metres)."""
    modes = shape_modes(target, target.points_m)
    return replace(target, points_m=target.points_m + bow_m[0] * modes[3] + bow_m[1] * modes[4])


def _images_only(seed: int, bow_m: tuple[float, float], described: Target) -> CalibrationProblem:
    """16 views of a board bowed by ``bow_m``, R1's camera, no robot; ``described``: the target
    the session names."""
    rng = np.random.default_rng(seed)
    real = _bowed(TARGET, bow_m)
    frames = [
        Frame(
            k,
            {
                "cam": sc.projected_detection(
                    sc.R1_K, sc.R1_DIST, T, real, sc.R1_SIZE_PX, SIGMA_PX, rng, 5.0
                )
            },
        )
        for k, T in enumerate(sc.camera_board_poses(rng, 16, TARGET))
    ]
    return CalibrationProblem(
        described, (CameraSpec("cam", *sc.R1_SIZE_PX),), tuple(frames), "none", "none"
    )


def test_a_bowed_board_is_measured_and_the_focal_length_is_covered():
    # a bow of 0.4 mm moves a flat-board solve's fx beyond 2 of its std (beyond 3 before the
    # solve read its residuals' correlation: the bow moves neighbouring corners alike, and the
    # frames' scores carry part of it, docs/METHOD.md); with the bow estimated
    # (the board's default flatness as prior) the bow comes out within 3 std of the truth, and
    # fx, taken halfway between the readings "the misfit is the board" and "it is not" with
    # their spread in its std, within 3 std of R1's
    bow = (4e-4, -2e-4)
    real = replace(TARGET, flatness_m=default_flatness_m(TARGET.points_m), print_tolerance=0.0)
    flat, fitted = [], []
    for seed in range(3):
        r0 = calibrate(_images_only(seed, bow, TARGET))  # described as exact: flat
        r1 = calibrate(_images_only(seed, bow, real))
        assert r0.board is None
        b = r1.board
        assert b is not None
        for k in range(2):
            assert abs(b.bow_mm[k] - 1000.0 * bow[k]) < 3.0 * b.bow_std_mm[k]
        c0, c1 = r0.cameras["cam"], r1.cameras["cam"]
        flat.append((c0.K[0, 0] - sc.R1_K[0, 0]) / c0.std["fx"])
        fitted.append((c1.K[0, 0] - sc.R1_K[0, 0]) / c1.std["fx"])
    assert min(np.abs(flat)) > 2.0
    assert max(np.abs(fitted)) < 3.0


def test_the_print_tolerance_widens_the_covariance_and_moves_nothing():
    # without a bow to estimate, the print's tolerance adds to the covariance (never removes)
    # and leaves the estimate where it was
    exact = calibrate(_images_only(7, (0.0, 0.0), TARGET))
    printed = calibrate(
        _images_only(7, (0.0, 0.0), replace(TARGET, print_tolerance=1e-3, flatness_m=0.0))
    )
    np.testing.assert_allclose(printed.cameras["cam"].K, exact.cameras["cam"].K, atol=1e-9)
    assert printed.board is not None and printed.board.bow_mm == (0.0, 0.0)
    gain = printed.covariance - exact.covariance
    assert np.linalg.eigvalsh(0.5 * (gain + gain.T)).min() > -1e-9 * np.abs(exact.covariance).max()
    for p in ("fx", "cx", "cy"):
        assert printed.cameras["cam"].std[p] > exact.cameras["cam"].std[p]


@pytest.mark.parametrize("flatness_m", [0.0, 2e-4])
def test_an_exact_board_is_left_alone_and_a_flat_one_barely_moves(flatness_m):
    # an exact board (0, 0) is solved as before; a flat board under a flatness prior gets a bow
    # estimate within 3 std of zero
    r = calibrate(_images_only(11, (0.0, 0.0), replace(TARGET, flatness_m=flatness_m)))
    if flatness_m == 0.0:
        assert r.board is None
    else:
        assert all(
            abs(v) < 3.0 * s for v, s in zip(r.board.bow_mm, r.board.bow_std_mm, strict=True)
        )
