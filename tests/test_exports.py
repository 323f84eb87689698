"""Exports: Kalibr camchain, mrcal camera models, the hand-eye in three forms, depthai JSON from
solve, the header, and a failed export reported, not swallowed."""

from __future__ import annotations

import ast
import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from slidecal.drivers.ur_pose import T_from_ur_pose
from slidecal.routines.exports import (
    camchain_dict,
    hand_eye_dict,
    mrcal_cameramodel,
    quat_xyzw,
    result_header,
    write_all_exports,
)
from slidecal.routines.solve import solve_session
from slidecal.solver.geometry import R_from_rvec, Rx, Ry, Rz
from slidecal.solver.result import TransformEstimate

DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    d = tmp_path_factory.mktemp("exp") / "s"
    shutil.copytree(DATA / "r1_session", d)
    return solve_session(d).result


def _rig(result):  # noqa: ANN001, ANN202
    """A two-camera rig (left = the solved camera, right 75 mm to its right, rotated 1 deg)."""
    cam = result.cameras["cam"]
    R = R_from_rvec(np.radians([0.0, 1.0, 0.0]))
    rig = TransformEstimate("T_right_left", R, np.array([-0.075, 0.0, 0.0]), 0.01, 0.05)
    return dataclasses.replace(
        result,
        cameras={
            "left": dataclasses.replace(cam, name="left"),
            "right": dataclasses.replace(cam, name="right"),
        },
        rig={"T_right_left": rig},
        reference_camera="left",
    )


def test_hand_eye_three_forms_agree(result) -> None:
    d = hand_eye_dict(result, result_header(None))
    e = d["T_tool_cam"]
    assert (e["parent_frame"], e["child_frame"]) == ("tool", "cam")
    T = np.array(e["matrix_4x4"])
    np.testing.assert_allclose(T, result.hand_eye.T, atol=1e-12)
    # translation + quaternion (x, y, z, w)
    q = np.array(e["quaternion_xyzw"])
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), T[:3, :3], atol=1e-9)
    np.testing.assert_allclose(e["translation_m"], T[:3, 3])
    # the UR pendant: millimetres and the rotation vector; RPY as the pendant shows it
    p = e["ur_pendant"]
    pose = [v / 1000.0 for v in p["position_mm"]] + p["rotation_vector_rad"]
    np.testing.assert_allclose(T_from_ur_pose(pose), T, atol=1e-9)
    r, pi, y = np.radians(p["rpy_deg"])
    np.testing.assert_allclose(Rz(y) @ Ry(pi) @ Rx(r), T[:3, :3], atol=1e-9)
    assert "x, y, z, w" in d["conventions"] and d["header"]["slidecal_version"]


def test_unobservable_translation_is_null(result) -> None:
    he = dataclasses.replace(result.hand_eye, t_m=None, std_t_mm=None)
    e = hand_eye_dict(dataclasses.replace(result, hand_eye=he))["T_tool_cam"]
    assert e["matrix_4x4"] is None and e["translation_m"] is None
    assert e["ur_pendant"]["position_mm"] is None and e["quaternion_xyzw"] is not None


