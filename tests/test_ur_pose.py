"""The UR pose <-> T_base_tool conversion (drivers/ur_pose.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slidecal.drivers.ur_pose import T_from_ur_pose, pendant_text, ur_pose_from_T
from slidecal.solver.geometry import Rx, Ry, Rz, T_from_Rt

unit_axes = (
    st.lists(st.floats(-1, 1, allow_nan=False), min_size=3, max_size=3)
    .map(np.array)
    .filter(lambda v: np.linalg.norm(v) > 1e-3)
    .map(lambda v: v / np.linalg.norm(v))
)
positions = st.lists(st.floats(-2, 2, allow_nan=False), min_size=3, max_size=3).map(np.array)


def _pose(t, axis, angle):
    return [*np.asarray(t, float), *(np.asarray(axis) * angle)]


@settings(max_examples=200, deadline=None)
@given(t=positions, axis=unit_axes, angle=st.floats(0.0, 3.0))
def test_pose_T_pose_round_trip(t, axis, angle):
    pose = _pose(t, axis, angle)
    back = ur_pose_from_T(T_from_ur_pose(pose))
    np.testing.assert_allclose(back, pose, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(t=positions, axis=unit_axes, angle=st.floats(0.0, 3.0))
def test_T_pose_T_round_trip_and_valid_rotation(t, axis, angle):
    T = T_from_ur_pose(_pose(t, axis, angle))
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    pose = ur_pose_from_T(T)
    assert 0.0 <= np.linalg.norm(pose[3:]) <= np.pi + 1e-12
    # Angles from 3.0 rad to pi are covered by test_angles_near_pi.
    np.testing.assert_allclose(T_from_ur_pose(pose), T, atol=1e-9)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-9, 1e-7, 1e-6, 1e-5])
def test_small_angles(angle):
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    pose = _pose([0.1, 0.2, 0.3], axis, angle)
    T = T_from_ur_pose(pose)
    np.testing.assert_allclose(ur_pose_from_T(T), pose, atol=1e-15)


@pytest.mark.parametrize(
    "eps",
    [
        0.0,
        1e-12,
        1e-9,
        1e-7,
        1e-5,
        1e-4,
        2e-4,
        1e-3,
        1e-2,
        0.14,
    ],
)
def test_angles_near_pi(eps):
    """UR poses with the tool pointing down sit near pi: the axis must stay exact there."""
    axis = np.array([0.6, 0.0, -0.8])
    angle = np.pi - eps
    T = T_from_ur_pose(_pose([0.0, 0.0, 0.0], axis, angle))
    back = np.array(ur_pose_from_T(T)[3:])
    assert np.linalg.norm(back) == pytest.approx(angle, abs=1e-9)
    if eps == 0.0:
        # At exactly pi, r and -r are the same rotation: either is correct.
        assert min(np.linalg.norm(back - axis * angle), np.linalg.norm(back + axis * angle)) < 1e-9
    else:
        np.testing.assert_allclose(back, axis * angle, atol=1e-9)


def test_known_values():
    # Tool pointing down (rotation pi about x): the pendant shows RX 180 deg.
    T = T_from_ur_pose([0.4, -0.1, 0.3, np.pi, 0.0, 0.0])
    np.testing.assert_allclose(T[:3, :3], Rx(np.pi), atol=1e-15)
    np.testing.assert_allclose(T[:3, 3], [0.4, -0.1, 0.3])
    T = T_from_ur_pose([0, 0, 0, 0, 0, np.pi / 2])
    np.testing.assert_allclose(T[:3, :3], Rz(np.pi / 2), atol=1e-15)
    # p_base = T_base_tool p_tool: the tool's x axis maps to the base's y axis.
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_pendant_text_millimetres_and_rpy():
    R = Rz(np.radians(30)) @ Ry(np.radians(-20)) @ Rx(np.radians(10))  # RPY = (10, -20, 30)
    text = pendant_text(T_from_Rt(R, [0.1234, -0.5, 0.25]))
    assert text == "X 123.40 Y -500.00 Z 250.00 mm, RPY 10.000 -20.000 30.000 deg"


@pytest.mark.parametrize(
    "bad",
    [[0.0] * 5, [0.0] * 7, [0.0, 0.0, np.nan, 0.0, 0.0, 0.0], [np.inf] + [0.0] * 5],
)
def test_bad_input(bad):
    with pytest.raises(ValueError, match="6 finite numbers"):
        T_from_ur_pose(bad)


def test_non_numeric_input_is_a_value_error():
    # numpy's own message ("could not convert string to float"), still a ValueError.
    with pytest.raises(ValueError):
        T_from_ur_pose(["x", 0, 0, 0, 0, 0])
