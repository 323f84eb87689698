"""The robot's accuracy and the model-adequacy test on disk, in the summary, in the options and
in the simulated cell (the files that carry them: results_io, session, config, mocks/cell)."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np
import pytest
import yaml

from slidecal.mocks import scenarios as sc
from slidecal.mocks.cell import SimulatedCell
from slidecal.routines.config import load_config, load_packaged_cell
from slidecal.routines.results_io import read_result, summary_text, write_result
from slidecal.routines.session import options_from_dict, options_to_dict
from slidecal.solver.calibrate import calibrate
from slidecal.solver.problem import ModelOptions


def test_adequacy_and_robot_accuracy_round_trip_and_are_summarised(tmp_path: Path) -> None:
    s = sc.r1(np.random.default_rng(31), 0.15, 1e-3, 0.05)
    res = calibrate(s.problem)
    path = write_result(res, tmp_path / "result.yaml")
    raw = yaml.safe_load(path.read_text())
    assert raw["adequacy"]["adequate"] is True
    assert raw["robot_accuracy"]["estimated"] is True
    assert 0.5 < raw["robot_accuracy"]["translation_mm"] < 1.5
    back = read_result(path)
    assert back.adequacy == res.adequacy
    assert back.robot_accuracy.worst_frames == res.robot_accuracy.worst_frames
    text = summary_text(res)
    assert "model adequacy: the model explains the images" in text
    assert "robot accuracy (estimated from the images)" in text


def test_an_inadequate_result_says_so_first(tmp_path: Path) -> None:
    opts = ModelOptions(robot_noise_m=5e-5, robot_noise_deg=0.005, estimate_robot_noise=False)
    s = sc.r1(np.random.default_rng(32), 0.15, 5e-3, 0.005, options=opts)
    res = calibrate(s.problem)
    text = summary_text(res)
    lines = text.splitlines()
    assert lines[3] == "MODEL INADEQUATE: do not use this result"
    assert "times the detector's noise" in lines[4]
    back = read_result(write_result(res, tmp_path / "result.yaml"))
    assert back.adequacy.adequate is False and back.adequacy.reasons == res.adequacy.reasons


def test_estimate_robot_noise_option_round_trips() -> None:
    o = options_from_dict({"estimate_robot_noise": False, "robot_noise_mm": 0.5}, "s.yaml")
    assert o.estimate_robot_noise is False and o.robot_noise_m == 0.0005
    assert options_from_dict(options_to_dict(o), "s.yaml") == o
    assert options_from_dict({}, "s.yaml").estimate_robot_noise is True


def test_simulated_cell_with_a_real_arms_kinematic_error(tmp_path) -> None:
    over = {"simulation": {"kinematic_error": {"mm": 1.0, "deg": 0.1}}}
    cfg = load_packaged_cell("default_cell.yaml", over)
    assert cfg.simulation.kinematic_error["repeatability_mm"] == 0.03
    cell = SimulatedCell.from_config(cfg, seed=3)
    cell.robot.connect()
    T_true, T_meas = cell.robot.true_pose(), cell.robot.measured_pose()
    err_mm = 1000 * np.linalg.norm(T_true[:3, 3] - T_meas[:3, 3])
    assert 0.1 < err_mm < 3.0
    assert cell.truth["noise"]["kinematic_error"]["deg"] == 0.1
    # the shipped cell carries a real arm; a cell without the key has an exact arm
    text = resources.files("slidecal.mocks").joinpath("default_cell.yaml").read_text()
    lines = [ln for ln in text.splitlines() if not ln.lstrip().startswith("kinematic_error:")]
    (tmp_path / "exact_arm.yaml").write_text("\n".join(lines) + "\n")
    plain = SimulatedCell.from_config(load_config(str(tmp_path / "exact_arm.yaml")), seed=3)
    assert plain.robot.kinematic_error is None
    assert "kinematic_error" not in plain.truth["noise"]


@pytest.mark.slow
def test_a_simulated_cell_can_bow_its_board() -> None:
    # simulation.board_bow_mm: the rig renders a bowed board (the images differ from the flat
    # board's at the same seed), the truth records the bow, the target is described as a real
    # board (a real board's tolerance by default); a bow of metres is refused with its field
    import pytest

    from slidecal.solver.errors import InputError

    flat_cfg = load_packaged_cell("default_cell.yaml")
    assert flat_cfg.target.flatness_m == 0.0 and flat_cfg.simulation.board_bow_mm == (0.0, 0.0)
    cfg = load_packaged_cell("default_cell.yaml", {"simulation": {"board_bow_mm": [0.4, -0.2]}})
    assert cfg.simulation.board_bow_mm == (0.4, -0.2)
    assert cfg.target.flatness_m > 0.0 and cfg.target.print_tolerance > 0.0
    images = []
    for c in (flat_cfg, cfg):
        cell = SimulatedCell.from_config(c, seed=3)
        cell.robot.connect()
        cell.rig.open()
        images.append(next(iter(cell.rig.capture().values())).astype(float))
    assert cell.rig.bow_m == (0.0004, -0.0002)
    assert cell.truth["board_bow_mm"] == [0.4, -0.2]
    changed = np.abs(images[1] - images[0]) > 20.0  # grey levels: edges moved by the bow
    assert 0 < changed.mean() < 0.05
    with pytest.raises(InputError, match="board_bow_mm"):
        load_packaged_cell("default_cell.yaml", {"simulation": {"board_bow_mm": [400, 0]}})


def test_the_summary_writes_an_undetermined_std_in_powers_of_ten() -> None:
    import dataclasses

    res = calibrate(sc.r1(np.random.default_rng(31)).problem)
    cam = res.cameras["cam"]
    huge = dataclasses.replace(cam, std={**cam.std, "fx": 4.8e15})
    text = summary_text(dataclasses.replace(res, cameras={**res.cameras, "cam": huge}))
    line = next(ln for ln in text.splitlines() if ln.lstrip().startswith("fx"))
    assert line.endswith("+- 4.8e+15 px")
    fy = next(ln for ln in text.splitlines() if ln.lstrip().startswith("fy"))
    assert f"+- {cam.std['fy']:.3f} px" in fy
