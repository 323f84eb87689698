"""The truth side of the simulator: errors of a result against the truth, the Cramer-Rao bounds
of a simulated session, and what a calibrated estimator's normalised errors look like.

Tests and the studies of ``tests/bench/`` measure the solver with these, on the scenes of
:mod:`slidecal.mocks.scenarios`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import binom, chi2, norm

from slidecal.mocks.scenarios import Scenario
from slidecal.solver.geometry import rvec_from_R
from slidecal.solver.model import ModelState, Structure
from slidecal.solver.problem import CalibrationProblem, hand_eye_names
from slidecal.solver.result import NamedCovariance
from slidecal.solver.uncertainty import equal_weight_covariance, predicted_covariance

#: the intrinsics by name: their (row, column) in K
INTRINSICS = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}
P_2SIGMA = float(norm.cdf(2.0) - norm.cdf(-2.0))  # 0.9545
P_3SIGMA = float(norm.cdf(3.0) - norm.cdf(-3.0))  # 0.9973
CHI2_3_2SIGMA = float(chi2.ppf(P_2SIGMA, 3))
CHI2_3_3SIGMA = float(chi2.ppf(P_3SIGMA, 3))
#: A row is miscalibrated when a calibrated Gaussian estimator would give its errors with
#: probability below this (two-sided; the tail test one-sided); the reports' intervals too.
VERDICT_P = 0.01


@dataclass(frozen=True)
class Calibration:
    """What a row's normalised errors say against a calibrated Gaussian estimator: the coverage
    inside 2 and beyond 3 sigma with their binomial ranges, the ``scale`` (rms of error / std per
    degree of freedom) with its chi-square interval, all at the level ``VERDICT_P``, and the
    ``verdict``: "consistent" or what is off."""

    trials: int
    dof: int
    inside_2: int
    inside_2_range: tuple[int, int]
    beyond_3: int
    beyond_3_range: tuple[int, int]
    scale: float
    scale_range: tuple[float, float]
    worst_z: float  # the largest error as a scalar z of the same tail probability
    verdict: str


def _two_sided(cdf_below: float, sf_above: float) -> float:
    return min(1.0, 2.0 * min(cdf_below, sf_above))


def calibration(values: list[float] | np.ndarray, dof: int) -> Calibration:
    """Compare normalised errors ``values`` (error / std, ``dof`` 1, or squared Mahalanobis
    distances, ``dof`` 3) with a calibrated Gaussian estimator (:class:`Calibration`)."""
    v = np.asarray(values, dtype=float)
    n = len(v)
    q = v**2 if dof == 1 else v  # squared distance per trial
    limit_2, limit_3 = (4.0, 9.0) if dof == 1 else (CHI2_3_2SIGMA, CHI2_3_3SIGMA)
    inside = int(np.sum(q <= limit_2))
    beyond = int(np.sum(q > limit_3))
    total = float(np.sum(q))
    nu = dof * n
    scale = float(np.sqrt(total / nu))
    lo, hi = chi2.ppf([1.0 - VERDICT_P / 2.0, VERDICT_P / 2.0], nu)
    scale_range = (float(np.sqrt(total / lo)), float(np.sqrt(total / hi)) if hi > 0 else np.inf)
    p_sum = _two_sided(float(chi2.cdf(total, nu)), float(chi2.sf(total, nu)))
    p_cov = _two_sided(
        float(binom.cdf(inside, n, P_2SIGMA)), float(binom.sf(inside - 1, n, P_2SIGMA))
    )
    p_tail = float(binom.sf(beyond - 1, n, 1.0 - P_3SIGMA)) if beyond else 1.0
    tail_max = float(chi2.sf(q.max(), dof))
    worst = float(norm.isf(tail_max / 2.0))
    lo_s, hi_s = scale_range
    if p_sum < VERDICT_P and scale > 1.0:
        verdict = f"std too small by {scale:.2f} ({lo_s:.2f}-{hi_s:.2f})"
    elif p_sum < VERDICT_P:
        verdict = f"std too large by {1.0 / scale:.2f} ({1.0 / hi_s:.2f}-{1.0 / lo_s:.2f})"
    elif p_cov < VERDICT_P:
        verdict = "coverage off (rms consistent)"
    elif p_tail < VERDICT_P:
        verdict = "heavy tail (rms consistent)"
    else:
        verdict = "consistent"
    return Calibration(
        n,
        dof,
        inside,
        tuple(int(k) for k in binom.interval(1.0 - VERDICT_P, n, P_2SIGMA)),
        beyond,
        tuple(int(k) for k in binom.interval(1.0 - VERDICT_P, n, 1.0 - P_3SIGMA)),
        scale,
        scale_range,
        worst,
        verdict,
    )


def hand_eye_errors(res, T_ref: np.ndarray) -> dict[str, np.ndarray]:  # noqa: ANN001
    """Per block ("rot", "t"): (the reported hand-eye's difference from ``T_ref`` (4, 4) in the
    result's parametrisation: rotation vector on the left, radians; translation, metres) and
    its covariance."""
    out = {}
    named = res.named_covariance
    he = res.hand_eye
    if named is None:
        return out
    C = named.block([f"{he.name}.{a}" for a in ("rx", "ry", "rz")])
    if C is not None:
        out["rot"] = (rvec_from_R(he.R @ T_ref[:3, :3].T), C)
    C = named.block([f"{he.name}.{a}" for a in ("tx", "ty", "tz")])
    if C is not None and he.t_m is not None:
        out["t"] = (he.t_m - T_ref[:3, 3], C)
    return out


def hand_eye_bounds(s: Scenario, sigma_px: float) -> tuple[float, float, float]:
    """Cramer-Rao bounds of the hand-eye rotation (deg, root of the trace), translation (mm)
    and ``fx`` (px) for the scenario's geometry, knowledge and noise model."""
    bound = predicted_covariance(s.problem, s.truth, sigma_px)
    he = hand_eye_names(s.problem.mount, ["cam"])["cam"]
    return bound.std_rot_deg(he), bound.std_t_mm(he), bound.std("cam.fx")


def rig_bounds(
    problem: CalibrationProblem,
    structure: Structure,
    truth: ModelState,
    sigma_by_camera_px: Mapping[str, float],
) -> tuple[NamedCovariance, NamedCovariance]:
    """(the Cramer-Rao bound with per-camera pixel noise ``sigma_by_camera_px``, the sandwich
    covariance of an estimator weighing all pixel rows alike), for the named quantities."""
    sig = dict(sigma_by_camera_px)
    ref = sig[problem.reference]
    crb = predicted_covariance(problem, truth, ref, structure=structure, camera_sigma_px=sig)
    return crb, equal_weight_covariance(problem, truth, sig, structure=structure)


# ------------------------------------------------------------------------------ split halves
def split_halves(
    groups: Sequence[int], rng: np.random.Generator, by_group: bool = False
) -> np.ndarray:
    """A random split of a session's frames into halves: True for half A, per frame. ``groups``:
    each frame's orientation group; half of each group to A, or with ``by_group`` half the groups.
    """
    g = np.asarray(groups)
    in_a = np.zeros(len(g), dtype=bool)
    if by_group:
        names = rng.permutation(np.unique(g))
        n_a = len(names) // 2 + int(len(names) % 2 and rng.random() < 0.5)
        return np.isin(g, names[:n_a])
    for name in np.unique(g):
        idx = rng.permutation(np.flatnonzero(g == name))
        n_a = len(idx) // 2 + int(len(idx) % 2 and rng.random() < 0.5)
        in_a[idx[:n_a]] = True
    return in_a


def halves_z(a: float, std_a: float, b: float, std_b: float) -> float:
    """``(a - b) / sqrt(std_a^2 + std_b^2)``: over random splits its rms is about 1 for an honest
    std."""
    return float((a - b) / np.hypot(std_a, std_b))


def rms(values: Sequence[float]) -> float:
    """The root mean square (NaN for none)."""
    v = np.asarray(values, dtype=float)
    return float(np.sqrt(np.mean(v**2))) if len(v) else float("nan")
