"""OAK driver: calibration writing against the real depthai; capture against a fake depthai.

The CalibrationHandler part runs on the installed depthai (no device needed). Capture cannot run
here (no device), so it runs against ``tests/fake_depthai.py``: the real depthai with only the
device-bound classes (Pipeline, Device, node.Camera and its output) faked, and a test that
checks every name of the fake against the installed depthai. One slow test checks that the
real library's "No available devices" becomes a HardwareFault.
"""

from __future__ import annotations

import inspect
import sys
import time
import types
from pathlib import Path

import cv2
import numpy as np
import pytest

dai_real = pytest.importorskip("depthai")
sys.path.insert(0, str(Path(__file__).parent))
import fake_depthai  # noqa: E402
from pybind_signatures import check_callable as _check_callable  # noqa: E402

from slidecal.drivers import oak  # noqa: E402
from slidecal.drivers.base import CameraRig  # noqa: E402
from slidecal.drivers.oak import (  # noqa: E402
    OakRig,
    choose_sensor_mode,
    device_camera,
    oak_calibration_handler,
    projection_shift_px,
    write_oak_calibration_json,
)
from slidecal.solver.errors import HardwareFault, InputError  # noqa: E402
from slidecal.solver.geometry import inv_T  # noqa: E402
from slidecal.solver.result import (  # noqa: E402
    CalibrationResult,
    CameraEstimate,
    TransformEstimate,
)
from tests.helpers import random_rotation  # noqa: E402

# ------------------------------------------------------------------ calibration (real depthai)


def _camera(name, w, h, rng):
    f = rng.uniform(800, 1200)
    K = np.array([[f, 0.0, w / 2 + rng.normal(0, 5)], [0.0, f * 1.001, h / 2 + rng.normal(0, 5)],
                  [0.0, 0.0, 1.0]])
    return CameraEstimate(name, w, h, K, rng.normal(0, 0.05, 5), {}, 0.1)


def _result(rng):
    cams = {
        "left": _camera("left", 1280, 800, rng),
        "right": _camera("right", 1280, 800, rng),
        "rgb": _camera("rgb", 1920, 1080, rng),
    }
    R_rl = random_rotation(rng, np.radians(1.0))
    rig = {
        "T_right_left": TransformEstimate("T_right_left", R_rl, np.array([-0.075, 0.0003, 0.001])),
        "T_rgb_left": TransformEstimate(
            "T_rgb_left", random_rotation(rng, np.radians(1.0)), np.array([-0.0375, 0.0, 0.0])
        ),
    }
    return CalibrationResult(
        cameras=cams, hand_eye=None, rig=rig, T_target=None, converged=True, iterations=5,
        reproj_rms_px=0.1, sigma_px=0.1, parameter_names=(), covariance=None, residuals_px={},
        outliers=(), unobservable={}, messages=(), reference_camera="left",
    )


def _f32(a):
    return np.asarray(a, dtype=np.float32).astype(float)


