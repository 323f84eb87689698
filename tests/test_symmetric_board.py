"""A chessboard that looks the same after a half turn (8 x 6 squares): frames whose corner 0 was
read at the opposite corner are turned back before the solve, by the robot's rotations or, without
a robot, by continuity; the pairing diagnosis names the half turn instead of the pairing."""

from dataclasses import replace

import numpy as np
import pytest

from slidecal.mocks import scenarios as sc
from slidecal.solver.adequacy import record_check
from slidecal.solver.calibrate import calibrate
from slidecal.solver.detect import half_turn_symmetric, half_turned, half_turns, resolve_half_turns
from slidecal.solver.errors import DegenerateError
from slidecal.solver.geometry import Rx, Rz, T_from_Rt
from slidecal.solver.problem import Target

FLIPPED = (3, 10, 11, 12, 13, 14, 29)  # 7 of 33 frames, as the ABB set's
TRANSLATIONS = (0, 1, 2, 3, 4, *range(20, 33))  # the frames at the first orientation


def _flipped(problem, frames=FLIPPED):
    return replace(
        problem,
        frames=tuple(
            replace(f, detections={"cam": half_turned(f.detections["cam"], problem.target)})
            if k in frames
            else f
            for k, f in enumerate(problem.frames)
        ),
    )


def _subset(problem, keep):
    return replace(problem, frames=tuple(problem.frames[k] for k in keep))


def _same_ids(a, b):
    return all(
        np.array_equal(f.detections["cam"].ids, g.detections["cam"].ids)
        for f, g in zip(a.frames, b.frames, strict=True)
    )


def test_which_boards_are_symmetric():
    assert half_turn_symmetric(Target.chessboard(8, 6, 0.03))
    assert half_turn_symmetric(Target.chessboard(9, 7, 0.03))
    assert not half_turn_symmetric(Target.chessboard(9, 6, 0.03))
    assert not half_turn_symmetric(Target.charuco(8, 6, 0.03, 0.022))


def test_flipped_frames_are_solved_as_if_not_flipped():
    s = sc.symmetric_board_r1(np.random.default_rng(1))
    truth = calibrate(s.problem)
    res = calibrate(_flipped(s.problem))
    turned = [m for m in res.messages if "half turn" in m]
    assert len(turned) == 1 and turned[0].startswith(f"frames {list(FLIPPED)} 'cam'")
    assert "robot rotations" in turned[0]
    # the turned-back session is the unflipped one: the same solve, and both near the truth
    assert np.allclose(res.cameras["cam"].K, truth.cameras["cam"].K, rtol=1e-9)
    assert res.adequacy.adequate
    for name, (a, b) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items():
        z = (res.cameras["cam"].K[a, b] - s.truth.K["cam"][a, b]) / res.cameras["cam"].std[name]
        assert abs(z) < 4.0, name


def test_flipped_pure_translations_are_not_refused():
    s = sc.symmetric_board_r1(np.random.default_rng(2))
    unflipped = _subset(s.problem, TRANSLATIONS)
    flipped = _subset(_flipped(s.problem), TRANSLATIONS)
    assert _same_ids(resolve_half_turns(flipped)[0], unflipped)
    res = calibrate(flipped)
    assert np.allclose(res.cameras["cam"].K, calibrate(unflipped).cameras["cam"].K, rtol=1e-9)


def test_without_poses_resolved_by_continuity():
    s = sc.symmetric_board_r1(np.random.default_rng(3))
    p = replace(s.problem, knowledge="none")
    resolved, notes = resolve_half_turns(_flipped(p))
    assert _same_ids(resolved, p)
    assert "the other frames" in notes[0]


def test_without_poses_refused_naming_the_symmetry_when_undecidable():
    # board poses a quarter turn apart about the board normal: turned or not, 90 deg apart
    _, margin = half_turns([Rx(0.3) @ Rz(k * np.pi / 2) for k in range(4)])
    assert np.all(margin < 1.0)
    s = sc.symmetric_board_r1(np.random.default_rng(4))
    target, rng = s.problem.target, np.random.default_rng(4)
    c = target.points_m.mean(axis=0)
    T0 = T_from_Rt(Rx(0.2), np.array([0.0, 0.0, 0.5]) - Rx(0.2) @ c)
    frames = []
    for k in range(4):
        T = T0 @ T_from_Rt(Rz(k * np.pi / 2), c - Rz(k * np.pi / 2) @ c)
        det = sc.projected_detection(sc.R1_K, sc.R1_DIST, T, target, sc.R1_SIZE_PX, 0.1, rng)
        frames.append(replace(s.problem.frames[k], detections={"cam": det}))
    p = replace(s.problem, frames=tuple(frames), knowledge="board_direction")
    with pytest.raises(DegenerateError, match="looks the same after a half turn.*one odd and one"):
        resolve_half_turns(p)
    # one camera without board-frame knowledge: each frame has its own board pose, no refusal
    resolve_half_turns(replace(p, knowledge="none"))


def test_pairing_diagnosis_names_the_half_turn():
    s = sc.symmetric_board_r1(np.random.default_rng(5))
    assert record_check(s.problem) is None
    msg = record_check(_flipped(s.problem))
    assert msg is not None and "half turn" in msg and "paired with other poses" not in msg
