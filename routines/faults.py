"""Injected hardware faults: ``--fault KIND@FRAME`` for ``slidecal run`` (simulated cell) and
``slidecal rehearse`` (loopback controller), and the table of what each does.

Kinds (:data:`FAULT_KINDS`): ``protective_stop``, ``emergency_stop`` (the arm stops halfway
through the move to that frame), ``disconnect`` (the robot's link is lost during that move),
``stall`` (the arm stops halfway without any fault and never arrives), ``no_frame`` (every
capture at that frame's pose times out, its retries included), ``camera_lost`` (the camera is
gone for good from that capture on: reconnecting fails).
``FRAME`` counts captured frames from 0: the fault hits the move to (or the capture of) that
frame, so every frame before it is on disk. The routine then stops the arm, records the event
in the session and exits with the hardware-fault code 3.

The table (``docs/FAULTS.md``) is made by running every kind at a few frames::

    slidecal bench faults --out docs/FAULTS.md --frames 2 [--no-rehearse]
"""

from __future__ import annotations

import argparse
import re
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slidecal.solver.errors import InputError

FAULT_KINDS = ("protective_stop", "emergency_stop", "disconnect", "stall", "no_frame",
               "camera_lost")
ROBOT_FAULTS = ("protective_stop", "emergency_stop", "disconnect", "stall")
#: How the simulated arm and camera rig (mocks/) produce each kind.
SIMULATED = {"protective_stop": "protective_stop", "emergency_stop": "emergency_stop",
             "disconnect": "disconnect", "stall": "timeout", "no_frame": "no_frame",
             "camera_lost": "lost"}
#: Captures a ``no_frame`` fault spoils from its frame on: more than any capture retries, so the
#: frame cannot be captured at that pose at all (a single dropped frame is retried, and survives)
NO_FRAME_CAPTURES = 20
#: The loopback controller's control command for each robot fault (mocks/ur_controller.py).
CONTROLLER = {"protective_stop": "pstop", "emergency_stop": "estop", "disconnect": "drop_next",
              "stall": "stall"}


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
    """Arms each fault just before the move to its frame (``before_frame``, called by the run).

    ``arm_robot(kind)`` makes the robot's next move fail that way; camera faults are injected
    into a simulated rig (``inject_fault(kind, at_capture)``, mocks/camera.py).
    """

    def __init__(self, specs: Iterable[FaultSpec | str], arm_robot: Callable[[str], None],
                 rig: Any) -> None:
        self.specs = tuple(s if isinstance(s, FaultSpec) else parse_fault(s) for s in specs)
        self._arm_robot = arm_robot
        self._rig = rig
        self.fired: list[FaultSpec] = []
        if any(s.kind not in ROBOT_FAULTS for s in self.specs) and not hasattr(
            rig, "inject_fault"
        ):
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
            self.fired.append(s)


# ------------------------------------------------------------------------------- the table
@dataclass(frozen=True)
class FaultRow:
    """What one injected fault did."""

    mode: str
    fault: str
    exit_code: int
    robot_stopped: bool
    frames_kept: int
    frames_expected: int
    event: str
    seconds: float


def _session_facts(out: Path) -> tuple[int, str]:
    from slidecal.routines.session import load_yaml

    data = load_yaml(out / "session.yaml", "session")
    events = [e for e in data.get("events", []) if e.get("kind") == "fault"]
    frames = len(data.get("frames", []))
    return frames, (" ".join(str(events[-1]["message"]).split()) if events else "")


def run_row(spec: FaultSpec, rehearse: bool, workdir: Path) -> FaultRow:
    """Run ``slidecal run`` (simulated cell) or ``slidecal rehearse`` with one fault."""
    import contextlib
    import io

    from slidecal.routines import cli

    out = workdir / f"{'rehearse' if rehearse else 'run'}_{spec.kind}_{spec.frame}"
    t0 = time.monotonic()
    stopped: list[bool] = []
    if rehearse:
        from slidecal.routines import rehearse as rh

        rh.LAST_CONTROLLER_STATE.clear()
        argv = ["rehearse", "--out", str(out), "--fault", str(spec), "--quiet"]
    else:
        argv = ["run", "--out", str(out), "--fault", str(spec), "--quiet", "--no-recording"]
        from slidecal.mocks import robot as simrobot

        original = simrobot.SimulatedUR.stop

        def spy(self: Any) -> None:
            stopped.append(True)
            original(self)

        simrobot.SimulatedUR.stop = spy  # type: ignore[method-assign]
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            code = cli.main(argv)
    finally:
        if not rehearse:
            simrobot.SimulatedUR.stop = original  # type: ignore[method-assign]
    if rehearse:
        st = rh.LAST_CONTROLLER_STATE
        at_rest = not st.get("moving", True) and not st.get("stalled", False)
        stopped.append(bool(at_rest))
    frames, event = _session_facts(out) if (out / "session.yaml").exists() else (0, "")
    return FaultRow("rehearse" if rehearse else "run", str(spec), code, bool(stopped and
                    all(stopped)), frames, spec.frame, event, time.monotonic() - t0)


def table(rows: Sequence[FaultRow]) -> str:
    """The Markdown table of :func:`run_row` results."""
    lines = [
        "| mode | fault | robot stopped | frames kept / before the fault | event recorded "
        "| exit code |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        ev = re.sub(r"\[[^\]]*\] \(X [^)]*deg\)", "<pose>", r.event)  # poses: noise here
        ev = ev if len(ev) < 160 else ev[:157] + "..."
        lines.append(
            f"| {r.mode} | `{r.fault}` | {'yes' if r.robot_stopped else 'NO'} | "
            f"{r.frames_kept} / {r.frames_expected} | {ev or 'NONE'} | {r.exit_code} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """``slidecal bench faults --out docs/FAULTS.md``: the fault table."""
    p = argparse.ArgumentParser(description="Inject every fault kind and tabulate the outcome.")
    p.add_argument("--out", help="Markdown file to write (default: print)")
    p.add_argument("--frames", type=int, nargs="+", default=[2])
    p.add_argument("--no-rehearse", action="store_true", help="simulated cell only")
    a = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for rehearse in (False,) if a.no_rehearse else (False, True):
            for kind in FAULT_KINDS:
                for frame in a.frames:
                    rows.append(run_row(FaultSpec(kind, frame), rehearse, Path(tmp)))
                    print(table(rows[-1:]).splitlines()[-1], flush=True)
    cmd = "slidecal bench faults" + (f" --out {a.out}" if a.out else "")
    cmd += " --frames " + " ".join(str(f) for f in a.frames)
    cmd += " --no-rehearse" if a.no_rehearse else ""
    text = (
        "# Injected faults\n\n"
        f"Made by `{cmd}`. `run`: `slidecal run --fault KIND@FRAME` on the "
        "simulated default cell; `rehearse`: `slidecal rehearse --fault KIND@FRAME`, the real "
        "ur-rtde client against the loopback controller. Robot stopped: `run`, the routine "
        "called `stop()`; `rehearse`, the controller's arm is at rest (not moving, not stalled) "
        "after the run. Frames kept: frames in the session / frames captured before the fault. "
        "Exit code 3 is the hardware-fault code.\n\n" + table(rows)
    )
    if a.out:
        Path(a.out).write_text(text, encoding="utf-8")
    else:
        print(text)
    ok = all(r.exit_code == 3 and r.robot_stopped and r.frames_kept == r.frames_expected
             and r.event for r in rows)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
