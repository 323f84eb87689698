"""Helpers only the tests and benchmarks use: a random rotation, a stereo head's relative rotation
from its infinite homography, and the maximum-likelihood step linearised at a known state (a
sampling reference beside the Cramer-Rao bound)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slidecal.solver.errors import DegenerateError
from slidecal.solver.geometry import R_from_rvec, project_to_SO3
from slidecal.solver.model import BundleModel, ModelState, Structure, build_structure
from slidecal.solver.problem import CalibrationProblem
from slidecal.solver.uncertainty import _jacobian, layout_of


def random_rotation(rng: np.random.Generator, max_angle_rad: float = np.pi) -> np.ndarray:
    """A random rotation with a uniformly drawn axis and an angle uniform in [0, max_angle_rad]."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return R_from_rvec(axis * rng.uniform(0.0, max_angle_rad))


def relative_rotation(K_a: np.ndarray, K_b: np.ndarray, H_inf: np.ndarray) -> np.ndarray:
    """``R_a_b`` (3, 3) from ``H_inf = K_a R_a_b K_b^-1`` (eq. 63), projected onto SO(3).

    ``K_a``, ``K_b``: (3, 3) intrinsics in pixels; ``H_inf``: (3, 3), any scale, camera b's image
    to camera a's. ``X_a = R_a_b X_b + t_a_b`` for camera-frame coordinates.
    """
    M = np.linalg.solve(np.asarray(K_a, float), np.asarray(H_inf, float) @ np.asarray(K_b, float))
    d = np.linalg.det(M)
    if not np.isfinite(d) or abs(d) < 1e-300:
        raise DegenerateError("relative_rotation: K_a^-1 H_inf K_b is singular; check H_inf")
    return project_to_SO3(M / (np.sign(d) * abs(d) ** (1.0 / 3.0)))


@dataclass(frozen=True)
class LinearisedEstimator:
    """``-(J'J)^-1 J' r`` at a known state, in the named quantities: exactly efficient by
    construction, so its spread over the same noise draws tells how far from the bound a
    perfect estimator lands with that many trials."""

    names: tuple[str, ...]
    gain: np.ndarray  # (n, R): named quantities from the residuals at the state
    structure: Structure
    state: ModelState

    def errors(self, problem: CalibrationProblem) -> dict[str, float]:
        """The error of every named quantity on ``problem``'s detections (the same frames,
        cameras and corner ids as the problem it was built on)."""
        r, _ = BundleModel(problem, self.structure).evaluate(self.state, jacobian=False)
        return dict(zip(self.names, -(self.gain @ r), strict=True))


def linearised_estimator(
    problem: CalibrationProblem, truth: ModelState, *, structure: Structure | None = None
) -> LinearisedEstimator:
    """The linearised estimator of ``problem`` at ``truth`` (``structure``: the problem's at the
    true hand-eye rotation when None)."""
    st = build_structure(problem, truth.X[0][:3, :3]) if structure is None else structure
    model = BundleModel(problem, st)
    state = model.with_corrections(truth)
    _, J = model.evaluate(state)
    names, Jn = _jacobian(layout_of(problem, st, truth), model.names)
    scale = np.linalg.norm(J, axis=0)
    scale[scale == 0] = 1.0
    Q, R = np.linalg.qr(J / scale)  # (J'J)^-1 J' without squaring the condition
    return LinearisedEstimator(names, Jn @ (np.linalg.solve(R, Q.T) / scale[:, None]), st, state)
