"""Failures of the black-box rehearsal (tests/test_blackbox_sessions.py) whose cause lies in the
solver's uncertainty model, kept as strict expected failures: a fix makes them pass, and the
marker must then go.

Eye-to-hand, one AprilTag (4 corners) on the tool, 205 frames in 7 orientations, the arm off
by 0.8 mm / 0.08 deg smoothly over its workspace (``mocks/scenarios.py`` ``real_arm_poses``),
detections given with 0.1 px noise. Over seeds 1-16 the intrinsics' |error| / reported std
has a largest value of 2.2-2.6 in a typical session (a calibrated estimator: about 2.0 for 9
parameters) and exceeds 3 in 2 of 16 sessions (seed 12: fx 3.1; seed 15: cx 3.75);
with the arm's error off (``arm_mm=0``) the same sessions give an rms |error| / std of 1.05 and
no value above 3. The per-frame robot-pose noise is modelled as independent between frames
(estimated 0.15-0.6 mm here), but the arm's error is smooth: frames at nearby poses share it, so
with 4 corners per image (the board pose rests on the robot poses) the intrinsics' std comes
out some 30-40 % too small.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import blackbox as bb  # noqa: E402


@pytest.mark.xfail(
    strict=True,
    reason="intrinsics' std too small under a smooth arm error (eye-to-hand, one tag): "
    "cx is 3.75 std off in this seeded session",
)
def test_eye_to_hand_one_tag_intrinsics_within_3_std(tmp_path):
    truth = bb.eye_to_hand_tag_session(tmp_path / "tag", seed=15)
    code, message, result, _ = bb.solve(tmp_path / "tag", in_process=True)
    assert code == 0 and result is not None, message
    assert max(bb.intrinsic_errors(result, truth.camera).values()) < 3.0