def test_kalibr_camchain_of_a_rig(result) -> None:
    rig = _rig(result)
    c = camchain_dict(rig)
    assert list(c) == ["cam0", "cam1"]
    assert c["cam0"]["camera_model"] == "pinhole" and c["cam0"]["distortion_model"] == "radtan"
    K = rig.cameras["left"].K
    assert c["cam0"]["intrinsics"] == pytest.approx([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
    assert len(c["cam0"]["distortion_coeffs"]) == 4 and c["cam0"]["resolution"] == [1280, 800]
    np.testing.assert_allclose(c["cam1"]["T_cn_cnm1"], rig.rig["T_right_left"].T, atol=1e-12)
    assert "T_cn_cnm1" not in c["cam0"]


def _mrcal_project(model: dict, p_ref: np.ndarray) -> np.ndarray:
    """Pixels of points in the reference frame (n, 3) by a ``.cameramodel`` read as mrcal's
    documentation reads it: ``rt_cam_ref`` into the camera, then LENSMODEL_OPENCV5's
    ``q = f (P_radial + P_tangential) + c`` with ``k_0 .. k_4`` (OPENCV4: ``k_4`` = 0)."""
    r, t = np.array(model["rt_cam_ref"][:3]), np.array(model["rt_cam_ref"][3:])
    p = p_ref @ R_from_rvec(r).T + t
    fx, fy, cx, cy, k0, k1, k2, k3, k4 = [*model["intrinsics"], 0.0][:9]
    P = p[:, :2] / p[:, 2:]
    r2 = (P**2).sum(axis=1)
    radial = (1 + k0 * r2 + k1 * r2**2 + k4 * r2**3)[:, None] * P
    x, y = P[:, 0], P[:, 1]
    tangential = np.column_stack(
        [2 * k2 * x * y + k3 * (r2 + 2 * x**2), 2 * k3 * x * y + k2 * (r2 + 2 * y**2)]
    )
    return (radial + tangential) * [fx, fy] + [cx, cy]


def test_mrcal_cameramodels_of_a_rig_project_as_the_result(result, tmp_path) -> None:
    import cv2

    rig = _rig(result)
    header = result_header(None)
    paths, errors = write_all_exports(rig, tmp_path, header)
    assert errors == []
    rng = np.random.default_rng(7)
    p_ref = np.column_stack([rng.uniform(-0.3, 0.3, (20, 2)), rng.uniform(0.4, 1.0, 20)])
    for name in ("left", "right"):
        path = tmp_path / f"mrcal_{name}.cameramodel"
        assert path in paths
        text = path.read_text()
        assert text.startswith("# slidecal_version: ")
        model = ast.literal_eval(text)  # how mrcal.cameramodel reads the file
        # mrcal's C reader wants the lens model before the intrinsics; both pose keys agree
        assert list(model)[:2] == ["lensmodel", "intrinsics"]
        # the session fixes k3: mrcal's OPENCV4 (mrcal-to-kalibr refuses an OPENCV5)
        assert model["lensmodel"] == "LENSMODEL_OPENCV4" and model["imagersize"] == [1280, 800]
        assert len(model["intrinsics"]) == 8
        assert model["rt_cam_ref"] == model["extrinsics"]
        cam = rig.cameras[name]
        T = np.eye(4) if name == "left" else rig.rig["T_right_left"].T
        got = _mrcal_project(model, p_ref)
        rvec = cv2.Rodrigues(T[:3, :3])[0]
        want = cv2.projectPoints(p_ref, rvec, T[:3, 3], cam.K, cam.distortion)[0].reshape(-1, 2)
        np.testing.assert_allclose(got, want, atol=1e-9)
    assert ast.literal_eval(mrcal_cameramodel(rig, "left"))["rt_cam_ref"] == [0.0] * 6


def test_a_skewed_camera_gets_no_kalibr_or_mrcal_file(result, tmp_path) -> None:
    cam = result.cameras["cam"]
    K = cam.K.copy()
    K[0, 1] = 0.8
    skewed = dataclasses.replace(result, cameras={"cam": dataclasses.replace(cam, K=K)})
    paths, errors = write_all_exports(skewed, tmp_path)
    assert len(errors) == 2 and all("\n" not in e and "skew of 0.8 px" in e for e in errors)
    assert errors[0].startswith("export camchain.yaml not written")
    assert errors[1].startswith("export mrcal_cam.cameramodel not written")
    assert (tmp_path / "opencv_cam.yaml") in paths and not (tmp_path / "camchain.yaml").exists()


def test_a_camera_with_k3_gets_no_kalibr_file(result, tmp_path) -> None:
    """Kalibr's radtan has k1 k2 p1 p2 only: a k3 would be dropped without a word."""
    cam = result.cameras["cam"]
    d = np.asarray(cam.distortion, dtype=float).copy()
    d[4] = 0.0305
    with_k3 = dataclasses.replace(result, cameras={"cam": dataclasses.replace(cam, distortion=d)})
    paths, errors = write_all_exports(with_k3, tmp_path)
    assert len(errors) == 1 and errors[0].startswith("export camchain.yaml not written")
    assert "\n" not in errors[0] and "k3 = 0.0305" in errors[0]
    assert (tmp_path / "mrcal_cam.cameramodel") in paths
    model = ast.literal_eval((tmp_path / "mrcal_cam.cameramodel").read_text())
    assert model["lensmodel"] == "LENSMODEL_OPENCV5" and model["intrinsics"][-1] == 0.0305
    assert not (tmp_path / "camchain.yaml").exists()


def test_depthai_json_for_an_oak_rig_and_failed_export_reported(result, tmp_path) -> None:
    dai = pytest.importorskip("depthai")
    rig = _rig(result)
    paths, errors = write_all_exports(rig, tmp_path, None, {"left": "CAM_B", "right": "CAM_C"})
    assert errors == []
    j = tmp_path / "depthai_calibration.json"
    assert j in paths
    h = dai.CalibrationHandler(str(j))
    K = np.array(h.getCameraIntrinsics(dai.CameraBoardSocket.CAM_B, 1280, 800))
    np.testing.assert_allclose(K, rig.cameras["left"].K, rtol=1e-6)
    # a socket missing for a camera: the other exports stand, the failure is one line
    paths, errors = write_all_exports(rig, tmp_path / "b", None, {"left": "CAM_B"})
    assert len(errors) == 1 and errors[0].startswith("export depthai_calibration.json not written")
    assert "\n" not in errors[0] and (tmp_path / "b" / "camchain.yaml").is_file()


def test_solve_writes_depthai_json_when_the_session_names_sockets(tmp_path: Path) -> None:
    pytest.importorskip("depthai")
    shutil.copytree(DATA / "r1_session", tmp_path / "s")
    doc = yaml.safe_load((tmp_path / "s" / "session.yaml").read_text())
    doc["cameras"][0]["socket"] = "CAM_A"
    (tmp_path / "s" / "session.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    o = solve_session(tmp_path / "s")
    assert (tmp_path / "s" / "export" / "depthai_calibration.json") in o.exports
    assert o.export_errors == ()


def test_result_header(tmp_path: Path) -> None:
    cell = tmp_path / "cell.yaml"
    cell.write_text("x: 1\n")
    h = result_header(cell)
    import hashlib

    assert h["cell"] == "cell.yaml" and h["cell_sha256"] == hashlib.sha256(b"x: 1\n").hexdigest()
    assert h["created_utc"].endswith("Z") and h["slidecal_version"]


def test_quaternion_matches_scipy():
    mats = [np.eye(3), Rx(np.pi), Ry(np.pi), Rz(np.pi), Rx(np.pi) @ Rz(np.pi / 2)]
    mats += list(Rotation.random(200, random_state=4).as_matrix())
    for R in mats:
        q = Rotation.from_matrix(R).as_quat()
        q = -q if q[3] < 0 else q
        ours = np.array(quat_xyzw(R))
        if abs(q[3]) < 1e-9:  # w = 0: q and -q are the same rotation
            ours = ours * np.sign(ours @ q)
        np.testing.assert_allclose(ours, q, atol=1e-12)
