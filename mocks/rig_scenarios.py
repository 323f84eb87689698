"""Synthetic rig problems with ground truth: stereo heads and multi-camera rigs (issue 5).

- :func:`s5_rig`: docs/SETUPS.md S5 (paper Figs. 7-9) as a general-motion calibration problem:
  cameras "left" and "right", reference "right", six board poses, nothing known about the
  motion (knowledge "none"), ``X_left = R_left_right X_right + t_left_right``.
- :func:`oak_rig`: the OAK-D-like head of ``mocks/camera.py`` eye-in-hand on the R1 cell
  (``scenarios.r1_poses``): reference "left", the other cameras' ``T_<cam>_left`` from
  ``oak_d_like_extrinsics``; points outside an image are simply not detected, so partial views
  arise naturally.
- :func:`hide_views`: the same problem with some cameras' views removed or cut (a camera that
  sees nothing or part of the board in a frame).

Every builder returns a :class:`RigScenario`: a :class:`~slidecal.mocks.scenarios.Scenario`
with the noise of each camera (cameras may differ, S5's second experiment).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from slidecal.mocks.camera import oak_d_like, oak_d_like_extrinsics
from slidecal.mocks.scenarios import (
    NO_DISTORTION,
    R1_T_TOOL_CAM,
    Scenario,
    _detect,
    _perturb,
    r1_poses,
)
from slidecal.solver.camera import K_matrix
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import R_from_rvec, Ry, T_from_Rt, inv_T
from slidecal.solver.problem import (
    CalibrationProblem,
    CameraSpec,
    Detection,
    Frame,
    ModelOptions,
    Target,
)
from slidecal.solver.refine import ModelState

S5_SIZE_PX = (300, 240)
S5_K_LEFT = K_matrix(420.0, 410.0, 152.0, 118.0)
S5_K_RIGHT = K_matrix(400.0, 400.0, 150.0, 120.0)
# X_left = R X_right + t (docs/SETUPS.md S5): T_left_right, l.u.
S5_T_LEFT_RIGHT = T_from_Rt(R_from_rvec(np.radians([0.0, 5.0, 0.0])), np.array([-20.0, 0.0, 0.0]))
S5_VIEWS_DEG = ((20, 0, 0), (0, 20, 0), (-20, -20, 0), (15, -15, 10), (-10, 25, -5), (25, 10, 5))


@dataclass(frozen=True)
class RigScenario(Scenario):
    """A rig :class:`Scenario`; ``sigma_by_camera_px``: the pixel noise of each camera.

    ``sigma_px`` is the reference camera's noise.
    """

    sigma_by_camera_px: Mapping[str, float] = field(default_factory=dict)


def s5_grid() -> Target:
    """S5's target: 14 x 10 points, pitch 5 l.u., centred on the board origin."""
    x, y = np.meshgrid((np.arange(14) - 6.5) * 5.0, (np.arange(10) - 4.5) * 5.0)
    return Target.points(np.column_stack([x.ravel(), y.ravel()]))


def s5_T_right_board() -> np.ndarray:
    """The right camera's six view poses ``T_right_board`` (6, 4, 4), l.u. (docs/SETUPS.md S5).

    ``R_right_board = R(r) diag(1, -1, -1)``, camera centre 130 l.u. from the grid centre on the
    optical axis.
    """
    flip = np.diag([1.0, -1.0, -1.0])
    out = []
    for rv in S5_VIEWS_DEG:
        R = R_from_rvec(np.radians(rv)) @ flip
        centre_board = -130.0 * R[2]
        out.append(T_from_Rt(R, -R @ centre_board))
    return np.stack(out)


def s5_rig(
    rng: np.random.Generator,
    sigma_px: float = 0.5,
    left_factor: float = 1.0,
    options: ModelOptions | None = None,
) -> RigScenario:
    """S5 as a general-motion rig problem (knowledge "none", mount "none", reference "right").

    ``sigma_px``: the right camera's corner noise; the left camera's is ``left_factor`` times
    it. Options default to zero skew and no distortion (the paper's model). Points outside the
    300 x 240 images are not detected.
    """
    target = s5_grid()
    Ts = s5_T_right_board()
    sig = {"left": left_factor * sigma_px, "right": sigma_px}
    K = {"left": S5_K_LEFT, "right": S5_K_RIGHT}
    T_cam_right = {"left": S5_T_LEFT_RIGHT, "right": np.eye(4)}
    frames = []
    for k, T in enumerate(Ts):
        dets = {
            c: _detect(K[c], np.zeros(5), T_cam_right[c] @ T, target, S5_SIZE_PX, sig[c], rng)
            for c in ("left", "right")
        }
        frames.append(Frame(k, dets))
    problem = CalibrationProblem(
        target,
        (CameraSpec("left", *S5_SIZE_PX), CameraSpec("right", *S5_SIZE_PX)),
        tuple(frames),
        "none",
        "none",
        options or ModelOptions(distortion=NO_DISTORTION),
        reference_camera="right",
    )
    truth = ModelState(
        {c: K[c].copy() for c in K},
        {c: np.zeros(5) for c in K},
        {"left": S5_T_LEFT_RIGHT.copy()},
        Ts,
        np.eye(4),
        np.zeros(len(Ts)),
    )
    return RigScenario(problem, truth, sigma_px, sigma_by_camera_px=sig)


