"""Degenerate configurations (docs/METHOD.md Sec. 7) refused, their neighbours accepted."""

import sys
from pathlib import Path

import numpy as np
import pytest

from slidecal.mocks import scenarios as sl
from slidecal.solver.degeneracy import check_configuration
from slidecal.solver.errors import DegenerateError
from slidecal.solver.homography import group_homographies
from slidecal.solver.linear import LinearGroup, linear_intrinsics

sys.path.insert(0, str(Path(__file__).parent))
import linear_scenes as lg  # noqa: E402

SIZE = sl.PAPER_SIZE_PX
NORMAL = lg.line_steps([0.0, 0.0, -1.0], 5)


def _dirs(T):
    d = np.zeros_like(T)
    nz = np.linalg.norm(T, axis=1) > 0
    d[nz] = T[nz] / np.linalg.norm(T[nz], axis=1, keepdims=True)
    return d


def _group(R, T, sigma, rng, K=sl.K_S2, motion=None):
    g = lg.make_group(K, R, sl.centre_on_axis(R), T, rng, sigma)
    return LinearGroup(group_homographies(g.observations), T if motion is None else motion)


@pytest.mark.parametrize("sigma", [0.0, 0.5])
def test_case2_single_axis_tilt_refused_both_axes_accepted(sigma):
    rng = np.random.default_rng(1)
    for ax, ay in ((30, 0), (0, 30)):
        grp = _group(sl.tilt_R(ax, ay), NORMAL, sigma, rng, motion=_dirs(NORMAL))
        with pytest.raises(DegenerateError, match="tilt about both board axes"):
            check_configuration([grp], "board_direction", image_size=SIZE)
    for order in ("xy", "yx"):
        grp = _group(sl.tilt_R(30, 30, order), NORMAL, sigma, rng, motion=_dirs(NORMAL))
        check_configuration([grp], "board_direction", image_size=SIZE)


@pytest.mark.parametrize("sigma", [0.0, 0.5])
def test_case1_fronto_parallel_refused_tilted_accepted(sigma):
    rng = np.random.default_rng(2)
    T = lg.line_steps([0.0, 0.0, -1.0], 5)
    grp = _group(sl.D0, T, sigma, rng, K=sl.K_S1)
    with pytest.raises(DegenerateError, match="tilt the camera by 20-30 deg"):
        check_configuration([grp], "lengths", unit_aspect=True, image_size=SIZE)
    with pytest.raises(DegenerateError, match="tilt the camera by 20-30 deg"):
        check_configuration([grp], "robot", unit_aspect=True, image_size=SIZE)
    g = lg.s1_group(30.0, 5, rng, sigma)
    grp = LinearGroup(group_homographies(g.observations), g.T_board)
    check_configuration([grp], "lengths", unit_aspect=True, image_size=SIZE)


@pytest.mark.parametrize("sigma", [0.0, 0.5])
def test_translations_parallel_to_board_refused(sigma):
    rng = np.random.default_rng(3)
    R = sl.tilt_R(30, 30)
    flat = np.array([[0, 0, 0], [5, 0, 0], [0, 5, 0], [5, 5, 0], [-5, 3, 0.0]])
    grp = _group(R, flat, sigma, rng, K=lg.K_SKEW)
    for knowledge in ("board_translation", "robot", "lengths"):
        with pytest.raises(DegenerateError, match="move along its normal"):
            check_configuration([grp], knowledge, skew=True, image_size=SIZE)
    tilted = flat + np.array([0, 0, -5.0]) * (np.arange(5) > 0)[:, None]
    grp = _group(R, tilted, sigma, rng, K=lg.K_SKEW)
    check_configuration([grp], "board_translation", skew=True, image_size=SIZE)


def test_too_few_frames_and_constraints():
    rng = np.random.default_rng(4)
    R = sl.tilt_R(30, 30)
    grp = _group(R, np.zeros((1, 3)), 0.0, rng)
    with pytest.raises(DegenerateError, match="single frame"):
        check_configuration([grp], "board_translation", image_size=SIZE)
    # Robot knowledge, one translation: 3 + 1 constraints for 5 unknowns with skew.
    grp = _group(R, NORMAL[:2], 0.0, rng)
    with pytest.raises(DegenerateError, match="too few constraints|singular"):
        check_configuration([grp], "robot", skew=True, image_size=SIZE)
    # Case 1 with fx != fy from one direction: enough rows, but rank-deficient.
    grp = _group(R, NORMAL, 0.0, rng)
    with pytest.raises(DegenerateError, match="singular"):
        check_configuration([grp], "lengths", image_size=SIZE)
    with pytest.raises(DegenerateError):
        linear_intrinsics([grp], "lengths", image_size=SIZE)


def test_hand_eye_needs_two_translation_directions():
    rng = np.random.default_rng(5)
    R = sl.tilt_R(30, 30)
    grp = _group(R, NORMAL, 0.0, rng)
    with pytest.raises(DegenerateError, match="colinear"):
        check_configuration([grp], "robot", unit_aspect=True, image_size=SIZE, hand_eye=True)
    T = np.array([[0, 0, 0], [0, 0, -10], [8, 0, -6], [0, 8, -6.0]])
    grp = _group(R, T, 0.0, rng)
    check_configuration([grp], "robot", unit_aspect=True, image_size=SIZE, hand_eye=True)


def test_multiple_orientations_rescue_in_plane_translations():
    # Three orientation groups determine K by Zhang's rows even with in-plane translations.
    rng = np.random.default_rng(6)
    flat = np.array([[0, 0, 0], [5, 0, 0], [0, 5, 0.0]])
    groups = [_group(sl.tilt_R(a, b), flat, 0.0, rng) for a, b in ((30, 0), (0, 30), (20, -25))]
    check_configuration(groups, "board_translation", skew=True, image_size=SIZE)


@pytest.mark.parametrize("knowledge", ["board_direction", "robot"])
def test_the_accepted_system_is_the_one_linear_intrinsics_solves(knowledge):
    """``check_configuration`` returns the system it accepted; solving it gives exactly what
    ``linear_intrinsics`` gives when it builds the system itself (the calibration's linear step
    builds it once)."""
    rng = np.random.default_rng(7)
    motion = _dirs(NORMAL) if knowledge == "board_direction" else NORMAL
    grp = _group(sl.tilt_R(30, 30, "xy"), NORMAL, 0.5, rng, motion=motion)
    grp2 = _group(sl.tilt_R(-25, 20, "yx"), NORMAL, 0.5, rng, motion=motion)
    system = check_configuration([grp, grp2], knowledge, image_size=SIZE)
    fresh = linear_intrinsics([grp, grp2], knowledge, image_size=SIZE)
    reused = linear_intrinsics([grp, grp2], knowledge, image_size=SIZE, system=system)
    np.testing.assert_array_equal(reused.K, fresh.K)
    np.testing.assert_array_equal(reused.singular_values, fresh.singular_values)