def test_calibration_json_round_trips_exactly(tmp_path):
    import depthai as dai

    S = dai.CameraBoardSocket
    result = _result(np.random.default_rng(4))
    path = write_oak_calibration_json(result, tmp_path / "calib.json")
    h = dai.CalibrationHandler(str(path))
    sockets = {"left": S.CAM_B, "right": S.CAM_C, "rgb": S.CAM_A}
    for name, cam in result.cameras.items():
        # depthai stores float32: the values come back exactly as float32 of what we wrote.
        np.testing.assert_array_equal(h.getCameraIntrinsics(sockets[name]), _f32(cam.K))
        d = np.zeros(14)
        d[:5] = cam.distortion
        np.testing.assert_array_equal(h.getDistortionCoefficients(sockets[name]), _f32(d))
        assert h.getDistortionModel(sockets[name]) == dai.CameraModel.Perspective
    # The stored link left -> right is T_right_left in centimetres, exactly (float32) in the
    # file; getCameraExtrinsics recomposes it (1 ulp of float32).
    T_rl = result.rig["T_right_left"].T
    raw = h.eepromToJson()
    ext = {int(c[0]): c[1]["extrinsics"] for c in raw["cameraData"]}
    left = ext[int(S.CAM_B)]
    np.testing.assert_array_equal(left["rotationMatrix"], _f32(T_rl[:3, :3]))
    t = [left["translation"][k] for k in "xyz"]
    np.testing.assert_array_equal(t, _f32(T_rl[:3, 3] * 100.0))
    T = np.array(h.getCameraExtrinsics(S.CAM_B, S.CAM_C))
    np.testing.assert_allclose(T[:3, :3], T_rl[:3, :3], atol=1e-6)
    np.testing.assert_allclose(T[:3, 3], T_rl[:3, 3] * 100.0, atol=1e-5)
    # The rgb camera is reached through the chain: float32 composition, 1e-5 cm and rad.
    T_rgb_left = result.rig["T_rgb_left"].T
    T = np.array(h.getCameraExtrinsics(S.CAM_B, S.CAM_A))
    np.testing.assert_allclose(T[:3, :3], T_rgb_left[:3, :3], atol=1e-6)
    np.testing.assert_allclose(T[:3, 3], T_rgb_left[:3, 3] * 100.0, atol=1e-5)
    T = np.array(h.getCameraExtrinsics(S.CAM_A, S.CAM_C))
    T_right_rgb = T_rl @ inv_T(T_rgb_left)
    np.testing.assert_allclose(T[:3, 3], T_right_rgb[:3, 3] * 100.0, atol=1e-5)
    assert h.getStereoLeftCameraId() == S.CAM_B and h.getStereoRightCameraId() == S.CAM_C
    R1 = np.array(h.getStereoLeftRectificationRotation())
    np.testing.assert_allclose(R1 @ R1.T, np.eye(3), atol=1e-6)
    # Rectified: both cameras' rotated baselines lie along x.
    R2 = np.array(h.getStereoRightRectificationRotation())
    c_right_in_left = inv_T(T_rl)[:3, 3]
    b = R1 @ c_right_in_left
    assert abs(b[1]) < 1e-6 and abs(b[2]) < 1e-6
    np.testing.assert_allclose(R2 @ T_rl[:3, :3] @ R1.T, np.eye(3), atol=1e-6)
    # The stored chain is the factory one: left -> right -> rgb.
    assert ext[int(S.CAM_B)]["toCameraSocket"] == int(S.CAM_C)
    assert ext[int(S.CAM_C)]["toCameraSocket"] == int(S.CAM_A)


def test_calibration_handler_refuses_incomplete_results():
    rng = np.random.default_rng(5)
    r = _result(rng)
    with pytest.raises(InputError, match="no OAK socket"):
        oak_calibration_handler(r, {"left": "CAM_B", "right": "CAM_C"})
    rig = dict(r.rig)
    rig["T_rgb_left"] = TransformEstimate("T_rgb_left", np.eye(3), None)
    r2 = CalibrationResult(**{**r.__dict__, "rig": rig})
    with pytest.raises(InputError, match="T_rgb_left"):
        oak_calibration_handler(r2)


def test_calibration_handler_keeps_a_base_handler_untouched():
    import depthai as dai

    base = dai.CalibrationHandler()
    base.setBoardInfo("OAK-D", "R0M0E0")
    h = oak_calibration_handler(_result(np.random.default_rng(6)), base=base)
    assert h.eepromToJson()["boardName"] == "OAK-D"
    assert not base.hasCameraCalibration(dai.CameraBoardSocket.CAM_B)


@pytest.mark.slow
def test_real_depthai_without_device_is_a_hardware_fault():
    rig = OakRig(sockets={"left": "CAM_B"}, sizes={"left": (1280, 800)}, colour=set())
    with pytest.raises(HardwareFault, match="USB3"):
        rig.open()



def test_handler_starts_from_the_device_and_keeps_what_was_not_calibrated():
    dai = dai_real
    S = dai.CameraBoardSocket
    device = dai.CalibrationHandler()
    device.setBoardInfo("OAK-D", "R3M2E3")
    device.setLensPosition(S.CAM_A, 120)
    R_imu = random_rotation(np.random.default_rng(1), 0.1)
    device.setImuExtrinsics(S.CAM_C, R_imu.tolist(), [1.0, 2.0, 3.0], [1.0, 2.0, 3.0])
    device.setCameraExtrinsics(S.CAM_B, S.CAM_C, np.eye(3).tolist(), [-7.5, 0, 0], [-7.5, 0, 0])
    result = _result(np.random.default_rng(7))
    h = oak_calibration_handler(result, base=device.eepromToJson(), lens_positions={"rgb": 131})
    js = h.eepromToJson()
    assert js["boardName"] == "OAK-D" and js["boardRev"] == "R3M2E3"
    np.testing.assert_allclose(js["imuExtrinsics"]["rotationMatrix"], R_imu, atol=1e-6)
    ext = {int(c[0]): c[1] for c in js["cameraData"]}
    assert ext[int(S.CAM_B)]["extrinsics"]["specTranslation"]["x"] == pytest.approx(-7.5)
    assert h.getLensPosition(S.CAM_A) == 131
    # what was calibrated is the result's
    np.testing.assert_allclose(
        h.getCameraIntrinsics(S.CAM_B), result.cameras["left"].K, rtol=1e-6
    )


