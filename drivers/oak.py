"""Luxonis OAK cameras through depthai v3 (``CameraRig`` of ``drivers/base.py``), the device's
own calibration, and a calibration result written into a depthai ``CalibrationHandler``.

Sensor modes, the exposure lock, synchronisation, a lost device, the calibration's units and
when ``depthai`` is imported: docs/DRIVERS.md.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from contextlib import suppress
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slidecal.solver.camera import distortion_model, project, undistort_normalised
from slidecal.solver.errors import HardwareFault, InputError
from slidecal.solver.geometry import inv_T
from slidecal.solver.problem import CameraSpec
from slidecal.solver.result import CalibrationResult

DEFAULT_SOCKETS = {"left": "CAM_B", "right": "CAM_C", "rgb": "CAM_A"}
DEFAULT_SIZES = {"left": (1280, 800), "right": (1280, 800), "rgb": (1920, 1080)}
#: Resize modes of ``requestOutput`` (``dai.ImgResizeMode``), as the cell file names them.
RESIZE_MODES = ("stretch", "crop", "letterbox")
#: Frame rate requested when the cell gives none: three streams well within USB3 and gigabit PoE.
DEFAULT_FPS = 10.0
DEFAULT_WHITE_BALANCE_K = 5000
#: How long the auto exposure runs after start before it is locked (cells without exposure_us).
AUTO_EXPOSURE_SETTLE_S = 1.0
#: Relative difference between a requested and a read-back exposure that counts as not taken.
READ_BACK_TOLERANCE = 0.05


def import_depthai() -> Any:
    """The ``depthai`` module, or an ``InputError`` naming the extra that brings it."""
    try:
        import depthai
    except ImportError as e:
        raise InputError(
            f"the OAK driver needs depthai, which is not installed ({e}); install it with "
            "pip install 'slidecal[oak]'"
        ) from None
    return depthai


def _board_socket(dai: Any, name: str, camera: str) -> Any:
    """The ``dai.CameraBoardSocket`` a cell file names (``CAM_A`` ...) for ``camera``."""
    names = sorted(n for n in dai.CameraBoardSocket.__members__ if n.startswith("CAM_"))
    if name not in names:
        raise InputError(
            f"camera {camera!r}: socket {name!r} is not an OAK board socket; use one of "
            f"{', '.join(names)}"
        )
    return dai.CameraBoardSocket.__members__[name]


def choose_sensor_mode(
    modes: Sequence[Mapping[str, Any]], size: tuple[int, int], fps: float
) -> dict[str, Any] | None:
    """The sensor mode to build a camera on: among ``modes`` (``{width, height, min_fps, max_fps,
    fov}``, the device's ``CameraFeatures.configs``) of the widest field of view (within 1 %) that
    run at ``fps``, the smallest covering ``size``, else the largest. None without modes;
    ``InputError`` when no widest-view mode runs at ``fps``."""
    if not modes:
        return None

    def area(m: Mapping[str, Any]) -> float:
        fov = m.get("fov") or (0, 0, 0, 0)
        return float(fov[2]) * float(fov[3]) or float(m["width"]) * float(m["height"])

    widest = max(area(m) for m in modes)
    wide = [m for m in modes if area(m) >= 0.99 * widest]
    ok = [m for m in wide if m["min_fps"] - 1e-6 <= fps <= m["max_fps"] + 1e-6]
    if not ok:
        rates = ", ".join(f"{m['width']}x{m['height']} {m['min_fps']}-{m['max_fps']}" for m in wide)
        raise InputError(
            f"no full-field-of-view sensor mode runs at {fps:g} fps (modes: {rates} fps); "
            "set cameras.fps within one of these ranges"
        )
    covering = [m for m in ok if m["width"] >= size[0] and m["height"] >= size[1]]
    if covering:
        return dict(min(covering, key=lambda m: m["width"] * m["height"]))
    return dict(max(ok, key=lambda m: m["width"] * m["height"]))


def _open_device(dai: Any, device_id: str | None, advice: str, pipeline: bool = False) -> Any:
    """A ``dai.Device`` (``pipeline``: a ``dai.Pipeline`` on it), ``device_id`` or any;
    ``HardwareFault`` ending in ``advice`` when none opens."""
    try:
        if device_id is None:
            return dai.Pipeline() if pipeline else dai.Device()
        device = dai.Device(dai.DeviceInfo(device_id))
        return dai.Pipeline(device) if pipeline else device
    except RuntimeError as e:
        which = "any OAK device" if device_id is None else f"OAK device {device_id}"
        raise HardwareFault(f"cannot open {which} ({e}); {advice}") from None


def _call(obj: Any, method: str) -> Any:
    """``obj.method()`` or None where the device or platform does not provide it."""
    try:
        return getattr(obj, method)()
    except (RuntimeError, AttributeError):
        return None


def _text(value: Any) -> str | None:
    if value is None:
        return None
    name = getattr(value, "name", None)
    return str(name) if isinstance(name, str) else str(value)


class OakRig:
    """The cameras of one OAK device, captured as a synchronised set; the arguments are the cell
    file's ``cameras:`` keys (docs/FORMATS.md) with ``sockets`` and ``sizes`` by camera name (the
    first socket the sync reference) and ``timeout_s``, :meth:`capture`'s wait for a set."""

    def __init__(
        self,
        device_id: str | None = None,
        sockets: Mapping[str, str] | None = None,
        sizes: Mapping[str, tuple[int, int]] | None = None,
        *,
        colour: frozenset[str] | set[str] = frozenset({"rgb"}),
        exposure_us: int | None = None,
        iso: int | None = None,
        focus: Mapping[str, int] | None = None,
        white_balance_k: Mapping[str, int] | None = None,
        fps: float = DEFAULT_FPS,
        resize_mode: str = "stretch",
        sync_tolerance_s: float | None = None,
        timeout_s: float = 3.0,
    ) -> None:
        self.device_id = device_id
        self.sockets = dict(DEFAULT_SOCKETS if sockets is None else sockets)
        if not self.sockets:
            raise InputError("an OAK rig needs at least one camera in sockets")
        sizes = dict(DEFAULT_SIZES if sizes is None else sizes)
        missing = [n for n in self.sockets if n not in sizes]
        if missing:
            raise InputError(f"no image size for camera(s) {missing}; add them to sizes")
        self.sizes = {n: (int(sizes[n][0]), int(sizes[n][1])) for n in self.sockets}
        self.colour = frozenset(colour)
        if (exposure_us is None) != (iso is None):
            raise InputError("give exposure_us and iso together (manual exposure) or neither")
        if exposure_us is not None and not (1 <= exposure_us <= 33000 and 100 <= iso <= 1600):
            raise InputError(
                f"exposure_us must be in 1..33000 and iso in 100..1600, got {exposure_us}, {iso}"
            )
        self.exposure_us = exposure_us
        self.iso = iso
        self.focus = dict(focus or {})
        for n, lens in self.focus.items():
            if n not in self.sockets or not 0 <= lens <= 255:
                raise InputError(f"focus[{n!r}] = {lens}: needs a camera name and a lens 0..255")
        self.white_balance_k = {
            n: DEFAULT_WHITE_BALANCE_K for n in self.colour if n in self.sockets
        }
        for n, k in (white_balance_k or {}).items():
            if n not in self.colour or not 1000 <= k <= 12000:
                raise InputError(
                    f"white_balance_k[{n!r}] = {k}: needs a colour camera and 1000..12000 K"
                )
            self.white_balance_k[n] = int(k)
        if not 0 < fps <= 120:
            raise InputError(f"fps is {fps}; request a frame rate in (0, 120]")
        self.fps = float(fps)
        if resize_mode not in RESIZE_MODES:
            raise InputError(f"resize mode {resize_mode!r}; use one of {', '.join(RESIZE_MODES)}")
        self.resize_mode = resize_mode
        self.sync_tolerance_s = 0.55 / self.fps if sync_tolerance_s is None else float(
            sync_tolerance_s
        )
        self.timeout_s = float(timeout_s)
        # depthai is needed from here on: a missing extra or a bad socket name is reported now,
        # before anything is opened or moved.
        self._dai: Any = import_depthai()
        self._board = {n: _board_socket(self._dai, s, n) for n, s in self.sockets.items()}
        self._pipeline: Any = None
        self._queues: dict[str, Any] = {}
        self._controls: dict[str, Any] = {}
        self._capabilities: dict[str, Any] = {}
        self._calibration: dict[str, Any] = {}

    @property
    def specs(self) -> tuple[CameraSpec, ...]:
        """Name and image size of every camera, in the order of ``sockets``."""
        return tuple(CameraSpec(n, *self.sizes[n]) for n in self.sockets)

    def open(self) -> None:
        """Build and start the pipeline; ``HardwareFault`` when the device or a camera is absent,
        ``InputError`` when the cell asks for what this device cannot do."""
        pipeline = _open_device(
            self._dai, self.device_id, "plug it into a USB3 port (or check its network link), "
            "check the udev rules, and in a container pass /dev/bus/usb through", pipeline=True
        )
        self._pipeline = pipeline
        try:
            try:
                self._queues = self._build(pipeline)
                pipeline.start()
            except RuntimeError as e:
                raise HardwareFault(
                    f"the OAK pipeline did not start ({e}); replug the device"
                ) from None
            try:
                self._lock_and_read_back()
            except (self._dai.MessageQueue.QueueException, RuntimeError) as e:
                raise self._lost(str(e) or type(e).__name__) from None
        except BaseException:  # HardwareFault, InputError, Ctrl-C: nothing is left running
            self.close()
            raise

    def _lock_and_read_back(self) -> None:
        """Lock a running auto exposure, then read every camera's settings back from two frame
        sets (docs/DRIVERS.md)."""
        dai = self._dai
        if self.exposure_us is None:
            time.sleep(AUTO_EXPOSURE_SETTLE_S)
            for q in self._controls.values():
                ctrl = dai.CameraControl()
                ctrl.setAutoExposureLock(True)
                q.send(ctrl)
            time.sleep(3.0 / self.fps)  # the lock applies from a later frame
        first, second = self._capture_set(), self._capture_set()
        messages: list[str] = []
        for name, out in self._capabilities["outputs"].items():
            a, b = _settings(first[name]), _settings(second[name])
            out["read_back"] = b
            if (a["exposure_us"], a["iso"]) != (b["exposure_us"], b["iso"]):
                raise HardwareFault(
                    f"camera {name} ({out['socket']}) still changes its exposure after it was "
                    f"locked ({a['exposure_us']} us ISO {a['iso']}, then {b['exposure_us']} us "
                    f"ISO {b['iso']}); set cameras.exposure_us and iso in the cell file"
                )
            messages += _not_taken(name, out, b)
        self._capabilities["exposure_locked"] = "manual" if self.exposure_us else "auto, locked"
        self._capabilities["messages"] = messages

    def _build(self, pipeline: Any) -> dict[str, Any]:
        dai = self._dai
        device = pipeline.getDefaultDevice()
        features = {_text(f.socket): f for f in device.getConnectedCameraFeatures()}
        absent = [f"{n} ({s})" for n, s in self.sockets.items() if s not in features]
        if absent:
            raise HardwareFault(
                f"camera(s) {', '.join(absent)} not on this device (it has "
                f"{sorted(features)}); fix the sockets in the cell file"
            )
        unfocused = [
            f"{n} ({s})"
            for n, s in self.sockets.items()
            if features[s].hasAutofocus and n not in self.focus
        ]
        if unfocused:
            raise InputError(
                f"camera(s) {', '.join(unfocused)} have autofocus and the cell gives no lens "
                "position; a calibration holds at one focus only: add focus: <0..255> to the "
                "camera in the cell file (the lens position that is sharp at the working "
                "distance, e.g. as depthai's autofocus reports it in ImgFrame.getLensPosition())"
            )
        pipeline.setAutoCalibrationMode(dai.Pipeline.AutoCalibrationMode.OFF)
        device.setMaxReconnectionAttempts(0)
        self._controls = {}
        resize = dai.ImgResizeMode.__members__[self.resize_mode.upper()]
        queues: dict[str, Any] = {}
        outputs: dict[str, Any] = {}
        for name, socket in self.sockets.items():
            size = self.sizes[name]
            modes = [
                _mode(c, fov=(float(c.fov.x), float(c.fov.y), float(c.fov.width),
                              float(c.fov.height)))
                for c in features[socket].configs
            ]
            try:
                mode = choose_sensor_mode(modes, size, self.fps)
            except InputError as e:
                raise InputError(f"camera {name!r} ({socket}): {e}") from None
            resolution = (mode["width"], mode["height"]) if mode else None
            cam = pipeline.create(dai.node.Camera).build(
                self._board[name], sensorResolution=resolution, sensorFps=self.fps
            )
            control = cam.initialControl
            if self.exposure_us is not None:
                control.setManualExposure(self.exposure_us, self.iso)
            if name in self.focus:
                control.setManualFocus(self.focus[name])
            if name in self.white_balance_k:
                control.setManualWhiteBalance(self.white_balance_k[name])
            kind = dai.ImgFrame.Type.BGR888i if name in self.colour else dai.ImgFrame.Type.GRAY8
            out = cam.requestOutput(
                size, type=kind, resizeMode=resize, fps=self.fps, enableUndistortion=False
            )
            queues[name] = out.createOutputQueue(maxSize=8, blocking=False)
            if self.exposure_us is None:  # created before start, as depthai v3 requires
                self._controls[name] = cam.inputControl.createInputQueue()
            outputs[name] = {
                "socket": socket,
                "size": list(size),
                "type": _text(kind),
                "resize_mode": self.resize_mode,
                "fps": self.fps,
                "sensor_mode": mode,
                "exposure_us": self.exposure_us,
                "iso": self.iso,
                "focus": self.focus.get(name),
                "white_balance_k": self.white_balance_k.get(name),
            }
        bytes_per_s = sum(
            self.sizes[n][0] * self.sizes[n][1] * (3 if n in self.colour else 1) * self.fps
            for n in self.sockets
        )
        bootloader = _call(device, "getBootloaderVersion")
        self._capabilities = {
            "driver": "oak",
            "depthai_version": str(getattr(dai, "__version__", "")),
            "device_id": _call(device, "getDeviceId"),
            "device_name": _text(_call(device, "getDeviceName")),
            "product_name": _text(_call(device, "getProductName")),
            "platform": _call(device, "getPlatformAsString"),
            "usb_speed": _text(_call(device, "getUsbSpeed")),
            "bootloader_version": None if bootloader is None else str(bootloader),
            "os_version": _text(_call(device, "getOSVersion")),  # RVC4 devices
            "sensors": [_features_dict(f) for f in features.values()],
            "outputs": outputs,
            "stream_mb_per_s": round(bytes_per_s / 1e6, 1),
        }
        self._calibration = {
            "user": _call(device, "readCalibration"),
            "factory": _call(device, "readFactoryCalibration"),
        }
        return queues

    def close(self) -> None:
        """Stop the pipeline (idempotent)."""
        if self._pipeline is not None:
            with suppress(RuntimeError):
                self._pipeline.stop()
                self._pipeline.wait()
        self._pipeline = None
        self._queues = {}
        self._controls = {}

    def capabilities(self) -> dict[str, Any]:
        """What the open device is and how it streams (plain data for the session)."""
        if not self._capabilities:
            raise HardwareFault("OAK rig not open: call open() first")
        return dict(self._capabilities)

    def device_calibrations(self) -> dict[str, dict[str, Any] | None]:
        """The device's calibrations as depthai JSON (``eepromToJson()``), read on open:
        ``user`` (``readCalibration``: what the device uses) and ``factory``
        (``readFactoryCalibration``); None where the device holds none."""
        empty = self._dai.CalibrationHandler().eepromToJson()
        out: dict[str, dict[str, Any] | None] = {}
        for kind, handler in self._calibration.items():
            data = None if handler is None else dict(handler.eepromToJson())
            # readCalibration answers an empty handler when the area holds nothing
            out[kind] = None if data == empty else data
        return out

    def _lost(self, reason: str) -> HardwareFault:
        self.close()
        which = f"OAK device {self._capabilities.get('device_id') or self.device_id or ''}"
        return HardwareFault(
            f"{which.strip()} lost during capture ({reason}); check the cable or PoE link and "
            "replug the device"
        )

    def capture(self) -> dict[str, np.ndarray]:
        """One synchronised set exposed after this call (docs/DRIVERS.md)."""
        if self._pipeline is None:
            raise HardwareFault("OAK rig not open: call open() first")
        try:
            found = self._capture_set()
        except (self._dai.MessageQueue.QueueException, RuntimeError) as e:
            raise self._lost(str(e) or type(e).__name__) from None
        return {n: self._image(n, msg) for n, msg in found.items()}

    def _capture_set(self) -> dict[str, Any]:
        """The frames (``dai.ImgFrame``) of one synchronised set, by camera name."""
        for q in self._queues.values():
            q.tryGetAll()  # frames exposed before the call (e.g. while the robot moved)
        t_call = self._dai.Clock.now().total_seconds()
        names = list(self.sockets)
        buffers: dict[str, list[tuple[float, Any]]] = {n: [] for n in names}
        deadline = time.monotonic() + self.timeout_s
        while True:
            if not self._pipeline.isRunning():
                raise self._lost("the pipeline stopped")
            if self._pipeline.getDefaultDevice().isClosed():
                raise self._lost("the device closed its connection")
            for n in names:
                for msg in self._queues[n].tryGetAll():
                    t = msg.getTimestamp().total_seconds()
                    if t >= t_call:
                        buffers[n].append((t, msg))
            found = self._match(buffers, names)
            if found is not None:
                return found
            if time.monotonic() > deadline:
                counts = {n: len(b) for n, b in buffers.items()}
                raise HardwareFault(
                    f"no set of frames within {self.sync_tolerance_s * 1000:.1f} ms of each other "
                    f"in {self.timeout_s} s (frames received: {counts}); check the cameras' "
                    "frame rates, the cable, or raise sync_tolerance_s"
                )
            time.sleep(0.002)

    def _match(self, buffers: dict[str, list[tuple[float, Any]]], names: list[str]) -> dict | None:
        ref, others = names[0], names[1:]
        for t_ref, msg_ref in buffers[ref]:
            chosen = {ref: msg_ref}
            for n in others:
                if not buffers[n] or buffers[n][-1][0] < t_ref:
                    return None  # its frame at or after t_ref, maybe the nearest, is still to come
                t, msg = min(buffers[n], key=lambda tm, t_ref=t_ref: abs(tm[0] - t_ref))
                if abs(t - t_ref) > self.sync_tolerance_s:
                    break
                chosen[n] = msg
            else:
                return chosen
        return None

    def _image(self, name: str, msg: Any) -> np.ndarray:
        img = np.ascontiguousarray(msg.getCvFrame(), dtype=np.uint8)
        w, h = self.sizes[name]
        if img.shape[:2] != (h, w):
            raise HardwareFault(
                f"camera {name} delivered {img.shape[1]}x{img.shape[0]} instead of {w}x{h}; the "
                "device cannot produce this size without resizing: pick a native size"
            )
        return img


