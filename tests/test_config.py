"""Cell files: the packaged cells load, bad fields are named, the default plan's geometry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from slidecal.routines.config import load_config, load_packaged_cell
from slidecal.routines.plan import check_plan, default_plan, read_plan, write_plan
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import inv_T, rotation_angle_deg


@pytest.mark.parametrize("name", ["default_cell.yaml", "oak_cell.yaml", "eye_to_hand_cell.yaml"])
def test_packaged_cells_load_and_are_simulated(name: str) -> None:
    cfg = load_packaged_cell(name)
    assert cfg.simulated and cfg.robot.driver == "simulated"
    if name == "oak_cell.yaml":
        assert [c.name for c in cfg.cameras] == ["left", "right", "rgb"]


def _cell(tmp_path: Path, **changes) -> Path:
    d = yaml.safe_load(
        (
            Path(load_packaged_cell.__code__.co_filename).parents[1] / "mocks" / "default_cell.yaml"
        ).read_text()
    )
    for k, v in changes.items():
        d[k] = v
    p = tmp_path / "cell.yaml"
    p.write_text(yaml.safe_dump(d))
    return p


_BAD = [
    ({"robot": {"driver": "ur"}}, "robot.host", "controller's address"),
    ({"robot": {"driver": "fanuc"}}, "robot.driver", "use one of"),
    ({"robot": {"speed_mps": 2.0}}, "robot.speed_mps", "slow"),
    ({"robot": {"wrkspace": {}}}, "robot.wrkspace", "not a robot field"),
    ({"robot": {"workspace": {"min_m": [0, 0, 1], "max_m": [1, 1, 0]}}}, "max_m", "larger"),
    ({"mount": "ceiling"}, "cell.yaml: mount", "use one of"),
    ({"cameras": {"driver": "oak"}}, "cameras.driver", "simulated robot"),
    ({"simulation": {"camera_preset": "r1"}}, "simulation.T_tool_cam", "missing"),
    ({"robot": {"start_pose": [0, 0, 0.5]}}, "robot.start_pose", "UR pose"),
    ({"target": {"kind": "charuco"}}, "target.squares_x", "missing"),
    ({"camras": {}}, "cell.yaml: camras", "not a cell field"),
]


@pytest.mark.parametrize(("changes", "where", "what"), _BAD)
def test_bad_cell_fields_are_named(tmp_path: Path, changes, where, what) -> None:
    with pytest.raises(InputError) as e:
        load_config(_cell(tmp_path, **changes))
    assert where in str(e.value) and what in str(e.value)
    assert "\n" not in str(e.value)


def test_real_robot_needs_real_cameras_and_a_host(tmp_path: Path) -> None:
    p = _cell(tmp_path, robot={"driver": "ur", "host": "10.0.0.2"})
    with pytest.raises(InputError, match="name the real cameras"):
        load_config(p)


def test_default_plan_geometry() -> None:
    cfg = load_config()
    plan = default_plan(cfg)
    assert len(plan.groups) == 4 and all(len(g) == 5 for g in plan.groups)
    T_he, T_tg = cfg.approx_T_hand_eye, cfg.approx_T_target
    tilts, normals = [], []
    for grp in plan.groups:
        R0 = grp[0][:3, :3]
        T_cam_board = [inv_T(T @ T_he) @ T_tg for T in grp]
        # pure translations inside a group
        assert all(rotation_angle_deg(T[:3, :3], R0) < 1e-9 for T in grp)
        tilts.append(np.degrees(np.arccos(T_cam_board[0][2, 2])))
        # camera displacements (camera axes) from the first frame: 40-80 mm, non-coplanar,
        # every one leaving the board plane
        d = np.array([(T @ T_he)[:3, 3] - (grp[0] @ T_he)[:3, 3] for T in grp[1:]])
        lengths_mm = np.linalg.norm(d, axis=1) * 1000
        assert np.all((lengths_mm > 40 - 1e-6) & (lengths_mm < 115))
        assert np.linalg.matrix_rank(d, tol=1e-3) == 3
        n_board_base = T_tg[:3, 2]
        assert np.all(np.abs(d @ n_board_base) > 0.02)
        normals.append(T_cam_board[0][:3, 2])
        # board centre on the optical axis at about the standoff
        c = T_cam_board[0][:3, :3] @ cfg.target.points_m.mean(0) + T_cam_board[0][:3, 3]
        assert abs(np.linalg.norm(c) - 0.5) < 1e-6 and np.linalg.norm(c[:2]) < 1e-6
    np.testing.assert_allclose(tilts, 25.0, atol=1e-6)
    # tilt axes differ between groups (hand-eye translation observable)
    assert np.linalg.matrix_rank(np.array(normals), tol=1e-3) == 3


def test_plan_round_trip_and_refusals(tmp_path: Path) -> None:
    cfg = load_config()
    plan = default_plan(cfg)
    q = read_plan(write_plan(plan, tmp_path / "plan.yaml"))
    for ga, gb in zip(plan.groups, q.groups, strict=True):
        np.testing.assert_allclose(np.array(ga), np.array(gb), atol=1e-12)
    assert q.predicted_std is None and q.duration_s is None
    check_plan(plan, cfg)
    far = load_config(
        overrides={"robot": {"workspace": {"min_m": [-0.3, -0.4, 0.2], "max_m": [0.0, 0.4, 0.9]}}}
    )
    with pytest.raises(InputError, match="outside the workspace box"):
        check_plan(plan, far)
    with pytest.raises(InputError, match="not reachable"):
        check_plan(plan, cfg, is_reachable=lambda T: False)
