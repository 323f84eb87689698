"""``slidecal import``: simulated recordings with their poses written in every supported
convention; the import must find the one used, refuse what the images cannot tell, and report
what does not pair, by name."""

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from slidecal.mocks import scenarios as sc
from slidecal.mocks.camera import single_camera
from slidecal.mocks.render import render_target
from slidecal.routines import importer
from slidecal.routines.cli import main as cli
from slidecal.routines.session import load_session
from slidecal.solver.calibrate import calibrate
from slidecal.solver.camera import K_matrix
from slidecal.solver.geometry import inv_T, rotation_angle_deg

CELL = str(Path(sc.__file__).with_name("default_cell.yaml"))
EULER_SEQ = {"Z-Y-X": "ZYX", "X-Y-Z fixed": "xyz", "X-Y-Z": "XYZ", "Z-Y-Z": "ZYZ"}

#: Half of R1's camera (640 x 400): recorded datasets render faster and keep R1's geometry
R1_HALF = replace(single_camera(), width=640, height=400, K=K_matrix(440.0, 440.0, 319.75, 199.75))


def recorded_dataset(directory: str | Path, s: sc.Scenario, rng: np.random.Generator) -> np.ndarray:
    """Scenario ``s``'s frames as another tool records them: each view of its target at the
    frame's ``T_base_tool`` (its truth's hand-eye and target pose) rendered by ``R1_HALF`` as
    ``1.png``, ``2.png``, ... in ``directory``. Returns the ``T_base_tool`` (F, 4, 4) of the
    images, metres, for writing in any convention."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    T = np.stack([f.T_base_tool for f in s.problem.frames])
    X, Y = s.truth.X[0], s.truth.Y  # T_cam_tool, T_base_board; eye-to-hand T_cam_base, T_tool_board
    for k, T_bt in enumerate(T):
        T_cam_board = X @ (inv_T(T_bt) if s.problem.mount == "eye_in_hand" else T_bt) @ Y
        img = render_target(s.problem.target, R1_HALF, T_cam_board, rng)
        cv2.imwrite(str(directory / f"{k + 1}.png"), img)
    return T


def record(T_base_tool, convention):
    """One row per pose in ``convention`` (importer's names), written with scipy's own
    conversions: the reverse of the reading the import must find."""
    unit, rotation, direction = convention.split(", ")
    rows = []
    for T in T_base_tool:
        T = T if direction == "tool in base" else inv_T(T)
        t = T[:3, 3] / (1e-3 if unit == "mm" else 1.0)
        rot = Rotation.from_matrix(T[:3, :3])
        deg = rotation.endswith("deg")
        if rotation.startswith("rotation vector"):
            rows.append([*t, *rot.as_rotvec(degrees=deg)])
        elif rotation.startswith("Euler"):
            rows.append(
                [*t, *rot.as_euler(EULER_SEQ[rotation[len("Euler ") : -len(" deg")]], degrees=deg)]
            )
        elif rotation.startswith("quaternion"):
            x, y, z, w = rot.as_quat()
            rows.append([*t, *([w, x, y, z] if "w-first" in rotation else [x, y, z, w])])
        else:
            M = np.vstack([np.column_stack([T[:3, :3], t]), [0, 0, 0, 1]])
            rows.append(
                list(
                    (M.T if "columns" in rotation else M).reshape(-1)[
                        : 12 if "3x4" in rotation else 16
                    ]
                )
            )
    return np.array(rows)


FAST = (
    "mm, Euler Z-Y-X deg, tool in base",
    "m, rotation vector rad, tool in base",
    "m, Euler X-Y-Z fixed rad, base in tool",
    "mm, quaternion w-first, tool in base",
    "m, quaternion w-last, base in tool",
    "m, 4x4 matrix by rows, tool in base",
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    d = tmp_path_factory.mktemp("recorded")
    s = sc.r1(np.random.default_rng(0), 0.0, 0.0, 0.0)
    return d, recorded_dataset(d / "images", s, np.random.default_rng(0))


def _import(tmp_path, images, poses, *extra):
    out = tmp_path / "session"
    code = cli(["import", str(images), str(poses), "--config", CELL, "--out", str(out), *extra])
    return code, out


@pytest.mark.parametrize(
    "convention",
    [
        pytest.param(c, marks=() if c in FAST else pytest.mark.slow)
        for n in (6, 7, 12, 16)
        for c in importer.conventions(n)
    ],
)
def test_import_finds_the_convention_used(dataset, tmp_path, capsys, convention):
    d, T_true = dataset
    rows = record(T_true, convention)
    header = "x,y,z," + ",".join(f"c{k}" for k in range(rows.shape[1] - 3))
    poses = tmp_path / "poses.csv"
    np.savetxt(poses, rows, delimiter=",", header=header, comments="")
    code, out = _import(tmp_path, d / "images", poses)
    text = capsys.readouterr()
    assert code == 0, text.err
    assert f"poses read as: {convention}\n" in text.out
    s = load_session(out)
    recorded = yaml.safe_load((out / "session.yaml").read_text())["import"]
    assert recorded["convention"] == dict(
        zip(("units", "rotation", "direction"), convention.split(", "), strict=True)
    )
    got = np.stack([f.T_base_tool for f in s.problem.frames])
    assert (
        max(rotation_angle_deg(a[:3, :3], b[:3, :3]) for a, b in zip(got, T_true, strict=True))
        < 1e-4
    )
    assert np.abs(got[:, :3, 3] - T_true[:, :3, 3]).max() < 1e-6


def test_sidecars_by_name_and_unpaired_reported(dataset, tmp_path, capsys):
    d, T_true = dataset
    rows = record(T_true, "mm, Euler Z-Y-X deg, tool in base")
    side = tmp_path / "poses"
    side.mkdir()
    for k, r in enumerate(rows[:-1]):  # the last image has no pose
        (side / f"{k + 1}.json").write_text(json.dumps({"pose_flange": list(r), "t": k}))
    (side / "99.yaml").write_text(yaml.safe_dump({"pose_flange": list(map(float, rows[0]))}))
    code, out = _import(tmp_path, d / "images", side)
    text = capsys.readouterr().out
    assert code == 0
    assert "rows without an image: 99.yaml (99)" in text
    assert f"images without a row: {len(rows)}.png" in text
    assert len(load_session(out).problem.frames) == len(rows) - 1


def test_rotation_free_dataset_is_refused_naming_what_cannot_be_told(tmp_path, capsys):
    s = sc.r1(np.random.default_rng(1), 0.0, 0.0, 0.0)  # its first orientation's 5 frames
    s = replace(s, problem=replace(s.problem, frames=s.problem.frames[:5]))
    T = recorded_dataset(tmp_path / "images", s, np.random.default_rng(1))
    poses = tmp_path / "poses.txt"
    np.savetxt(poses, record(T, "mm, Euler Z-Y-X deg, tool in base"))
    code, _ = _import(tmp_path, tmp_path / "images", poses)
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert "no rotation between frames" in err and "--convention" in err
    # the reading meant, given, is taken: the poses are the recorded ones
    forced = ("--convention", "mm, Euler Z-Y-X deg, tool in base")
    code, out = _import(tmp_path, tmp_path / "images", poses, *forced)
    assert code == 0
    got = np.stack([f.T_base_tool for f in load_session(out).problem.frames])
    assert np.abs(got - T).max() < 1e-6


def test_count_mismatch_in_order_is_refused(dataset, tmp_path, capsys):
    d, T_true = dataset
    poses = tmp_path / "poses.txt"
    np.savetxt(poses, record(T_true[:-2], "m, rotation vector rad, tool in base"))
    code, _ = _import(tmp_path, d / "images", poses)
    err = capsys.readouterr().err
    assert code == 2 and f"{len(T_true)} images but {len(T_true) - 2} pose rows" in err


def test_natural_order():
    names = ["10.jpg", "2.jpg", "1.jpg"]
    assert sorted(names, key=importer.natural_key) == ["1.jpg", "2.jpg", "10.jpg"]


@pytest.mark.slow  # renders 33 images, solves: the second CI tier
def test_symmetric_board_turned_in_view_imported_and_solved(tmp_path, capsys):
    # the ABB-like case through the real renderer and detector: an 8 x 6-square chessboard on the
    # tool, eye-to-hand; in 6 frames the tool turns the board 150 deg in view, so the detector's
    # rule reads its corner 0 at the opposite corner there. The import still finds the poses'
    # convention; the solve turns those frames back by the robot and the focal length matches
    rolled = (6, 7, 8, 9, 15, 16)
    s = sc.symmetric_board_r1(np.random.default_rng(6), 0.0, 0.0, 0.0, rolled=rolled)
    T = recorded_dataset(tmp_path / "images", s, np.random.default_rng(6))
    cell = tmp_path / "cell.yaml"
    cfg = yaml.safe_load(Path(CELL).with_name("eye_to_hand_cell.yaml").read_text())
    cfg["target"] = {"kind": "chessboard", "squares_x": 8, "squares_y": 6, "square_size_m": 0.03}
    cell.write_text(yaml.safe_dump(cfg))
    poses = tmp_path / "poses.txt"
    np.savetxt(poses, record(T, "mm, Euler Z-Y-X deg, tool in base"))
    out = tmp_path / "session"
    argv = [
        "import",
        str(tmp_path / "images"),
        str(poses),
        "--config",
        str(cell),
        "--out",
        str(out),
    ]
    assert cli(argv) == 0, capsys.readouterr().err
    assert "poses read as: mm, Euler Z-Y-X deg, tool in base\n" in capsys.readouterr().out
    problem = load_session(out).problem
    # the frames the detector read the other way round than the truth (or all the others)
    flipped = []
    for k, f in enumerate(problem.frames):
        X, Y = s.truth.X[0], s.truth.Y
        px = sc.projected_detection(
            R1_HALF.K,
            R1_HALF.dist,
            X @ T[k] @ Y,
            problem.target,
            (640, 400),
            0.0,
            np.random.default_rng(),
        ).px
        det = f.detections[name := problem.reference]
        if np.linalg.norm(det.px[0] - px[0]) > np.linalg.norm(det.px[0] - px[-1]):
            flipped.append(k)
    assert flipped and len(flipped) < len(T)
    if 2 * len(flipped) > len(T):
        flipped = [k for k in range(len(T)) if k not in flipped]
    res = calibrate(problem)
    turned = next(m for m in res.messages if "half turn" in m)
    assert turned.startswith(f"frames {flipped} ")
    # 33 views of 35 corners at about 0.1 px: the focal length to a few tenths of a percent
    assert res.cameras[name].K[0, 0] == pytest.approx(R1_HALF.K[0, 0], rel=5e-3)
    assert res.adequacy.adequate


def test_bad_pose_files_are_refused_in_one_line(dataset, tmp_path, capsys):
    d, T_true = dataset
    poses = tmp_path / "poses.csv"
    rows = record(T_true, "m, rotation vector rad, tool in base")
    text = "x,y,z,rx,ry,rz\n" + "\n".join(",".join(map(str, r)) for r in rows)
    poses.write_text(text.replace(",".join(map(str, rows[1])), "1,2,3,4,5", 1))
    assert _import(tmp_path, d / "images", poses)[0] == 2
    err = capsys.readouterr().err
    assert (
        err.startswith("slidecal: poses.csv: line 3: a pose must be 6 numbers")
        and err.count("\n") == 1
    )
    assert _import(tmp_path, tmp_path / "nowhere", poses)[0] == 2
    assert "nowhere" in capsys.readouterr().err
    side = tmp_path / "side"
    side.mkdir()
    (side / "1.json").write_text(json.dumps({"joints": [0.0] * 6}))
    assert _import(tmp_path, d / "images", side)[0] == 2
    assert "1.json: has none of the keys" in capsys.readouterr().err
