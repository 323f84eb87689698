"""Injected hardware faults (``--fault KIND@FRAME``, :data:`FAULT_KINDS`) for ``slidecal run`` on a
simulated cell and ``slidecal rehearse``: ``FRAME`` counts captured frames from 0, the fault
hits the move to (or the capture of) that frame. The table of what each kind does is
docs/results/FAULTS.md (``python -m tests.bench faults``)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from slidecal.solver.errors import InputError

#: How the simulated arm and camera rig (mocks/) produce each kind.
SIMULATED = {"protective_stop": "protective_stop", "emergency_stop": "emergency_stop",
             "disconnect": "disconnect", "stall": "timeout", "no_frame": "no_frame",
             "camera_lost": "lost"}
FAULT_KINDS = tuple(SIMULATED)
#: Captures a ``no_frame`` fault spoils from its frame on: more than any capture retries, so the
#: frame cannot be captured at that pose at all (a single dropped frame is retried, and survives)
NO_FRAME_CAPTURES = 20
#: The loopback controller's control command for each robot fault (mocks/ur_controller.py).
CONTROLLER = {"protective_stop": "pstop", "emergency_stop": "estop", "disconnect": "drop_next",
              "stall": "stall"}
ROBOT_FAULTS = tuple(CONTROLLER)


@dataclass(frozen=True)
class FaultSpec:
    """One fault to inject: ``kind`` (:data:`FAULT_KINDS`) at captured frame ``frame`` (from 0)."""

    kind: str
    frame: int

    def __str__(self) -> str:
        return f"{self.kind}@{self.frame}"


def parse_fault(text: str) -> FaultSpec:
    """``"protective_stop@3"`` -> ``FaultSpec("protective_stop", 3)``; ``InputError`` otherwise."""
    kind, sep, frame = str(text).strip().partition("@")
    if not sep or kind not in FAULT_KINDS or not frame.isdigit():
        raise InputError(
            f"{text!r} is not KIND@FRAME; KIND is one of {', '.join(FAULT_KINDS)} and FRAME a "
            "frame number from 0, e.g. protective_stop@3",
            where="--fault",
        )
    return FaultSpec(kind, int(frame))


class FaultInjector:
    """Arms each fault just before the move to its frame (``before_frame``): ``arm_robot(kind)`` for
    the robot, ``inject_fault(kind, at_capture)`` for a simulated rig."""

    def __init__(self, specs: Iterable[FaultSpec | str], arm_robot: Callable[[str], None],
                 rig: Any) -> None:
        self.specs = tuple(s if isinstance(s, FaultSpec) else parse_fault(s) for s in specs)
        self._arm_robot = arm_robot
        self._rig = rig
        if any(s.kind not in ROBOT_FAULTS for s in self.specs) and not hasattr(rig, "inject_fault"):
            raise InputError("camera faults need a simulated camera rig", where="--fault")

    @classmethod
    def for_simulated(cls, specs: Iterable[FaultSpec | str], robot: Any,
                      rig: Any) -> FaultInjector:
        """Faults for the simulated cell (mocks/robot.py, mocks/camera.py)."""
        if not hasattr(robot, "inject_fault"):
            raise InputError(
                "faults are injected only into the simulated cell or a rehearsal, never into "
                "real hardware; remove --fault",
                where="--fault",
            )
        return cls(specs, lambda kind: robot.inject_fault(SIMULATED[kind], robot.moves), rig)

    def before_frame(self, frame: int) -> None:
        """Arm the faults of ``frame`` (the robot's next move, the rig's next capture)."""
        for s in self.specs:
            if s.frame != frame:
                continue
            if s.kind in ROBOT_FAULTS:
                self._arm_robot(s.kind)
            elif s.kind == "no_frame":
                for k in range(NO_FRAME_CAPTURES):
                    self._rig.inject_fault("no_frame", self._rig.capture_count + k)
            else:
                self._rig.inject_fault(SIMULATED[s.kind], self._rig.capture_count)
