"""Luxonis OAK cameras through depthai v3 (``CameraRig`` protocol of ``drivers/base.py``), and
writing a calibration result into a depthai ``CalibrationHandler``.

Capture (HARDWARE_NOTES.md): one ``dai.node.Camera`` per socket, outputs requested with
``enableUndistortion=False`` at the calibrated size, manual exposure and focus, and the
pipeline's auto-calibration turned OFF (it is on by default and would rewrite the stereo
calibration on start). ``depthai`` is imported in :meth:`OakRig.open`, so this module imports
without a device.

Synchronisation: :meth:`OakRig.capture` first discards every frame already queued, notes the
host time, then keeps only frames whose device timestamp (``ImgFrame.getTimestamp()``, on the
host's steady clock) is later than that. It returns the oldest frame of the first camera for
which every other camera has a frame within ``sync_tolerance_s`` of it (the nearest one), so the
set was exposed after the call and together. The stereo pair of an OAK-D is hardware-synced
(a few microseconds apart); the colour camera is not, hence a tolerance of half a frame period.

Calibration files: extrinsics in depthai are in CENTIMETRES and ``setCameraExtrinsics(src, dst,
R, t)`` maps points of ``src`` into ``dst`` (``R_dst_src``, ``t_dst_src``). Each camera stores one
link; we chain them as the factory calibration does: stereo left -> stereo right -> the others.
Distortion is 14 coefficients in OpenCV order (k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 tx ty),
zero-padded. The handler stores float32: values round-trip exactly at that precision.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from slidecal.solver.errors import HardwareFault, InputError
from slidecal.solver.geometry import inv_T
from slidecal.solver.problem import CameraSpec
from slidecal.solver.result import CalibrationResult

DEFAULT_SOCKETS = {"left": "CAM_B", "right": "CAM_C", "rgb": "CAM_A"}
DEFAULT_SIZES = {"left": (1280, 800), "right": (1280, 800), "rgb": (1920, 1080)}


def _import_depthai() -> Any:
    try:
        import depthai
    except ImportError as e:
        raise HardwareFault(
            f"depthai is not importable ({e}); install it with 'pip install depthai>=3.6,<4'"
        ) from None
    return depthai


class OakRig:
    """The cameras of one OAK device, captured as a synchronised set.

    Parameters
    ----------
    device_id
        The device's id (MxId or IP) or None for the first device found.
    sockets
        Camera name -> board socket name (``"CAM_A"`` ...). The first is the sync reference.
    sizes
        Camera name -> (width, height) in pixels of the requested output.
    colour
        Names of the cameras delivered as BGR (``BGR888i``); the others as grey (``GRAY8``).
    exposure_us, iso
        Manual exposure for every camera (both or neither).
    focus
        Camera name -> manual lens position 0..255 (auto-focus cameras only).
    sync_tolerance_s
        Largest timestamp difference within a set.
    timeout_s
        How long :meth:`capture` waits for a complete set.
    """

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
        sync_tolerance_s: float = 0.015,
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
        self.sync_tolerance_s = float(sync_tolerance_s)
        self.timeout_s = float(timeout_s)
        self._pipeline: Any = None
        self._queues: dict[str, Any] = {}
        self._dai: Any = None

    @property
    def specs(self) -> tuple[CameraSpec, ...]:
        """Name and image size of every camera, in the order of ``sockets``."""
        return tuple(CameraSpec(n, *self.sizes[n]) for n in self.sockets)

    def open(self) -> None:
        """Build and start the pipeline; ``HardwareFault`` when the device or a camera is absent."""
        dai = self._dai = _import_depthai()
        try:
            if self.device_id is None:
                pipeline = dai.Pipeline()
            else:
                pipeline = dai.Pipeline(dai.Device(dai.DeviceInfo(self.device_id)))
        except RuntimeError as e:
            which = "any OAK device" if self.device_id is None else f"OAK device {self.device_id}"
            raise HardwareFault(
                f"cannot open {which} ({e}); plug it into a USB3 port (or check its network "
                "link), check the udev rules, and in a container pass /dev/bus/usb through"
            ) from None
        try:
            connected = list(pipeline.getDefaultDevice().getConnectedCameras())
            absent = [
                f"{n} ({s})"
                for n, s in self.sockets.items()
                if getattr(dai.CameraBoardSocket, s) not in connected
            ]
            if absent:
                raise HardwareFault(
                    f"camera(s) {', '.join(absent)} not on this device (it has "
                    f"{[str(c) for c in connected]}); fix the sockets in the cell file"
                )
            pipeline.setAutoCalibrationMode(dai.Pipeline.AutoCalibrationMode.OFF)
            queues = {}
            for name, socket in self.sockets.items():
                board_socket = getattr(dai.CameraBoardSocket, socket)
                cam = pipeline.create(dai.node.Camera).build(board_socket)
                if self.exposure_us is not None:
                    cam.initialControl.setManualExposure(self.exposure_us, self.iso)
                if name in self.focus:
                    cam.initialControl.setManualFocus(self.focus[name])
                kind = dai.ImgFrame.Type.GRAY8
                if name in self.colour:
                    kind = dai.ImgFrame.Type.BGR888i
                out = cam.requestOutput(self.sizes[name], type=kind, enableUndistortion=False)
                queues[name] = out.createOutputQueue(maxSize=8, blocking=False)
            pipeline.start()
        except RuntimeError as e:
            self._stop(pipeline)
            raise HardwareFault(
                f"the OAK pipeline did not start ({e}); replug the device"
            ) from None
        except HardwareFault:
            self._stop(pipeline)
            raise
        self._pipeline = pipeline
        self._queues = queues

    @staticmethod
    def _stop(pipeline: Any) -> None:
        try:
            pipeline.stop()
            pipeline.wait()
        except RuntimeError:
            pass

    def close(self) -> None:
        """Stop the pipeline (idempotent)."""
        if self._pipeline is not None:
            self._stop(self._pipeline)
        self._pipeline = None
        self._queues = {}

    def read_calibration(self) -> Any:
        """The device's current ``dai.CalibrationHandler`` (keep it as a backup before flashing)."""
        if self._pipeline is None:
            raise HardwareFault("OAK rig not open: call open() first")
        return self._pipeline.getDefaultDevice().readCalibration()

    def capture(self) -> dict[str, np.ndarray]:
        """One synchronised set exposed after this call (see the module docstring)."""
        if self._pipeline is None:
            raise HardwareFault("OAK rig not open: call open() first")
        for q in self._queues.values():
            q.tryGetAll()  # frames exposed before the call (e.g. while the robot moved)
        t_call = self._dai.Clock.now().total_seconds()
        names = list(self.sockets)
        buffers: dict[str, list[tuple[float, Any]]] = {n: [] for n in names}
        deadline = time.monotonic() + self.timeout_s
        while True:
            if not self._pipeline.isRunning():
                raise HardwareFault("the OAK pipeline stopped (device lost?); replug the device")
            for n in names:
                for msg in self._queues[n].tryGetAll():
                    t = msg.getTimestamp().total_seconds()
                    if t >= t_call:
                        buffers[n].append((t, msg))
            found = self._match(buffers, names)
            if found is not None:
                return {n: self._image(n, found[n]) for n in names}
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
                if not buffers[n]:
                    return None
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


