"""A fake ``depthai`` for the OAK driver's tests: only the device-bound parts are fake.

What needs no device is the installed depthai itself: the enums (``CameraBoardSocket``,
``ImgFrame.Type``, ``ImgResizeMode``, ``Pipeline.AutoCalibrationMode``, ``UsbSpeed``), the
messages and queues (``ImgFrame``, ``MessageQueue`` with its ``QueueException``), the initial
``CameraControl`` each camera node carries, ``CameraFeatures`` / ``CameraSensorConfig``, ``Clock``
and ``CalibrationHandler``. Faked: ``Pipeline`` (a device-backed pipeline cannot be made here),
``Device``, ``node.Camera``, the ``Node.Output`` and ``Node.Input`` it has and the ``InputQueue``
of its control input. Once started, the fake pipeline sends real ``ImgFrame`` messages (a subclass
that reports the exposure, ISO, lens position and colour temperature the camera runs with) into
real ``MessageQueue`` objects from a thread, at the frame rate each output requested, timestamped
on depthai's own clock. The camera runs as its initial ``CameraControl`` says (manual exposure,
lens, white balance) and otherwise with an auto exposure that keeps changing until a control
with the auto-exposure lock arrives on its input queue. Losing the device does what depthai-core
3.x does (``DeviceBase::monitorCallback``, ``XLinkInHost::run``, ``PipelineImpl::stop``): the
frames stop, ``Device.isClosed()`` turns True, the pipeline still says it runs and the output
queues stay open (only ``Pipeline.stop()`` closes them). ``tests/test_oak_driver.py`` checks
every name defined here against the installed depthai (kind, members, method names and
signatures), so the fake cannot drift.
"""

from __future__ import annotations

import re
import threading
import types
from collections import deque
from datetime import timedelta
from typing import Any

import depthai as dai
import numpy as np

#: The names of the installed depthai this fake hands through unchanged.
REAL_NAMES = (
    "CalibrationHandler",
    "CameraBoardSocket",
    "CameraControl",
    "CameraFeatures",
    "CameraModel",
    "CameraSensorConfig",
    "Clock",
    "DeviceInfo",
    "EepromError",
    "ImgFrame",
    "ImgResizeMode",
    "MessageQueue",
    "UsbSpeed",
)


def sensor(socket: str, name: str, modes, autofocus: bool = False, colour: bool = False):
    """A real ``dai.CameraFeatures``: ``modes`` are (width, height, min_fps, max_fps, fov)."""
    f = dai.CameraFeatures()
    f.socket = dai.CameraBoardSocket.__members__[socket]
    f.sensorName = name
    f.width, f.height = modes[0][0], modes[0][1]
    f.hasAutofocus = autofocus
    configs = []
    for w, h, lo, hi, fov in modes:
        c = dai.CameraSensorConfig()
        c.width, c.height, c.minFps, c.maxFps = w, h, lo, hi
        c.fov = dai.Rect(*fov)
        c.type = dai.CameraSensorType.COLOR if colour else dai.CameraSensorType.MONO
        configs.append(c)
    f.configs = configs
    return f


def oak_d_sensors() -> list[Any]:
    """An OAK-D's sensors: IMX378 colour with autofocus (its 1080p mode is a 16:9 crop of the
    4056x3040 array), two OV9282 mono (1280x800, 640x400 binned over the whole array)."""
    return [
        sensor(
            "CAM_A", "IMX378",
            [(4056, 3040, 1.0, 30.0, (0, 0, 4056, 3040)),
             (1920, 1080, 1.0, 60.0, (0, 440, 4056, 2160)),
             (2028, 1520, 1.0, 60.0, (0, 0, 4056, 3040))],
            autofocus=True, colour=True,
        ),
        sensor("CAM_B", "OV9282", [(1280, 800, 1.0, 120.0, (0, 0, 1280, 800)),
                                   (640, 400, 1.0, 120.0, (0, 0, 1280, 800))]),
        sensor("CAM_C", "OV9282", [(1280, 800, 1.0, 120.0, (0, 0, 1280, 800)),
                                   (640, 400, 1.0, 120.0, (0, 0, 1280, 800))]),
    ]


