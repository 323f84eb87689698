"""A user's mistakes that once passed the verdict (issue 39): each built from a good simulated
session plus the one mistake, judged as ``slidecal solve`` judges it; none may be accepted, and
each finding names its cause. The good session beside it must stay accepted."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from slidecal.mocks import scenarios as sc
from slidecal.routines.config import load_packaged_cell
from slidecal.routines.ops.install import NotInstalled, install
from slidecal.routines.ops.report import robot_panel
from slidecal.routines.ops.verdict import judge
from slidecal.routines.run import RunRequest, run_calibration
from slidecal.routines.session import load_session
from slidecal.routines.solve import solve_session
from slidecal.solver.calibrate import calibrate
from slidecal.solver.errors import DegenerateError, InputError
from tests.session_io import centre_only, copy_session, edit_session, focus_changed, swap_cameras

OAK_SOCKETS = {"left": "CAM_B", "right": "CAM_C"}


@pytest.fixture(scope="module")
def stereo():
    return sc.oak_rig(np.random.default_rng(3), cameras=("left", "right")).problem


def test_stereo_pair_in_socket_order_is_accepted(stereo):
    v = judge(calibrate(stereo), problem=stereo, sockets=OAK_SOCKETS, command="solve")
    (c,) = [c for c in v.checks if c.test == "stereo"]
    assert c.passed and 70 < c.value < 80  # right lies 75 mm along the left's +x
    assert v.verdict == "accepted", v.lines()


def test_stereo_left_and_right_swapped_is_rejected_naming_the_swap(stereo):
    swapped = swap_cameras(stereo, "left", "right")
    v = judge(calibrate(swapped), problem=swapped, sockets=OAK_SOCKETS, command="solve")
    assert v.verdict == "rejected" and v.exit_code == 4
    (c,) = [c for c in v.reasons if c.test == "stereo"]
    assert -80 < c.value < -70 and "swapped" in c.message and "CAM_C" in c.message


@pytest.fixture(scope="module")
def eye_to_hand(tmp_path_factory):
    """A good run of the simulated eye-to-hand cell (seed 1): its problem and result."""
    cfg = load_packaged_cell("eye_to_hand_cell.yaml")
    o = run_calibration(
        RunRequest(
            cfg,
            out_dir=tmp_path_factory.mktemp("e2h") / "s",
            progress=False,
            recording=False,
            seed=1,
        )
    )
    assert o.verdict.verdict == "accepted", o.verdict.lines()
    return load_session(o.session_dir).problem, o


@pytest.mark.parametrize("factor", [1.01, 1.003])
def test_focus_changed_halfway_is_rejected_naming_the_change(eye_to_hand, factor):
    problem, o = eye_to_hand
    assert all(c.passed for c in o.verdict.checks if c.test == "intrinsics")
    half = len(problem.frames) // 2
    changed = focus_changed(problem, "cam", o.result.cameras["cam"].K, factor, half)
    v = judge(calibrate(changed), problem=changed, command="solve")
    assert v.verdict == "rejected"
    (c,) = [c for c in v.reasons if c.test == "intrinsics"]
    assert "focus" in c.message and c.value > c.limit
    if factor == 1.01:  # where it changed (a 0.3 % change is placed only roughly)
        assert f"from frame {problem.frames[half].id} on" in c.message


def images_one_frame_late(doc: dict) -> None:
    """The first image dropped: each image recorded with the previous frame's robot pose."""
    frames = doc["frames"]
    for k in range(len(frames) - 1, 0, -1):
        frames[k]["T_base_tool"] = frames[k - 1]["T_base_tool"]
    del frames[0]


def test_images_paired_with_the_previous_pose_name_the_shift_alone(eye_to_hand, tmp_path):
    _, o = eye_to_hand
    d = edit_session(copy_session(o.session_dir, tmp_path / "s"), images_one_frame_late)
    try:
        v = solve_session(d).verdict
    except DegenerateError as e:  # refused before a solve: the shift is the one cause given
        message = str(e)
    else:
        assert v.verdict == "rejected"
        assert [c.test for c in v.reasons if c.test != "session"] == ["adequacy"]
        assert not v.notes
        message = v.reasons[-1].message
    assert "1 frame(s) later" in message and "shifted" in message
    assert "T_tool_base" not in message and "did NOT converge" not in message


