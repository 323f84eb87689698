"""The verdict: garbage calibrations rejected with reasons, good ones accepted, changes from
the installed calibration flagged (against a recorded simulated session with known truth)."""

from __future__ import annotations

import dataclasses
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).parent))
from unattended_helpers import (  # noqa: E402
    DATA,
    copy_session,
    edit_session,
    record_without_translation,
    rotations_in_degrees,
    square_size,
)

from slidecal.routines.config import load_config  # noqa: E402
from slidecal.routines.ops.verdict import (  # noqa: E402
    ONE_ORIENTATION_FOCAL,
    STD_HINT,
    Limits,
    compare,
    judge,
    limits_from_dict,
)
from slidecal.routines.session import load_session  # noqa: E402
from slidecal.routines.solve import solve_session  # noqa: E402
from slidecal.solver.errors import InputError  # noqa: E402
from slidecal.solver.geometry import R_from_rvec  # noqa: E402
from slidecal.solver.result import ModelAdequacy, ScaleCheck  # noqa: E402


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    d = tmp_path_factory.mktemp("v") / "s"
    shutil.copytree(DATA / "r1_session", d)
    o = solve_session(d)
    return o, load_session(d).problem


def test_good_session_is_accepted_with_exports(solved) -> None:
    o, _ = solved
    assert o.verdict.verdict == "accepted" and o.exit_code == 0
    v = yaml.safe_load((o.session_dir / "verdict.yaml").read_text())
    assert v["format"] == "slidecal.verdict/1"
    assert v["verdict"] == "accepted" and v["reasons"] == [] and v["exit_code"] == 0
    tests = {c["test"] for c in v["checks"]}
    assert {"converged", "std", "scale", "coverage"} <= tests
    assert tests & {"reprojection", "adequacy"}  # the solver's adequacy test when it made one
    assert (o.session_dir / "export" / "camchain.yaml").is_file()
    assert (o.session_dir / "export" / "hand_eye.yaml").is_file()
    assert o.result_path == o.session_dir / "result.yaml"
    header = yaml.safe_load(o.result_path.read_text())["header"]
    assert header["verdict"] == "accepted" and header["slidecal_version"]


def _solve_edited(tmp_path: Path, edit) -> object:  # noqa: ANN001
    d = edit_session(copy_session(DATA / "r1_session", tmp_path / "s"), edit)
    return solve_session(d)


def test_rotations_in_degrees_refused_as_they_are_read(tmp_path: Path) -> None:
    # a camera looking down turns about 180 deg: written in degrees, no axis-angle component of
    # a rotation can be that large, so the session reader says so before anything is solved
    with pytest.raises(InputError, match="look like degrees"):
        _solve_edited(tmp_path, rotations_in_degrees)
    assert not (tmp_path / "s" / "result.yaml").exists()
    assert not (tmp_path / "s" / "rejected").exists()


def test_rejected_result_is_kept_apart_without_exports(tmp_path: Path) -> None:
    o = _solve_edited(tmp_path, square_size(0.025))
    assert o.verdict.verdict == "rejected" and o.exit_code == 4
    # the result is kept for a person to look at, apart and without exports
    assert o.result_path == tmp_path / "s" / "rejected" / "result.yaml"
    assert not (tmp_path / "s" / "result.yaml").exists()
    assert not (tmp_path / "s" / "export").exists() and not o.exports
    assert "verdict: rejected" in (tmp_path / "s" / "rejected" / "summary.txt").read_text()


@pytest.mark.parametrize("given_m", [0.025, 0.036])
def test_wrong_square_size_rejected(tmp_path: Path, given_m: float) -> None:
    # 0.036 given for the recorded 0.030 board is the ratio of a 0.025 board given as 0.030
    o = _solve_edited(tmp_path, square_size(given_m))
    assert o.verdict.verdict == "rejected" and o.exit_code == 4
    assert any(c.test in ("reprojection", "adequacy", "scale") for c in o.verdict.reasons)


@pytest.mark.slow
def test_plan_without_translation_rejected(tmp_path: Path) -> None:
    d = record_without_translation(tmp_path / "s")
    o = solve_session(d)
    assert o.verdict.verdict == "rejected"
    assert any(c.test == "std" for c in o.verdict.reasons)