class World:
    """What the fake device is and does; tests change it before or during a run."""

    def __init__(self) -> None:
        self.calls: list[tuple] = []
        self.no_device = False
        self.sensors = oak_d_sensors()
        self.device_id = "18443010D1E4F1F500"
        self.offsets = {"CAM_A": 0.004, "CAM_B": 0.0, "CAM_C": 0.00001}
        self.deliver_size: tuple[int, int] | None = None
        self.user = dai.CalibrationHandler()
        self.user.setBoardInfo("OAK-D", "R3M2E3")
        self.factory: Any = dai.CalibrationHandler()
        self.factory.setBoardInfo("OAK-D", "R3M2E3")
        self.flash_fails = False
        self.flash_corrupts = False
        self.pipelines: list[Any] = []
        #: socket name -> image of what the camera sees now (None: flat frames numbered k % 200)
        self.render: Any = None
        #: the auto exposure's exposure (us) and ISO before it is locked; it changes every frame
        self.auto_exposure = (12000, 400)
        self.ignore_exposure_lock = False  # a device whose auto exposure does not lock
        self.exposure_limit_us: int | None = None  # longer manual exposures are clamped
        self.lost = False

    def lose_device(self) -> None:
        """Unplug (or a firmware crash): the frames stop and the device is closed; the queues
        stay open and the pipeline still says it runs, as in depthai-core."""
        self.lost = True
        for p in self.pipelines:
            p._halt.set()

    def close_queues(self) -> None:
        """Every output queue of every pipeline is closed (reads raise QueueException)."""
        for p in self.pipelines:
            for out in p.outputs:
                if out._queue is not None:
                    out._queue.close()


def _copy(handler: Any) -> Any:
    return dai.CalibrationHandler.fromJson(handler.eepromToJson())


class _Frame(dai.ImgFrame):
    """A real ``ImgFrame`` carrying the camera settings depthai fills in on a device (its
    Python binding has getters only)."""

    _settings: tuple[int, int, int, int] = (0, 0, 0, 0)

    def getExposureTime(self):
        return timedelta(microseconds=self._settings[0])

    def getSensitivity(self):
        return self._settings[1]

    def getLensPosition(self):
        return self._settings[2]

    def getColorTemperature(self):
        return self._settings[3]