def _poses_off(problem, mm: float, seed: int = 0):  # noqa: ANN001, ANN202
    """The robot's recorded positions off by ``mm`` per axis (one sigma), frame by frame."""
    rng = np.random.default_rng(seed)
    frames = []
    for f in problem.frames:
        T = np.array(f.T_base_tool, dtype=float)
        T[:3, 3] += rng.normal(0.0, mm / 1000.0, 3)
        frames.append(dataclasses.replace(f, T_base_tool=T))
    return dataclasses.replace(problem, frames=tuple(frames))


def test_learned_arm_error_beyond_the_installed_level_is_not_accepted(eye_to_hand):
    problem, o = eye_to_hand
    (c,) = [c for c in o.verdict.checks if c.test == "arm"]
    assert c.passed and c.value < 0.5  # this cell's arm: tenths of a millimetre
    off = _poses_off(problem, 1.0)
    v = judge(calibrate(off), problem=off, installed=o.result, installed_problem=problem)
    assert v.verdict != "accepted"
    (c,) = [c for c in v.reasons if c.test == "arm"]
    assert c.value > 2.5 and "installed calibration's" in c.message


def test_learned_arm_error_beyond_its_class_is_rejected(eye_to_hand):
    problem, _ = eye_to_hand
    off = _poses_off(problem, 3.0, seed=1)
    v = judge(calibrate(off), problem=off, command="solve")
    assert v.verdict == "rejected"
    assert any(c.test == "arm" and "beyond any arm of its class" in c.message for c in v.reasons)


@pytest.fixture(scope="module")
def store(eye_to_hand, tmp_path_factory):
    """The eye-to-hand run installed as a run installs it (its cell named)."""
    _, o = eye_to_hand
    s = tmp_path_factory.mktemp("store") / "store"
    install(s, o.session_dir, o.result, "accepted", info={"cell": "eye_to_hand_cell.yaml"})
    return s


@pytest.mark.parametrize(
    "edit, says",
    [
        (lambda doc: doc.update(cell="default_cell.yaml"), "holds the calibration of cell"),
        (lambda doc: doc["cameras"][0].update(width=1920, height=1200), "1280x800, this one"),
    ],
)
def test_solve_against_another_cells_store_says_so_before_comparing(
    eye_to_hand, store, tmp_path, edit, says
):
    _, o = eye_to_hand
    d = edit_session(copy_session(o.session_dir, tmp_path / "s"), edit)
    with pytest.raises(InputError) as e:
        solve_session(d, installed=store)
    assert says in str(e.value) and "nothing was compared" in str(e.value)
    assert "drift" not in str(e.value).replace("not a drift", "")
    assert not (d / "result.yaml").exists()


def test_a_drifted_result_names_a_flag_run_has_and_exits_0_once_installed(eye_to_hand, store):
    _, o = eye_to_hand
    with pytest.raises(NotInstalled, match="run again with --accept-drift"):
        install(store, o.session_dir, o.result, "drifted")
    drifted = dataclasses.replace(o, verdict=dataclasses.replace(o.verdict, verdict="drifted"))
    assert drifted.exit_code == 5
    assert dataclasses.replace(drifted, installed_to=store / "history" / "x").exit_code == 0


def test_projection_uncertainty_at_the_image_corners_is_said(eye_to_hand):
    problem, o = eye_to_hand
    (c,) = [c for c in o.verdict.checks if c.test == "projection"]
    whole = float(c.message.split("px where its views reached, ")[1].split(" px")[0])
    assert c.passed and c.value < 1.0 and 1.2 <= whole <= 3.0  # the standard cells' range
    assert not any("beyond the image area" in n for n in o.verdict.notes)
    centre = centre_only(problem, 0.35)  # a sixth of the image's cells, none at its corners
    v = judge(calibrate(centre), problem=centre, command="solve")
    (c,) = [c for c in v.checks if c.test == "projection"]
    assert c.passed and c.value < 2.0  # where the views reached, the calibration holds
    (n,) = [n for n in v.notes if "beyond the image area" in n]
    assert "corners and edges" in n and float(n.split("reaches ")[1].split(" px")[0]) > 10


def test_report_names_its_quantities_and_draws_axes(eye_to_hand):
    _, o = eye_to_hand
    html = (o.session_dir / "report.html").read_text()
    assert html.index("The calibration") < html.index("Every test")  # the values near the top
    assert "robot poses corrected within the arm's learned accuracy" in o.summary
    img = robot_panel(o.result)
    assert (img[20:160, 70] < 100).all() and (img[160, 70:540] < 100).all()  # both axes drawn
