"""A user's mistakes that once passed the verdict (issue 39): each built from a good simulated
session plus the one mistake, judged as ``slidecal solve`` judges it; none may be accepted, and
each finding names its cause. The good session beside it must stay accepted."""

from __future__ import annotations

import numpy as np
import pytest

from slidecal.mocks import scenarios as sc
from slidecal.routines.ops.verdict import judge
from slidecal.solver.calibrate import calibrate

OAK_SOCKETS = {"left": "CAM_B", "right": "CAM_C"}


@pytest.fixture(scope="module")
def stereo():
    return sc.oak_rig(np.random.default_rng(3), cameras=("left", "right")).problem


def test_stereo_pair_in_socket_order_is_accepted(stereo):
    v = judge(calibrate(stereo), problem=stereo, sockets=OAK_SOCKETS, command="solve")
    (c,) = [c for c in v.checks if c.test == "stereo"]
    assert c.passed and 70 < c.value < 80  # right lies 75 mm along the left's +x
    assert v.verdict == "accepted", v.lines()


def test_stereo_left_and_right_swapped_is_rejected_naming_the_swap(stereo):
    swapped = sc.swap_cameras(stereo, "left", "right")
    v = judge(calibrate(swapped), problem=swapped, sockets=OAK_SOCKETS, command="solve")
    assert v.verdict == "rejected" and v.exit_code == 4
    (c,) = [c for c in v.reasons if c.test == "stereo"]
    assert -80 < c.value < -70 and "swapped" in c.message and "CAM_C" in c.message
