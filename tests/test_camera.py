"""The camera model against OpenCV and against finite differences of itself."""

import cv2
import numpy as np

from slidecal.solver.camera import (
    K_matrix,
    distortion_jacobian,
    project,
    project_with_jacobians,
    undistort_normalised,
)

DIST = np.array([-0.12, 0.05, 5e-4, -3e-4, 0.01])


def _points(rng, n=50):
    return np.column_stack([rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(0.4, 1.2, n)])


def test_projection_matches_opencv():
    rng = np.random.default_rng(1)
    K = K_matrix(880.0, 870.0, 640.0, 400.0)
    P = _points(rng)
    ours = project(K, DIST, P)
    cv, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, DIST)
    np.testing.assert_allclose(ours, cv.reshape(-1, 2), atol=1e-9)


def test_jacobians_match_central_differences():
    rng = np.random.default_rng(2)
    K = K_matrix(880.0, 870.0, 640.0, 400.0, s=1.5)
    P = _points(rng, 20)
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
    for j in range(5):
        du, dd = DIST.copy(), DIST.copy()
        du[j] += h
        dd[j] -= h
        num = (project(K, du, P) - project(K, dd, P)) / (2 * h)
        np.testing.assert_allclose(pr.d_dist[:, :, j], num, rtol=1e-6, atol=1e-4)


def test_undistort_inverts_projection():
    rng = np.random.default_rng(3)
    K = K_matrix(880.0, 870.0, 640.0, 400.0, s=0.5)
    P = _points(rng)
    px = project(K, DIST, P)
    xy = undistort_normalised(K, DIST, px)
    np.testing.assert_allclose(xy, P[:, :2] / P[:, 2:], atol=1e-10)


def test_distortion_jacobian_is_the_projection_at_unit_depth():
    rng = np.random.default_rng(4)
    K = np.array([[880.0, 0.4, 640.0], [0.0, 870.0, 400.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.12, 0.05, 5e-4, -3e-4, 0.01])
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
