"""The rerun recording, read back with rerun.chunk.RrdReader: entity paths and counts."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
from rerun.chunk import RrdReader

from slidecal.routines.rerun_log import RerunLog
from slidecal.solver.geometry import Rx, T_from_Rt
from slidecal.solver.problem import CalibrationProblem, CameraSpec, Detection, Frame, Target
from slidecal.solver.result import CalibrationResult, CameraEstimate, TransformEstimate


def test_recording_has_the_entity_tree(tmp_path: Path) -> None:
    target = Target.chessboard(5, 4, 0.03)
    spec = CameraSpec("cam", 64, 48)
    T_tool_cam = T_from_Rt(np.eye(3), [0.0, 0.0, 0.05])
    T_base_board = T_from_Rt(Rx(np.pi), [0.0, 0.0, 0.0])
    path = tmp_path / "r.rrd"
    log = RerunLog(path, [spec], target, "eye_in_hand", T_tool_cam, T_base_board)
    frames = []
    for i in range(3):
        T = T_from_Rt(Rx(np.pi), [0.01 * i, 0.0, 0.5])
        det = Detection(np.arange(4), np.full((4, 2), 10.0 + i))
        log.frame(i, T, {"cam": np.zeros((48, 64), np.uint8)}, {"cam": det}, robot_time_s=2.0 * i)
        frames.append(Frame(i, {"cam": det}, T_base_tool=T))
    log.event("a fault", level="ERROR")
    K = np.array([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]])
    result = CalibrationResult(
        cameras={"cam": CameraEstimate("cam", 64, 48, K, np.zeros(5), {"fx": 0.1}, 0.1)},
        hand_eye=TransformEstimate("T_tool_cam", np.eye(3), np.array([0, 0, 0.05]), 0.01, 0.1),
        rig={},
        T_target=TransformEstimate("T_base_board", Rx(np.pi), np.zeros(3), 0.01, 0.1),
        converged=True,
        iterations=3,
        reproj_rms_px=0.1,
        sigma_px=0.1,
        parameter_names=(),
        covariance=None,
        residuals_px={(i, "cam"): 0.1 * (i + 1) for i in range(3)},
        outliers=(),
        unobservable={},
        messages=(),
    )
    problem = CalibrationProblem(target, (spec,), tuple(frames))
    log.final(problem, result, "final estimate: fx 50 +- 0.1 px")
    assert log.close() == path

    rows: Counter[str] = Counter()
    for chunk in RrdReader(path).stream().to_chunks():
        rows[str(chunk.entity_path)] += chunk.to_record_batch().num_rows
    paths = set(rows)
    for p in (
        "/world/base",
        "/world/board",
        "/world/board/corners",
        "/world/tool",
        "/world/tool_path",
        "/world/tool/cam",
        "/world/tool/cam/image",
        "/world/tool/cam/image/detections",
        "/world/tool/cam/image/reprojections",
        "/residuals/cam",
        "/log",
    ):
        assert p in paths, (p, sorted(paths))
    # one image, one detection set, one residual per frame; event + final summary in the log
    assert rows["/world/tool/cam/image"] == 3
    assert rows["/residuals/cam"] == 3
    assert rows["/world/tool/cam/image/reprojections"] == 3
    assert rows["/log"] == 2
