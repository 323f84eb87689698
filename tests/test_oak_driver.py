"""OAK driver: calibration writing against the real depthai; capture against a fake depthai.

The CalibrationHandler part runs on the installed depthai 3.12 (no device needed). Capture
cannot run here (no device), so it is checked against a fake ``depthai`` module with the
classes and methods the driver uses, plus one slow test that the real library's "No available
devices" becomes a HardwareFault.
"""

from __future__ import annotations

import sys
import time
import types
from datetime import timedelta

import numpy as np
import pytest

from slidecal.drivers.base import CameraRig
from slidecal.drivers.oak import OakRig, oak_calibration_handler, write_oak_calibration_json
from slidecal.solver.errors import HardwareFault, InputError
from slidecal.solver.geometry import inv_T, random_rotation
from slidecal.solver.result import CalibrationResult, CameraEstimate, TransformEstimate

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
    rig = OakRig(sockets={"left": "CAM_B"}, sizes={"left": (1280, 800)})
    with pytest.raises(HardwareFault, match="USB3"):
        rig.open()


# -------------------------------------------------------------------- capture (fake depthai)


class FakeWorld:
    def __init__(self):
        self.calls = []
        self.no_device = False
        self.connected = ["CAM_A", "CAM_B", "CAM_C"]
        self.period_s = 1 / 30
        self.offsets = {"CAM_A": 0.004, "CAM_B": 0.0, "CAM_C": 0.00001}
        self.deliver_size = None


def make_fake_depthai(world: FakeWorld) -> types.ModuleType:
    dai = types.ModuleType("depthai")

    class CameraBoardSocket:
        CAM_A, CAM_B, CAM_C, CAM_D = "CAM_A", "CAM_B", "CAM_C", "CAM_D"

    class ImgFrameType:
        GRAY8, BGR888i = "GRAY8", "BGR888i"

    class ImgFrame:
        Type = ImgFrameType

    class Clock:
        @staticmethod
        def now():
            return timedelta(seconds=time.monotonic())

    class Frame:
        def __init__(self, t, img):
            self.t, self.img = t, img

        def getTimestamp(self):
            return timedelta(seconds=self.t)

        def getCvFrame(self):
            return self.img

    class Queue:
        def __init__(self, socket, size, kind):
            self.socket, self.size, self.kind = socket, size, kind
            off = world.offsets[socket]
            # Two stale frames from before the capture call, marked 255.
            self.pending = [Frame(time.monotonic() - 1.0 + off, self._img(255)),
                            Frame(time.monotonic() - 0.5 + off, self._img(255))]
            self.k_next = int(np.ceil(time.monotonic() / world.period_s))

        def _img(self, value):
            w, h = world.deliver_size or self.size
            shape = (h, w, 3) if self.kind == "BGR888i" else (h, w)
            return np.full(shape, value, np.uint8)

        def tryGetAll(self):
            now = time.monotonic()
            while self.k_next * world.period_s + world.offsets[self.socket] <= now:
                t = self.k_next * world.period_s + world.offsets[self.socket]
                self.pending.append(Frame(t, self._img(self.k_next % 200)))
                self.k_next += 1
            out, self.pending = self.pending, []
            return out

    class Output:
        def __init__(self, socket, size, kind):
            self.args = (socket, size, kind)

        def createOutputQueue(self, maxSize=16, blocking=False):
            world.calls.append(("createOutputQueue", maxSize, blocking))
            return Queue(*self.args)

    class Control:
        def __init__(self, socket):
            self.socket = socket

        def setManualExposure(self, exposureTimeUs, sensitivityIso):
            world.calls.append(("setManualExposure", self.socket, exposureTimeUs, sensitivityIso))

        def setManualFocus(self, lensPosition):
            world.calls.append(("setManualFocus", self.socket, lensPosition))

    class Camera:
        def build(self, boardSocket):
            world.calls.append(("build", boardSocket))
            self.socket = boardSocket
            self.initialControl = Control(boardSocket)
            return self

        def requestOutput(self, size, type=None, enableUndistortion=None):  # noqa: A002
            call = ("requestOutput", self.socket, tuple(size), type, enableUndistortion)
            world.calls.append(call)
            return Output(self.socket, tuple(size), type)

    class Device:
        def getConnectedCameras(self):
            return list(world.connected)

    class AutoCalibrationMode:
        OFF, ON_START, CONTINUOUS = "OFF", "ON_START", "CONTINUOUS"

    class Pipeline:
        def __init__(self, device=None):
            if world.no_device:
                raise RuntimeError("No available devices")
            self.running = False

        def getDefaultDevice(self):
            return Device()

        def setAutoCalibrationMode(self, mode):
            world.calls.append(("setAutoCalibrationMode", mode))

        def create(self, cls):
            return cls()

        def start(self):
            world.calls.append(("start",))
            self.running = True

        def isRunning(self):
            return self.running

        def stop(self):
            world.calls.append(("stop",))
            self.running = False

        def wait(self):
            world.calls.append(("wait",))

    Pipeline.AutoCalibrationMode = AutoCalibrationMode
    dai.CameraBoardSocket = CameraBoardSocket
    dai.ImgFrame = ImgFrame
    dai.Clock = Clock
    dai.Pipeline = Pipeline
    dai.Device = lambda info: Device()
    dai.DeviceInfo = lambda s: s
    dai.node = types.SimpleNamespace(Camera=Camera)
    return dai


