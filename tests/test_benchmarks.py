"""``slidecal bench NAME``: one command for every benchmark, one report header without paths."""

import importlib
import os

import pytest

from slidecal.routines.benchmarks import BENCHMARKS, report_header
from slidecal.routines.cli import main


def test_every_benchmark_module_has_a_main():
    for name, (module, _) in BENCHMARKS.items():
        assert callable(importlib.import_module(module).main), name


def test_list_names_every_benchmark(capsys):
    assert main(["bench", "--list"]) == 0
    out = capsys.readouterr().out
    for name in BENCHMARKS:
        assert name in out


def test_header_names_versions_and_machine_but_no_path():
    lines = report_header("A title", "run", ["--seeds", "3"], 12.0)
    text = "\n".join(lines)
    assert lines[0] == "# A title"
    assert "`slidecal bench run --seeds 3`" in text
    assert "numpy" in text and "opencv" in text and "cores" in text
    assert os.getcwd() not in text and "/" not in text.replace("slidecal bench", "")


def test_scale_session_has_the_requested_frames_and_cameras():
    from slidecal.routines.bench_scale import session

    p = session(45, 2)
    assert len(p.frames) == 45 and [f.id for f in p.frames] == list(range(45))
    assert {c.name for c in p.cameras} == {"left", "right"}


def test_scale_arm_session_and_targets():
    import numpy as np

    from slidecal.routines.bench_scale import _targets, session

    exact, arm = session(25, 1), session(25, 1, arm_error=True)
    assert len(arm.frames) == 25
    assert arm.options.robot_noise_m == 0.0  # the solve is told nothing: it learns the arm
    moved = [
        np.linalg.norm(a.T_base_tool[:3, 3] - e.T_base_tool[:3, 3])
        for a, e in zip(arm.frames, exact.frames, strict=True)
    ]
    assert 0 < np.median(moved) < 0.01  # the measured poses carry the arm's error
    rows = [
        {"cameras": 1, "frames": 100, "slidecal_s": 0.2, "opencv_s": 0.05},
        {"cameras": 1, "frames": 400, "slidecal_s": 0.9, "opencv_s": 0.2},
    ]
    text = "\n".join(_targets(rows, {"slidecal_s": 0.03, "opencv_s": 0.012}))
    assert "| 2.5 | 1.5 |" in text and "| 4.5 | 2 |" in text and "| 4.5 | 5 |" in text
    split = {"solve_s": 0.03, "learned_s": 0.012}  # the rest: 18 ms, 1.5 times OpenCV's 12
    text = "\n".join(_targets(rows, {"slidecal_s": 0.03, "opencv_s": 0.012}, None, split))
    assert "covariance: 18 of 30 ms) / cv2.calibrateCamera | 1.5 | 1.5 |" in text


def test_scale_bench_times_the_learned_refinement_inside_the_solve():
    from slidecal.routines.bench_scale import learned_refinement_s

    t = learned_refinement_s(2)
    assert 0.0 < t["learned_s"] < t["solve_s"]


def test_public_data_bench_writes_sessions_a_user_would_and_names_missing_data(tmp_path):
    # the public KUKA data is not shipped: a folder without it is refused with what to give;
    # a set's poses (row-major 4 x 4, metres) and images become a session read back exactly
    import cv2
    import numpy as np

    from slidecal.routines import bench_public
    from slidecal.routines.session import read_session
    from slidecal.solver.errors import InputError

    with pytest.raises(InputError, match="kuka_1, kuka_2 and kuka_3"):
        bench_public.main(["--data", str(tmp_path)])
    d = tmp_path / "kuka_1"
    d.mkdir()
    T = np.eye(4)
    T[:3, 3] = [1.205, -0.808, 0.524]
    np.savetxt(d / "RobotPosesVec.txt", np.stack([T.ravel(), T.ravel()]), delimiter="\t")
    for k in (1, 2):
        cv2.imwrite(str(d / f"{k:02d}.png"), np.full((120, 160), 200, np.uint8))
    s = bench_public.write_session("kuka_1", tmp_path, tmp_path / "s")
    p = read_session(s)
    assert [f.id for f in p.frames] == [1, 2]
    np.testing.assert_allclose(p.frames[1].T_base_tool, T, atol=1e-12)
    assert bench_public.translation_frames("kuka_1", tmp_path) == [1, 2]
    # no board in the images: no peer answer (not an OpenCV exception)
    assert bench_public.opencv_reference("kuka_1", tmp_path) is None
    # the solve with the levels given: the session file carries them
    fixed = {"robot_noise_mm": 0.6, "robot_noise_deg": 0.04, "estimate_robot_noise": False}
    o = read_session(bench_public.write_session("kuka_1", tmp_path, tmp_path / "f", options=fixed))
    assert not o.options.estimate_robot_noise
    assert o.options.robot_noise_m == pytest.approx(6e-4) and o.options.robot_noise_deg == 0.04
    assert p.options.estimate_robot_noise  # none given: the defaults


def test_public_data_bench_compares_rotations_in_the_results_convention():
    # R_b = exp([d]x) R_a: the angle of d and its Mahalanobis distance under the covariance
    import numpy as np
    from scipy.spatial.transform import Rotation

    from slidecal.routines.bench_public import _rotation_difference

    R_a = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    d = np.radians([0.1, 0.0, 0.0])
    R_b = Rotation.from_rotvec(d).as_matrix() @ R_a
    cov = np.diag(np.radians([0.05, 0.5, 0.5]) ** 2)
    angle, z = _rotation_difference(R_a, R_b, cov)
    assert angle == pytest.approx(0.1, rel=1e-6)
    assert z == pytest.approx(2.0, rel=1e-6)  # 0.1 deg along x, whose std is 0.05 deg
    # on the right instead (R_a exp([d]x)) the difference is another axis in the left frame
    assert _rotation_difference(R_a, R_a @ Rotation.from_rotvec(d).as_matrix(), cov)[1] < 1.9


def test_header_shows_an_out_of_project_report_path_as_its_place_in_docs():
    lines = report_header("T", "run", ["--seeds", "3", "--out", "/tmp/scratch/RUN.md"], 1.0)
    assert "`slidecal bench run --seeds 3 --out docs/RUN.md`" in lines[2]
    lines = report_header("T", "stereo", ["--out=/home/me/figs/"], 1.0)
    assert "`slidecal bench stereo --out=docs/`" in lines[2]
    lines = report_header("T", "run", ["--out", "docs/RUN.md"], 1.0)
    assert "--out docs/RUN.md`" in lines[2]
