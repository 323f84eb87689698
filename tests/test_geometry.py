"""Property tests of the transform helpers (solver/geometry.py)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from slidecal.solver.geometry import (
    R_from_rvec,
    T_from_Rt,
    inv_T,
    look_at_R_cam_world,
    project_to_SO3,
    rotation_angle_deg,
    rvec_from_R,
    transform_points,
)

finite = st.floats(-1.0, 1.0, allow_nan=False)
vec3 = st.tuples(finite, finite, finite).map(np.array)
angle = st.floats(0.0, np.pi, allow_nan=False)


def _rvec(axis: np.ndarray, theta: float) -> np.ndarray:
    n = np.linalg.norm(axis)
    return np.zeros(3) if n < 1e-6 else axis / n * theta


@settings(max_examples=300, deadline=None)
@given(vec3, angle)
def test_rvec_round_trip_and_rotation(axis, theta):
    r = _rvec(axis, theta)
    R = R_from_rvec(r)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(R) - 1.0) < 1e-12
    back = rvec_from_R(R)
    # the same rotation (at exactly pi, r and -r are the same rotation)
    np.testing.assert_allclose(R_from_rvec(back), R, atol=1e-12)
    if theta < np.pi - 1e-6:
        np.testing.assert_allclose(back, r, atol=1e-9)
    assert abs(rotation_angle_deg(R) - np.degrees(np.linalg.norm(r))) < 1e-9


@settings(max_examples=200, deadline=None)
@given(vec3, angle, vec3, vec3, angle, vec3)
def test_inverse_and_composition(a1, t1, p1, a2, t2, p2):
    A = T_from_Rt(R_from_rvec(_rvec(a1, t1)), p1)
    B = T_from_Rt(R_from_rvec(_rvec(a2, t2)), p2)
    np.testing.assert_allclose(A @ inv_T(A), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(inv_T(A @ B), inv_T(B) @ inv_T(A), atol=1e-12)
    pts = np.stack([p1, p2, a1])
    # T_a_c = T_a_b T_b_c: mapping in two steps equals mapping once
    np.testing.assert_allclose(
        transform_points(A @ B, pts), transform_points(A, transform_points(B, pts)), atol=1e-12
    )


@settings(max_examples=200, deadline=None)
@given(vec3, angle, vec3, angle)
def test_rotation_angle_is_a_metric(a1, t1, a2, t2):
    R1, R2 = R_from_rvec(_rvec(a1, t1)), R_from_rvec(_rvec(a2, t2))
    d12 = rotation_angle_deg(R1, R2)
    assert abs(d12 - rotation_angle_deg(R2, R1)) < 1e-7
    assert rotation_angle_deg(R1, R1) < 1e-9
    assert d12 <= rotation_angle_deg(R1) + rotation_angle_deg(R2) + 1e-7


@settings(max_examples=100, deadline=None)
@given(vec3, angle, st.floats(0.0, 0.01))
def test_project_to_SO3_nearest(a, t, eps):
    R = R_from_rvec(_rvec(a, t))
    np.testing.assert_allclose(project_to_SO3(R), R, atol=1e-12)
    noisy = R + eps * np.sin(np.arange(9.0)).reshape(3, 3)
    P = project_to_SO3(noisy)
    np.testing.assert_allclose(P @ P.T, np.eye(3), atol=1e-12)
    assert rotation_angle_deg(P, R) < np.degrees(3 * eps) + 1e-9


def test_look_at_points_the_optical_axis():
    R_cam_world = look_at_R_cam_world(np.array([1.0, 2.0, 3.0]), np.zeros(3), np.array([0, 0, 1.0]))
    z_world = R_cam_world.T @ np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(z_world, -np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0), atol=1e-12)
    up_in_cam = R_cam_world @ np.array([0.0, 0.0, 1.0])
    assert up_in_cam[1] < 0  # world up appears as up (-y) in the image


def test_right_singular_matches_the_full_svd_for_short_and_tall_systems():
    from slidecal.solver.geometry import right_singular

    rng = np.random.default_rng(5)
    for m in (8, 9, 2000):
        A = rng.normal(size=(m, 9))
        if m == 8:  # 4 points: the null vector is the 9th right singular vector
            sv, Vt = right_singular(A)
            assert sv.shape == (9,) and sv[-1] == 0.0
            assert np.linalg.norm(A @ Vt[-1]) < 1e-12
        else:
            sv, Vt = right_singular(A)
            sv_full = np.linalg.svd(A, compute_uv=False)
            assert np.allclose(sv, sv_full)
            assert abs(abs(Vt[-1] @ np.linalg.svd(A)[2][-1]) - 1.0) < 1e-9