def test_device_camera_maps_the_calibration_to_the_output_size():
    h = dai_real.CalibrationHandler()
    K0 = np.array([[3000.0, 0, 2020.0], [0, 3001.0, 1530.0], [0, 0, 1]])
    h.setCameraIntrinsics(dai_real.CameraBoardSocket.CAM_A, K0.tolist(), 4056, 3040)
    h.setDistortionCoefficients(dai_real.CameraBoardSocket.CAM_A, [0.1] + [0.0] * 13)
    js = h.eepromToJson()
    K, d = device_camera(js, "CAM_A", (2028, 1520), "stretch")
    np.testing.assert_allclose(K[[0, 1], [0, 1]], K0[[0, 1], [0, 1]] / 2, rtol=1e-6)
    assert K[0, 2] == pytest.approx((2020.0 + 0.5) / 2 - 0.5, abs=1e-3)
    assert d[0] == pytest.approx(0.1)
    # 1920x1080 stretched: x scaled by 1920/4056, y by 1080/3040; cropped: one scale, centred
    K, _ = device_camera(js, "CAM_A", (1920, 1080), "stretch")
    assert K[0, 0] / K[1, 1] == pytest.approx(3000 / 3001 * (1920 / 4056) / (1080 / 3040), 1e-5)
    K, _ = device_camera(js, "CAM_A", (1920, 1080), "crop")
    s = 1920 / 4056
    assert K[1, 2] == pytest.approx(s * 1530.5 - 0.5 + (1080 - s * 3040) / 2, abs=1e-3)
    assert device_camera(js, "CAM_B", (1280, 800)) is None


#: A session's record of an OAK-D's colour stream (OakRig.capabilities): 1920x1080 stretched
#: from the binned 2028x1520 mode, which sees the whole 4056x3040 array.
RGB_STRETCHED = {
    "sensors": [{"socket": "CAM_A", "width": 4056, "height": 3040,
                 "calibration_resolution": None}],
    "outputs": {"rgb": {"socket": "CAM_A", "size": [1920, 1080], "resize_mode": "stretch",
                        "sensor_mode": {"width": 2028, "height": 1520,
                                        "fov": [0, 0, 4056, 3040]}}},
}


