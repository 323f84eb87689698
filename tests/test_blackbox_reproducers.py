"""Sessions of the black-box rehearsal (tests/test_blackbox_sessions.py) that once failed for a
cause in the solver's uncertainty model, kept as regression tests.

The checker's 13 translation-only frames (one orientation, 12 moves of 40-80 mm, given
detections with 0.05 px noise, the arm 1 mm / 0.1 deg off; seed 3): the solve had learned a
trend of the translation along the moves from the one group, estimated the frames' own error
at 0.05 mm and reported fx to 0.042 % where it was 0.136 % off (3.2 std; cy 4.2 std). One
orientation's translation trend is a scale of the moves, which is the focal length's: its level
is no longer learned from the images, and the reading that the frames' translation error is
all trend is carried in the covariance (solver/robot_error.py ``smooth_field_excess``); 40 such
sessions: fx, cy rms error/std 0.75, 0.97, none beyond 3 (``python tests/blackbox.py
--translation-seeds 40``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import blackbox as bb  # noqa: E402

#: (id, the session)
CASES = (("translation_only_13_frames", lambda d: bb.translation_only_session(d, seed=3)),)


@pytest.mark.parametrize("make", [pytest.param(make, id=name) for name, make in CASES])
def test_intrinsics_within_3_std(tmp_path, make):
    truth = make(tmp_path / "session")
    code, message, result, _ = bb.solve(tmp_path / "session", in_process=True)
    assert code == 0 and result is not None, message
    assert max(bb.intrinsic_errors(result, truth.camera).values()) < 3.0
