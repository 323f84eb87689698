"""Failures of the black-box rehearsal (tests/test_blackbox_sessions.py) whose cause lies in the
solver's uncertainty model, kept as strict expected failures: a fix makes them pass, and the
marker must then go.

The checker's 13 translation-only frames (one orientation, 12 moves of 40-80 mm, given
detections with 0.05 px noise, the arm 1 mm / 0.1 deg off; seeds 1-9): fx's reported std
ranges from 0.04 % to 0.25 % of fx between sessions of the same geometry, following the
robot accuracy the solve estimates from 13 frames (0.05-0.15 mm); seed 3 estimates 0.05 mm,
reports fx to 0.042 % and is 0.136 % off (3.2 std; cy 4.2 std). The other seeds stay within 2.1
std. With the arm's error off the same seed gives 0.003 %. fx to 0.1 % from 13 translation-only
frames is therefore a matter of the arm: its smooth error changes each move's length by
0.1-0.8 %.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import blackbox as bb  # noqa: E402

#: (id, the session, why it fails): strict expected failures
CASES = (
    (
        "translation_only_13_frames",
        lambda d: bb.translation_only_session(d, seed=3),
        "13 translation-only frames on a 1 mm arm: the robot accuracy is estimated at 0.05 mm, "
        "fx is 3.2 and cy 4.2 std off",
    ),
)


@pytest.mark.parametrize(
    "make",
    [
        pytest.param(make, id=name, marks=pytest.mark.xfail(strict=True, reason=why))
        for name, make, why in CASES
    ],
)
def test_intrinsics_within_3_std(tmp_path, make):
    truth = make(tmp_path / "session")
    code, message, result, _ = bb.solve(tmp_path / "session", in_process=True)
    assert code == 0 and result is not None, message
    assert max(bb.intrinsic_errors(result, truth.camera).values()) < 3.0
