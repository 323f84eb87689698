"""Sessions for the verdict tests and the verdict study (tests/bench/verdict.py): the garbage
a user can feed slidecal (the session-file edits are in :mod:`tests.session_io`)."""

from __future__ import annotations

import sys
from pathlib import Path

from slidecal.mocks.cell import SimulatedCell
from slidecal.routines.acquire import acquire
from slidecal.routines.config import load_config
from slidecal.routines.plan import Plan, write_plan
from slidecal.routines.planner import make_plan
from slidecal.routines.progress import Progress
from slidecal.routines.session import SessionWriter
from tests.session_io import (  # noqa: F401 - re-exported for the tests
    copy_session,
    edit_session,
    rotations_in_degrees,
    square_size,
)

DATA = Path(__file__).parent / "data"


def record_without_translation(out: Path, seed: int = 0) -> Path:
    """A session recorded with a plan whose groups hold no translation (each group repeats
    its first pose): what a hand-made plan can do (``slidecal run`` refuses such a plan
    before the robot moves; this records it anyway, to show what the verdict makes of it)."""
    cfg = load_config()
    plan = make_plan(cfg)
    bad = Plan.build([[g[0] for _ in g] for g in plan.groups], plan, via=plan.via)
    cell = SimulatedCell.from_config(cfg, seed)
    writer = SessionWriter(
        out, cfg.target, cell.rig.specs, options=cfg.options, simulation=cell.truth
    )
    write_plan(bad, out / "plan.yaml")
    cell.robot.connect()
    cell.rig.open()
    acquire(cell.robot, cell.rig, bad, cfg, writer, None, Progress(bad.n_poses, quiet=True))
    writer.finish("complete")
    return out


def simulated_run_command(out: Path, seed: int = 1) -> list[str]:
    """The command line of ``slidecal run`` on the default simulated cell into ``out``, without
    a recording, run by this interpreter (a subprocess a signal can be sent to)."""
    cli = [sys.executable, "-m", "slidecal.routines.cli"]
    return [*cli, "run", "--out", str(out), "--no-recording", "--seed", str(seed)]
