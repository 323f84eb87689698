"""The fixed default plan of a cell: the reference the planner is measured against
(``python -m tests.bench planner``) and a plan of known geometry for the tests."""

from __future__ import annotations

import numpy as np

from slidecal.routines.config import CellConfig
from slidecal.routines.plan import Plan, tool_pose
from slidecal.routines.planner import group_R_board_cam
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import Rz, T_from_Rt, inv_T

#: Camera displacements within a group, board axes, as fractions of ``step_mm[1]``: five
#: positions whose four moves from the first are non-coplanar and all leave the board plane
#: (board-normal components of 40 to 75 % of ``step_mm[1]``).
_OFFSETS = np.array(
    [
        [0.0, 0.0, 0.0],
        [0.75, 0.5, -0.625],
        [-0.875, 0.375, 0.5],
        [0.375, -0.875, 0.75],
        [-0.625, -0.625, -0.5],
    ]
)


def camera_poses_board(
    target_centre_board: np.ndarray,
    standoff_m: float,
    tilt_deg: float,
    step_m: float,
    frames_per_group: int = 5,
    groups: int = 4,
) -> list[list[np.ndarray]]:
    """Desired ``T_cam_board`` (4, 4) per group and frame (the default plan's geometry).

    ``target_centre_board`` (3,): board frame, metres. Group ``g`` looks at the centre from
    ``standoff_m``, tilted by ``tilt_deg`` about the in-plane axis at ``45 + 360 g / groups``
    degrees and rolled about the optical axis by ``(-10, 10, -20, 20, ...)`` degrees; frame
    ``k`` is displaced by ``_OFFSETS[k] * step_m`` in board axes.
    """
    if frames_per_group < 2 or frames_per_group > len(_OFFSETS):
        raise InputError(f"frames_per_group must be 2..{len(_OFFSETS)}, got {frames_per_group}")
    c = np.asarray(target_centre_board, dtype=float).reshape(3)
    rolls = [-10.0, 10.0, -20.0, 20.0, 0.0, 30.0]
    out = []
    for g in range(groups):
        # camera axes aligned with the board's (looking along +z_board), tilted, then rolled
        R_tilt = group_R_board_cam(tilt_deg, 45.0 + 360.0 * g / groups)
        R_board_cam = R_tilt @ Rz(np.radians(rolls[g % 6]))
        centre_cam = c - standoff_m * R_board_cam[:, 2]
        frames = []
        for k in range(frames_per_group):
            p_cam_board = centre_cam + _OFFSETS[k] * step_m
            frames.append(inv_T(T_from_Rt(R_board_cam, p_cam_board)))
        out.append(frames)
    return out


def default_plan(cfg: CellConfig) -> Plan:
    """The fixed default plan of a cell (:func:`camera_poses_board`: four groups tilted 25 deg,
    five frames each, moves up to 80 mm); ``slidecal run`` executes the planner's plan. Poses
    through the cell's approximate hand-eye and target pose (``approximate:``), at
    ``standoff_m``."""
    centre = cfg.target.points_m.mean(axis=0)
    T_cb = camera_poses_board(centre, cfg.standoff_m, 25.0, 0.08)
    plan_groups = tuple(tuple(tool_pose(cfg, T) for T in grp) for grp in T_cb)
    via = tool_pose(cfg, camera_poses_board(centre, cfg.standoff_m, 0.0, 0.0, 2, 1)[0][0])
    return Plan.build(
        plan_groups,
        cfg.robot,
        via=via,
        notes=(
            "default plan: 4 groups tilted 25 deg, 5 frames each, moves up to 80 mm at "
            f"{cfg.standoff_m:g} m",
        ),
    )
