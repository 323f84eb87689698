"""Session directories: write then read gives the same problem; every bad input names its field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from slidecal.drivers.ur_pose import T_from_ur_pose
from slidecal.routines.ops.install import install, installed_session
from slidecal.routines.session import (
    SESSION_FILE,
    SessionWriter,
    dump_yaml,
    load_session,
    load_yaml,
)
from slidecal.routines.solve import solve_session
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import T_from_Rt
from slidecal.solver.problem import (
    CalibrationProblem,
    CameraSpec,
    Detection,
    Frame,
    ModelOptions,
    Target,
)
from tests.helpers import random_rotation
from tests.session_io import read_session, write_session


def _problem(rng: np.random.Generator, n_frames: int = 4) -> CalibrationProblem:
    target = Target.charuco(11, 8, 0.03, 0.022)
    cams = (CameraSpec("left", 1280, 800), CameraSpec("right", 1280, 800))
    frames = []
    for i in range(n_frames):
        T = T_from_Rt(random_rotation(rng, 0.5), rng.uniform(-0.5, 0.5, 3))
        dets = {}
        for c in cams:
            ids = np.sort(rng.choice(70, size=int(rng.integers(5, 60)), replace=False))
            dets[c.name] = Detection(ids, rng.uniform(0, 800, (len(ids), 2)))
        if i == 2:  # the right camera saw nothing: the entry stays, with empty ids
            dets["right"] = Detection(np.zeros(0, int), np.zeros((0, 2)))
        frames.append(Frame(i, dets, T_base_tool=T, group=i // 2))
    return CalibrationProblem(
        target, cams, tuple(frames), options=ModelOptions(skew=True, outlier_threshold_px=3.0)
    )


def _same(a: CalibrationProblem, b: CalibrationProblem) -> None:
    assert a.target.kind == b.target.kind
    np.testing.assert_allclose(a.target.points_m, b.target.points_m, atol=1e-15)
    assert a.cameras == b.cameras
    assert (a.mount, a.knowledge, a.options) == (b.mount, b.knowledge, b.options)
    assert [f.id for f in a.frames] == [f.id for f in b.frames]
    for fa, fb in zip(a.frames, b.frames, strict=True):
        assert fa.group == fb.group
        if fa.T_base_tool is None:
            assert fb.T_base_tool is None
        else:
            np.testing.assert_allclose(fa.T_base_tool, fb.T_base_tool, atol=1e-14)
        assert set(fa.detections) == set(fb.detections)
        for name, d in fa.detections.items():
            np.testing.assert_array_equal(d.ids, fb.detections[name].ids)
            np.testing.assert_array_equal(d.px, fb.detections[name].px)


def test_round_trip_gives_the_same_problem(tmp_path: Path) -> None:
    p = _problem(np.random.default_rng(3))
    write_session(tmp_path / "s", p, simulation={"seed": 7})
    q = read_session(tmp_path / "s")
    _same(p, q)
    assert len(q.frames[2].detections["right"].ids) == 0
    s = load_session(tmp_path / "s")
    assert s.simulation == {"seed": 7} and s.status == "complete"


def test_writer_appends_frames_at_once_with_images(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    p = _problem(rng, 3)
    w = SessionWriter(tmp_path / "s", p.target, p.cameras, simulation={"seed": 7})
    img = rng.integers(0, 255, (800, 1280), dtype=np.uint8)
    for k, fr in enumerate(p.frames):
        T = fr.T_base_tool
        w.append_frame(T, {"left": img}, fr.detections, group=fr.group, T_base_tool_true=T)
        # after each append the file on disk is a valid session holding every frame so far
        s = load_session(tmp_path / "s", detect_images=False)
        assert len(s.problem.frames) == k + 1 and s.status == "recording"
        assert (tmp_path / "s" / "images" / f"{k:04d}_left.png").is_file()
    w.add_event("fault", "protective stop", frame=3)
    s = load_session(tmp_path / "s")
    assert s.events[0]["kind"] == "fault"
    # each frame's text (and its truth's) is made once, and the file is the dump of the whole
    text = (tmp_path / "s" / SESSION_FILE).read_text()
    assert text == dump_yaml(load_yaml(tmp_path / "s" / SESSION_FILE, "session"))
    assert not list((tmp_path / "s").glob(".*.tmp"))  # no temporary file left behind
    with pytest.raises(InputError, match="already holds a session"):
        SessionWriter(tmp_path / "s", p.target, p.cameras)


def test_sessions_without_robot_have_no_knowledge_and_no_mount(tmp_path: Path) -> None:
    p = _problem(np.random.default_rng(5))
    frames = tuple(Frame(f.id, f.detections) for f in p.frames)
    p2 = CalibrationProblem(p.target, p.cameras, frames, mount="none", knowledge="none")
    write_session(tmp_path / "s", p2)
    q = read_session(tmp_path / "s")
    assert (q.mount, q.knowledge) == ("none", "none")


def test_points_and_chessboard_targets_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    for k, target in enumerate(
        [Target.chessboard(9, 7, 0.025), Target.points(rng.uniform(0, 0.2, (12, 2)))]
    ):
        frames = (Frame(0, {"c": Detection([0, 1, 3], rng.uniform(0, 99, (3, 2)))}),)
        p = CalibrationProblem(
            target, (CameraSpec("c", 640, 480),), frames, mount="none", knowledge="none"
        )
        write_session(tmp_path / f"s{k}", p)
        _same(p, read_session(tmp_path / f"s{k}"))


def test_ur_pose_is_converted_by_the_ur_adapter(tmp_path: Path) -> None:
    pose = [0.4, -0.1, 0.3, 0.1, 2.9, -0.2]
    _write(tmp_path, frames=[{"id": 0, "T_base_tool": pose, "detections": _det()}])
    q = read_session(tmp_path)
    np.testing.assert_allclose(q.frames[0].T_base_tool, T_from_ur_pose(pose), atol=1e-15)


def test_robot_pose_in_another_controllers_form(tmp_path: Path) -> None:
    # one pose as UR records it and as ABB (quaternion, mm), KUKA/Fanuc (fixed-axes angles, mm)
    # and a matrix give one transform; scipy's rotations are the independent oracle
    from scipy.spatial.transform import Rotation

    pose = [0.4, -0.1, 0.3, 0.1, 2.9, -0.2]
    rot = Rotation.from_rotvec(pose[3:])
    x, y, z, w = (float(v) for v in rot.as_quat())
    t_mm = [1000.0 * v for v in pose[:3]]
    forms = [
        {"q_wxyz": [w, x, y, z], "t_mm": t_mm},
        {"q_wxyz": [-w, -x, -y, -z], "t_m": pose[:3]},
        {"rpy_deg": rot.as_euler("xyz", degrees=True).tolist(), "t_mm": t_mm},
        {"R": rot.as_matrix().tolist(), "t_m": pose[:3]},
    ]
    frames = [{"id": k, "T_base_tool": p, "detections": _det()} for k, p in enumerate(forms)]
    _write(tmp_path, frames=frames)
    for fr in read_session(tmp_path).frames:
        np.testing.assert_allclose(fr.T_base_tool, T_from_ur_pose(pose), atol=1e-12)


@pytest.mark.parametrize(
    ("pose", "field", "says"),
    [
        ({"q_wxyz": [1, 0, 0, 0], "R": np.eye(3).tolist(), "t_m": [0.4, 0, 0.3]}, "q_wxyz", "once"),
        ({"q_wxyz": [1, 0, 0, 0], "t_m": [0.4, 0, 0.3], "t_mm": [400, 0, 300]}, "t_mm", "once"),
        ({"q_wxyz": [0.5, 0.5, 0.5, 0.6], "t_m": [0.4, 0, 0.3]}, "q_wxyz", "unit quaternion"),
        ({"q_wxyz": [1, 0, 0, 0], "t_m": [400, 0, 300]}, "t_m", "t_mm"),
        ({"q_wxyz": [1, 0, 0], "t_m": [0.4, 0, 0.3]}, "q_wxyz", "4"),
        ({"t_mm": [400, 0, 300]}, "R", "q_wxyz"),
        ({"quat": [1, 0, 0, 0], "t_mm": [400, 0, 300]}, "quat", "q_wxyz"),
    ],
)
def test_bad_robot_pose_transform_names_its_field(tmp_path: Path, pose, field, says) -> None:
    _write(tmp_path, frames=[{"id": 0, "T_base_tool": pose, "detections": _det()}])
    with pytest.raises(InputError) as e:
        read_session(tmp_path)
    assert f"frames[0].T_base_tool.{field}" in str(e.value)
    assert says in str(e.value)


def test_image_of_another_size_than_its_camera_is_refused(tmp_path: Path) -> None:
    import cv2

    (tmp_path / "images").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "a.png"), np.full((720, 1280), 128, np.uint8))
    _write(
        tmp_path,
        frames=[
            {"id": 0, "T_base_tool": [0.4, 0, 0.3, 0, 3.1, 0], "images": {"left": "images/a.png"}}
        ],
    )
    with pytest.raises(InputError) as e:
        read_session(tmp_path)
    assert "frames[0].images.left" in str(e.value)
    assert "a.png is 1280 x 720 pixels, but camera 'left' is 1280 x 800" in str(e.value)


# ----------------------------------------------------------------------------- bad input

_GOOD = {
    "format": "slidecal.session/1",
    "mount": "eye_in_hand",
    "target": {
        "kind": "charuco",
        "squares_x": 11,
        "squares_y": 8,
        "square_size_m": 0.03,
        "marker_size_m": 0.022,
        "dictionary": "DICT_5X5_100",
    },
    "cameras": [{"name": "left", "width": 1280, "height": 800}],
}


def _det(ids=(0, 1, 2), px=((1.0, 2.0), (3.0, 4.0), (5.0, 6.0))):
    return {"left": {"ids": list(ids), "px": [list(p) for p in px]}}


def _write(d: Path, **changes) -> None:
    data = yaml.safe_load(yaml.safe_dump(_GOOD))
    data["frames"] = [{"id": 0, "T_base_tool": [0.4, 0, 0.3, 0, 3.1, 0], "detections": _det()}]
    for k, v in changes.items():
        if v is None:
            data.pop(k, None)
        else:
            data[k] = v
    d.mkdir(parents=True, exist_ok=True)
    (d / SESSION_FILE).write_text(yaml.safe_dump(data))


_T = [0.4, 0, 0.3, 0, 3.1, 0]
_CASES = [
    ({"format": "slidecal.sesion/1"}, "session.yaml: format", "not a slidecal session"),
    ({"format": "slidecal.session/2"}, "session.yaml: format", "upgrade slidecal"),
    ({"format": None}, "session.yaml: format", "missing"),
    ({"target": {**_GOOD["target"], "kind": "circles"}}, "target.kind", "use one of"),
    ({"target": {**_GOOD["target"], "square_size_m": 30}}, "square_size_m", "metres"),
    ({"target": {**_GOOD["target"], "dictionary": "DICT_9X9_1"}}, "target.dictionary", "OpenCV"),
    ({"target": {**_GOOD["target"], "marker_size_m": 0.04}}, "marker_size_m", "smaller"),
    ({"target": {"kind": "points", "points_m": [[0, 0], [1, 0]]}}, "points_m", "at least 4"),
    ({"cameras": []}, "session.yaml: cameras", "list"),
    ({"cameras": [{"name": "left", "width": -5, "height": 800}]}, "cameras[0].width", "least"),
    (
        {"frames": [{"id": 0, "T_base_tool": [0.4, 0, 0.3, 0, 3.1], "detections": _det()}]},
        "session.yaml: frames[0].T_base_tool",
        "has 5 numbers",
    ),
    (
        {"frames": [{"id": 0, "T_base_tool": [0.4, 0, "x", 0, 3.1, 0], "detections": _det()}]},
        "frames[0].T_base_tool",
        "array of numbers",
    ),
    (
        {"frames": [{"id": 0, "T_base_tool": _T, "detections": _det(ids=(0, 1))}]},
        "frames[0].detections.left.px",
        "3 positions for 2 ids",
    ),
    (
        {"frames": [{"id": 0, "T_base_tool": _T, "detections": _det(ids=(0, 1, 70))}]},
        "frames[0].detections.left.ids",
        "not on the target",
    ),
    (
        {"frames": [{"id": 0, "T_base_tool": _T, "detections": {"middle": {"ids": []}}}]},
        "frames[0].detections.middle",
        "unknown camera",
    ),
    (
        {"frames": [{"id": 0, "T_base_tool": _T, "images": {"left": "images/0000_left.png"}}]},
        "frames[0].images.left",
        "not found",
    ),
    (
        {
            "frames": [
                {"id": 0, "T_base_tool": _T, "detections": _det()},
                {"id": 1, "detections": _det()},
            ]
        },
        "frames[1].T_base_tool",
        "for every frame or for none",
    ),
    (
        {"frames": [{"id": 0, "detections": _det()}, {"id": 0, "detections": _det()}]},
        "frames[1].id",
        "twice",
    ),
    ({"mount": "on_the_wall"}, "session.yaml: mount", "use one of"),
    ({"reference_camera": "right"}, "reference_camera", "not a camera"),
    ({"options": {"distortion": [True, True]}}, "options.distortion", "5 booleans"),
]


@pytest.mark.parametrize(("changes", "where", "what"), _CASES)
def test_bad_input_names_file_and_field(tmp_path: Path, changes, where, what) -> None:
    _write(tmp_path, **changes)
    with pytest.raises(InputError) as e:
        read_session(tmp_path)
    assert where in str(e.value) and what in str(e.value)
    assert e.value.where is not None and e.value.where.startswith("session.yaml")


def test_an_image_path_that_names_a_folder_is_told_as_such(tmp_path: Path) -> None:
    (tmp_path / "images").mkdir()
    _write(tmp_path, frames=[{"id": 0, "T_base_tool": _T, "images": {"left": "images"}}])
    with pytest.raises(InputError, match=r"frames\[0\]\.images\.left: images is a folder"):
        read_session(tmp_path)


def test_missing_directory_and_file_and_bad_yaml(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not a session directory"):
        read_session(tmp_path / "nope")
    with pytest.raises(InputError, match="session.yaml not found"):
        read_session(tmp_path)
    (tmp_path / SESSION_FILE).write_text("format: [unclosed\n")
    with pytest.raises(InputError, match="not valid YAML at line"):
        read_session(tmp_path)


# ----------------------------------------------------------------------------- what solve needs

DATA = Path(__file__).parent / "data"


def test_old_sessions_still_load() -> None:
    """tests/data holds a slidecal.session/1 file as the first version wrote it."""
    s = load_session(DATA / "r1_session", detect_images=False)
    assert len(s.problem.frames) > 10 and s.cell == "default_cell.yaml"
    assert s.cell_sha256 is None and s.sockets == {} and s.camera_driver == "simulated"
    assert s.simulation is not None and s.status == "complete"


def test_old_sessions_with_inline_detections_read_as_rewritten_in_the_table_form(
    tmp_path: Path,
) -> None:
    old = load_session(DATA / "r1_session", detect_images=False)
    write_session(tmp_path / "s", old.problem)
    doc = yaml.safe_load((tmp_path / "s" / SESSION_FILE).read_text())
    assert doc["detections_file"] == "detections.npy"
    assert all(isinstance(n, int) for f in doc["frames"] for n in f["detections"].values())
    _same(old.problem, read_session(tmp_path / "s"))


def test_an_install_keeps_the_detections_table(tmp_path: Path) -> None:
    old = load_session(DATA / "r1_session", detect_images=False)
    write_session(tmp_path / "s", old.problem)
    result = solve_session(tmp_path / "s").result
    entry = install(tmp_path / "store", tmp_path / "s", result, "accepted")
    _same(old.problem, installed_session(entry))


def test_the_detections_table_is_numpys_own_format(tmp_path: Path) -> None:
    p = _problem(np.random.default_rng(8), 3)
    write_session(tmp_path / "s", p)
    table = np.load(tmp_path / "s" / "detections.npy")
    f1 = table[table["frame"] == 1]
    left = f1[f1["camera"] == 0]
    np.testing.assert_array_equal(left["id"], p.frames[1].detections["left"].ids)
    np.testing.assert_array_equal(left["u"], p.frames[1].detections["left"].px[:, 0])


def test_a_frame_in_flight_is_not_read_and_is_overwritten_on_resume(tmp_path: Path) -> None:
    """A crash after a frame's corners reached the table but before session.yaml listed it:
    the reader ignores the rows, and the resumed run writes its next frame over them."""
    p = _problem(np.random.default_rng(9), 4)
    w = SessionWriter(tmp_path / "s", p.target, p.cameras, options=p.options)
    for fr in p.frames[:2]:
        w.append_frame(fr.T_base_tool, detections=fr.detections, group=fr.group)
    listed = (tmp_path / "s" / SESSION_FILE).read_text()
    w.append_frame(p.frames[2].T_base_tool, detections=p.frames[2].detections)
    (tmp_path / "s" / SESSION_FILE).write_text(listed)  # the crash: session.yaml not rewritten
    assert len(read_session(tmp_path / "s").frames) == 2
    w2 = SessionWriter.reopen(tmp_path / "s")
    for fr in p.frames[2:]:
        w2.append_frame(fr.T_base_tool, detections=fr.detections, group=fr.group)
    _same(p, read_session(tmp_path / "s"))
    n_rows = sum(len(d.ids) for fr in p.frames for d in fr.detections.values())
    assert len(np.load(tmp_path / "s" / "detections.npy")) == n_rows


def test_a_damaged_or_missing_detections_table_is_named(tmp_path: Path) -> None:
    p = _problem(np.random.default_rng(10), 2)
    write_session(tmp_path / "s", p)
    table = np.load(tmp_path / "s" / "detections.npy")
    np.save(tmp_path / "s" / "detections.npy", table[:-1])
    with pytest.raises(InputError, match=r"^detections.npy: frame 1, camera 'right': holds \d+"):
        read_session(tmp_path / "s")
    table["id"][0] = 500
    np.save(tmp_path / "s" / "detections.npy", table)
    with pytest.raises(InputError, match="frame 0, camera 'left': id 500 is not on the target"):
        read_session(tmp_path / "s")
    np.save(tmp_path / "s" / "detections.npy", np.zeros((3, 5)))
    with pytest.raises(InputError, match="detections.npy: is not a detections table"):
        read_session(tmp_path / "s")
    (tmp_path / "s" / "detections.npy").unlink()
    with pytest.raises(InputError, match="detections_file: detections.npy not found"):
        read_session(tmp_path / "s")


def test_session_records_the_cell_and_the_oak_sockets(tmp_path: Path) -> None:
    import hashlib

    p = _problem(np.random.default_rng(1), n_frames=2)
    sha = hashlib.sha256(b"a cell").hexdigest()
    w = SessionWriter(
        tmp_path / "s",
        p.target,
        p.cameras,
        extra={"cell": "line4.yaml", "cell_sha256": sha, "camera_driver": "oak"},
        sockets={"left": "CAM_B", "right": "CAM_C"},
    )
    for fr in p.frames:
        w.append_frame(fr.T_base_tool, detections=fr.detections, group=fr.group)
    s = load_session(w.finish())
    assert (s.cell, s.cell_sha256, s.camera_driver) == ("line4.yaml", sha, "oak")
    assert s.sockets == {"left": "CAM_B", "right": "CAM_C"}


def test_writer_refuses_a_field_the_reader_would_refuse(tmp_path: Path) -> None:
    p = _problem(np.random.default_rng(2), n_frames=1)
    with pytest.raises(InputError, match="declare it in SESSION_KEYS"):
        SessionWriter(tmp_path / "s", p.target, p.cameras, extra={"cel": "x.yaml"})
    assert not (tmp_path / "s" / SESSION_FILE).exists()