def test_a_stretched_stream_is_written_at_the_size_the_device_stores():
    """Issue 36 item 1, against the real CalibrationHandler. depthai's
    ``getCameraIntrinsics(socket, w, h)`` (``keepAspectRatio``, its default) reads a calibration
    at another aspect ratio than the stored one as a centred crop with one scale, the principal
    point scaled as it is: a K written at the stretched size reads back with fy 25 % short."""
    dai = dai_real
    A = dai.CameraBoardSocket.CAM_A
    f, cx, cy = 3090.0, 2031.0, 1512.0
    K_full = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    truth = dai.CalibrationHandler()
    truth.setCameraIntrinsics(A, K_full.tolist(), 4056, 3040)
    # the K the session solves for the stretched stream: one scale per axis, pixel centres
    sx, sy = 1920 / 4056, 1080 / 3040
    K_out = np.array([[f * sx, 0.0, sx * (cx + 0.5) - 0.5], [0.0, f * sy, sy * (cy + 0.5) - 0.5],
                      [0.0, 0.0, 1.0]])
    r = _result(np.random.default_rng(9))
    rgb = CameraEstimate("rgb", 1920, 1080, K_out, np.zeros(5), {}, 0.1)
    r = CalibrationResult(**{**r.__dict__, "cameras": {**r.cameras, "rgb": rgb}})
    streams = oak.stream_geometry(RGB_STRETCHED)
    # a device with nothing stored for CAM_A: written at the full array
    h = oak_calibration_handler(r, streams=streams)
    assert h.getDefaultIntrinsics(A)[1:] == (4056, 3040)
    K = np.array(h.getCameraIntrinsics(A, 4056, 3040))
    np.testing.assert_allclose(K, K_full, rtol=1e-6)
    assert K[0, 0] == K[1, 1]
    np.testing.assert_allclose(h.getCameraIntrinsics(A, 1920, 1080),
                               truth.getCameraIntrinsics(A, 1920, 1080), rtol=1e-6)
    # the other cameras have no stream record: written at their own size as before
    assert h.getDefaultIntrinsics(dai.CameraBoardSocket.CAM_B)[1:] == (1280, 800)
    # a device that stores CAM_A at 1080p (a 16:9 crop of the array), as the base or as the
    # sensor's calibrationResolution: written there, and read there as the crop stream's K
    crop_K = np.array(truth.getCameraIntrinsics(A, 1920, 1080))
    base = dai.CalibrationHandler()
    base.setCameraIntrinsics(A, crop_K.tolist(), 1920, 1080)
    calib_1080p = {**RGB_STRETCHED, "sensors": [
        {**RGB_STRETCHED["sensors"][0], "calibration_resolution": [1920, 1080]}]}
    for h in (oak_calibration_handler(r, base=base, streams=streams),
              oak_calibration_handler(r, streams=oak.stream_geometry(calib_1080p))):
        assert h.getDefaultIntrinsics(A)[1:] == (1920, 1080)
        np.testing.assert_allclose(h.getCameraIntrinsics(A, 1920, 1080), crop_K, rtol=1e-6)
        # and the comparison reads that stored 16:9 calibration back to the stretched stream
        K, _ = device_camera(h.eepromToJson(), "CAM_A", (1920, 1080), "stretch", streams["rgb"])
        np.testing.assert_allclose(K, K_out, rtol=1e-6)
    assert projection_shift_px(r, h.eepromToJson(), {"rgb": "CAM_A", "left": "CAM_B"}, 0.5,
                               streams=streams)["rgb"]["max_px"] < 2e-3


def test_projection_shift_against_a_device_calibration():
    r = _result(np.random.default_rng(8))
    cams = {n: CameraEstimate(n, c.width, c.height, c.K, np.zeros(5), {}, 0.1)
            for n, c in r.cameras.items()}
    r = CalibrationResult(**{**r.__dict__, "cameras": dict(cams)})
    same = oak_calibration_handler(r).eepromToJson()
    shift = projection_shift_px(r, same, {"left": "CAM_B", "right": "CAM_C", "rgb": "CAM_A"}, 0.5)
    assert set(shift) == {"left", "right", "rgb"}
    assert max(v["max_px"] for v in shift.values()) < 2e-3  # float32 storage only
    # the device's left fx 2 px larger: a point at normalised x moves 2 x px, largest at the
    # lattice's edge (5 % in from the border)
    K = np.array(r.cameras["left"].K, float)
    K[0, 0] += 2.0
    cams["left"] = CameraEstimate("left", 1280, 800, K, np.zeros(5), {}, 0.1)
    dev = oak_calibration_handler(CalibrationResult(**{**r.__dict__, "cameras": cams}))
    shift = projection_shift_px(r, dev.eepromToJson(), {"left": "CAM_B"}, 0.5)
    K0 = np.asarray(r.cameras["left"].K)
    x_edge = max(abs(0.05 * 1279 - K0[0, 2]), abs(0.95 * 1279 - K0[0, 2])) / K0[0, 0]
    assert shift["left"]["max_px"] == pytest.approx(2.0 * x_edge, rel=1e-3)


def test_projection_shift_reads_a_fisheye_result_as_fisheye():
    # our fisheye camera against the device's perspective one with the same K and no distortion:
    # the lattice's rays are the fisheye's (cv2.undistortPoints would read its four
    # coefficients as k1 k2 p1 p2), so the shift is the pinhole image of the fisheye's rays
    r = _result(np.random.default_rng(8))
    d4 = np.array([0.05, -0.01, 0.002, -0.0005])
    cams = {n: CameraEstimate(n, c.width, c.height, c.K, np.zeros(5), {}, 0.1)
            for n, c in r.cameras.items()}
    device = oak_calibration_handler(CalibrationResult(**{**r.__dict__, "cameras": dict(cams)}))
    cams["left"] = CameraEstimate("left", 1280, 800, cams["left"].K, d4, {}, 0.1)
    ours = CalibrationResult(**{**r.__dict__, "cameras": cams})
    shift = projection_shift_px(ours, device.eepromToJson(), {"left": "CAM_B"}, 0.5)
    K = np.asarray(cams["left"].K, float)
    lattice = np.linspace(0.05, 0.95, 9)
    u, v = np.meshgrid(lattice * 1279, lattice * 799)
    px = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    rays = cv2.fisheye.undistortPoints(px, K, d4).reshape(-1, 2)
    want = np.linalg.norm(px.reshape(-1, 2) - (rays @ K[:2, :2].T + K[:2, 2]), axis=1).max()
    assert shift["left"]["max_px"] == pytest.approx(want, rel=1e-3)


