"""The injected-fault table: every fault kind of ``slidecal run --fault`` (simulated cell) and
``slidecal rehearse --fault`` (loopback controller) at a few frames, and what each did.

    python -m tests.bench faults --frames 2 [--no-rehearse]   (writes docs/results/FAULTS.md)
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slidecal.mocks import robot as simrobot
from slidecal.routines import cli
from slidecal.routines.ops import rehearse as rh
from slidecal.routines.ops.faults import FAULT_KINDS, FaultSpec
from slidecal.routines.session import load_yaml
from tests.bench.report import RESULTS, bench_command, publish_report


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
    data = load_yaml(out / "session.yaml", "session")
    events = [e for e in data.get("events", []) if e.get("kind") == "fault"]
    frames = len(data.get("frames", []))
    return frames, (" ".join(str(events[-1]["message"]).split()) if events else "")


def run_row(spec: FaultSpec, rehearse: bool, workdir: Path) -> FaultRow:
    """Run ``slidecal run`` (simulated cell) or ``slidecal rehearse`` with one fault."""
    out = workdir / f"{'rehearse' if rehearse else 'run'}_{spec.kind}_{spec.frame}"
    t0 = time.monotonic()
    stopped: list[bool] = []
    if rehearse:
        argv = ["rehearse", "--out", str(out), "--fault", str(spec), "--quiet"]
    else:
        argv = ["run", "--out", str(out), "--fault", str(spec), "--quiet", "--no-recording"]
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
        rehearsal = out / rh.REHEARSAL_FILE  # what the controller saw last
        at_rest = rehearsal.is_file() and load_yaml(rehearsal, "rehearsal").get("arm_at_rest")
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
    """``python -m tests.bench faults``: the fault table (docs/results/FAULTS.md by default)."""
    p = argparse.ArgumentParser(description="Inject every fault kind and tabulate the outcome.")
    p.add_argument("--out", default=str(RESULTS / "FAULTS.md"), help="Markdown file to write")
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
    text = (
        "# Injected faults\n\n"
        f"Made by `{bench_command('faults', argv)}`. `run`: `slidecal run --fault KIND@FRAME` on "
        "the simulated default cell; `rehearse`: `slidecal rehearse --fault KIND@FRAME`, the real "
        "ur-rtde client against the loopback controller. Robot stopped: `run`, the routine "
        "called `stop()`; `rehearse`, the controller's arm is at rest (not moving, not stalled) "
        "after the run. Frames kept: frames in the session / frames captured before the fault. "
        "Exit code 3 is the hardware-fault code.\n\n" + table(rows)
    )
    publish_report(text, a.out)
    ok = all(r.exit_code == 3 and r.robot_stopped and r.frames_kept == r.frames_expected
             and r.event for r in rows)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
