"""Motion plans: orientation groups of ``T_base_tool`` poses, and a fixed default plan.

A plan is what the robot will do: groups of poses sharing one orientation (pure translations
inside a group, MATH.md Sec. 3) and the tilt changes between groups that make the hand-eye
translation observable (Sec. 4). ``plan.yaml``::

    format: slidecal.plan/1
    speed_mps: 0.25
    accel_mps2: 1.0
    settle_s: 0.5
    groups:                       # each a list of UR poses [x, y, z, rx, ry, rz] (m, rad)
      - [[...], [...]]
    via: [x, y, z, rx, ry, rz]    # optional: visited before each group, no capture (a safe,
                                  # untilted pose: big reorientations never run as one line)
    predicted_std: null           # reserved for the planner: predicted one-sigma per parameter
    duration_s: null              # reserved for the planner: predicted robot time

:func:`default_plan` is the fixed plan used until the planner exists: four groups tilted by
``tilt_deg`` about four different axes in the board plane (plus a small roll about the optical
axis), five frames each, translations of 40-80 mm in non-coplanar directions with components
along the viewing axis (translations parallel to the board plane alone are degenerate, MATH.md
Sec. 7), every pose looking at the board from ``standoff_m``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slidecal.drivers.ur_pose import T_from_ur_pose, ur_pose_from_T
from slidecal.routines.config import CellConfig
from slidecal.routines.session import Fields, as_array, dump_yaml, load_yaml, write_atomic
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import R_from_rvec, Rz, T_from_Rt, inv_T

PLAN_FORMAT = "slidecal.plan/1"

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


@dataclass(frozen=True)
class Plan:
    """Orientation groups of ``T_base_tool`` (4, 4) poses (metres) and how to move between them.

    ``via`` (4, 4): visited before each group without a capture (None: straight to the group).
    ``predicted_std`` (parameter name -> one-sigma) and ``duration_s`` are reserved for the
    planner; None here.
    """

    groups: tuple[tuple[np.ndarray, ...], ...]
    via: np.ndarray | None = None
    speed_mps: float = 0.1
    accel_mps2: float = 0.5
    settle_s: float = 0.5
    predicted_std: dict[str, float] | None = None
    duration_s: float | None = None
    notes: tuple[str, ...] = field(default=())

    @property
    def poses(self) -> list[tuple[int, np.ndarray]]:
        """(group index, ``T_base_tool``) of every pose, in execution order."""
        return [(g, T) for g, grp in enumerate(self.groups) for T in grp]

    @property
    def n_poses(self) -> int:
        """Number of poses."""
        return sum(len(g) for g in self.groups)


def plan_to_dict(plan: Plan) -> dict[str, Any]:
    """The ``plan.yaml`` mapping."""
    return {
        "format": PLAN_FORMAT,
        "speed_mps": plan.speed_mps,
        "accel_mps2": plan.accel_mps2,
        "settle_s": plan.settle_s,
        "groups": [[ur_pose_from_T(T) for T in g] for g in plan.groups],
        "via": ur_pose_from_T(plan.via) if plan.via is not None else None,
        "predicted_std": plan.predicted_std,
        "duration_s": plan.duration_s,
        "notes": list(plan.notes),
    }


def write_plan(plan: Plan, path: str | Path) -> Path:
    """Write ``plan.yaml`` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, dump_yaml(plan_to_dict(plan)))
    return path


def read_plan(path: str | Path) -> Plan:
    """Read and validate a ``plan.yaml``."""
    path = Path(path)
    return plan_from_dict(load_yaml(path, "plan file"), path.name)


def plan_from_dict(data: Any, source: str = "plan.yaml") -> Plan:
    """Validate a parsed plan; errors name ``source: field``."""
    f = Fields(data, source)
    if f.get("format") != PLAN_FORMAT:
        raise f.error("format", f"is {f.get('format')!r}; expected {PLAN_FORMAT!r}")
    groups_raw = f.require("groups")
    if not isinstance(groups_raw, list) or not groups_raw:
        raise f.error("groups", "must be a non-empty list of groups of UR poses")
    groups = []
    for g, grp in enumerate(groups_raw):
        if not isinstance(grp, list) or not grp:
            raise f.error(f"groups[{g}]", "must be a non-empty list of UR poses")
        poses = []
        for k, p in enumerate(grp):
            where = f.where(f"groups[{g}][{k}]")
            v = as_array(p, (-1,), where)
            if v.shape != (6,):
                raise InputError(
                    f"has {v.size} numbers; a UR pose is [x, y, z, rx, ry, rz] (m, rad)",
                    where=where,
                )
            poses.append(T_from_ur_pose(v))
        groups.append(tuple(poses))
    pstd = f.get("predicted_std")
    if pstd is not None and not isinstance(pstd, Mapping):
        raise f.error("predicted_std", "must be a mapping parameter -> one-sigma, or null")
    dur = f.get("duration_s")
    via = None
    if f.has("via"):
        v = f.array("via", (-1,))
        if v.shape != (6,):
            raise f.error("via", f"has {v.size} numbers; a UR pose is [x, y, z, rx, ry, rz]")
        via = T_from_ur_pose(v)
    return Plan(
        groups=tuple(groups),
        via=via,
        speed_mps=f.number("speed_mps", 0.1, positive=True),
        accel_mps2=f.number("accel_mps2", 0.5, positive=True),
        settle_s=f.number("settle_s", 0.5, minimum=0.0),
        predicted_std=dict(pstd) if pstd is not None else None,
        duration_s=f.number("duration_s") if dur is not None else None,
        notes=tuple(str(n) for n in f.get("notes", [])),
    )


