"""Sessions for the verdict tests: a recorded run and the garbage a user can feed it."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import yaml

from slidecal.mocks.cell import SimulatedCell
from slidecal.routines.config import load_config
from slidecal.routines.plan import Plan, write_plan
from slidecal.routines.planner import make_plan
from slidecal.routines.progress import Progress
from slidecal.routines.run import _acquire
from slidecal.routines.session import SessionWriter

DATA = Path(__file__).parent / "data"


def copy_session(src: Path, dst: Path) -> Path:
    """The session file and plan of ``src`` (detections inline, no images) in ``dst``."""
    dst.mkdir(parents=True)
    for name in ("session.yaml", "plan.yaml"):
        if (src / name).is_file():
            shutil.copy(src / name, dst / name)
    doc = yaml.safe_load((dst / "session.yaml").read_text())
    for f in doc["frames"]:
        f.pop("images", None)
    (dst / "session.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return dst


def edit_session(d: Path, fn) -> Path:  # noqa: ANN001 - fn edits the parsed document
    doc = yaml.safe_load((d / "session.yaml").read_text())
    fn(doc)
    (d / "session.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return d


def rotations_in_degrees(doc: dict) -> None:
    """The robot's rotation vectors written in degrees where radians are meant."""
    for f in doc["frames"]:
        p = f["T_base_tool"]
        f["T_base_tool"] = p[:3] + [float(np.degrees(v)) for v in p[3:]]


def square_size(size_m: float):  # noqa: ANN201
    """A wrong square size (the marker scaled alike) in the session's target."""

    def edit(doc: dict) -> None:
        t = doc["target"]
        t["marker_size_m"] = t["marker_size_m"] * size_m / t["square_size_m"]
        t["square_size_m"] = size_m

    return edit


def record_without_translation(out: Path, seed: int = 0) -> Path:
    """A session recorded with a plan whose groups hold no translation (each group repeats
    its first pose): what a user's hand-made plan can do."""
    cfg = load_config()
    plan = make_plan(cfg).plan
    groups = tuple(tuple(g[0] for _ in g) for g in plan.groups)
    bad = Plan(
        groups=groups,
        via=plan.via,
        speed_mps=plan.speed_mps,
        accel_mps2=plan.accel_mps2,
        settle_s=plan.settle_s,
    )
    cell = SimulatedCell.from_config(cfg, seed)
    writer = SessionWriter(
        out, cfg.target, cell.rig.specs, options=cfg.options, simulation=cell.truth
    )
    write_plan(bad, out / "plan.yaml")
    cell.robot.connect()
    cell.rig.open()
    _acquire(cell.robot, cell.rig, bad, cfg, writer, None, Progress(bad.n_poses, quiet=True))
    writer.finish("complete")
    return out