# ------------------------------------------------------------------------ calibration writing
def _reference(result: CalibrationResult) -> str:
    if result.reference_camera:
        return result.reference_camera
    linked = {k.split("_")[1] for k in result.rig}
    roots = [n for n in result.cameras if n not in linked]
    if len(roots) != 1:
        raise InputError("the result names no reference camera; set reference_camera")
    return roots[0]


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


def oak_calibration_handler(
    result: CalibrationResult,
    sockets: Mapping[str, str] | None = None,
    *,
    stereo: tuple[str, str] | None = ("left", "right"),
    base: Any = None,
) -> Any:
    """A ``dai.CalibrationHandler`` holding the result's intrinsics, distortion and extrinsics.

    ``sockets``: camera name -> board socket name (default left CAM_B, right CAM_C, rgb CAM_A).
    ``stereo``: the (left, right) names of the stereo pair, or None; rectification rotations
    come from ``cv2.stereoRectify``. ``base``: a handler to start from (e.g. the device's
    current calibration, to keep its IMU and board data); it is not modified.
    """
    import cv2

    dai = _import_depthai()
    sockets = dict(DEFAULT_SOCKETS if sockets is None else sockets)
    unknown = [n for n in result.cameras if n not in sockets]
    if unknown:
        raise InputError(f"no OAK socket for camera(s) {unknown}; add them to sockets")
    handler = dai.CalibrationHandler() if base is None else dai.CalibrationHandler.fromJson(
        base.eepromToJson()
    )
    sock = {n: getattr(dai.CameraBoardSocket, sockets[n]) for n in result.cameras}
    for name, cam in result.cameras.items():
        K = np.asarray(cam.K, float).tolist()
        handler.setCameraIntrinsics(sock[name], K, cam.width, cam.height)
        d = np.zeros(14)
        dist = np.asarray(cam.distortion, float).reshape(-1)
        if dist.size > 14:
            raise InputError(f"camera {name}: {dist.size} distortion coefficients, OAK takes 14")
        d[: dist.size] = dist
        handler.setDistortionCoefficients(sock[name], d.tolist())
    ref = _reference(result)
    order = [n for n in (stereo or ()) if n in result.cameras]
    order += [n for n in result.cameras if n not in order]
    T_ref = {n: _T_cam_ref(result, n, ref) for n in order}
    for src, dst in zip(order[:-1], order[1:], strict=True):
        T_dst_src = T_ref[dst] @ inv_T(T_ref[src])
        handler.setCameraExtrinsics(
            sock[src], sock[dst], T_dst_src[:3, :3].tolist(), (T_dst_src[:3, 3] * 100.0).tolist()
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
    *,
    stereo: tuple[str, str] | None = ("left", "right"),
) -> Path:
    """Write the result as a depthai calibration JSON (``eepromToJsonFile``); returns the path.

    Load it with ``dai.CalibrationHandler(path)``; flash it with ``device.flashCalibration``.
    """
    handler = oak_calibration_handler(result, sockets, stereo=stereo)
    path = Path(path)
    if not handler.eepromToJsonFile(str(path)):
        raise InputError("depthai could not write the file; check the directory", where=str(path))
    return path
