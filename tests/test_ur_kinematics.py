"""UR e-Series kinematics: fk/ik round trips, limits, singularities, reach."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, seed, settings
from hypothesis import strategies as st

from slidecal.drivers import ur_kinematics as urk
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import T_from_Rt, inv_T, rotation_angle_deg

angles = st.floats(-np.pi, np.pi, allow_nan=False)
joint_vectors = st.lists(angles, min_size=6, max_size=6).map(np.array)


def _pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Translation error in mm and rotation error in degrees."""
    return (
        float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]) * 1000.0),
        rotation_angle_deg(T_a[:3, :3], T_b[:3, :3]),
    )


def test_fk_home_matches_published_geometry():
    # At q = 0 the UR arm lies stretched along -x of the base (a2, a3 < 0), the flange points
    # along -y of the base after the wrist offsets: x = a2 + a3, y = -(d4 + d6), z = d1 - d5.
    m = urk.UR5E
    T = urk.fk(np.zeros(6), m)
    np.testing.assert_allclose(T[:3, 3], [m.a2 + m.a3, -(m.d4 + m.d6), m.d1 - m.d5], atol=1e-12)


@pytest.mark.parametrize("model", list(urk.MODELS.values()), ids=lambda m: m.name)
@seed(20261201)
@settings(max_examples=60, deadline=None)
@given(q=joint_vectors)
def test_fk_of_every_ik_solution_is_the_pose(model, q):
    T = urk.fk(q, model)
    sols = urk.ik(T, model=model)
    # At a wrist singularity q6 is free and taken from q_near: with q_near = q a solution exists
    # even where the arm is also stretched out (elbow singular).
    assert sols or urk.ik(T, q_near=q, model=model), "a pose computed by fk must have a solution"
    sols = sols + urk.ik(T, q_near=q, model=model)
    for s in sols:
        dt_mm, dr_deg = _pose_error(urk.fk(s, model), T)
        # At exact singularities arccos near +-1 loses half the digits: 1e-8 rad, nanometres.
        assert dt_mm < 1e-3 and dr_deg < 1e-4
        assert np.all(s >= np.array(model.q_min) - 1e-9)
        assert np.all(s <= np.array(model.q_max) + 1e-9)


@seed(20261202)
@settings(max_examples=80, deadline=None)
@given(q=joint_vectors)
def test_ik_nearest_solution_recovers_the_joints(q):
    # Away from wrist and elbow singularities the generating joint vector is one of the
    # solutions, and with q_near = q it comes first (near them arccos loses half the digits).
    if abs(np.sin(q[4])) < 1e-3 or abs(np.sin(q[2])) < 1e-3:
        return
    sols = urk.ik(urk.fk(q), q_near=q)
    np.testing.assert_allclose(sols[0], q, atol=1e-7)


@pytest.mark.parametrize("model", list(urk.MODELS.values()), ids=lambda m: m.name)
def test_ik_finds_a_solution_near_double_singularities(model):
    """Elbow stretched (or folded) and the wrist 1e-7 rad from singular: the arccos of q5 then
    carries eps / sin(q5) of error, which pushed the elbow's cosine past 1 by up to 2e-9 and
    lost the only solutions (an unseeded Hypothesis run found it; 78 of 3000 of these failed)."""
    rng = np.random.default_rng(7)
    q_fail = np.array([3.05218063, -0.452235284, 0.0, -2.63062083, -1e-7, 2.77532163])
    cases = [q_fail]
    for _ in range(400):
        q = rng.uniform(-np.pi, np.pi, 6)
        q[2] = rng.choice([0.0, 1e-9, -1e-8, np.pi, np.pi - 1e-9])
        q[4] = rng.choice([1e-7, -1e-7, 2e-7, 5e-8, 3e-7, 1e-6, np.pi - 1e-7, -np.pi + 2e-7])
        cases.append(q)
    for q in cases:
        T = urk.fk(q, model)
        sols = urk.ik(T, model=model) + urk.ik(T, q_near=q, model=model)
        assert sols, f"no IK solution for fk({q.tolist()})"
        for s in sols:
            dt_mm, dr_deg = _pose_error(urk.fk(s, model), T)
            assert dt_mm < 1e-3 and dr_deg < 1e-4


