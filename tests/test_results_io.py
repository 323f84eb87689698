"""result.yaml as docs/FORMATS.md says, its round trip, and the OpenCV / ROS exports."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from slidecal.routines.exports import camera_info_dict, write_all_exports
from slidecal.routines.results_io import (
    RESULT_FORMAT,
    errors_against_truth,
    read_result,
    summary_text,
    write_result,
)
from slidecal.solver.geometry import Rx, Ry, Rz
from slidecal.solver.result import (
    CalibrationResult,
    CameraEstimate,
    ScaleCheck,
    TransformEstimate,
)

K = np.array([[880.4, 0.1, 640.2], [0.0, 879.8, 399.7], [0.0, 0.0, 1.0]])
DIST = np.array([-0.12, 0.05, 5e-4, -3e-4, 0.0])


def _result(rig: bool = False, t_observable: bool = True, mount: str = "eye_in_hand"):
    cams = {
        "left": CameraEstimate(
            "left", 1280, 800, K, DIST, {"fx": 0.4, "fy": 0.4, "cx": 0.3, "cy": 0.3}, 0.12
        )
    }
    rigs = {}
    if rig:
        cams["right"] = CameraEstimate(
            "right", 1280, 800, K + 1.0 * np.eye(3) * [1, 1, 0], DIST, {"fx": 0.5}, 0.15
        )
        rigs["T_right_left"] = TransformEstimate(
            "T_right_left", Ry(0.05), np.array([-0.075, 0.0, 0.001]), 0.01, 0.2
        )
    R_he = Rz(0.1) @ Rx(0.02)
    he = TransformEstimate(
        "T_tool_cam",
        R_he,
        np.array([0.01, -0.06, 0.04]) if t_observable else None,
        0.02,
        0.3 if t_observable else None,
    )
    unobs = {} if t_observable else {"T_tool_cam.t": "no rotations between frames"}
    return CalibrationResult(
        cameras=cams,
        hand_eye=he,
        rig=rigs,
        T_target=TransformEstimate("T_base_board", Rx(np.pi), np.array([0.3, 0.1, 0.0]), 0.01, 0.5),
        converged=True,
        iterations=7,
        reproj_rms_px=0.13,
        sigma_px=0.131,
        parameter_names=("fx", "fy"),
        covariance=np.array([[0.16, 0.01], [0.01, 0.16]]),
        residuals_px={(0, "left"): 0.11, (1, "left"): 0.14},
        outliers=((1, "left", 17),),
        unobservable=unobs,
        messages=("covariance of k3 is ill-conditioned",),
        scale_checks=(ScaleCheck(0, 1, 60.0, 60.03),),
        H_inf={"left<-right": np.eye(3)} if rig else {},
        linear={"left": K},
        mount=mount,
        reference_camera="left",
    )


def test_result_yaml_has_the_contract_fields(tmp_path: Path) -> None:
    path = write_result(_result(), tmp_path / "result.yaml")
    d = yaml.safe_load(path.read_text())
    assert d["format"] == RESULT_FORMAT
    c = d["cameras"]["left"]
    assert (c["width"], c["height"], c["distortion_model"]) == (1280, 800, "opencv5")
    np.testing.assert_allclose(c["K"], K)
    np.testing.assert_allclose(c["distortion"], DIST)
    assert c["std"] == {"fx": 0.4, "fy": 0.4, "cx": 0.3, "cy": 0.3}
    assert c["reproj_rms_px"] == 0.12
    he = d["T_tool_cam"]
    np.testing.assert_allclose(he["R"], Rz(0.1) @ Rx(0.02))
    np.testing.assert_allclose(he["t_m"], [0.01, -0.06, 0.04])
    assert (he["std_rot_deg"], he["std_t_mm"]) == (0.02, 0.3)
    assert d["T_base_board"]["t_m"] == [0.3, 0.1, 0.0]
    assert d["scale_checks"][0]["ratio"] == pytest.approx(60.03 / 60.0)


def test_unobservable_translation_is_null_never_a_number(tmp_path: Path) -> None:
    d = yaml.safe_load(write_result(_result(t_observable=False), tmp_path / "r.yaml").read_text())
    assert d["T_tool_cam"]["t_m"] is None and d["T_tool_cam"]["std_t_mm"] is None
    assert "T_tool_cam.t" in d["unobservable"]
    text = summary_text(_result(t_observable=False))
    assert "translation: not determined" in text and "no rotations between frames" in text


def test_a_parameter_held_by_the_options_reads_fixed_not_unknown() -> None:
    lines = summary_text(_result()).splitlines()
    assert any(line.split() == ["s", "=", "0.100", "px", "(fixed)"] for line in lines)
    assert any(line.split()[:3] == ["fx", "=", "880.400"] and "+-" in line for line in lines)
    # no covariance at all: every std is unknown, none is called fixed
    bare = replace(_result(), cameras={"left": replace(_result().cameras["left"], std={})})
    assert "(fixed)" not in summary_text(bare) and "+- n/a px" in summary_text(bare)


def _scale_line(ratios: list[float]) -> str:
    checks = tuple(ScaleCheck(i, i + 1, 60.0, 60.0 * q) for i, q in enumerate(ratios))
    text = summary_text(replace(_result(), scale_checks=checks))
    return next(line for line in text.splitlines() if line.startswith("scale check"))


def test_the_scale_line_blames_the_square_size_only_when_the_verdict_would() -> None:
    # one short move off by 1.7 % among moves that agree: the robot's accuracy over that move,
    # not a wrong square size (the median, which a wrong square size moves, is 1)
    line = _scale_line([0.9997, 1.0003, 0.9995, 1.0001, 1.0174, 0.9999])
    assert "median 1.0000" in line and "worst move 1.0174" in line
    assert "square_size" not in line and "<-" not in line
    # every move 3 % long: the square size or the TCP scale
    line = _scale_line([1.0297, 1.0303, 1.0295, 1.0301, 1.0304, 1.0299])
    assert "check target.square_size_m and the robot's TCP and units" in line
    # moves that disagree by tens of percent cannot check the scale
    line = _scale_line([0.7, 1.3, 0.8, 1.25, 1.0, 0.9])
    assert "disagree too much" in line


def test_rig_names_and_composed_hand_eye(tmp_path: Path) -> None:
    # the composed hand-eye's std is read from the joint covariance under its own name
    var = np.array([1e-8, 2e-8, 3e-8, 1e-8, 4e-8, 4e-8])
    r = replace(
        _result(rig=True),
        parameter_names=tuple(f"T_tool_right.{a}" for a in ("rx", "ry", "rz", "tx", "ty", "tz")),
        covariance=np.diag(var),
    )
    d = yaml.safe_load(write_result(r, tmp_path / "r.yaml").read_text())
    assert {"T_tool_left", "T_tool_right", "T_right_left"} <= set(d)
    assert "T_tool_cam" not in d
    # T_tool_right = T_tool_left @ inv(T_right_left)
    T_tl = np.eye(4)
    T_tl[:3, :3], T_tl[:3, 3] = d["T_tool_left"]["R"], d["T_tool_left"]["t_m"]
    T_rl = np.eye(4)
    T_rl[:3, :3], T_rl[:3, 3] = d["T_right_left"]["R"], d["T_right_left"]["t_m"]
    T_tr = np.eye(4)
    T_tr[:3, :3], T_tr[:3, 3] = d["T_tool_right"]["R"], d["T_tool_right"]["t_m"]
    np.testing.assert_allclose(T_tr, T_tl @ np.linalg.inv(T_rl), atol=1e-12)
    assert d["T_tool_right"]["std_t_mm"] == pytest.approx(1000.0 * np.sqrt(var[3:].sum()))
    assert d["T_tool_right"]["std_rot_deg"] == pytest.approx(np.degrees(np.sqrt(var[:3].sum())))
    # without it, no made-up number (the root sum of squares ignored the correlations)
    d = yaml.safe_load(write_result(_result(rig=True), tmp_path / "q.yaml").read_text())
    assert d["T_tool_right"]["std_t_mm"] is None and d["T_tool_right"]["std_rot_deg"] is None


@pytest.mark.parametrize("rig", [False, True])
def test_result_round_trip(tmp_path: Path, rig: bool) -> None:
    r = _result(rig=rig)
    q = read_result(write_result(r, tmp_path / "r.yaml"))
    assert set(q.cameras) == set(r.cameras)
    for n, c in r.cameras.items():
        np.testing.assert_array_equal(q.cameras[n].K, c.K)
        assert q.cameras[n].std == c.std
    np.testing.assert_array_equal(q.hand_eye.R, r.hand_eye.R)
    np.testing.assert_array_equal(q.hand_eye.t_m, r.hand_eye.t_m)
    assert set(q.rig) == set(r.rig)
    np.testing.assert_array_equal(q.covariance, r.covariance)
    assert q.residuals_px == r.residuals_px and q.outliers == r.outliers
    assert q.unobservable == r.unobservable and q.messages == r.messages


def test_opencv_filestorage_reads_the_export_back(tmp_path: Path) -> None:
    paths, _ = write_all_exports(_result(), tmp_path)
    fs = cv2.FileStorage(str(tmp_path / "opencv_left.yaml"), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("camera_matrix").mat(), K)
    np.testing.assert_allclose(fs.getNode("distortion_coefficients").mat().ravel(), DIST)
    assert int(fs.getNode("image_width").real()) == 1280
    assert int(fs.getNode("image_height").real()) == 800
    fs.release()
    assert tmp_path / "camera_info_left.yaml" in paths


def test_ros_camera_info_layout(tmp_path: Path) -> None:
    write_all_exports(_result(), tmp_path)
    d = yaml.safe_load((tmp_path / "camera_info_left.yaml").read_text())
    assert d == camera_info_dict(_result().cameras["left"])
    assert d["distortion_model"] == "plumb_bob" and d["camera_name"] == "left"
    assert (d["camera_matrix"]["rows"], d["camera_matrix"]["cols"]) == (3, 3)
    np.testing.assert_allclose(np.reshape(d["camera_matrix"]["data"], (3, 3)), K)
    np.testing.assert_allclose(d["distortion_coefficients"]["data"], DIST)
    np.testing.assert_allclose(np.reshape(d["rectification_matrix"]["data"], (3, 3)), np.eye(3))
    P = np.reshape(d["projection_matrix"]["data"], (3, 4))
    np.testing.assert_allclose(P[:, :3], K)
    np.testing.assert_allclose(P[:, 3], 0.0)


def test_summary_and_errors_against_truth() -> None:
    r = _result()
    truth = {
        "cameras": {
            "left": {"K": [[880, 0, 640], [0, 880, 400], [0, 0, 1]], "distortion": [0] * 5}
        },
        "T_tool_cam": {
            "R": (Rz(0.1) @ Rx(0.02) @ Ry(np.radians(0.01))).tolist(),
            "t_m": [0.01, -0.06, 0.041],
        },
    }
    e = errors_against_truth(r, truth)
    assert e["left.fx_rel"] == pytest.approx(0.4 / 880)
    assert e["T_tool_cam.rot_deg"] == pytest.approx(0.01, rel=1e-3)
    assert e["T_tool_cam.t_mm"] == pytest.approx(1.0, rel=1e-6)
    text = summary_text(r, truth)
    for s in (
        "reprojection rms 0.130 px",
        "fx  =    880.400 px  +- 0.400",
        "mm",
        "deg",
        "scale check (1 moves",
        "T_tool_cam.t_mm",
        "pendant",
    ):
        assert s in text, s
