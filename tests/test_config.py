"""Cell files: the packaged cells load, bad fields are named, the default plan's geometry."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from slidecal.routines.acquire import sockets
from slidecal.routines.config import load_config, load_packaged_cell
from slidecal.routines.plan import check_plan, read_plan, write_plan
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import inv_T, rotation_angle_deg

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout: tests.*
from tests.fixed_plan import default_plan  # noqa: E402 - the reference plan


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
    ({"robot": {"wrkspace": {}}}, "robot.wrkspace", "did you mean workspace?"),
    ({"robot": {"workspace": {"min_m": [0, 0, 1], "max_m": [1, 1, 0]}}}, "max_m", "larger"),
    ({"mount": "ceiling"}, "cell.yaml: mount", "use one of"),
    ({"cameras": {"driver": "oak"}}, "cameras.driver", "simulated robot"),
    ({"simulation": {"camera_preset": "r1"}}, "simulation.T_tool_cam", "missing"),
    ({"robot": {"start_pose": [0, 0, 0.5]}}, "robot.start_pose", "UR pose"),
    ({"target": {"kind": "charuco"}}, "target.squares_x", "missing"),
    ({"camras": {}}, "cell.yaml: camras", "did you mean cameras?"),
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


# -- the simulation uses the user's approximate values; plan keys act or are refused ------------


def _default_dict() -> dict:
    path = Path(load_packaged_cell.__code__.co_filename).parents[1] / "mocks" / "default_cell.yaml"
    return yaml.safe_load(path.read_text())


def test_simulated_cell_uses_the_approximate_values_as_given() -> None:
    from slidecal.solver.geometry import Rx, Ry, Rz

    cfg = load_config()
    d = _default_dict()["approximate"]
    r, p, y = np.radians(d["T_tool_cam"]["rpy_deg"])
    np.testing.assert_allclose(cfg.approx_T_hand_eye[:3, :3], Rz(y) @ Ry(p) @ Rx(r), atol=1e-12)
    np.testing.assert_allclose(cfg.approx_T_hand_eye[:3, 3], d["T_tool_cam"]["t_m"])
    np.testing.assert_allclose(cfg.approx_T_target[:3, 3], d["T_base_board"]["t_m"])
    # and not the simulated truth (which differs by about a degree and a few millimetres)
    assert (
        rotation_angle_deg(cfg.approx_T_hand_eye[:3, :3], cfg.simulation.T_hand_eye[:3, :3]) > 0.5
    )


@pytest.mark.parametrize("driver", ["simulated", "ur"])
def test_wrong_mount_approximate_entry_is_refused_in_simulation_as_on_hardware(
    tmp_path: Path, driver: str
) -> None:
    d = _default_dict()
    d["approximate"]["T_base_cam"] = d["approximate"].pop("T_tool_cam")
    if driver == "ur":
        d["robot"] = {"driver": "ur", "host": "10.0.0.2"}
        d["cameras"] = {
            "driver": "oak",
            "list": [{"name": "cam", "width": 1280, "height": 800, "socket": "CAM_A"}],
        }
    p = tmp_path / "cell.yaml"
    p.write_text(yaml.safe_dump(d))
    with pytest.raises(InputError, match=r"approximate\.T_base_cam: is a pose of an eye_to_hand"):
        load_config(p)


def test_missing_approximate_target_pose_is_refused_in_simulation(tmp_path: Path) -> None:
    d = _default_dict()
    del d["approximate"]["T_base_board"]  # the old code took the simulated truth instead
    p = tmp_path / "cell.yaml"
    p.write_text(yaml.safe_dump(d))
    with pytest.raises(InputError, match=r"approximate\.T_base_board: is missing"):
        load_config(p)


@pytest.mark.parametrize(
    ("key", "value", "hint"),
    [
        ("frames_per_group", 5, "max_frames_per_group"),
        ("groups", 4, "max_groups"),
        ("tilt_deg", 20, "tilts_deg"),
    ],
)
def test_plan_keys_that_did_nothing_are_refused_with_the_key_that_acts(key, value, hint) -> None:
    with pytest.raises(InputError) as e:
        load_config(overrides={"plan": {key: value}})
    assert f"cell.yaml: plan.{key}: no longer acts" in str(e.value) and hint in str(e.value)


def test_every_plan_key_of_the_packaged_cells_is_a_planner_option() -> None:
    from importlib import resources

    from slidecal.routines.config import PLAN_KEYS

    for name in ("default_cell.yaml", "oak_cell.yaml", "eye_to_hand_cell.yaml"):
        data = yaml.safe_load(resources.files("slidecal.mocks").joinpath(name).read_text())
        assert set(data.get("plan") or {}) <= set(PLAN_KEYS)
        load_packaged_cell(name)  # and the cell reader accepts them


def test_plan_tilts_override_changes_the_plan() -> None:
    """``plan={"tilts_deg": [20]}`` (the CI helper's documented override) acts."""
    from slidecal.routines.planner import make_plan

    def tilts(cfg) -> set[float]:
        plan = make_plan(cfg)
        out = set()
        for grp in plan.groups:
            T_cam_board = inv_T(grp[0] @ cfg.approx_T_hand_eye) @ cfg.approx_T_target
            out.add(round(float(np.degrees(np.arccos(T_cam_board[2, 2]))), 6))
        return out

    assert tilts(load_config(overrides={"plan": {"tilts_deg": [20]}})) == {20.0}
    assert tilts(load_config()) != {20.0}


def test_cell_records_its_hash_and_oak_sockets(tmp_path: Path) -> None:
    import hashlib

    d = _default_dict()
    d["robot"] = {"driver": "ur", "host": "10.0.0.2"}
    d["cameras"] = {
        "driver": "oak",
        "list": [
            {"name": "left", "width": 1280, "height": 800, "socket": "CAM_B"},
            {"name": "right", "width": 1280, "height": 800, "socket": "CAM_C"},
        ],
    }
    p = tmp_path / "cell.yaml"
    p.write_text(yaml.safe_dump(d))
    cfg = load_config(p)
    assert sockets(cfg) == {"left": "CAM_B", "right": "CAM_C"}
    assert cfg.session_fields()["cell_sha256"] == hashlib.sha256(p.read_bytes()).hexdigest()
    assert cfg.session_fields()["cell"] == "cell.yaml"


def test_simulated_cameras_are_the_simulator_type() -> None:
    from slidecal.mocks.camera import SimCamera

    cfg = load_packaged_cell("oak_cell.yaml")
    assert all(type(c) is SimCamera for c in cfg.simulation.cameras)
    over = load_config(overrides={"simulation": {"cameras": {"cam": {"noise_std": 5.0}}}})
    (cam,) = over.simulation.cameras
    assert cam.noise_std == 5.0 and cam.K[0, 0] == 880.0  # the preset, with one value changed


def test_mocks_import_only_solver_and_drivers() -> None:
    """mocks/ sits below routines: no module of it imports slidecal.routines (AST walk)."""
    import ast

    mocks = Path(load_packaged_cell.__code__.co_filename).parents[1] / "mocks"
    offenders = []
    for path in sorted(mocks.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                package = ["slidecal", "mocks"][: 2 - max(node.level - 1, 0)] if node.level else []
                names = [".".join([*package, *([node.module] if node.module else [])])]
            for n in names:
                if n.startswith("slidecal.") and not n.startswith(
                    ("slidecal.solver", "slidecal.drivers", "slidecal.mocks")
                ):
                    offenders.append(f"{path.name}: {n}")
    assert offenders == []
    assert len(list(mocks.glob("*.py"))) >= 5


def test_formats_doc_names_every_declared_key() -> None:
    """docs/FORMATS.md documents every key the readers accept (one schema per format)."""
    import re

    from slidecal.routines.config import CELL_KEYS, GOAL_KEYS
    from slidecal.routines.config import PLAN_KEYS as PLANNER_KEYS
    from slidecal.routines.plan import PLAN_KEYS
    from slidecal.routines.results_io import RESULT_KEYS, RESULT_PART_KEYS
    from slidecal.routines.session import OPTIONS_KEYS, SESSION_KEYS, TARGET_KEYS

    doc = (Path(__file__).parents[1] / "docs" / "FORMATS.md").read_text(encoding="utf-8")
    keys = {
        k
        for table in (CELL_KEYS, SESSION_KEYS, TARGET_KEYS, RESULT_PART_KEYS)
        for v in table.values()
        for k in v
    }
    keys |= set(PLAN_KEYS) | set(PLANNER_KEYS) | set(GOAL_KEYS) | set(RESULT_KEYS)
    keys |= set(OPTIONS_KEYS)
    missing = sorted(k for k in keys if not re.search(rf"(?<![\w]){re.escape(k)}(?![\w])", doc))
    assert missing == []


def _same_config(a, b) -> None:
    from dataclasses import fields

    def same(x, y) -> bool:
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            return x is not None and y is not None and np.allclose(x, y, atol=1e-12)
        if isinstance(x, dict) and isinstance(y, dict):
            return x.keys() == y.keys() and all(same(x[k], y[k]) for k in x)
        if isinstance(x, tuple | list) and isinstance(y, tuple | list):
            return len(x) == len(y) and all(same(u, v) for u, v in zip(x, y, strict=True))
        if hasattr(x, "__dataclass_fields__"):
            return all(
                same(getattr(x, f.name), getattr(y, f.name)) for f in fields(x) if f.name != "raw"
            )
        return x == y

    for f in fields(a):
        if f.name in ("raw", "source", "sha256"):
            continue
        assert same(getattr(a, f.name), getattr(b, f.name)), f.name


@pytest.mark.parametrize("name", ["default_cell.yaml", "oak_cell.yaml", "eye_to_hand_cell.yaml"])
def test_cell_write_then_read_gives_the_same_cell(tmp_path: Path, name: str) -> None:
    from tests.session_io import write_config

    cfg = load_packaged_cell(name)
    _same_config(cfg, load_config(write_config(cfg, tmp_path / "cell.yaml")))


def test_real_cell_write_then_read_gives_the_same_cell(tmp_path: Path) -> None:
    from tests.session_io import write_config

    d = _default_dict()
    del d["simulation"]
    d["robot"] = {"driver": "ur", "host": "10.0.0.2", "tcp": [0, 0, 0.1, 0, 0, 0],
                  "take_control": True, "upper_range_registers": True}  # fmt: skip
    d["cameras"] = {
        "driver": "oak",
        "device_id": "1844301011B5",
        "list": [
            {"name": "left", "width": 1280, "height": 800, "socket": "CAM_B", "colour": False}
        ],
    }
    p = tmp_path / "in.yaml"
    p.write_text(yaml.safe_dump(d))
    cfg = load_config(p)
    _same_config(cfg, load_config(write_config(cfg, tmp_path / "out.yaml")))