def test_choose_sensor_mode():
    full, crop = (0, 0, 4056, 3040), (0, 440, 4056, 2160)
    modes = [
        {"width": 4056, "height": 3040, "min_fps": 1, "max_fps": 30, "fov": full},
        {"width": 1920, "height": 1080, "min_fps": 1, "max_fps": 60, "fov": crop},
        {"width": 2028, "height": 1520, "min_fps": 1, "max_fps": 60, "fov": full},
    ]
    assert choose_sensor_mode(modes, (1920, 1080), 10)["width"] == 2028  # full view, smallest
    assert choose_sensor_mode(modes, (3000, 2000), 10)["width"] == 4056
    assert choose_sensor_mode(modes, (3000, 2000), 45)["width"] == 2028  # 4056 cannot do 45
    with pytest.raises(InputError, match="no full-field-of-view sensor mode runs at 90 fps"):
        choose_sensor_mode(modes, (1920, 1080), 90)
    assert choose_sensor_mode([], (640, 480), 10) is None


# -------------------------------------------------------------------- capture (fake depthai)


@pytest.fixture
def world(monkeypatch):
    w = fake_depthai.World()
    monkeypatch.setitem(sys.modules, "depthai", fake_depthai.make_fake_depthai(w))
    monkeypatch.setattr(oak, "AUTO_EXPOSURE_SETTLE_S", 0.05, raising=False)
    yield w
    for p in w.pipelines:
        p.stop()


def _requests(world):
    return {c[1]: c for c in world.calls if c[0] == "requestOutput"}


def test_open_configures_the_pipeline_for_calibration(world):
    dai = dai_real
    rig = OakRig(exposure_us=8000, iso=400, focus={"rgb": 130}, white_balance_k={"rgb": 4500})
    assert isinstance(rig, CameraRig)
    rig.open()
    off = ("setAutoCalibrationMode", dai.Pipeline.AutoCalibrationMode.OFF)
    assert world.calls.index(off) < world.calls.index(("start",))
    req = _requests(world)
    gray, bgr = dai.ImgFrame.Type.GRAY8, dai.ImgFrame.Type.BGR888i
    stretch = dai.ImgResizeMode.STRETCH
    # the whole field of view, at a requested frame rate, undistortion off
    assert req["CAM_B"][2:] == ((1280, 800), gray, stretch, 10.0, False)
    assert req["CAM_C"][2:] == ((1280, 800), gray, stretch, 10.0, False)
    assert req["CAM_A"][2:] == ((1920, 1080), bgr, stretch, 10.0, False)
    builds = {c[1]: c[2:] for c in world.calls if c[0] == "build"}
    assert builds["CAM_A"] == ((2028, 1520), 10.0)  # binned full-view mode, not the 1080p crop
    assert builds["CAM_B"] == ((1280, 800), 10.0)
    # the initial controls, read back from depthai's own CameraControl
    controls = {c._socket: c.initialControl for c in world.pipelines[0].cameras}
    for ctrl in controls.values():
        assert ctrl.getExposureTime().total_seconds() == pytest.approx(0.008)
        assert ctrl.getSensitivity() == 400
    assert controls["CAM_A"].getLensPosition() == 130
    assert "wbColorTemp: 4500" in str(controls["CAM_A"])
    assert "wbColorTemp: 0" in str(controls["CAM_B"])
    rig.close()
    rig.close()
    assert world.calls.count(("stop",)) == 1