def test_solve_does_not_overwrite_a_result(solved) -> None:
    o, _ = solved
    with pytest.raises(InputError, match="already holds a result"):
        solve_session(o.session_dir)


def test_aborted_session_is_said_and_rejected(tmp_path: Path) -> None:
    def abort(doc: dict) -> None:
        doc["status"] = "aborted"
        doc["frames"] = doc["frames"][:12]
        doc["events"] = [{"kind": "interrupted", "message": "stopped by SIGTERM"}]

    o = _solve_edited(tmp_path, abort)
    assert o.verdict.verdict == "rejected"
    assert o.verdict.reasons[0].test == "session" and "aborted" in o.verdict.reasons[0].message
    assert "SESSION ABORTED" in o.summary and "SIGTERM" in o.summary


# ----------------------------------------------------------------------------- gate by gate


def _failed(result, problem=None, **kw) -> set[str]:  # noqa: ANN001
    return {c.test for c in judge(result, problem=problem, **kw).reasons}


def test_each_gate_fails_on_its_own(solved) -> None:
    o, problem = solved
    r = dataclasses.replace(o.result, adequacy=None)  # the rms limit applies without it
    assert _failed(r, problem) == set()
    assert _failed(dataclasses.replace(r, converged=False)) == {"converged"}
    cam = r.cameras["cam"]
    big = dataclasses.replace(cam, std={**cam.std, "fx": 0.01 * cam.K[0, 0]})
    assert _failed(dataclasses.replace(r, cameras={"cam": big})) == {"std"}
    bad_rms = dataclasses.replace(cam, reproj_rms_px=3.0)
    assert _failed(dataclasses.replace(r, cameras={"cam": bad_rms})) == {"reprojection"}
    # a board 0.025 m given as 0.030 m: the camera sees 5/6 of the robot's lengths
    scaled = tuple(
        ScaleCheck(s.frame_a, s.frame_b, s.robot_mm, s.robot_mm * 0.025 / 0.030 * (1 + 1e-4 * k))
        for k, s in enumerate(r.scale_checks)
    )
    assert _failed(dataclasses.replace(r, scale_checks=scaled)) == {"scale"}
    # the model-adequacy test of the solver replaces the rms limit when present
    bad = ModelAdequacy(
        {"cam": 0.1},
        {"cam": 7.5},
        ((3, "cam", 12.0),),
        False,
        ("camera cam: residuals 7.5 times the detector noise (limit 1.5)",),
    )
    v = judge(dataclasses.replace(r, adequacy=bad))
    assert {c.test for c in v.reasons} == {"adequacy"} and "7.5 times" in v.reasons[0].message
    good = dataclasses.replace(bad, normalised_rms={"cam": 1.02}, adequate=True, reasons=())
    assert _failed(dataclasses.replace(r, adequacy=good)) == set()


