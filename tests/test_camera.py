"""The camera model against OpenCV and against finite differences of itself."""

import cv2
import numpy as np
import pytest

from slidecal.solver.camera import (
    K_matrix,
    distortion_jacobian,
    distortion_model,
    project,
    project_with_jacobians,
    undistort_normalised,
)

DIST = np.array([-0.12, 0.05, 5e-4, -3e-4, 0.01])
# one lens of each model (the distortion vector's length names it)
DISTS = {
    "opencv5": DIST,
    "rational": np.array([0.4, -0.1, 5e-4, -3e-4, 0.02, 0.52, -0.05, 0.03]),
    "fisheye": np.array([-0.02, 0.01, -0.004, 0.001]),
}
MODELS = pytest.mark.parametrize("model", list(DISTS))


def _opencv(K, dist, P):
    if distortion_model(dist) == "fisheye":
        px = cv2.fisheye.projectPoints(
            P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist, alpha=K[0, 1] / K[0, 0]
        )[0]
    else:
        px = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, dist)[0]
    return px.reshape(-1, 2)


def _points(rng, n=50):
    return np.column_stack([rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(0.4, 1.2, n)])


@MODELS
def test_projection_matches_opencv(model):
    rng = np.random.default_rng(1)
    K = K_matrix(880.0, 870.0, 640.0, 400.0, s=0.0 if model != "fisheye" else 1.2)
    P = _points(rng)
    P[0] = (0.0, 0.0, 1.0)  # on the axis
    P[1] = (1e-9, 0.0, 1.0)  # the fisheye's series
    P[2] = (3.0, 1.0, 1.0)  # 72 degrees off the axis
    assert distortion_model(DISTS[model]) == model
    np.testing.assert_allclose(project(K, DISTS[model], P), _opencv(K, DISTS[model], P), atol=1e-9)


@MODELS
def test_jacobians_match_central_differences(model):
    DIST = DISTS[model]
    rng = np.random.default_rng(2)
    K = K_matrix(880.0, 870.0, 640.0, 400.0, s=1.5)
    P = _points(rng, 20)
    P[0] = (1e-9, 2e-9, 1.0)  # the fisheye's series
    pr = project_with_jacobians(K, DIST, P)
    h = 1e-6
    for j in range(3):
        dP = np.zeros(3)
        dP[j] = h
        num = (project(K, DIST, P + dP) - project(K, DIST, P - dP)) / (2 * h)
        np.testing.assert_allclose(pr.d_P[:, :, j], num, rtol=1e-6, atol=1e-4)
    params = [880.0, 870.0, 640.0, 400.0, 1.5]
    for j in range(5):
        up, dn = list(params), list(params)
        up[j] += h
        dn[j] -= h
        num = (project(K_matrix(*up), DIST, P) - project(K_matrix(*dn), DIST, P)) / (2 * h)
        np.testing.assert_allclose(pr.d_K[:, :, j], num, rtol=1e-6, atol=1e-6)
    for j in range(len(DIST)):
        du, dd = DIST.copy(), DIST.copy()
        du[j] += h
        dd[j] -= h
        num = (project(K, du, P) - project(K, dd, P)) / (2 * h)
        np.testing.assert_allclose(pr.d_dist[:, :, j], num, rtol=1e-6, atol=1e-4)


@MODELS
def test_undistort_inverts_projection(model):
    DIST = DISTS[model]
    rng = np.random.default_rng(3)
    K = K_matrix(880.0, 870.0, 640.0, 400.0, s=0.5)
    P = _points(rng)
    if model == "fisheye":  # out to 75 degrees off the axis
        P[:, :2] *= 3.7 / np.abs(P[:, :2]).max() * P[:, 2:]
    px = project(K, DIST, P)
    xy = undistort_normalised(K, DIST, px)
    np.testing.assert_allclose(xy, P[:, :2] / P[:, 2:], atol=1e-10)


@MODELS
def test_distortion_jacobian_is_the_projection_at_unit_depth(model):
    rng = np.random.default_rng(4)
    K = np.array([[880.0, 0.4, 640.0], [0.0, 870.0, 400.0], [0.0, 0.0, 1.0]])
    dist = DISTS[model]
    xy = rng.uniform(-0.8, 0.8, (200, 2))
    px, J = distortion_jacobian(K, dist, xy)
    full = project_with_jacobians(K, dist, np.column_stack([xy, np.ones(len(xy))]))
    assert np.array_equal(px, full.px)
    assert np.array_equal(J, full.d_P[:, :, :2])
    # and the Jacobian is the derivative: central differences
    h = 1e-6
    for a in range(2):
        e = np.zeros(2)
        e[a] = h
        num = (
            distortion_jacobian(K, dist, xy + e)[0] - distortion_jacobian(K, dist, xy - e)[0]
        ) / (2 * h)
        assert np.allclose(J[:, :, a], num, rtol=1e-6, atol=1e-4)