def test_capabilities_and_device_calibrations_are_reported(world):
    rig = OakRig(focus={"rgb": 130}, fps=15)
    rig.open()
    cap = rig.capabilities()
    assert cap["device_id"] == world.device_id and cap["usb_speed"] == "SUPER"
    assert cap["product_name"] == "OAK-D" and cap["platform"] == "RVC2"
    sensors = {s["socket"]: s for s in cap["sensors"]}
    assert sensors["CAM_A"]["sensor"] == "IMX378" and sensors["CAM_A"]["autofocus"]
    assert len(sensors["CAM_B"]["modes"]) == 2
    rgb = cap["outputs"]["rgb"]
    assert rgb["sensor_mode"]["width"] == 2028 and rgb["fps"] == 15.0
    assert rgb["focus"] == 130 and rgb["white_balance_k"] == 5000
    assert cap["stream_mb_per_s"] == pytest.approx((2 * 1280 * 800 + 3 * 1920 * 1080) * 15 / 1e6,
                                                   abs=0.1)
    cal = rig.device_calibrations()
    assert cal["user"]["boardName"] == "OAK-D" and cal["factory"]["boardName"] == "OAK-D"
    rig.close()


def test_autofocus_camera_without_focus_is_refused_and_the_pipeline_stopped(world):
    with pytest.raises(InputError, match=r"rgb \(CAM_A\) have autofocus.*add focus"):
        OakRig().open()
    assert ("stop",) in world.calls and ("start",) not in world.calls


def test_unknown_socket_lists_the_valid_ones_and_opens_nothing(world):
    with pytest.raises(InputError, match="'CAM_Q' is not an OAK board socket; use one of CAM_A"):
        OakRig(sockets={"left": "CAM_Q"}, sizes={"left": (1280, 800)})
    assert world.pipelines == []


def test_capture_returns_a_fresh_synchronised_set(world):
    rig = OakRig(sync_tolerance_s=0.005, focus={"rgb": 130}, fps=30)
    rig.open()
    assert [s.name for s in rig.specs] == ["left", "right", "rgb"]
    for _ in range(3):
        images = rig.capture()
        assert images["left"].shape == (800, 1280) and images["left"].dtype == np.uint8
        assert images["rgb"].shape == (1080, 1920, 3)
        values = {n: int(img.flat[0]) for n, img in images.items()}
        assert 255 not in values.values()  # frames queued before the call were dropped
        assert len(set(values.values())) == 1  # the same frame period on every camera
    rig.close()


def test_device_lost_mid_run_is_a_hardware_fault_and_stops_the_pipeline(world):
    """depthai v3 keeps the output queues open and the pipeline running when the device
    crashes or is unplugged (XLinkInHost waits for a reconnection): only Device.isClosed()
    says so. The fault comes at once and names the device, not after the capture time-out
    as a synchronisation problem; reconnection is off (it would lose the exposure lock)."""
    rig = OakRig(focus={"rgb": 130}, fps=30, timeout_s=3.0)
    rig.open()
    assert ("setMaxReconnectionAttempts", 0) in world.calls
    rig.capture()
    world.lose_device()
    assert world.pipelines[0].isRunning() and not world.pipelines[0].outputs[0]._queue.isClosed()
    t0 = time.monotonic()
    with pytest.raises(HardwareFault, match=f"OAK device {world.device_id} lost during capture"
                       r" \(the device closed its connection\)"):
        rig.capture()
    assert time.monotonic() - t0 < 1.0
    assert ("stop",) in world.calls
    with pytest.raises(HardwareFault, match="not open"):
        rig.capture()


def test_closed_queues_are_a_lost_device(world):
    rig = OakRig(focus={"rgb": 130}, fps=30)
    rig.open()
    world.close_queues()
    with pytest.raises(HardwareFault, match="lost during capture .MessageQueue was closed"):
        rig.capture()
    assert not world.pipelines[0].isRunning()


def test_auto_exposure_is_locked_before_any_capture_and_read_back(world):
    """Without exposure_us the auto exposure settles, then is locked through each camera's
    control input; the settings the frames report are recorded. The old driver left the
    auto exposure running for the whole session."""
    rig = OakRig(focus={"rgb": 130}, fps=30)
    rig.open()
    controls = [c for c in world.calls if c[0] == "createInputQueue"]
    assert world.calls.index(controls[-1]) < world.calls.index(("start",))
    cams = {c._socket: c for c in world.pipelines[0].cameras}
    for cam in cams.values():
        sent = cam.inputControl._queue._messages
        assert len(sent) == 1 and sent[0].getCommand(dai_real.CameraControl.Command.AE_LOCK)
    cap = rig.capabilities()
    assert cap["exposure_locked"] == "auto, locked" and cap["messages"] == []
    read = {n: o["read_back"] for n, o in cap["outputs"].items()}
    assert read["rgb"]["lens_position"] == 130 and read["rgb"]["colour_temperature_k"] == 5000
    assert read["left"]["colour_temperature_k"] == 0
    locked = {n: (r["exposure_us"], r["iso"]) for n, r in read.items()}
    for _ in range(3):  # the exposure no longer moves
        rig.capture()
        assert {n: c._locked for n, c in zip(("rgb", "left", "right"),
                                             (cams["CAM_A"], cams["CAM_B"], cams["CAM_C"]),
                                             strict=True)} == locked
    rig.close()