def test_a_hand_eye_from_translations_alone_has_its_own_limit(solved) -> None:
    # one orientation: the hand-eye translation is not observable and the rotation comes from
    # the translations, a few tenths of a degree on a real arm; the full hand-eye's 0.2 deg
    # would reject the intrinsics with it
    o, problem = solved
    r = dataclasses.replace(o.result, adequacy=None)
    he = r.hand_eye
    full = dataclasses.replace(he, std_rot_deg=0.5)
    assert _failed(dataclasses.replace(r, hand_eye=full)) == {"std"}
    alone = dataclasses.replace(he, std_rot_deg=0.5, t_m=None, std_t_mm=None)
    assert _failed(dataclasses.replace(r, hand_eye=alone)) == set()
    # accepted, but its focal lengths are said to rest on what one orientation cannot check
    assert ONE_ORIENTATION_FOCAL in judge(dataclasses.replace(r, hand_eye=alone)).notes
    assert ONE_ORIENTATION_FOCAL not in judge(r).notes
    worse = dataclasses.replace(alone, std_rot_deg=1.5)
    v = judge(dataclasses.replace(r, hand_eye=worse), Limits())
    assert {c.test for c in v.reasons} == {"std"}
    assert "from translations alone" in v.reasons[0].message
    strict = Limits(hand_eye_rot_std_deg_from_translations=0.3)
    assert {c.test for c in judge(dataclasses.replace(r, hand_eye=alone), strict).reasons} == {
        "std"
    }
    # the principal point of such a session rests on the arm's orientation accuracy: 5 px is
    # within its own limit (8 px), beyond the general one (3 px)
    cam = r.cameras["cam"]
    loose = dataclasses.replace(cam, std={**cam.std, "cy": 5.0})
    with_loose = dataclasses.replace(r, cameras={"cam": loose})
    assert _failed(with_loose) == {"std"}  # the session's own full hand-eye: 3 px
    assert _failed(dataclasses.replace(with_loose, hand_eye=alone)) == set()
    worst = dataclasses.replace(cam, std={**cam.std, "cy": 9.0})
    v = judge(dataclasses.replace(r, cameras={"cam": worst}, hand_eye=alone), Limits())
    assert [c.message for c in v.reasons] == [
        "camera cam: cy one-sigma 9.000 px (limit 8 px, a session of one orientation; "
        "limits.cxy_std_px_from_translations)"
    ]
    assert STD_HINT in v.notes  # what to do about it
    undetermined = dataclasses.replace(he, R=None)  # no one-sigma to narrow: no such note
    v = judge(dataclasses.replace(r, hand_eye=undetermined), Limits())
    assert [c.message for c in v.reasons] == ["T_tool_cam: rotation not determined"]
    assert STD_HINT not in v.notes


def test_coverage_gate(solved) -> None:
    o, problem = solved
    few = dataclasses.replace(problem, frames=problem.frames[:1])
    v = judge(o.result, Limits(min_coverage=0.5), few)
    assert "coverage" in {c.test for c in v.reasons}


# ----------------------------------------------------------------------------- installed


def _changed(r, fx_rel=0.0, cx_px=0.0, he_deg=0.0):  # noqa: ANN001, ANN202
    cam = r.cameras["cam"]
    K = np.array(cam.K, dtype=float)
    K[0, 0] *= 1 + fx_rel
    K[1, 1] *= 1 + fx_rel
    K[0, 2] += cx_px
    he = r.hand_eye
    R = R_from_rvec(np.radians(he_deg) * np.array([0.6, 0.0, 0.8])) @ he.R
    return dataclasses.replace(
        r,
        cameras={"cam": dataclasses.replace(cam, K=K)},
        hand_eye=dataclasses.replace(he, R=R),
    )


def test_unchanged_installed_is_accepted(solved) -> None:
    o, problem = solved
    v = judge(o.result, problem=problem, installed=o.result)
    assert v.verdict == "accepted"
    assert v.installed["max_sigma"] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(
    "change", [{"fx_rel": 0.003}, {"cx_px": 1.0}, {"he_deg": 0.1}], ids=["fx", "cx", "hand_eye"]
)
def test_change_from_installed_is_drifted(solved, change) -> None:
    o, problem = solved
    v = judge(o.result, problem=problem, installed=_changed(o.result, **change))
    assert v.verdict == "drifted" and v.exit_code == 5
    assert {c.test for c in v.reasons} == {"installed"}


def test_compare_reports_sigma_and_pixels(solved) -> None:
    o, _ = solved
    checks, info = compare(o.result, _changed(o.result, cx_px=1.0))
    assert info["max_sigma_parameter"] == "cam.cx"
    assert info["max_displacement_px"]["cam"] == pytest.approx(1.0, abs=0.05)
    assert len(checks) == 2


def test_rejected_stays_rejected_against_installed(solved) -> None:
    o, _ = solved
    v = judge(dataclasses.replace(o.result, converged=False), installed=o.result)
    assert v.verdict == "rejected"


# ----------------------------------------------------------------------------- paired

#: the noise of a re-run at the same poses: per-corner detector noise and the per-pose shift
#: of the arm's repeatability, one-sigma per axis, px (what the simulated cell shows)
CORNER_PX, POSE_PX = 0.06, 0.1