def make_fake_depthai(world: World) -> types.ModuleType:
    """A ``depthai`` module for ``sys.modules``, driven by ``world``."""
    fake = types.ModuleType("depthai")
    for name in REAL_NAMES:
        setattr(fake, name, getattr(dai, name))
    fake.__version__ = dai.__version__

    class Device:
        def __init__(self, deviceInfo=None):
            if world.no_device:
                raise RuntimeError("No available devices")
            world.calls.append(("Device", None if deviceInfo is None else deviceInfo.deviceId))
            self.closed = False

        def getConnectedCameraFeatures(self):
            return list(world.sensors)

        def getConnectedCameras(self):
            return [f.socket for f in world.sensors]

        def getDeviceId(self):
            return world.device_id

        def getDeviceName(self):
            return "OAK-D"

        def getProductName(self):
            return "OAK-D"

        def getPlatformAsString(self):
            return "RVC2"

        def getUsbSpeed(self):
            return dai.UsbSpeed.SUPER

        def getBootloaderVersion(self):
            return None

        def readCalibration(self):  # an empty handler when the user area holds nothing
            return dai.CalibrationHandler() if world.user is None else _copy(world.user)

        def readFactoryCalibration(self):
            if world.factory is None:
                raise dai.EepromError("No factory calibration")
            return _copy(world.factory)

        def flashCalibration(self, calibrationObj):
            if world.flash_fails:
                raise dai.EepromError("EEPROM write failed")
            world.calls.append(("flashCalibration",))
            data = calibrationObj.eepromToJson()
            if world.flash_corrupts:  # the EEPROM keeps something else than was sent
                data["cameraData"][0][1]["intrinsicMatrix"][0][0] += 1.0
            world.user = dai.CalibrationHandler.fromJson(data)

        def close(self):
            self.closed = True

        def isClosed(self):
            return self.closed or world.lost

        def setMaxReconnectionAttempts(self, maxAttempts, callback=None):
            world.calls.append(("setMaxReconnectionAttempts", maxAttempts))

    class Output:  # the fake's own state is private (underscored): depthai has none of it
        _queue: Any = None

        def createOutputQueue(self, maxSize=16, blocking=False):
            world.calls.append(("createOutputQueue", maxSize, blocking))
            self._queue = dai.MessageQueue(self._socket, maxSize, blocking)
            return self._queue

    class InputQueue:
        def __init__(self) -> None:
            self._messages: list[Any] = []

        def send(self, msg):
            self._messages.append(msg)

    class Input:
        _queue: Any = None

        def createInputQueue(self, maxSize=16, blocking=False):
            world.calls.append(("createInputQueue", self._socket))
            self._queue = InputQueue()
            return self._queue

    class Camera:
        initialControl: Any = None
        inputControl: Any = None

        def _settings(self, k):
            """(exposure us, ISO, lens, colour temperature K) of frame ``k``."""
            ctrl = self.initialControl
            if ctrl.getCommand(dai.CameraControl.Command.AE_MANUAL):
                exposure = round(ctrl.getExposureTime().total_seconds() * 1e6)
                if world.exposure_limit_us is not None:
                    exposure = min(exposure, world.exposure_limit_us)
                self._exposure = (exposure, ctrl.getSensitivity())
            elif self._locked is None:
                sent = self.inputControl._queue._messages if self.inputControl._queue else []
                if any("aeLockMode: true" in str(m) for m in sent) and not \
                        world.ignore_exposure_lock:
                    self._locked = self._exposure
                exposure, iso = world.auto_exposure
                self._exposure = (exposure + 40 * (k % 25), iso)
            if self._locked is not None:
                self._exposure = self._locked
            wb = re.search(r"wbColorTemp: (\d+)", str(ctrl))
            return (*self._exposure, max(ctrl.getLensPosition(), 0), int(wb.group(1)))

        def build(self, boardSocket, sensorResolution=None, sensorFps=None):
            world.calls.append(("build", boardSocket.name, sensorResolution, sensorFps))
            features = {f.socket: f for f in world.sensors}
            if boardSocket not in features:
                raise RuntimeError(f"Camera on socket {boardSocket.name} not found")
            if sensorResolution is not None:  # as depthai-core's Camera::build checks it
                modes = {(c.width, c.height): c for c in features[boardSocket].configs}
                mode = modes.get(tuple(sensorResolution))
                if mode is None:
                    raise RuntimeError("Invalid sensor resolution specified")
                if sensorFps is not None and not mode.minFps <= sensorFps <= mode.maxFps:
                    raise RuntimeError("Invalid sensor FPS specified")
            self._socket = boardSocket.name
            self.initialControl = dai.CameraControl()
            self.inputControl = Input()
            self.inputControl._socket = boardSocket.name
            self._locked: tuple[int, int] | None = None
            self._exposure = world.auto_exposure
            self._pipeline.cameras.append(self)
            return self

        def requestOutput(self, size, type=None, resizeMode=dai.ImgResizeMode.CROP,  # noqa: A002
                          fps=None, enableUndistortion=None):
            call = ("requestOutput", self._socket, tuple(size), type, resizeMode, fps,
                    enableUndistortion)
            world.calls.append(call)
            out = Output()
            out._socket, out._size, out._kind, out._fps = self._socket, tuple(size), type, fps or 30
            out._camera = self
            self._pipeline.outputs.append(out)
            return out

    class Pipeline:
        AutoCalibrationMode = dai.Pipeline.AutoCalibrationMode

        def __init__(self, defaultDevice=None):
            self.device = defaultDevice if defaultDevice is not None else Device()
            self.running = False
            self.cameras: list[Camera] = []
            self.outputs: list[Output] = []
            self._halt = threading.Event()
            self._thread: threading.Thread | None = None
            self._sent: deque = deque(maxlen=256)  # keeps the frames' Python objects alive
            world.pipelines.append(self)

        def getDefaultDevice(self):
            return self.device

        def setAutoCalibrationMode(self, mode):
            world.calls.append(("setAutoCalibrationMode", mode))

        def create(self, cls):
            node = cls()
            node._pipeline = self
            return node

        def start(self):
            world.calls.append(("start",))
            self.running = True
            now = dai.Clock.now().total_seconds()
            for out in self.outputs:  # two frames from before the capture call, marked 255
                for age in (1.0, 0.5):
                    self._send(out, now - age + world.offsets[out._socket], 255)
            self._thread = threading.Thread(target=self._stream, daemon=True)
            self._thread.start()

        def _send(self, out, t, value, k=0):
            w, h = world.deliver_size or out._size
            colour = out._kind == dai.ImgFrame.Type.BGR888i
            if world.render is not None and value != 255:
                img = world.render(out._socket)
            else:
                img = np.full((h, w, 3) if colour else (h, w), value, np.uint8)
            frame = _Frame()
            frame.setCvFrame(img, out._kind)
            frame.setTimestamp(timedelta(seconds=t))
            frame._settings = out._camera._settings(k)
            self._sent.append(frame)
            if out._queue is not None and not out._queue.isClosed():
                out._queue.send(frame)

        def _stream(self):
            period = 1.0 / max(out._fps for out in self.outputs)
            k = int(np.ceil(dai.Clock.now().total_seconds() / period))
            while not self._halt.is_set():
                t = k * period
                wait = t + max(world.offsets.values()) - dai.Clock.now().total_seconds()
                if wait > 0 and self._halt.wait(wait):
                    break
                for out in self.outputs:
                    self._send(out, t + world.offsets[out._socket], k % 200, k)
                k += 1

        def isRunning(self):
            return self.running

        def stop(self):
            world.calls.append(("stop",))
            self.running = False
            self._halt.set()
            if self._thread is not None:
                self._thread.join()
            for out in self.outputs:  # as PipelineImpl::stop: the queues, then the device
                if out._queue is not None:
                    out._queue.close()
            self.device.close()

        def wait(self):
            world.calls.append(("wait",))

    fake.Pipeline = Pipeline
    fake.Device = Device
    fake.InputQueue = InputQueue
    fake.Node = types.SimpleNamespace(Output=Output, Input=Input)
    fake.node = types.SimpleNamespace(Camera=Camera)
    return fake
