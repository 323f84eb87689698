"""Degenerate configurations of the linear method (docs/METHOD.md Sec. 7; paper Sec. III-A):
:func:`check_configuration` raises ``DegenerateError`` naming the configuration and the fix,
by geometric tests on the camera poses the homographies imply (robust to noise) and by the
conditioned linear system's null space.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from slidecal.solver.errors import DegenerateError
from slidecal.solver.handeye import (
    board_pose_from_homography,
    camera_displacements,
    n_directions,
)
from slidecal.solver.linear import LinearGroup, LinearSystem, _check_groups, linear_system

MIN_ANGLE_DEG = 5.0  # a smaller angle makes the linear estimate several times noisier
MIN_CONDITIONING = 1e-6  # degenerate configurations give 1e-14 to 1e-16


def nominal_K(image_size: tuple[float, float]) -> np.ndarray:
    """Nominal intrinsics (3, 3) pixels: ``f`` = image width, principal point at the centre."""
    w, h = float(image_size[0]), float(image_size[1])
    return np.array([[w, 0.0, (w - 1) / 2], [0.0, w, (h - 1) / 2], [0.0, 0.0, 1.0]])


def _conditioning(A: np.ndarray) -> float:
    """Second-smallest over largest singular value of the homogeneous system ``A x = 0``
    (the null space is one-dimensional when it is not ~0). A system with one row fewer than
    unknowns is exactly determined (the paper's minimal cases, e.g. two images): not singular
    by itself."""
    rows, cols = A.shape
    if rows < cols - 1:
        return 0.0
    sv = np.linalg.svd(A, compute_uv=False)
    sv = np.concatenate([sv, np.zeros(cols - len(sv))])
    return float(sv[-2] / sv[0])


def check_configuration(
    groups: Sequence[LinearGroup],
    knowledge: str,
    *,
    image_size: tuple[float, float],
    K_guess: np.ndarray | None = None,
    hand_eye: bool = False,
    robot_translations: Sequence[np.ndarray] | None = None,
    **options,
) -> LinearSystem:
    """Refuse degenerate data for the linear method with a ``DegenerateError`` saying the fix;
    return the conditioned linear system it accepted (``linear_intrinsics`` solves it as is).

    ``groups``, ``knowledge``, ``image_size`` and ``options`` (``skew``, ``unit_aspect``): as
    for ``linear_intrinsics``. ``K_guess`` (3, 3) pixels: used for the geometric tests (default
    :func:`nominal_K`). ``hand_eye``: the hand-eye rotation is also wanted; then the robot
    translations (``robot_translations``: per group (n, 3), default ``group.motion``) must span
    two directions.
    """
    _check_groups(groups, knowledge)
    K = nominal_K(image_size) if K_guess is None else np.asarray(K_guess, dtype=float)
    if knowledge != "none":
        for g, grp in enumerate(groups):
            if len(grp.H) < 2 and len(groups) == 1:
                raise DegenerateError(
                    f"group {g} has a single frame: the translation methods need at least two "
                    "frames per orientation (add translated frames)"
                )
    if hand_eye:
        moves = robot_translations
        if moves is None:
            moves = [np.asarray(grp.motion, dtype=float) for grp in groups]
        if n_directions(np.concatenate([np.asarray(m, float).reshape(-1, 3) for m in moves])) < 2:
            raise DegenerateError(
                "all robot translations are colinear: the hand-eye rotation about that line is "
                "undetermined; translate along at least two non-parallel directions"
            )

    # Geometric tests, only when the orientations alone (Zhang) cannot rescue the system.
    first = [LinearGroup(np.asarray(grp.H)[:1]) for grp in groups]
    zhang = linear_system(first, "none", image_size=image_size, **options)
    if knowledge != "none" and _conditioning(zhang.A) < MIN_CONDITIONING:
        _geometric_tests(groups, knowledge, K)

    system = linear_system(groups, knowledge, image_size=image_size, **options)
    n_unknowns = system.A.shape[1] - 1
    if system.A.shape[0] < n_unknowns:
        raise DegenerateError(
            f"too few constraints ({system.A.shape[0]}) for {n_unknowns} unknowns "
            f"({', '.join(system.unknowns)} up to scale): add translated frames, orientation "
            "groups, or assume zero skew / unit aspect"
        )
    cond = _conditioning(system.A)
    if cond < MIN_CONDITIONING:
        raise DegenerateError(
            f"the linear calibration system is singular (conditioning {cond:.1e}) for knowledge "
            f"{knowledge!r}: the frames do not determine {', '.join(system.unknowns)}; tilt the "
            "camera toward the board about both board axes, translate out of the board plane "
            "in several directions, or add orientation groups"
        )
    return system


def _geometric_tests(groups: Sequence[LinearGroup], knowledge: str, K: np.ndarray) -> None:
    sin_min = np.sin(np.radians(MIN_ANGLE_DEG))
    out_of_plane, tilted, axes_ok = [], [], []
    colinear = []
    for grp in groups:
        H = np.asarray(grp.H, dtype=float)
        R = board_pose_from_homography(K, H[0])[:3, :3]  # R_cam_board
        T_board = camera_displacements(K, grp) @ R  # rows: R' d_k
        nz = np.linalg.norm(T_board, axis=1) > 0
        if np.any(nz):
            T = T_board[nz]
            out_of_plane.append(np.max(np.abs(T[:, 2]) / np.linalg.norm(T, axis=1)) >= sin_min)
        tilted.append(np.hypot(R[2, 0], R[2, 1]) >= sin_min)  # optical axis vs board normal
        axes_ok.append(min(abs(R[0, 2]), abs(R[1, 2])) >= sin_min)  # camera x, y leave the board
        motion = np.asarray(grp.motion, dtype=float) if grp.motion is not None else T_board
        colinear.append(n_directions(motion) <= 1)
    if out_of_plane and not any(out_of_plane):
        raise DegenerateError(
            "every translation is parallel to the board plane (within "
            f"{MIN_ANGLE_DEG:g} deg), which only adds points on the plane: tilt the camera "
            "toward the board or move along its normal"
        )
    case1 = knowledge == "lengths" or (knowledge == "robot" and all(colinear))
    if case1 and not any(tilted):
        raise DegenerateError(
            "the board plane is parallel to the image plane (within "
            f"{MIN_ANGLE_DEG:g} deg), which is degenerate when only translation lengths are "
            "known (Case 1): tilt the camera by 20-30 deg relative to the board"
        )
    if knowledge == "board_direction" and not any(axes_ok):
        raise DegenerateError(
            "the camera's x or y axis is parallel to the board plane (within "
            f"{MIN_ANGLE_DEG:g} deg), which is degenerate when only the translation direction "
            "is known (Case 2): tilt about both board axes (e.g. 30 deg about x, then 30 deg "
            "about y)"
        )