def _axis_angle(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    return R_from_rvec(np.asarray(axis, dtype=float) / np.linalg.norm(axis) * angle_rad)


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
        phi = np.radians(45.0 + 360.0 * g / groups)
        axis = np.array([np.cos(phi), np.sin(phi), 0.0])
        # camera axes aligned with the board's (looking along +z_board), tilted, then rolled
        R_board_cam = _axis_angle(axis, np.radians(tilt_deg)) @ Rz(np.radians(rolls[g % 6]))
        centre_cam = c - standoff_m * R_board_cam[:, 2]
        frames = []
        for k in range(frames_per_group):
            p_cam_board = centre_cam + _OFFSETS[k] * step_m
            frames.append(inv_T(T_from_Rt(R_board_cam, p_cam_board)))
        out.append(frames)
    return out


def default_plan(cfg: CellConfig) -> Plan:
    """The fixed default plan of a cell (see the module docstring).

    Uses the cell's approximate target pose and mount (``approximate:``), ``standoff_m`` and
    ``plan: {frames_per_group, tilt_deg, step_mm: [min, max], groups}``; poses are converted
    to ``T_base_tool`` through the approximate hand-eye (eye-in-hand) or target-on-tool
    transform (eye-to-hand).
    """
    pf = Fields(cfg.plan, cfg.source, "plan")
    frames = pf.integer("frames_per_group", 5, minimum=2)
    n_groups = pf.integer("groups", 4, minimum=2)
    tilt = pf.number("tilt_deg", 25.0, positive=True)
    if tilt > 45.0:
        raise pf.error("tilt_deg", f"is {tilt}; tilts beyond 45 deg lose the board's corners")
    step = pf.array("step_mm", (2,), [40.0, 80.0])
    if not 0 < step[0] <= step[1]:
        raise pf.error("step_mm", "must be [min, max] with 0 < min <= max (millimetres)")
    centre = cfg.target.points_m.mean(axis=0)
    T_cb = camera_poses_board(centre, cfg.standoff_m, tilt, step[1] / 1000.0, frames, n_groups)
    groups = tuple(tuple(tool_pose(cfg, T) for T in grp) for grp in T_cb)
    via = tool_pose(cfg, camera_poses_board(centre, cfg.standoff_m, 0.0, 0.0, 2, 1)[0][0])
    return Plan(
        groups=groups,
        via=via,
        speed_mps=cfg.robot.speed_mps,
        accel_mps2=cfg.robot.accel_mps2,
        settle_s=cfg.robot.settle_s,
        notes=(
            f"default plan: {n_groups} groups tilted {tilt:g} deg, {frames} frames each, "
            f"moves up to {step[1]:g} mm at {cfg.standoff_m:g} m",
        ),
    )


def tool_pose(cfg: CellConfig, T_cam_board: np.ndarray) -> np.ndarray:
    """``T_base_tool`` (4, 4) that puts the (reference) camera at ``T_cam_board`` (4, 4), using
    the cell's approximate hand-eye and target poses."""
    if cfg.mount == "eye_in_hand":
        T_base_cam = cfg.approx_T_target @ inv_T(T_cam_board)
        return T_base_cam @ inv_T(cfg.approx_T_hand_eye)
    T_base_board = cfg.approx_T_hand_eye @ T_cam_board
    return T_base_board @ inv_T(cfg.approx_T_target)


def check_plan(plan: Plan, cfg: CellConfig, is_reachable=None) -> None:
    """Refuse a plan before the robot moves: a pose outside the workspace box or unreachable.

    ``is_reachable``: the robot's ``is_reachable`` (optional). Raises ``InputError`` naming the
    pose (group, index) and what to change.
    """
    lo, hi = cfg.robot.workspace_min_m, cfg.robot.workspace_max_m
    named = [
        (f"plan: groups[{g}][{k}]", T)
        for g, grp in enumerate(plan.groups)
        for k, T in enumerate(grp)
    ]
    if plan.via is not None:
        named.insert(0, ("plan: via", plan.via))
    for where, T in named:
        p = T[:3, 3]
        if lo is not None and hi is not None and (np.any(p < lo) or np.any(p > hi)):
            raise InputError(
                f"TCP position {np.round(p * 1000, 1).tolist()} mm is outside the workspace "
                f"box of {cfg.source} (robot.workspace); move the target or widen the box",
                where=where,
            )
        if is_reachable is not None and not is_reachable(T):
            raise InputError(
                f"pose {np.round(ur_pose_from_T(T), 4).tolist()} is not reachable by the "
                "robot; move the target closer or reduce plan.tilt_deg",
                where=where,
            )