def test_an_exposure_that_does_not_lock_is_refused(world):
    world.ignore_exposure_lock = True
    with pytest.raises(HardwareFault, match="still changes its exposure after it was locked"):
        OakRig(focus={"rgb": 130}, fps=30).open()
    assert not world.pipelines[0].isRunning()


def test_manual_settings_are_read_back_and_a_clamped_one_reported(world):
    world.exposure_limit_us = 20000
    rig = OakRig(focus={"rgb": 130}, fps=30, exposure_us=30000, iso=800)
    rig.open()
    assert not any(c[0] == "createInputQueue" for c in world.calls)  # nothing to lock
    cap = rig.capabilities()
    assert cap["exposure_locked"] == "manual"
    assert cap["outputs"]["left"]["read_back"]["exposure_us"] == 20000
    assert cap["outputs"]["left"]["read_back"]["iso"] == 800
    assert any("camera left: exposure 30000 us requested, frames report 20000 us" in m
               for m in cap["messages"])
    rig.close()


def test_a_free_running_colour_camera_half_a_period_off_is_matched(world):
    """At 10 fps the colour camera's frames can sit up to 50 ms from the stereo pair's (a
    fixed phase): the default tolerance (0.55 / fps) still makes sets; the old fixed 15 ms
    waited for a match that never comes."""
    world.offsets["CAM_A"] = 0.045
    rig = OakRig(focus={"rgb": 130}, timeout_s=1.0)
    assert rig.sync_tolerance_s == pytest.approx(0.055)
    rig.open()
    images = rig.capture()
    assert len({int(img.flat[0]) for img in images.values()}) == 1
    rig.close()


def test_the_nearest_frame_is_taken_only_once_it_cannot_come_later(world):
    """A colour camera 45 ms after the stereo pair at 10 fps: its frame 54 ms before a stereo
    frame is within the tolerance too. Read first (each camera has its own queue), it used to
    make a set with the wrong period (a race the test above lost under load); the driver waits
    for the colour frame at or after the stereo frame's time and takes the nearest."""
    rig = OakRig(focus={"rgb": 130}, timeout_s=1.0)
    names = list(rig.sockets)
    ref, colour = names[0], "rgb"
    assert ref != colour  # the first camera, whose frames the others are matched to
    buffers = {n: [(1.0, f"{n}@1.0")] for n in names}
    buffers[colour] = [(0.946, "rgb@0.946")]
    assert abs(1.0 - 0.946) <= rig.sync_tolerance_s
    assert rig._match(buffers, names) is None  # the next colour frame may be nearer
    buffers[colour].append((1.045, "rgb@1.045"))
    assert rig._match(buffers, names) == {n: f"{n}@1.0" for n in names if n != colour} | {
        colour: "rgb@1.045"
    }


def test_capture_fault_when_cameras_are_not_synchronised(world):
    world.offsets["CAM_A"] = 0.016  # half a frame period away from the stereo pair
    rig = OakRig(sync_tolerance_s=0.005, timeout_s=0.2, focus={"rgb": 130}, fps=30)
    with pytest.raises(HardwareFault, match="no set of frames within 5.0 ms"):
        rig.open()  # reading the settings back needs a set already
    assert not world.pipelines[0].isRunning()
    with pytest.raises(HardwareFault, match="not open"):
        rig.capture()


def test_no_device_and_missing_camera_are_hardware_faults(world):
    world.no_device = True
    with pytest.raises(HardwareFault, match="plug it into a USB3 port"):
        OakRig(focus={"rgb": 130}).open()
    world.no_device = False
    world.sensors = world.sensors[1:]
    with pytest.raises(HardwareFault, match=r"rgb \(CAM_A\) not on this device"):
        OakRig(focus={"rgb": 130}).open()
    assert ("stop",) in world.calls and ("start",) not in world.calls


def test_wrong_delivered_size_is_a_fault(world):
    world.deliver_size = (640, 400)
    rig = OakRig(sockets={"left": "CAM_B"}, sizes={"left": (1280, 800)}, fps=30)
    rig.open()
    with pytest.raises(HardwareFault, match="640x400 instead of 1280x800"):
        rig.capture()
    rig.close()