def test_ik_still_refuses_a_pose_just_out_of_reach():
    # the singular tolerance is nanometres of reach: 1 um beyond the stretched arm has no solution
    q = np.array([0.3, -0.4, 0.0, -1.2, 1e-7, 0.5])
    T = urk.fk(q)
    m = urk.UR5E
    p_shoulder = np.array([0.0, 0.0, m.d1])
    wrist = T[:3, 3] - m.d6 * T[:3, 2]
    out = T.copy()
    out[:3, 3] += 1e-6 * (wrist - p_shoulder) / np.linalg.norm(wrist - p_shoulder)
    assert urk.ik(T, q_near=q)
    assert urk.ik(out) == [] and urk.ik(out, q_near=q) == []


def test_ik_with_tcp_offset():
    rng = np.random.default_rng(3)
    T_flange_tcp = T_from_Rt(np.eye(3), [0.01, -0.02, 0.15])
    for _ in range(50):
        q = rng.uniform(-np.pi, np.pi, 6)
        T = urk.fk(q, T_flange_tcp=T_flange_tcp)
        np.testing.assert_allclose(T, urk.fk(q) @ T_flange_tcp, atol=1e-12)
        for s in urk.ik(T, T_flange_tcp=T_flange_tcp):
            np.testing.assert_allclose(urk.fk(s, T_flange_tcp=T_flange_tcp), T, atol=1e-9)


def test_ik_shifts_angles_toward_q_near_within_limits():
    q = np.array([0.3, -1.2, 1.4, -1.8, -1.5, 0.4])
    q_near = q + np.array([-2 * np.pi, 0, 0, 2 * np.pi, 0, -2 * np.pi])
    sols = urk.ik(urk.fk(q), q_near=q_near)
    np.testing.assert_allclose(sols[0], q_near, atol=1e-7)
    # The elbow is limited to +-pi, so it is never shifted by a turn.
    for s in sols:
        assert abs(s[2]) <= np.pi + 1e-9


def test_reachable_typical_pose_and_out_of_reach():
    q = np.array([0.0, -1.9, 1.6, -1.3, -1.57, 0.0])
    T = urk.fk(q)
    assert urk.singularity(q) is None
    assert urk.reachable(T)
    assert urk.reachable(T, q_near=q)
    far = T.copy()
    far[:3, 3] = [1.5, 0.0, 0.3]  # beyond |a2| + |a3| + wrist offsets of a UR5e
    assert urk.ik(far) == []
    assert not urk.reachable(far)


@pytest.mark.parametrize(
    ("q", "word"),
    [
        ([0.0, -1.9, 1.6, -1.3, 0.02, 0.0], "wrist"),
        ([0.0, -1.9, 0.03, -1.3, -1.57, 0.0], "elbow"),
    ],
)
def test_singular_configurations_rejected(q, word):
    q = np.array(q)
    assert word in urk.singularity(q)
    assert not urk.reachable(urk.fk(q), q_near=q)


def test_shoulder_singularity_wrist_point_on_base_axis():
    # Put the wrist point above the base: the horizontal distance r of the wrist point in the
    # arm's plane is a2 c2 + a3 c23 + d5 s234; choose q4 so that it vanishes.
    m = urk.UR5E
    q1, q2, q3, q5 = 0.2, -1.4, -0.3, -1.4
    rest = m.a2 * np.cos(q2) + m.a3 * np.cos(q2 + q3)
    q234 = np.arcsin(-rest / m.d5)
    q = np.array([q1, q2, q3, q234 - q2 - q3, q5, 0.0])
    T = urk.fk(q)
    p05 = T[:3, 3] - m.d6 * T[:3, 2]
    assert np.hypot(p05[0], p05[1]) == pytest.approx(m.d4, abs=1e-9)
    assert "shoulder" in urk.singularity(q)
    assert not urk.reachable(T)


def test_model_lookup_and_bad_input():
    assert urk.model_by_name("ur10E") is urk.UR10E
    with pytest.raises(InputError, match="unknown robot model"):
        urk.model_by_name("UR7")
    with pytest.raises(InputError, match="6 finite angles"):
        urk.fk(np.zeros(5))
    with pytest.raises(InputError, match="4x4"):
        urk.ik(np.eye(3))


def test_inverse_of_fk_is_consistent_with_inv_T():
    q = np.array([1.0, -1.0, 1.2, -0.5, 1.1, 0.3])
    T = urk.fk(q)
    np.testing.assert_allclose(inv_T(T) @ T, np.eye(4), atol=1e-12)