def _settings(msg: Any) -> dict[str, Any]:
    """What a frame says its camera ran with: exposure (us), ISO, lens position, colour
    temperature (K; 0 for a mono camera)."""
    return {
        "exposure_us": int(round(msg.getExposureTime().total_seconds() * 1e6)),
        "iso": int(msg.getSensitivity()),
        "lens_position": int(msg.getLensPosition()),
        "colour_temperature_k": int(msg.getColorTemperature()),
    }


def _not_taken(name: str, out: Mapping[str, Any], got: Mapping[str, Any]) -> list[str]:
    """One line per requested setting the frames show the camera did not take."""
    lines = []
    want = out.get("exposure_us")
    if want and abs(got["exposure_us"] - want) > READ_BACK_TOLERANCE * want:
        lines.append(f"camera {name}: exposure {want} us requested, frames report "
                     f"{got['exposure_us']} us (the sensor's limit at this frame rate?)")
    if out.get("iso") and got["iso"] != out["iso"]:
        lines.append(f"camera {name}: ISO {out['iso']} requested, frames report {got['iso']}")
    if out.get("focus") is not None and got["lens_position"] != out["focus"]:
        lines.append(f"camera {name}: lens position {out['focus']} requested, frames report "
                     f"{got['lens_position']}")
    return lines


