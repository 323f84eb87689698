"""Simulated cameras: a ``CameraRig`` that renders the target at the true poses of the cell, and
the presets ``single_camera()`` (R1's camera) and ``oak_d_like()`` (an OAK-D-like head)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from slidecal.mocks.render import Photo, render_target
from slidecal.solver.camera import K_matrix, as_distortion
from slidecal.solver.errors import HardwareFault, InputError
from slidecal.solver.geometry import R_from_rvec, T_from_Rt
from slidecal.solver.problem import CameraSpec, Target

FAULT_KINDS = ("no_frame", "disconnect", "lost")
#: One lens of each model for R1's 1280 x 800 camera (``solver/camera.py``): an M12-like rational
#: lens and a mild fisheye (the opencv5 one is R1's).
LENSES = {
    "opencv5": np.array([-0.12, 0.05, 5e-4, -3e-4, 0.0]),
    "rational": np.array([0.3, -0.1, 5e-4, -3e-4, 0.01, 0.42, -0.08, 0.02]),
    "fisheye": np.array([-0.02, 0.01, -0.004, 0.001]),
}


@dataclass(frozen=True)
class SimCamera:
    """A simulated camera: ``K`` (3, 3) px, ``dist`` (5,), (8,) or (4,) (its length names the lens
    model, ``solver/camera.py``), ``blur_sigma_px``, ``noise_std`` (grey levels), ``exposure``
    gain (1.0: white at about 217), ``colour`` (BGR),
    ``vignetting``, ``photo`` (:class:`~slidecal.mocks.render.Photo`; None: the clean renderer)."""

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    blur_sigma_px: float = 0.6
    noise_std: float = 2.0
    exposure: float = 1.0
    colour: bool = False
    vignetting: float = 0.0
    photo: Photo | None = None

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=float)
        if K.shape != (3, 3):
            raise InputError(f"camera {self.name!r}: K must be 3x3, got shape {K.shape}")
        dd = np.asarray(self.dist, dtype=float).reshape(-1)
        if len(dd) > 5 and len(dd) != 8:
            raise InputError(
                f"camera {self.name!r}: dist takes at most 5 values (k1 k2 p1 p2 k3), 8 (rational) "
                "or 4 (fisheye)"
            )
        d = as_distortion(dd)
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"camera {self.name!r}: width and height must be positive")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", d)

    @property
    def spec(self) -> CameraSpec:
        """Name and image size."""
        return CameraSpec(self.name, int(self.width), int(self.height))


def single_camera(name: str = "cam", **overrides: float | bool | Photo) -> SimCamera:
    """The R1 camera (docs/results/BENCHMARKS.md); keyword overrides for blur, noise, exposure,
    colour, photo."""
    return SimCamera(
        name,
        1280,
        800,
        K_matrix(880.0, 880.0, 640.0, 400.0),
        LENSES["opencv5"],
        **overrides,
    )


#: The OAK-D-like head's cameras (two OV9282 mono, an IMX378 colour between them): image size
#: (px), (fx, fy, cx, cy) px and distortion (k1 k2 p1 p2 k3), each its own.
OAK_D_LIKE = {
    "left": ((1280, 800), (881.2, 880.6, 643.1, 401.7), (-0.052, 0.021, 2e-4, -1e-4, 0.0)),
    "right": ((1280, 800), (879.8, 879.5, 636.4, 398.9), (-0.049, 0.018, -1e-4, 3e-4, 0.0)),
    "rgb": ((1920, 1080), (1402.5, 1401.8, 957.3, 543.6), (0.071, -0.112, 4e-4, 2e-4, 0.03)),
}


def oak_d_like(**overrides: float | bool | Photo) -> list[SimCamera]:
    """An OAK-D-like head: mono "left", "right" (1280 x 800) and colour "rgb" (1920 x 1080); keyword
    overrides (blur, noise, exposure) apply to all three."""
    rgb = {**overrides, "colour": True}
    return [
        SimCamera(n, *size, K_matrix(*k), np.array(d), **(rgb if n == "rgb" else overrides))
        for n, (size, k, d) in OAK_D_LIKE.items()
    ]


def oak_d_like_extrinsics() -> dict[str, np.ndarray]:
    """True ``T_<name>_left`` (4, 4), metres: right 75 mm, rgb 37.5 mm along the left camera's +x,
    each a few tenths of a degree misaligned."""
    R_left_right = R_from_rvec(np.deg2rad([0.12, -0.35, 0.08]))
    R_left_rgb = R_from_rvec(np.deg2rad([-0.25, 0.18, -0.30]))
    T_left_right = T_from_Rt(R_left_right, np.array([0.0750, 0.0003, -0.0002]))
    T_left_rgb = T_from_Rt(R_left_rgb, np.array([0.0375, 0.0004, 0.0008]))
    return {
        "left": np.eye(4),
        "right": np.linalg.inv(T_left_right),
        "rgb": np.linalg.inv(T_left_rgb),
    }


@dataclass
class SimulatedCameraRig:
    """A ``CameraRig`` of simulated cameras looking at ``target``: ``poses()`` gives each camera's
    true ``T_<camera>_board`` (4, 4) m, ``capture()`` renders there and keeps them in
    ``last_poses``; ``capture_count`` counts calls, failed ones included; ``bow_m``: the board's bow
    (metres)."""

    cameras: Sequence[SimCamera]
    target: Target
    poses: Callable[[], dict[str, np.ndarray]]
    rng: np.random.Generator
    bow_m: tuple[float, float] = (0.0, 0.0)
    is_open: bool = False
    capture_count: int = 0
    last_poses: dict[str, np.ndarray] = field(default_factory=dict)
    _faults: list[tuple[str, int]] = field(default_factory=list)  # (kind, at capture)
    _disconnected: bool = False
    _lost: bool = False

    def __post_init__(self) -> None:
        names = [c.name for c in self.cameras]
        if not names or len(set(names)) != len(names):
            raise InputError(f"a rig needs at least one camera and unique names, got {names}")

    @property
    def specs(self) -> tuple[CameraSpec, ...]:
        """Name and image size of every camera, in the order given."""
        return tuple(c.spec for c in self.cameras)

    def open(self) -> None:
        """Start streaming (reconnects after an injected "disconnect", not after "lost")."""
        if self._lost:
            raise HardwareFault("no camera found: the camera rig is gone (injected fault)")
        self.is_open = True
        self._disconnected = False

    def close(self) -> None:
        """Stop streaming (idempotent)."""
        self.is_open = False

    def inject_fault(self, kind: str, at_capture: int) -> None:
        """Make capture ``at_capture`` (from 0) fail with ``HardwareFault``: ``"no_frame"`` that
        one, ``"disconnect"`` every one until the rig is reopened, ``"lost"`` for good."""
        if kind not in FAULT_KINDS:
            raise InputError(f"unknown fault {kind!r}; use one of {FAULT_KINDS}")
        self._faults.append((kind, int(at_capture)))

    def capture(self) -> dict[str, np.ndarray]:
        """One synchronised set of images by camera name (uint8 grey, or BGR for colour)."""
        if not self.is_open:
            raise HardwareFault("capture() on a closed camera rig: call open() first")
        index = self.capture_count
        self.capture_count += 1
        for kind, at_capture in self._faults:
            if at_capture == index:
                if kind in ("disconnect", "lost"):
                    self._disconnected = True
                    self._lost = self._lost or kind == "lost"
                else:
                    names = [c.name for c in self.cameras]
                    raise HardwareFault(
                        f"no frame from cameras {names} within the time-out (capture {index}); "
                        "check the cable and retry"
                    )
        if self._disconnected:
            raise HardwareFault(
                "camera rig disconnected; check the USB cable and power, then close() and open()"
            )
        poses = self.poses()
        missing = [c.name for c in self.cameras if c.name not in poses]
        if missing:
            raise InputError(f"the cell gave no T_cam_board for cameras {missing}")
        self.last_poses = {c.name: np.array(poses[c.name], dtype=float) for c in self.cameras}
        return {
            c.name: render_target(
                self.target,
                c,
                self.last_poses[c.name],
                self.rng,
                vignetting=c.vignetting,
                bow_m=self.bow_m,
            )
            for c in self.cameras
        }