def test_bad_configuration(world):
    with pytest.raises(InputError, match="together"):
        OakRig(exposure_us=1000)
    with pytest.raises(InputError, match="no image size"):
        OakRig(sockets={"cam": "CAM_D"}, sizes={})
    with pytest.raises(InputError, match="lens"):
        OakRig(focus={"rgb": 300})
    with pytest.raises(InputError, match="resize mode"):
        OakRig(resize_mode="squash")
    with pytest.raises(InputError, match="white_balance_k"):
        OakRig(white_balance_k={"left": 5000})
    with pytest.raises(HardwareFault, match="open"):
        OakRig().capture()


def test_missing_depthai_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "depthai", None)  # import now fails
    with pytest.raises(InputError, match=r"pip install 'slidecal\[oak\]'"):
        OakRig()


# ------------------------------------------------------- the fake against the installed depthai


def _check(fake, real, where):
    if fake is real:
        return
    if isinstance(fake, types.SimpleNamespace):
        for k, v in vars(fake).items():
            assert hasattr(real, k), f"{where}.{k}: not in the installed depthai"
            _check(v, getattr(real, k), f"{where}.{k}")
        return
    assert hasattr(real, "__members__") is False, f"{where}: depthai's is an enum; use it"
    if inspect.isclass(fake):
        assert inspect.isclass(real), f"{where}: a class in the fake, not in depthai"
        for k, v in vars(fake).items():
            if k.startswith("_") and k != "__init__":
                continue
            assert hasattr(real, k), f"{where}.{k}: not in the installed depthai"
            r = getattr(real, k)
            if inspect.isfunction(v):
                _check_callable(v, r, k, f"{where}.{k}")
            elif inspect.isclass(v) or isinstance(v, types.SimpleNamespace):
                _check(v, r, f"{where}.{k}")
            elif v is not None:
                assert type(v) is type(r), f"{where}.{k}: {type(v)} against {type(r)}"
        return
    raise AssertionError(f"{where}: {type(fake).__name__} is neither depthai's nor a class")


def test_the_fake_depthai_matches_the_installed_one():
    fake = fake_depthai.make_fake_depthai(fake_depthai.World())
    names = [n for n in vars(fake) if not n.startswith("_")]
    assert set(fake_depthai.REAL_NAMES) < set(names)
    faked = []
    for n in names:
        assert hasattr(dai_real, n), f"depthai.{n} does not exist"
        _check(getattr(fake, n), getattr(dai_real, n), f"depthai.{n}")
        faked += [n] if getattr(fake, n) is not getattr(dai_real, n) else []
    assert sorted(faked) == ["Device", "InputQueue", "Node", "Pipeline", "node"]
    # and the checker catches a drifted fake: a renamed keyword, a method depthai lacks
    class Drifted:
        def requestOutput(self, size, type=None, resize_mode=None):  # noqa: A002
            ...

    with pytest.raises(AssertionError, match="matches no overload"):
        _check(Drifted, dai_real.node.Camera, "Camera")
    Drifted.requestOutput = lambda self, size: None
    Drifted.grabFrame = lambda self: None
    with pytest.raises(AssertionError, match="grabFrame: not in the installed depthai"):
        _check(Drifted, dai_real.node.Camera, "Camera")


def test_a_device_without_calibration_reports_none(world):
    world.user, world.factory = None, None
    rig = OakRig(focus={"rgb": 130})
    rig.open()
    assert rig.device_calibrations() == {"user": None, "factory": None}
    rig.close()


def test_a_sensor_mode_the_device_refuses_is_never_requested(world):
    """depthai-core's Camera::build refuses a resolution that is not one of the sensor's
    modes, or a frame rate outside that mode's range (RuntimeError); the driver asks for a
    mode that fits instead, or says in one line that none does."""
    with pytest.raises(InputError, match=r"camera 'rgb' \(CAM_A\): no full-field-of-view"):
        OakRig(focus={"rgb": 130}, fps=90.0).open()
    assert world.pipelines[-1].isRunning() is False and ("start",) not in world.calls
    rig = OakRig(focus={"rgb": 130}, fps=45.0)  # the full 4056x3040 mode stops at 30 fps
    rig.open()
    assert rig.capabilities()["outputs"]["rgb"]["sensor_mode"]["width"] == 2028
    rig.close()