def oak_rig(
    rng: np.random.Generator,
    sigma_px: float | Mapping[str, float] = 0.15,
    cameras: Sequence[str] = ("left", "right"),
    robot_noise_m: float = 0.0,
    robot_noise_deg: float = 0.0,
    options: ModelOptions | None = None,
    view_offset_deg: float = 20.0,
) -> RigScenario:
    """The OAK-D-like head eye-in-hand on the R1 cell; reference camera "left".

    ``sigma_px``: corner noise (pixels) of every camera, or per camera name. ``cameras``: which
    of "left", "right", "rgb" the rig has (must include "left"). ``robot_noise_m``,
    ``robot_noise_deg``: one-sigma noise injected into the measured ``T_base_tool`` (the model
    is told through ``options``). ``view_offset_deg``: the left camera is R1's camera turned by
    this angle about its y axis (the robot poses stay R1's), so the board sits off-centre and,
    at 20 deg, the right camera loses up to a third of the corners in half of the frames.
    Corners outside an image (2 px margin) are not detected.
    """
    sims = {c.name: c for c in oak_d_like()}
    cameras = tuple(cameras)
    if "left" not in cameras or any(c not in sims for c in cameras):
        raise InputError(f"cameras must include 'left' and be among {list(sims)}, got {cameras}")
    sig = (
        {c: float(sigma_px[c]) for c in cameras}
        if isinstance(sigma_px, Mapping)
        else {c: float(sigma_px) for c in cameras}
    )
    extr = oak_d_like_extrinsics()
    T_tool_left = R1_T_TOOL_CAM @ T_from_Rt(Ry(np.radians(view_offset_deg)), np.zeros(3))
    target = Target.charuco(11, 8, 0.030, 0.022)
    T_base_board, poses = r1_poses()
    frames = []
    for k, T_base_tool in enumerate(poses):
        T_left_board = inv_T(T_base_tool @ T_tool_left) @ T_base_board
        dets = {}
        for c in cameras:
            s = sims[c]
            dets[c] = _detect(
                s.K, s.dist, extr[c] @ T_left_board, target, (s.width, s.height), sig[c], rng, 2.0
            )
        measured = _perturb(T_base_tool, rng, robot_noise_m, robot_noise_deg)
        frames.append(Frame(k, dets, T_base_tool=measured))
    problem = CalibrationProblem(
        target,
        tuple(sims[c].spec for c in cameras),
        tuple(frames),
        "eye_in_hand",
        "robot",
        options or ModelOptions(),
        reference_camera="left",
    )
    truth = ModelState(
        {c: sims[c].K.copy() for c in cameras},
        {c: sims[c].dist.copy() for c in cameras},
        {c: extr[c].copy() for c in cameras if c != "left"},
        inv_T(T_tool_left)[None],
        T_base_board,
        np.zeros(len(poses)),
    )
    return RigScenario(
        problem, truth, sig["left"], T_tool_left, T_base_board, sigma_by_camera_px=sig
    )


Hide = Literal["none", "empty", "half"]


def hide_views(
    problem: CalibrationProblem, hidden: Mapping[tuple[int, str], Hide]
) -> CalibrationProblem:
    """The problem with some views removed or cut, keyed by (frame index, camera name).

    ``"none"``: the camera has no detection in that frame; ``"empty"``: a detection with no
    corners (a session records it so); ``"half"``: only the corners whose board x is below the
    median of the detected ones (the board half out of view).
    """
    frames = list(problem.frames)
    for (fi, cam), how in hidden.items():
        f = frames[fi]
        dets = dict(f.detections)
        if cam not in dets:
            raise InputError(f"frame {fi} has no detection of camera {cam!r} to hide")
        if how == "none":
            del dets[cam]
        elif how == "empty":
            dets[cam] = Detection(np.zeros(0, dtype=int), np.zeros((0, 2)))
        elif how == "half":
            d = dets[cam]
            x = problem.target.points_m[d.ids, 0]
            keep = x < np.median(x)
            dets[cam] = Detection(d.ids[keep], d.px[keep])
        else:
            raise InputError(f"unknown way to hide a view {how!r}; use none, empty or half")
        frames[fi] = replace(f, detections=dets)
    return replace(problem, frames=tuple(frames))
