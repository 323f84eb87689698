"""Motion plans (``slidecal.plan/1``, every key in :data:`PLAN_KEYS` and their meaning:
docs/FORMATS.md): groups of ``T_base_tool`` poses sharing one orientation (pure translations
inside a group, docs/METHOD.md Sec. 3) and the tilt changes between groups that make the
hand-eye translation observable (Sec. 4).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from slidecal.drivers.ur_pose import ur_pose_from_T
from slidecal.routines.schema import Fields, load_yaml, write_yaml
from slidecal.routines.session import ur_pose_field
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import inv_T, rotation_angle_deg

if TYPE_CHECKING:  # plans are read without the cell schema (slidecal solve)
    from slidecal.routines.config import CellConfig, RobotConfig

PLAN_FORMAT = "slidecal.plan/1"
#: The keys of ``plan.yaml`` (one list; :func:`plan_to_dict` writes exactly these).
PLAN_KEYS = (
    "format",
    "speed_mps",
    "accel_mps2",
    "settle_s",
    "groups",
    "via",
    "predicted_std",
    "duration_s",
    "notes",
)
#: Poses of one group may differ in orientation by this much (numerical round trips only).
MAX_GROUP_ROTATION_DEG = 0.01
#: Speed and acceleration limits of calibration moves (as for the cell's ``robot:``).
MAX_SPEED_MPS = 1.0
MAX_ACCEL_MPS2 = 2.5


@dataclass(frozen=True)
class Plan:
    """Orientation groups of ``T_base_tool`` (4, 4) poses (metres) and how to move between them;
    the fields are ``plan.yaml``'s keys (docs/FORMATS.md; ``via`` None: straight to each group)."""

    groups: tuple[tuple[np.ndarray, ...], ...]
    via: np.ndarray | None = None
    speed_mps: float = 0.1
    accel_mps2: float = 0.5
    settle_s: float = 0.5
    predicted_std: dict[str, float] | None = None
    duration_s: float | None = None
    notes: tuple[str, ...] = field(default=())

    @classmethod
    def build(
        cls,
        groups: Sequence[Sequence[np.ndarray]],
        motion: RobotConfig | Plan,
        *,
        via: np.ndarray | None = None,
        notes: Sequence[str] = (),
    ) -> Plan:
        """A new plan: ``groups`` of ``T_base_tool`` (4, 4) poses moved with the speed,
        acceleration and settling time of ``motion``, the cell's ``robot:`` section
        (``cfg.robot``) or the plan whose poses these are taken from."""
        return cls(
            groups=tuple(tuple(g) for g in groups),
            via=via,
            speed_mps=motion.speed_mps,
            accel_mps2=motion.accel_mps2,
            settle_s=motion.settle_s,
            notes=tuple(notes),
        )

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
    return write_yaml(path, plan_to_dict(plan))


def read_plan(path: str | Path) -> Plan:
    """Read and validate a ``plan.yaml``."""
    path = Path(path)
    return plan_from_dict(load_yaml(path, "plan file"), path.name)


def plan_from_dict(data: Any, source: str = "plan.yaml") -> Plan:
    """Validate a parsed plan (the inverse of :func:`plan_to_dict`); errors name
    ``source: field``."""
    f = Fields(data, source)
    fmt = f.require("format")
    if fmt != PLAN_FORMAT:
        raise f.error("format", f"is {fmt!r}; expected {PLAN_FORMAT!r}")
    f.only(PLAN_KEYS)
    groups_raw = f.list("groups", non_empty=True, hint="group (a list of UR poses)")
    groups = []
    for g, grp in enumerate(groups_raw):
        if not isinstance(grp, list) or not grp:
            raise f.error(f"groups[{g}]", "must be a non-empty list of UR poses")
        poses = [ur_pose_field(_Item(f, f"groups[{g}]", grp), str(k)) for k in range(len(grp))]
        for k, T in enumerate(poses[1:], start=1):
            angle = rotation_angle_deg(T[:3, :3], poses[0][:3, :3])
            if angle > MAX_GROUP_ROTATION_DEG:
                raise f.error(
                    f"groups[{g}][{k}]",
                    f"turns {angle:.3g} deg from the group's first pose; the poses of a group "
                    "differ by translations only (same rx, ry, rz; rotations in radians)",
                )
        groups.append(tuple(poses))
    pstd = f.section("predicted_std")
    predicted = {str(k): pstd.number(str(k), minimum=0.0) for k in pstd.data} or None
    return Plan(
        speed_mps=f.number("speed_mps", 0.1, positive=True, maximum=MAX_SPEED_MPS),
        accel_mps2=f.number("accel_mps2", 0.5, positive=True, maximum=MAX_ACCEL_MPS2),
        settle_s=f.number("settle_s", 0.5, minimum=0.0, maximum=60.0),
        groups=tuple(groups),
        via=ur_pose_field(f, "via") if f.has("via") else None,
        predicted_std=predicted if f.has("predicted_std") else None,
        duration_s=f.optional_number("duration_s", minimum=0.0),
        notes=tuple(f.strings("notes")),
    )


class _Item(Fields):
    """The entries of a YAML list addressed as fields ``0``, ``1``, ... (``groups[2][3]``)."""

    def __init__(self, parent: Fields, path: str, items: list[Any]) -> None:
        super().__init__({str(i): v for i, v in enumerate(items)}, parent.file, path)

    def where(self, key: str | None = None) -> str:
        return f"{self.file}: {self.path}" + (f"[{key}]" if key is not None else "")


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
                "robot; move the target closer or lower plan.tilts_deg",
                where=where,
            )
