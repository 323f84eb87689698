"""Homographies: DLT, LM refinement, joint and constrained group estimates.

docs/METHOD.md Sec. 3."""

import sys
from pathlib import Path

import numpy as np
import pytest

from slidecal.mocks import scenarios as sl
from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.homography import (
    group_homographies,
    homography_dlt,
    homography_rms_px,
    refine_homography,
)

sys.path.insert(0, str(Path(__file__).parent))
import linear_scenes as lg  # noqa: E402


def _unit(H):
    return H / np.linalg.norm(H)


def test_dlt_noise_free_exact_and_sign_convention():
    rng = np.random.default_rng(1)
    for R in (sl.tilt_R(30, 30), sl.tilt_R(-40, 10), sl.D0):
        g = lg.make_group(sl.K_S2, R, sl.centre_on_axis(R), np.zeros((1, 3)), rng)
        H = homography_dlt(*g.observations[0])
        assert np.abs(H - _unit(g.H[0])).max() < 1e-10
        assert H[2, 2] > 0 and abs(np.linalg.norm(H) - 1) < 1e-12
        assert homography_rms_px(H, *g.observations[0]) < 1e-8


def test_refinement_residual_matches_injected_noise():
    rng = np.random.default_rng(2)
    sigma = 0.5
    rms = []
    for _ in range(20):
        g = lg.s2_group(1, rng, sigma)
        b, p = g.observations[0]
        H0 = homography_dlt(b, p)
        H = refine_homography(H0, b, p)
        assert homography_rms_px(H, b, p) <= homography_rms_px(H0, b, p) + 1e-12
        rms.append(homography_rms_px(H, b, p) ** 2)
    n = len(b)
    expected = sigma * np.sqrt(2 * (n - 4) / n)  # 8 dof fitted to 2n coordinates
    assert abs(np.sqrt(np.mean(rms)) / expected - 1) < 0.1


def test_group_homographies_share_h1_h2_and_match_truth():
    rng = np.random.default_rng(3)
    g = lg.s2_group(5, rng)
    Hs = group_homographies(g.observations)
    truth = g.H / np.linalg.norm(g.H[0])
    assert np.abs(Hs - truth).max() < 1e-10
    assert Hs[0, 2, 2] > 0


def test_group_homographies_without_iterations_are_the_rescaled_dlts(monkeypatch):
    # max_iter=0 (the refinement's start): the per-frame DLTs with a common h1, h2, and no
    # residual evaluated for a Levenberg-Marquardt that does not run
    import slidecal.solver.homography as hom

    g = lg.s2_group(5, np.random.default_rng(3))
    monkeypatch.setattr(hom, "_residual_and_jac", None)
    Hs = group_homographies(g.observations, 0)
    truth = g.H / np.linalg.norm(g.H[0])
    assert np.abs(Hs - truth).max() < 1e-10  # noise-free: the DLTs are exact
    assert np.abs(Hs[:, :, :2] - Hs[0, :, :2]).max() < 1e-12


def test_group_homographies_noisy_common_scale_and_residual():
    rng = np.random.default_rng(4)
    sigma = 0.5
    g = lg.s2_group(5, rng, sigma)
    Hs = group_homographies(g.observations)
    assert np.all(Hs[:, :, :2] == Hs[0, :, :2])
    r2 = np.concatenate(
        [[homography_rms_px(H, b, p) ** 2] for H, (b, p) in zip(Hs, g.observations, strict=True)]
    )
    n_coords = 2 * 63 * 5
    expected = sigma * np.sqrt(2 * (n_coords - (6 + 15 - 1)) / n_coords)  # per point, x and y
    assert abs(np.sqrt(r2.mean()) / expected - 1) < 0.1
    # Delta_k = h3_0 - h3_k close to the truth in direction (eqs. 12-13).
    truth = g.H / np.linalg.norm(g.H[0])
    d, dt = Hs[0, :, 2] - Hs[4, :, 2], truth[0, :, 2] - truth[4, :, 2]
    assert np.degrees(np.arccos(d @ dt / np.linalg.norm(d) / np.linalg.norm(dt))) < 2.0


def test_input_errors():
    xy = sl.board_xy()
    with pytest.raises(InputError):
        homography_dlt(xy, xy[:-1])
    with pytest.raises(InputError):
        homography_dlt(xy[:3], xy[:3])
    line = np.column_stack([np.arange(10.0), 2 * np.arange(10.0)])
    with pytest.raises(DegenerateError):
        homography_dlt(line, line * 3)