def _rerun(problem, seed: int, shift=(0.0, 0.0), moved_m: float = 0.0):  # noqa: ANN001, ANN202
    """``problem`` seen again at the same robot poses: fresh noise, every corner shifted by
    ``shift`` px (a changed camera), the measured poses moved by ``moved_m`` along x."""
    rng = np.random.default_rng(seed)
    frames = []
    for fr in problem.frames:
        dets = {
            n: dataclasses.replace(
                d,
                px=np.asarray(d.px)
                + np.asarray(shift)
                + rng.normal(0.0, CORNER_PX, (len(d.ids), 2))
                + rng.normal(0.0, POSE_PX, 2),
            )
            for n, d in fr.detections.items()
        }
        T = np.array(fr.T_base_tool, dtype=float)
        T[0, 3] += moved_m
        frames.append(dataclasses.replace(fr, detections=dets, T_base_tool=T))
    return dataclasses.replace(problem, frames=tuple(frames))


def test_paired_unchanged_is_accepted(solved) -> None:
    o, problem = solved
    for seed in range(5):
        v = judge(
            o.result, problem=_rerun(problem, seed), installed=o.result, installed_problem=problem
        )
        assert v.verdict == "accepted", v.lines()
        info = v.installed["paired"]
        assert info["usable"] and info["shared_poses"] == len(problem.frames)
        assert info["cameras"]["cam"]["max_px"] < 0.3


def test_paired_one_pixel_shift_is_drifted_and_named(solved) -> None:
    o, problem = solved
    new = _rerun(problem, 1, shift=(1.0, 0.0))
    v = judge(o.result, problem=new, installed=o.result, installed_problem=problem)
    assert v.verdict == "drifted" and v.exit_code == 5
    (reason,) = v.reasons  # the parameters are the same: only the paired test sees it
    assert reason.test == "paired" and "the camera changed or the board moved" in reason.message
    eq = v.installed["paired"]["cameras"]["cam"]["equivalent"]
    n = len(problem.frames)
    assert eq["cx_px"] == pytest.approx(1.0, abs=5 * POSE_PX * np.sqrt(2 / n))


def test_paired_needs_shared_poses(solved) -> None:
    o, problem = solved
    new = _rerun(problem, 2, shift=(1.0, 0.0), moved_m=0.005)
    v = judge(o.result, problem=new, installed=o.result, installed_problem=problem)
    assert v.verdict == "accepted" and "paired" not in {c.test for c in v.checks}
    assert not v.installed["paired"]["usable"]
    assert any("no paired comparison" in n for n in v.notes)


@pytest.mark.slow
def test_check_pairs_or_falls_back_and_says_so(solved) -> None:
    from slidecal.routines.ops.check import judge_problem

    o, problem = solved
    cfg = load_config()
    new = _rerun(problem, 3, shift=(1.0, 0.0))
    expected = {"cam": 0.3}
    v = judge_problem(new, o.result, expected, cfg, installed_problem=problem)
    assert v.verdict == "drifted" and [c.test for c in v.reasons] == ["paired"]
    assert v.notes[0].startswith(f"paired comparison at {len(problem.frames)}")
    assert "change" in v.extra["check"]  # the re-estimate's figures are kept
    v = judge_problem(_rerun(problem, 3), o.result, expected, cfg, installed_problem=problem)
    assert v.verdict == "ok", v.lines()
    v = judge_problem(new, o.result, expected, cfg, installed_problem=None)
    assert v.notes[0].startswith("no paired comparison (the install keeps no session")
    assert "paired" not in {c.test for c in v.reasons}


# ----------------------------------------------------------------------------- limits


def test_limits_from_cell_file(tmp_path: Path) -> None:
    from importlib import resources

    text = resources.files("slidecal.mocks").joinpath("default_cell.yaml").read_text()
    cell = tmp_path / "cell.yaml"
    cell.write_text(text + "limits: {max_rms_px: 0.5, coverage_grid: [4, 3]}\n")
    lim = load_config(cell).limits
    assert lim.max_rms_px == 0.5 and lim.coverage_grid == (4, 3) and lim.fx_rel_std == 0.005


def test_unknown_limit_refused_with_nearest() -> None:
    with pytest.raises(InputError, match="did you mean 'max_rms_px'"):
        limits_from_dict({"max_rms": 1.0}, "cell.yaml")
    with pytest.raises(InputError, match="must be positive"):
        limits_from_dict({"max_rms_px": -1.0}, "cell.yaml")
