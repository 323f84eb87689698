"""A single UVC (USB video class) camera through ``cv2.VideoCapture``: a ``CameraRig`` of one.

The resolution is set and read back (a camera silently falls back to another size, which
would make the intrinsics wrong: we refuse a mismatch). Manual exposure is asked for where
the backend supports it (V4L2: ``CAP_PROP_AUTO_EXPOSURE`` 1 means manual); when it does not,
a note is kept in :attr:`UvcCamera.messages`. Drivers buffer a few frames, so a capture right
after the robot stopped could return an image exposed while it moved: :meth:`UvcCamera.capture`
grabs and drops ``drop_frames`` frames first, then retrieves a fresh one.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from slidecal.solver.errors import HardwareFault, InputError
from slidecal.solver.problem import CameraSpec

#: V4L2's value of CAP_PROP_AUTO_EXPOSURE for manual exposure (3 is aperture priority/auto).
V4L2_MANUAL_EXPOSURE = 1


class UvcCamera:
    """One camera by index (``/dev/video<index>``), device path or video file path.

    Parameters
    ----------
    index_or_path
        ``cv2.VideoCapture`` source.
    name
        The camera's name in sessions and results.
    width, height
        Required image size in pixels; anything else is refused.
    fourcc
        Pixel format such as ``"MJPG"`` (needed by many cameras for large sizes), or None.
    exposure
        Manual exposure in the backend's unit (V4L2: 100 microsecond steps), or None for auto.
    drop_frames
        Buffered frames discarded before each capture.
    """

    def __init__(
        self,
        index_or_path: int | str | Path,
        name: str,
        width: int,
        height: int,
        fourcc: str | None = None,
        exposure: float | None = None,
        drop_frames: int = 4,
    ) -> None:
        if width <= 0 or height <= 0:
            raise InputError(f"camera {name}: width and height must be positive")
        if fourcc is not None and len(fourcc) != 4:
            raise InputError(f"camera {name}: fourcc must be 4 characters, got {fourcc!r}")
        if drop_frames < 0:
            raise InputError(f"camera {name}: drop_frames must not be negative")
        self.source = str(index_or_path) if isinstance(index_or_path, Path) else index_or_path
        self.name = name
        self.width = int(width)
        self.height = int(height)
        self.fourcc = fourcc
        self.exposure = exposure
        self.drop_frames = int(drop_frames)
        self.messages: list[str] = []
        self._cap: cv2.VideoCapture | None = None

    @property
    def specs(self) -> tuple[CameraSpec, ...]:
        """The one camera's name and size."""
        return (CameraSpec(self.name, self.width, self.height),)

    def open(self) -> None:
        """Open, set format and size (refusing a mismatch) and exposure."""
        cap = cv2.VideoCapture(self.source)
        if not cap.isOpened():
            raise HardwareFault(
                f"camera {self.name}: cannot open {self.source!r}; check that it is plugged in, "
                "that no other program uses it, and the index or path (v4l2-ctl --list-devices)"
            )
        if self.fourcc is not None:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*self.fourcc))
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        got = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        if got != (self.width, self.height):
            cap.release()
            raise HardwareFault(
                f"camera {self.name} delivers {got[0]}x{got[1]} instead of "
                f"{self.width}x{self.height}; pick a size it supports (v4l2-ctl "
                "--list-formats-ext), possibly with fourcc MJPG"
            )
        if self.exposure is not None:
            ok = cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_MANUAL_EXPOSURE)
            ok = cap.set(cv2.CAP_PROP_EXPOSURE, float(self.exposure)) and ok
            if not ok:
                self.messages.append(
                    f"camera {self.name}: manual exposure not supported by this backend; "
                    "auto exposure stays on"
                )
        self._cap = cap

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