def _features_dict(f: Any) -> dict[str, Any]:
    calib = getattr(f, "calibrationResolution", None)
    return {
        "socket": _text(f.socket),
        "sensor": str(f.sensorName),
        "width": int(f.width),
        "height": int(f.height),
        "calibration_resolution": None if calib is None else [int(calib.width), int(calib.height)],
        "autofocus": bool(f.hasAutofocus),
        "modes": [_mode(c, type=_text(c.type)) for c in f.configs],
    }


def _mode(c: Any, **more: Any) -> dict[str, Any]:
    """A sensor mode (``CameraSensorConfig``) as plain data, with ``more``."""
    return {
        "width": int(c.width),
        "height": int(c.height),
        "min_fps": float(c.minFps),
        "max_fps": float(c.maxFps),
        **more,
    }


# ---------------------------------------------------------------------- the device's EEPROM
class OakCalibrationStore:
    """The calibration areas of one OAK device (a context manager, for ``slidecal flash``):
    ``read()`` the calibration in use, ``flash(handler)`` writes the user area (never the factory
    area) and returns what the device holds afterwards."""

    def __init__(self, device_id: str | None = None) -> None:
        self.device_id = device_id
        self._dai = import_depthai()
        self._device: Any = None

    def __enter__(self) -> OakCalibrationStore:
        self._device = _open_device(self._dai, self.device_id, "plug it in and retry")
        return self

    def __exit__(self, *exc: object) -> None:
        if self._device is not None:
            with suppress(RuntimeError):
                self._device.close()
        self._device = None

    def connected_id(self) -> str:
        """The connected device's id (MX id, or IP for PoE devices)."""
        return str(self._device.getDeviceId())

    def read(self) -> Any:
        """The ``dai.CalibrationHandler`` the device uses now."""
        try:
            return self._device.readCalibration()
        except RuntimeError as e:
            raise HardwareFault(f"could not read the device's calibration ({e})") from None

    def flash(self, handler: Any) -> Any:
        """Write ``handler`` to the user area and return the calibration read back."""
        try:
            self._device.flashCalibration(handler)
        except RuntimeError as e:
            raise HardwareFault(
                f"the device refused the calibration ({e}); its previous calibration is "
                "unchanged or in the backup file"
            ) from None
        return self.read()


