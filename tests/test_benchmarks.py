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


def test_public_data_bench_compares_hand_eyes_in_the_results_convention():
    # a result's hand-eye against a transform moved by d on the left (R_b = exp([d]x) R_a, the
    # result's convention) and by 1 mm: the angle and distance, and their Mahalanobis distances
    # under the result's covariance (and under two results' summed)
    import numpy as np
    from scipy.spatial.transform import Rotation

    from slidecal.mocks.scenarios import classic
    from slidecal.routines.bench_public import _hand_eye_cells
    from slidecal.solver.calibrate import calibrate

    res = calibrate(classic(np.random.default_rng(1)).problem)
    he = res.hand_eye
    d = np.radians([0.1, 0.0, 0.0])
    dt = np.array([1e-3, 0.0, 0.0])
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(d).as_matrix() @ he.R
    T[:3, 3] = he.t_m + dt
    C_r = res.named_covariance.block([f"{he.name}.{a}" for a in ("rx", "ry", "rz")])
    C_t = res.named_covariance.block([f"{he.name}.{a}" for a in ("tx", "ty", "tz")])
    z_r = float(np.sqrt(d @ np.linalg.solve(C_r, d)))
    z_t = float(np.sqrt(dt @ np.linalg.solve(C_t, dt)))
    assert _hand_eye_cells(res, T) == (f"0.100 deg ({z_r:.2f})", f"1.00 mm ({z_t:.2f})")
    halved = (f"0.100 deg ({z_r / np.sqrt(2):.2f})", f"1.00 mm ({z_t / np.sqrt(2):.2f})")
    assert _hand_eye_cells(res, T, other=res) == halved
    # on the right instead (R_a exp([d]x)) the difference is another axis in the left frame
    T[:3, :3] = he.R @ Rotation.from_rotvec(d).as_matrix()
    assert _hand_eye_cells(res, T)[0] != f"0.100 deg ({z_r:.2f})"


def test_header_shows_an_out_of_project_report_path_as_its_place_in_docs():
    lines = report_header("T", "run", ["--seeds", "3", "--out", "/tmp/scratch/RUN.md"], 1.0)
    assert "`slidecal bench run --seeds 3 --out docs/RUN.md`" in lines[2]
    lines = report_header("T", "stereo", ["--out=/home/me/figs/"], 1.0)
    assert "`slidecal bench stereo --out=docs/`" in lines[2]
    lines = report_header("T", "run", ["--out", "docs/RUN.md"], 1.0)
    assert "--out docs/RUN.md`" in lines[2]


def test_public_data_bench_leaves_frames_out_and_reports_each_verdict(tmp_path, monkeypatch):
    # each session of a set with two frames left out: drawn without repeat, seeded by the set,
    # solved as a user solves it; a session not accepted is named with the frames it lacks
    from types import SimpleNamespace

    import cv2
    import numpy as np

    from slidecal.routines import bench_public
    from slidecal.routines.session import read_session

    d = tmp_path / "kuka_1"
    d.mkdir()
    T = np.eye(4)
    np.savetxt(d / "RobotPosesVec.txt", np.stack([T.ravel()] * 5), delimiter="\t")
    for k in range(1, 6):
        cv2.imwrite(str(d / f"{k:02d}.png"), np.full((120, 160), 200, np.uint8))

    def result(t_mm: float, fx: float):  # noqa: ANN202 - the fields the bench reads
        he = SimpleNamespace(t_m=np.array([t_mm, 0.0, 0.0]) / 1000, std_t_mm=1.5, std_rot_deg=0.1)
        return SimpleNamespace(
            hand_eye=he, cameras={"cam": SimpleNamespace(K=np.diag([fx, fx, 1]))}
        )

    full = result(0.0, 1000.0)
    seen = []

    def solve(session):  # noqa: ANN001, ANN202
        kept = [f.id for f in read_session(session).frames]
        seen.append(kept)
        return (4 if 3 not in kept else 0), result(2.0, 1001.0), 0.1

    monkeypatch.setattr(bench_public, "solve", solve)
    rows = bench_public.leave_out_rows("kuka_1", tmp_path, tmp_path / "w", full, 4)
    assert len(rows) == 4
    for r, kept in zip(rows, seen, strict=True):
        assert len(set(r.gone)) == 2 and set(r.gone) <= {1, 2, 3, 4, 5}
        assert sorted(kept + r.gone) == [1, 2, 3, 4, 5]
        assert r.code == (4 if 3 in r.gone else 0)
        assert r.dfx_px == 1.0 and abs(r.dt_mm - 2.0) < 1e-9
    again = bench_public.leave_out_rows("kuka_1", tmp_path, tmp_path / "w2", full, 4)
    assert [r.gone for r in again] == [r.gone for r in rows]  # seeded by the set
    table = bench_public._leave_out_section({"kuka_1": rows})
    line = next(x for x in table if x.startswith("| kuka_1 |"))
    accepted = sum(3 not in r.gone for r in rows)
    assert line.startswith(f"| kuka_1 | 4 | {accepted} | 0.100 to 0.100 | 1.50 to 1.50 |")
    for r in rows:
        assert (f"frames {r.gone} left out: exit 4" in line) == (3 in r.gone)
