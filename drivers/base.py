"""The hardware interfaces the routine drives: small ``typing.Protocol`` classes that the real
drivers (``ur``, ``oak``, ``uvc``) and the simulated cell implement alike. Every failure is a
:class:`slidecal.solver.errors.HardwareFault` saying what to do. Real drivers may also report
``capabilities()`` and ``device_calibrations()`` (``user``/``factory``) for the session."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

from slidecal.solver.errors import InputError
from slidecal.solver.problem import CameraSpec


def checked_move(robot: Any, T_base_tool: np.ndarray, speed_mps: float, accel_mps2: float) -> Any:
    """``T_base_tool`` as a float array, ``InputError`` unless it is a finite 4x4 transform and the
    speed and acceleration are within (0, the robot's ``max_speed_mps``, ``max_accel_mps2``]: the
    arguments of ``Robot.move_linear``."""
    if not 0 < speed_mps <= robot.max_speed_mps:
        raise InputError(f"speed_mps must be in (0, {robot.max_speed_mps}], got {speed_mps}")
    if not 0 < accel_mps2 <= robot.max_accel_mps2:
        raise InputError(f"accel_mps2 must be in (0, {robot.max_accel_mps2}], got {accel_mps2}")
    T = np.asarray(T_base_tool, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"move_linear needs a finite 4x4 T_base_tool, got shape {T.shape}")
    return T


@runtime_checkable
class Robot(Protocol):
    """A robot arm that moves its TCP in straight lines and reports where it is: poses are
    ``T_base_tool`` (4, 4), metres, of the TCP the robot was configured with."""

    def connect(self) -> None:
        """Open the connection; raise ``HardwareFault`` when the robot is not ready to move."""

    def close(self) -> None:
        """Close the connection (idempotent); never moves the robot."""

    def measured_pose(self) -> np.ndarray:
        """``T_base_tool`` (4, 4) as measured now; raise ``HardwareFault`` if the data is stale."""

    def move_linear(self, T_base_tool: np.ndarray, speed_mps: float, accel_mps2: float) -> None:
        """Move the TCP in a straight line to ``T_base_tool`` and block until it arrives; after
        stopping the robot, ``HardwareFault`` on a stop, a lost connection or a time-out."""

    def wait_settled(self, settle_s: float) -> None:
        """Wait until the arm is at rest (vibrations decayed) before a capture."""

    def stop(self) -> None:
        """Decelerate and stop any motion now. Safe to call at any time, also after a fault."""

    def is_reachable(self, T_base_tool: np.ndarray) -> bool:
        """Whether the pose has an inverse-kinematics solution inside joint and safety limits."""


@runtime_checkable
class CameraRig(Protocol):
    """One or more rigidly mounted, synchronised cameras (a single UVC camera is a rig of one)."""

    @property
    def specs(self) -> tuple[CameraSpec, ...]:
        """Name and image size of every camera, in a fixed order."""

    def open(self) -> None:
        """Start streaming; raise ``HardwareFault`` when a camera is missing."""

    def close(self) -> None:
        """Stop streaming (idempotent)."""

    def capture(self) -> dict[str, np.ndarray]:
        """One synchronised set of images, by camera name: uint8, (H, W) grey or (H, W, 3) BGR."""