# ------------------------------------------------------------- image geometry of an output
def stream_geometry(camera: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Camera name -> how its output was made from the sensor, from a session's
    ``devices.camera`` block (:meth:`OakRig.capabilities`): ``size``, ``resize_mode``, ``fov``
    (x, y, w, h: the sensor mode's view of the full pixel array), ``full`` (the array's width,
    height) and ``calibration_size`` (``CameraFeatures.calibrationResolution``, or None)."""
    sensors = {s.get("socket"): s for s in camera.get("sensors") or ()}
    out = {}
    for name, o in (camera.get("outputs") or {}).items():
        sensor = sensors.get(o.get("socket"))
        if sensor is None:
            continue
        full = (int(sensor["width"]), int(sensor["height"]))
        fov = (o.get("sensor_mode") or {}).get("fov") or (0, 0, *full)
        out[name] = {
            "size": tuple(o["size"]),
            "resize_mode": o.get("resize_mode", "stretch"),
            "fov": tuple(float(v) for v in fov),
            "full": full,
            "calibration_size": sensor.get("calibration_resolution"),
        }
    return out


def _pixel_map(ax: float, bx: float, ay: float, by: float) -> np.ndarray:
    """``u' = ax u + bx``, ``v' = ay v + by`` as the 3x3 matrix that maps a K with it."""
    return np.array([[ax, 0.0, bx], [0.0, ay, by], [0.0, 0.0, 1.0]])


def _output_from_full(size: tuple[int, int], resize_mode: str, fov: Sequence[float]) -> np.ndarray:
    """Full pixel array -> an output of ``size`` made from ``fov`` with ``resize_mode``.

    Pixel centres follow OpenCV ((0, 0) is the centre of the top-left pixel): a scale ``s`` and
    an offset ``o`` map ``u`` to ``s (u + 0.5) - 0.5 + o``."""
    x0, y0, fw, fh = fov
    w, h = size
    sx, sy = w / fw, h / fh
    if resize_mode == "crop":
        sx = sy = max(sx, sy)
    elif resize_mode == "letterbox":
        sx = sy = min(sx, sy)
    ox, oy = (w - sx * fw) / 2.0, (h - sy * fh) / 2.0
    return _pixel_map(sx, sx * (0.5 - x0) - 0.5 + ox, sy, sy * (0.5 - y0) - 0.5 + oy)


def _stored_from_full(full: Sequence[int], stored: Sequence[int]) -> np.ndarray:
    """Full pixel array -> the size a socket's calibration is stored at, as depthai relates
    them (``CalibrationHandler.getCameraIntrinsics`` with ``keepAspectRatio``): one scale, the
    limiting side whole, the other cropped centrally, the principal point scaled as it is."""
    (W, H), (w0, h0) = full, stored
    s = max(w0 / W, h0 / H)
    return _pixel_map(s, (w0 - s * W) / 2.0, s, (h0 - s * H) / 2.0)


# ------------------------------------------------------------------------ calibration writing
def _T_cam_ref(result: CalibrationResult, name: str, ref: str) -> np.ndarray:
    if name == ref:
        return np.eye(4)
    te = result.rig.get(f"T_{name}_{ref}")
    if te is None or te.T is None:
        raise InputError(
            f"the result has no complete T_{name}_{ref} (rotation and translation); calibrate "
            "the rig with both cameras seeing the board before writing an OAK calibration"
        )
    return te.T


def handler_from_json(data: Mapping[str, Any] | None) -> Any:
    """A ``dai.CalibrationHandler`` from depthai calibration JSON (``eepromToJson()``), or an
    empty one for None."""
    dai = import_depthai()
    return dai.CalibrationHandler() if data is None else dai.CalibrationHandler.fromJson(dict(data))


def _spec_translation(base_json: Mapping[str, Any] | None, socket: int) -> list[float]:
    for key, cam in (base_json or {}).get("cameraData", []):
        if int(key) == socket:
            st = cam.get("extrinsics", {}).get("specTranslation", {})
            return [float(st.get(k, 0.0)) for k in "xyz"]
    return [0.0, 0.0, 0.0]


def oak_calibration_handler(
    result: CalibrationResult,
    sockets: Mapping[str, str] | None = None,
    *,
    stereo: tuple[str, str] | None = ("left", "right"),
    base: Any = None,
    lens_positions: Mapping[str, int] | None = None,
    streams: Mapping[str, Mapping[str, Any]] | None = None,
) -> Any:
    """A ``dai.CalibrationHandler`` holding the result's intrinsics, distortion and extrinsics.

    ``sockets``: camera name -> board socket (default left CAM_B, right CAM_C, rgb CAM_A).
    ``stereo``: the (left, right) pair, rectified with ``cv2.stereoRectify``, or None. ``base``: a
    handler or JSON dict to start from, unmodified (the device's own). ``lens_positions``: name ->
    0..255.
    ``streams``: name -> how its output was made (:func:`stream_geometry`): its K is mapped back to
    the size the device stores that socket at; without one, written at its own size.
    """
    dai = import_depthai()
    sockets = dict(DEFAULT_SOCKETS if sockets is None else sockets)
    unknown = [n for n in result.cameras if n not in sockets]
    if unknown:
        raise InputError(f"no OAK socket for camera(s) {unknown}; add them to sockets")
    base_json = base if base is None or isinstance(base, Mapping) else base.eepromToJson()
    handler = handler_from_json(base_json)
    sock = {n: _board_socket(dai, sockets[n], n) for n in result.cameras}
    for name, cam in result.cameras.items():
        K, size = np.asarray(cam.K, float), (cam.width, cam.height)
        stream = (streams or {}).get(name)
        if stream is not None:
            if handler.hasCameraCalibration(sock[name]):
                size = tuple(handler.getDefaultIntrinsics(sock[name])[1:])
            else:
                size = tuple(stream.get("calibration_size") or stream["full"])
            out = _output_from_full((cam.width, cam.height), stream["resize_mode"], stream["fov"])
            K = _stored_from_full(stream["full"], size) @ np.linalg.solve(out, K)
        handler.setCameraIntrinsics(sock[name], K.tolist(), *size)
        d = np.zeros(14)
        dist = np.asarray(cam.distortion, float).reshape(-1)
        if dist.size > 14:
            raise InputError(f"camera {name}: {dist.size} distortion coefficients, OAK takes 14")
        d[: dist.size] = dist  # perspective: OpenCV's order; fisheye: k1-k4 first (depthai's)
        handler.setDistortionCoefficients(sock[name], d.tolist())
        fisheye = distortion_model(dist) == "fisheye"
        model = dai.CameraModel.Fisheye if fisheye else dai.CameraModel.Perspective
        handler.setCameraType(sock[name], model)
    for name, lens in (lens_positions or {}).items():
        if name in sock:
            handler.setLensPosition(sock[name], int(lens))
    ref = result.reference_camera or next(iter(result.cameras))
    order = [n for n in (stereo or ()) if n in result.cameras]
    order += [n for n in result.cameras if n not in order]
    T_ref = {n: _T_cam_ref(result, n, ref) for n in order}
    for src, dst in zip(order[:-1], order[1:], strict=True):
        T_dst_src = T_ref[dst] @ inv_T(T_ref[src])
        handler.setCameraExtrinsics(
            sock[src], sock[dst], T_dst_src[:3, :3].tolist(), (T_dst_src[:3, 3] * 100.0).tolist(),
            _spec_translation(base_json, int(sock[src])),
        )
    if stereo is not None and all(n in result.cameras for n in stereo):
        left, right = stereo
        T_right_left = T_ref[right] @ inv_T(T_ref[left])
        cl, cr = result.cameras[left], result.cameras[right]
        R1, R2, *_ = cv2.stereoRectify(
            np.asarray(cl.K, float), np.asarray(cl.distortion, float),
            np.asarray(cr.K, float), np.asarray(cr.distortion, float),
            (cl.width, cl.height), T_right_left[:3, :3], T_right_left[:3, 3],
        )
        handler.setStereoLeft(sock[left], R1.tolist())
        handler.setStereoRight(sock[right], R2.tolist())
    return handler


def write_oak_calibration_json(
    result: CalibrationResult,
    path: str | Path,
    sockets: Mapping[str, str] | None = None,
    **options: Any,
) -> Path:
    """Write the result as a depthai calibration JSON (``eepromToJsonFile``); ``options``: the
    keywords of :func:`oak_calibration_handler`. Returns the path."""
    handler = oak_calibration_handler(result, sockets, **options)
    path = Path(path)
    if not handler.eepromToJsonFile(str(path)):
        raise InputError("depthai could not write the file; check the directory", where=str(path))
    return path


# --------------------------------------------------------------- comparing two calibrations
def device_camera(
    data: Mapping[str, Any],
    socket: str,
    size: tuple[int, int],
    resize_mode: str = "stretch",
    stream: Mapping[str, Any] | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """``(K (3, 3) px, distortion (14,))`` of a socket in depthai calibration JSON, mapped to an
    output of ``size`` made with ``resize_mode`` from ``stream``'s ``fov`` (:func:`stream_geometry`;
    none: the stored calibration's view); None without a perspective calibration of that socket."""
    dai = import_depthai()
    h = handler_from_json(data)
    s = _board_socket(dai, socket, socket)
    if not h.hasCameraCalibration(s) or h.getDistortionModel(s) != dai.CameraModel.Perspective:
        return None
    K0, w0, h0 = h.getDefaultIntrinsics(s)
    K0 = np.asarray(K0, float)
    if w0 <= 0 or h0 <= 0:
        return None
    full = (w0, h0) if stream is None else stream["full"]
    fov = (0, 0, *full) if stream is None else stream["fov"]
    K = _output_from_full(size, resize_mode, fov) @ np.linalg.solve(
        _stored_from_full(full, (w0, h0)), K0
    )
    return K, np.asarray(h.getDistortionCoefficients(s), float)


def projection_shift_px(
    result: CalibrationResult,
    data: Mapping[str, Any],
    sockets: Mapping[str, str],
    distance_m: float,
    resize_mode: str = "stretch",
    grid: int = 9,
    streams: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, dict[str, float]]:
    """How far the device's calibration moves projected points against ``result``, per camera:
    ``{name: {rms_px, max_px}}`` over a ``grid`` x ``grid`` lattice of the reference camera's pixels
    back-projected to ``distance_m`` and projected with both models (``streams``: as in
    :func:`device_camera`)."""
    dai = import_depthai()
    h = handler_from_json(data)
    ref = result.reference_camera or next(iter(result.cameras))
    cref = result.cameras[ref]
    lattice = np.linspace(0.05, 0.95, grid)
    u, v = np.meshgrid(lattice * (cref.width - 1), lattice * (cref.height - 1))
    px = np.stack([u.ravel(), v.ravel()], axis=1)
    rays = undistort_normalised(np.asarray(cref.K, float), cref.distortion, px)  # any lens model
    P_ref = np.hstack([rays, np.ones((len(px), 1))]) * distance_m
    out: dict[str, dict[str, float]] = {}
    for name, cam in result.cameras.items():
        if name not in sockets:
            continue
        dev = device_camera(
            data, sockets[name], (cam.width, cam.height), resize_mode, (streams or {}).get(name)
        )
        a, b = (_board_socket(dai, sockets[n], sockets[n]) for n in (ref, name))
        try:  # T_cam_ref (4, 4), depthai's centimetres
            T_dev = np.eye(4) if a == b else np.asarray(h.getCameraExtrinsics(a, b), float)
            T_ours = _T_cam_ref(result, name, ref)
        except (RuntimeError, InputError):
            continue  # the device or the result has no complete transform of this camera
        if dev is None:
            continue
        T_dev[:3, 3] /= 100.0
        ours = project(cam.K, cam.distortion, P_ref @ T_ours[:3, :3].T + T_ours[:3, 3])
        # the device's model: OpenCV's 14-coefficient perspective one
        theirs, _ = cv2.projectPoints(P_ref @ T_dev[:3, :3].T + T_dev[:3, 3], np.zeros(3),
                                      np.zeros(3), *dev)
        e = np.linalg.norm(ours - theirs.reshape(-1, 2), axis=1)
        out[name] = {"rms_px": float(np.sqrt(np.mean(e**2))), "max_px": float(e.max())}
    return out
