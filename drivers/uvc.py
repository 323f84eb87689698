"""A single UVC camera through ``cv2.VideoCapture`` (V4L2, raw property ranges): a ``CameraRig``
of one. Every setting is set, read back and recorded (docs/DRIVERS.md)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slidecal.solver.errors import HardwareFault, InputError
from slidecal.solver.problem import CameraSpec

#: V4L2's value of CAP_PROP_AUTO_EXPOSURE for manual exposure (3 is aperture priority/auto).
V4L2_MANUAL_EXPOSURE = 1
#: Frames the auto exposure and white balance run before they are locked (about 1 s).
SETTLE_FRAMES = 30


class UvcCamera:
    """One camera by index (``/dev/video<index>``), device path or video file path; the arguments
    are the cell file's ``cameras:`` keys (docs/FORMATS.md; ``exposure`` in V4L2's 100 us steps).
    """

    def __init__(
        self,
        index_or_path: int | str | Path,
        name: str,
        width: int,
        height: int,
        fourcc: str | None = None,
        exposure: float | None = None,
        focus: float | None = None,
        fps: float | None = None,
        drop_frames: int = 4,
        settle_frames: int = SETTLE_FRAMES,
    ) -> None:
        if width <= 0 or height <= 0:
            raise InputError(f"camera {name}: width and height must be positive")
        if fourcc is not None and len(fourcc) != 4:
            raise InputError(f"camera {name}: fourcc must be 4 characters, got {fourcc!r}")
        if drop_frames < 0:
            raise InputError(f"camera {name}: drop_frames must not be negative")
        if fps is not None and fps <= 0:
            raise InputError(f"camera {name}: fps must be positive, got {fps}")
        self.source = str(index_or_path) if isinstance(index_or_path, Path) else index_or_path
        self.name = name
        self.width = int(width)
        self.height = int(height)
        self.fourcc = fourcc
        self.exposure = exposure
        self.focus = focus
        self.fps = fps
        self.drop_frames = int(drop_frames)
        self.settle_frames = int(settle_frames)
        self.messages: list[str] = []
        #: setting -> {requested, read_back, accepted}, filled by :meth:`open`.
        self.settings: dict[str, dict[str, Any]] = {}
        self._cap: cv2.VideoCapture | None = None
        self._backend: str | None = None

    @property
    def specs(self) -> tuple[CameraSpec, ...]:
        """The one camera's name and size."""
        return (CameraSpec(self.name, self.width, self.height),)

    def _record(self, key: str, requested: Any, read_back: Any, accepted: bool) -> bool:
        """Record what became of a setting in :attr:`settings`; returns ``accepted``."""
        self.settings[key] = {"requested": requested, "read_back": read_back, "accepted": accepted}
        return accepted

    def _set(self, cap: cv2.VideoCapture, key: str, prop: int, value: float) -> bool:
        """Set, read back and record a property; True when the camera holds the value."""
        ok = bool(cap.set(prop, float(value)))
        got = float(cap.get(prop))
        return self._record(key, float(value), got,
                            ok and abs(got - float(value)) <= max(0.5, 0.01 * abs(float(value))))

    def open(self) -> None:
        """Open; set format, size, frame rate, focus and exposure, and read them back."""
        v4l2 = sys.platform.startswith("linux") and not Path(str(self.source)).is_file()
        cap = cv2.VideoCapture(self.source, cv2.CAP_V4L2 if v4l2 else cv2.CAP_ANY)
        if not cap.isOpened():
            raise HardwareFault(
                f"camera {self.name}: cannot open {self.source!r}; check that it is plugged in, "
                "that no other program uses it, and the index or path (v4l2-ctl --list-devices)"
            )
        try:
            self._configure(cap)
        except BaseException:  # a refused setting, a cv2.error, Ctrl-C: the device is freed
            cap.release()
            raise
        self._cap = cap

    def _configure(self, cap: cv2.VideoCapture) -> None:
        self.settings, self.messages = {}, []
        try:
            self._backend = str(cap.getBackendName())
        except cv2.error:
            self._backend = None
        if self._backend == "V4L2":  # raw property ranges (docs/DRIVERS.md); reads back 0
            self._set(cap, "raw_ranges", cv2.CAP_PROP_MODE, 0)
        if self.fourcc is not None:
            code = cv2.VideoWriter_fourcc(*self.fourcc)
            if not self._set(cap, "fourcc", cv2.CAP_PROP_FOURCC, code):
                self.messages.append(
                    f"camera {self.name}: pixel format {self.fourcc} not taken; it delivers "
                    f"{_fourcc_text(self.settings['fourcc']['read_back'])}"
                )
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        got = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        if not self._record("size", [self.width, self.height], list(got),
                            got == (self.width, self.height)):
            raise HardwareFault(
                f"camera {self.name} delivers {got[0]}x{got[1]} instead of "
                f"{self.width}x{self.height}; pick a size it supports (v4l2-ctl "
                "--list-formats-ext), possibly with fourcc MJPG"
            )
        if self.fps is not None and not self._set(cap, "fps", cv2.CAP_PROP_FPS, self.fps):
            self.messages.append(
                f"camera {self.name}: frame rate {self.fps:g} not taken (reads "
                f"{self.settings['fps']['read_back']:g})"
            )
        self._lock_focus(cap)
        auto_wb = float(cap.get(cv2.CAP_PROP_AUTO_WB)) > 0
        if (self.exposure is None or auto_wb) and not Path(str(self.source)).is_file():
            for _ in range(self.settle_frames):  # let the automatics settle, then lock them
                if not cap.grab():
                    break
        self._lock_exposure(cap)
        self._lock_white_balance(cap, auto_wb)

    def _lock_exposure(self, cap: cv2.VideoCapture) -> None:
        manual = self._set(cap, "auto_exposure", cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_MANUAL_EXPOSURE)
        value = self.exposure
        if value is None:  # keep what the auto exposure reached
            value = float(cap.get(cv2.CAP_PROP_EXPOSURE))
            if not manual and value <= 0:
                self.messages.append(
                    f"camera {self.name}: no exposure control (a video file, or a camera that "
                    "does not expose it); the exposure is not locked"
                )
                return
        if self._set(cap, "exposure", cv2.CAP_PROP_EXPOSURE, value) and manual:
            return
        reads = (f"(auto exposure reads {self.settings['auto_exposure']['read_back']:g}, "
                 f"exposure {self.settings['exposure']['read_back']:g})")
        if self.exposure is not None:
            raise HardwareFault(
                f"camera {self.name}: manual exposure {value:g} not taken {reads}; set an exposure "
                "the camera supports (v4l2-ctl -l), or remove exposure to lock the auto exposure"
            )
        self.messages.append(
            f"camera {self.name}: locking the exposure at {value:g} not taken {reads}; auto "
            "exposure may stay on"
        )

    def _lock_white_balance(self, cap: cv2.VideoCapture, auto_wb: bool) -> None:
        if not auto_wb:  # off already, or no such control (a grey camera, a video file)
            self._record("auto_white_balance", 0.0, float(cap.get(cv2.CAP_PROP_AUTO_WB)), True)
            return
        kelvin = float(cap.get(cv2.CAP_PROP_WB_TEMPERATURE))
        off = self._set(cap, "auto_white_balance", cv2.CAP_PROP_AUTO_WB, 0)
        held = kelvin > 0 and self._set(cap, "white_balance_k", cv2.CAP_PROP_WB_TEMPERATURE,
                                        kelvin)
        if not (off and held):
            self.messages.append(
                f"camera {self.name}: the auto white balance could not be locked (reads "
                f"{self.settings['auto_white_balance']['read_back']:g}, colour temperature "
                f"{float(cap.get(cv2.CAP_PROP_WB_TEMPERATURE)):g} K); it may keep changing"
            )

    def _lock_focus(self, cap: cv2.VideoCapture) -> None:
        ok = bool(cap.set(cv2.CAP_PROP_AUTOFOCUS, 0))
        af = float(cap.get(cv2.CAP_PROP_AUTOFOCUS))
        self._record("autofocus", 0.0, af, af == 0)
        if af > 0:
            raise HardwareFault(
                f"camera {self.name} keeps autofocus on (reads {af:g} after switching it off); "
                "a calibration holds at one focus only: switch it off (v4l2-ctl -c "
                "focus_automatic_continuous=0) or use a fixed-focus camera"
            )
        if not ok and af < 0:
            self.settings["autofocus"]["accepted"] = True
            self.messages.append(f"camera {self.name}: no autofocus control (fixed focus)")
        if self.focus is not None and not self._set(cap, "focus", cv2.CAP_PROP_FOCUS, self.focus):
            self.messages.append(
                f"camera {self.name}: focus {self.focus:g} not taken (reads "
                f"{self.settings['focus']['read_back']:g}); the lens stays where it is"
            )

    def capabilities(self) -> dict[str, Any]:
        """What the camera is and what it did with each setting (plain data for the session)."""
        if self._cap is None:
            raise HardwareFault(f"camera {self.name} not open: call open() first")
        return {
            "driver": "uvc",
            "source": str(self.source),
            "backend": self._backend,
            "settings": {k: dict(v) for k, v in self.settings.items()},
            "messages": list(self.messages),
        }

    def close(self) -> None:
        """Release the camera (idempotent)."""
        if self._cap is not None:
            self._cap.release()
        self._cap = None

    def capture(self) -> dict[str, np.ndarray]:
        """A fresh image: uint8 (H, W) grey or (H, W, 3) BGR, by camera name."""
        if self._cap is None:
            raise HardwareFault(f"camera {self.name} not open: call open() first")
        for _ in range(self.drop_frames + 1):
            if not self._cap.grab():
                raise HardwareFault(
                    f"camera {self.name} delivered no frame (unplugged, or end of the file); "
                    "check the cable and reopen"
                )
        ok, img = self._cap.retrieve()
        if not ok or img is None:
            raise HardwareFault(f"camera {self.name}: could not decode the frame; reopen it")
        if img.shape[:2] != (self.height, self.width):
            raise HardwareFault(
                f"camera {self.name} delivered {img.shape[1]}x{img.shape[0]} instead of "
                f"{self.width}x{self.height}; reopen it"
            )
        return {self.name: np.ascontiguousarray(img, dtype=np.uint8)}


def _fourcc_text(code: float) -> str:
    c = int(code)
    return "".join(chr((c >> (8 * i)) & 0xFF) for i in range(4)) if c > 0 else "unknown"