@pytest.fixture
def world(monkeypatch):
    w = FakeWorld()
    monkeypatch.setitem(sys.modules, "depthai", make_fake_depthai(w))
    return w


def test_open_configures_the_pipeline_for_calibration(world):
    rig = OakRig(exposure_us=8000, iso=400, focus={"rgb": 130})
    assert isinstance(rig, CameraRig)
    rig.open()
    assert ("setAutoCalibrationMode", "OFF") in world.calls
    req = [c for c in world.calls if c[0] == "requestOutput"]
    assert ("requestOutput", "CAM_B", (1280, 800), "GRAY8", False) in req
    assert ("requestOutput", "CAM_C", (1280, 800), "GRAY8", False) in req
    assert ("requestOutput", "CAM_A", (1920, 1080), "BGR888i", False) in req
    assert all(c[4] is False for c in req)
    assert sum(c[0] == "setManualExposure" and c[2:] == (8000, 400) for c in world.calls) == 3
    assert ("setManualFocus", "CAM_A", 130) in world.calls
    assert world.calls.index(("setAutoCalibrationMode", "OFF")) < world.calls.index(("start",))
    rig.close()
    rig.close()
    assert world.calls.count(("stop",)) == 1


def test_capture_returns_a_fresh_synchronised_set(world):
    rig = OakRig(sync_tolerance_s=0.005)
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


def test_capture_fault_when_cameras_are_not_synchronised(world):
    world.offsets["CAM_A"] = 0.016  # half a frame period away from the stereo pair
    rig = OakRig(sync_tolerance_s=0.005, timeout_s=0.2)
    rig.open()
    with pytest.raises(HardwareFault, match="no set of frames within 5.0 ms"):
        rig.capture()


def test_no_device_and_missing_camera_are_hardware_faults(world):
    world.no_device = True
    with pytest.raises(HardwareFault, match="plug it into a USB3 port"):
        OakRig().open()
    world.no_device = False
    world.connected = ["CAM_B", "CAM_C"]
    with pytest.raises(HardwareFault, match=r"rgb \(CAM_A\) not on this device"):
        OakRig().open()
    assert ("stop",) in world.calls and ("start",) not in world.calls


def test_wrong_delivered_size_is_a_fault(world):
    world.deliver_size = (640, 400)
    rig = OakRig(sockets={"left": "CAM_B"}, sizes={"left": (1280, 800)})
    rig.open()
    with pytest.raises(HardwareFault, match="640x400 instead of 1280x800"):
        rig.capture()


def test_bad_configuration():
    with pytest.raises(InputError, match="together"):
        OakRig(exposure_us=1000)
    with pytest.raises(InputError, match="no image size"):
        OakRig(sockets={"cam": "CAM_D"}, sizes={})
    with pytest.raises(InputError, match="lens"):
        OakRig(focus={"rgb": 300})
    with pytest.raises(HardwareFault, match="open"):
        OakRig().capture()

