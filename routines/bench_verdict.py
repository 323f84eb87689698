"""Figures of the unattended verdict on the simulated cell (``docs/VERDICT.md``).

``slidecal bench verdict --part gate|garbage|check|faults [--seeds N]``
runs one part and rewrites its section of ``docs/VERDICT.md`` (between ``<!-- part: X -->``
and ``<!-- end: X -->``), so that each part stays under a few minutes of a shared machine:

- ``gate``: ``N`` runs of the default cell (seeds 1..N). Unchanged cell: each run judged
  against every other run's result as the installed calibration (N (N - 1) ordered pairs):
  anything but ``accepted`` is a false reject. Changed cell: the installed calibration differs
  from the cell by a 0.3 % focal length, a 1 px principal point or a 0.1 deg hand-eye rotation
  (applied to the installed result; to first order the same as changing the cell, which
  ``--real-changes`` also does with real runs of changed cells): ``accepted`` is a false accept.
- ``garbage``: the issue's garbage calibrations (recorded session, edited), their verdicts.
- ``check``: one install (seed 1), then ``slidecal check`` on the unchanged cell and on the
  three changed cells with seeds 100.. (N each).
- ``faults``: SIGTERM, SIGHUP and Ctrl-C sent to a ``slidecal run`` subprocess after a given
  frame, and faults injected in-process at several frames: robot stopped, frames kept, event
  recorded, ``--resume`` completes with an accepted verdict.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from slidecal.routines.config import load_config
from slidecal.routines.session import load_session
from slidecal.routines.verdict import judge
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import R_from_rvec

DOC = Path(__file__).resolve().parent.parent / "docs" / "VERDICT.md"
COMMAND = "slidecal bench verdict"

CHANGES = {
    "focal length +0.3 %": {"fx_rel": 0.003},
    "principal point +1 px": {"cx_px": 1.0},
    "hand-eye rotation 0.1 deg": {"he_deg": 0.1},
}


def changed(result, fx_rel: float = 0.0, cx_px: float = 0.0, he_deg: float = 0.0):  # noqa: ANN001, ANN201
    """``result`` with every camera's focal length scaled, principal point shifted and the
    hand-eye rotated (about a fixed axis oblique to the optical axis)."""
    cams = {}
    for n, cam in result.cameras.items():
        K = np.array(cam.K, dtype=float)
        K[0, 0] *= 1 + fx_rel
        K[1, 1] *= 1 + fx_rel
        K[0, 2] += cx_px
        cams[n] = dataclasses.replace(cam, K=K)
    he = result.hand_eye
    axis = np.array([0.6, 0.0, 0.8])
    R = R_from_rvec(np.radians(he_deg) * axis) @ he.R
    return dataclasses.replace(result, cameras=cams, hand_eye=dataclasses.replace(he, R=R))


# ----------------------------------------------------------------------------- garbage makers


def copy_session(src: Path, dst: Path) -> Path:
    """The session file and plan of ``src`` (detections inline, no images) in ``dst``."""
    import yaml

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
    """Apply ``fn`` to the parsed ``session.yaml`` of ``d`` and write it back."""
    import yaml

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
    its first pose): what a hand-made plan can do (``slidecal run`` refuses such a plan
    before the robot moves; this records it anyway, to show what the verdict makes of it)."""
    from slidecal.mocks.cell import SimulatedCell
    from slidecal.routines.plan import Plan, write_plan
    from slidecal.routines.planner import make_plan
    from slidecal.routines.progress import Progress
    from slidecal.routines.run import _acquire
    from slidecal.routines.session import SessionWriter

    cfg = load_config()
    plan = make_plan(cfg).plan
    bad = Plan.build([[g[0] for _ in g] for g in plan.groups], plan, via=plan.via)
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


def cell_overrides(fx_rel: float = 0.0, cx_px: float = 0.0, he_deg: float = 0.0) -> dict:
    """Overrides of the default cell's truth for the same changes (a changed cell)."""
    from slidecal.solver.geometry import Rx, Ry, Rz

    f = 880.0 * (1 + fx_rel)
    sim: dict = {"cameras": {"cam": {"K": [[f, 0.0, 640.0 + cx_px], [0.0, f, 400.0], [0, 0, 1]]}}}
    if he_deg:
        r, p, y = np.radians([0.8, -1.2, 90.5])  # the default cell's true T_tool_cam
        R = R_from_rvec(np.radians(he_deg) * np.array([0.6, 0.0, 0.8])) @ Rz(y) @ Ry(p) @ Rx(r)
        rpy = np.degrees(
            [np.arctan2(R[2, 1], R[2, 2]), -np.arcsin(R[2, 0]), np.arctan2(R[1, 0], R[0, 0])]
        )  # the cell's rpy_deg convention: R = Rz(yaw) Ry(pitch) Rx(roll)
        sim["T_tool_cam"] = {"rpy_deg": rpy.tolist(), "t_m": [0.032, -0.061, 0.045]}
    return {"simulation": sim}


def _runs(n: int, work: Path, overrides: dict | None = None, first: int = 1):
    from slidecal.routines.run import run_calibration

    cfg = load_config(overrides=overrides)
    out = []
    for seed in range(first, first + n):
        o = run_calibration(
            cfg,
            out_dir=work / f"run{seed}_{len(list(work.iterdir()))}",
            progress=False,
            recording=False,
            seed=seed,
        )
        out.append((o, load_session(o.session_dir).problem))
    return out


def _rate(k: int, n: int) -> str:
    return f"{k} / {n} ({100.0 * k / n:.1f} %)" if n else "0 / 0"


def part_gate(n: int, real_changes: int, work: Path) -> list[str]:
    from slidecal.routines.verdict import Limits

    lim = Limits()
    t0 = time.monotonic()
    runs = _runs(n, work)
    alone = sum(o.verdict.verdict == "accepted" for o, _ in runs)
    pairs = [(i, j) for i in range(n) for j in range(n) if i != j]
    fr = sum(
        judge(runs[j][0].result, problem=runs[j][1], installed=runs[i][0].result).verdict
        != "accepted"
        for i, j in pairs
    )
    sig = [
        judge(runs[j][0].result, problem=runs[j][1], installed=runs[i][0].result).installed
        for i, j in pairs
    ]
    max_sig = max(s["max_sigma"] for s in sig)
    max_px = max(max(s["max_displacement_px"].values()) for s in sig)
    lines = [
        f"{n} runs of the default simulated cell (seeds 1..{n}); {len(pairs)} ordered pairs "
        "(new run, installed run).",
        "",
        "| case | flagged (drifted or rejected) | what |",
        "|---|---|---|",
        f"| each run alone | {_rate(n - alone, n)} | gate without an installed calibration |",
        f"| unchanged cell | {_rate(fr, len(pairs))} | false rejects; largest change seen "
        f"{max_sig:.2f} sigma (limit {lim.max_change_sigma:g}), {max_px:.2f} px (limit "
        f"{lim.max_change_px:g}) |",
    ]
    for name, ch in CHANGES.items():
        flagged = 0
        worst = []
        for i, j in pairs:
            v = judge(
                runs[j][0].result, problem=runs[j][1], installed=changed(runs[i][0].result, **ch)
            )
            flagged += v.verdict != "accepted"
            worst.append(
                (v.installed["max_sigma"], max(v.installed["max_displacement_px"].values()))
            )
        lo_s = min(w[0] for w in worst)
        lo_p = min(w[1] for w in worst)
        lines.append(
            f"| {name} | {_rate(flagged, len(pairs))} | false accepts "
            f"{_rate(len(pairs) - flagged, len(pairs))}; "
            f"smallest change seen {lo_s:.1f} sigma, {lo_p:.2f} px |"
        )
    if real_changes:
        lines += [
            "",
            "Real changed cells (the truth of the simulated cell changed, installed = "
            "unchanged run of seed 1):",
            "",
            "| change | seed | verdict | sigma | px |",
            "|---|---|---|---|---|",
        ]
        for name, ch in CHANGES.items():
            for k, (o, p) in enumerate(_runs(real_changes, work, cell_overrides(**ch), 50)):
                v = judge(o.result, problem=p, installed=runs[0][0].result)
                lines.append(
                    f"| {name} | {50 + k} | {v.verdict} | "
                    f"{v.installed['max_sigma']:.1f} | "
                    f"{max(v.installed['max_displacement_px'].values()):.2f} |"
                )
    lines += ["", f"Took {time.monotonic() - t0:.0f} s."]
    return lines


def part_garbage(work: Path) -> list[str]:
    from slidecal.routines.run import solve_session

    ((o, _),) = _runs(1, work)
    cases = [
        ("robot rotations in degrees", rotations_in_degrees),
        ("square size 0.025 m for a 0.030 m board", square_size(0.025)),
        ("square size 0.036 m for 0.030 m (= 0.025 given as 0.030)", square_size(0.036)),
    ]
    lines = [
        "Each case: the session of a good run (default cell, seed 1) edited as a user's mistake "
        "would make it, then `slidecal solve`.",
        "",
        "| garbage | verdict | exit | fx (px) | first reasons |",
        "|---|---|---|---|---|",
        _garbage_row("none (the good run)", o),
    ]
    for k, (name, fn) in enumerate(cases):
        d = edit_session(copy_session(o.session_dir, work / f"g{k}"), fn)
        try:
            lines.append(_garbage_row(name, solve_session(d)))
        except InputError as e:  # refused as it is read: the clearest answer of all
            msg = " ".join(str(e).split()).replace("|", "/")
            lines.append(f"| {name} | refused as bad input | 2 | - | {msg} |")
    o = solve_session(record_without_translation(work / "notr", seed=1))
    lines.append(_garbage_row("plan with no translation inside any group", o))
    return lines


def _garbage_row(name: str, o) -> str:  # noqa: ANN001
    fx = float(next(iter(o.result.cameras.values())).K[0, 0])
    why = "; ".join(c.message for c in o.verdict.reasons[:2]).replace("|", "/")
    return f"| {name} | {o.verdict.verdict} | {o.exit_code} | {fx:.0f} | {why} |"


def part_check(n: int, work: Path) -> list[str]:
    from slidecal.routines.check import chain_rms_px, run_check
    from slidecal.routines.install import install

    t0 = time.monotonic()
    ((o, p),) = _runs(1, work)
    store = work / "store"
    info = {"chain_rms_px": chain_rms_px(o.result, p)}
    install(store, o.session_dir, o.result, o.verdict.verdict, info=info)
    lines = [
        f"Installed: seed 1 of the default cell. {n} checks per case (seeds 100..{99 + n}).",
        "",
        "| case | verdict drifted | largest sigma (min-max) | largest px (min-max) | robot time |",
        "|---|---|---|---|---|",
    ]
    for name, ch in [("unchanged cell", {})] + list(CHANGES.items()):
        cfg = load_config(overrides=cell_overrides(**ch)) if ch else load_config()
        drifted, sig, px, rt = 0, [], [], []
        for seed in range(100, 100 + n):
            v, _ = run_check(
                cfg, store, work / f"chk_{len(list(work.iterdir()))}", progress=False, seed=seed
            )
            drifted += v.verdict == "drifted"
            c = v.extra["check"]["change"]
            sig.append(c["max_sigma"])
            px.append(max(c["max_displacement_px"].values()))
            rt.append(v.extra["check"]["robot_time_s"])
        label = "false rejects" if not ch else "false accepts"
        bad = drifted if not ch else n - drifted
        lines.append(
            f"| {name} | {_rate(drifted, n)} ({label} {bad}) | {min(sig):.1f}-{max(sig):.1f} | "
            f"{min(px):.2f}-{max(px):.2f} | {max(rt):.1f} s |"
        )
    lines += ["", f"Took {time.monotonic() - t0:.0f} s."]
    return lines


def _signal_row(sig: int, name: str, after: int, work: Path) -> str:
    out = work / f"sig_{name}_{after}"
    env = {**os.environ, "SLIDECAL_LOCK_DIR": str(work)}
    cmd = [
        sys.executable,
        "-m",
        "slidecal.routines.cli",
        "run",
        "--out",
        str(out),
        "--no-recording",
        "--seed",
        "1",
    ]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    while True:
        line = p.stderr.readline()
        if not line or (f"frame {after} of" in line and "done" in line):
            break
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    s = load_session(out, detect_images=False)
    ev = s.events[-1] if s.events else {}
    stopped = "robot stopped" in ev.get("message", "")
    kept = len(s.problem.frames)
    r = subprocess.run(
        cmd[:4] + ["--resume", str(out), "--quiet"], capture_output=True, text=True, env=env
    )
    s2 = load_session(out, detect_images=False)
    return (
        f"| {name} after frame {after} | {p.returncode} | {'yes' if stopped else 'NO'} | {kept} | "
        f"{ev.get('kind')}: {ev.get('message', '')} | {r.returncode}, {len(s2.problem.frames)} "
        f"frames, {r.stdout.strip().splitlines()[0] if r.stdout.strip() else r.stderr.strip()} |"
    )


def _fault_row(kind: str, at: int, work: Path) -> str:
    from slidecal.mocks.cell import SimulatedCell
    from slidecal.routines.run import run_calibration
    from slidecal.solver.errors import HardwareFault

    cfg = load_config()
    cell = SimulatedCell.from_config(cfg, seed=1)
    if kind in ("protective_stop", "timeout"):
        cell.robot.inject_fault(kind, at_move=at)
    elif kind == "camera lost for good":
        cell.rig.inject_fault("disconnect", at_capture=at)
        real_open, opened = cell.rig.open, []

        def open_once() -> None:  # the camera does not come back for this run
            if opened:
                raise HardwareFault("no camera found")
            opened.append(1)
            real_open()

        cell.rig.open = open_once
    else:
        cell.rig.inject_fault(kind, at_capture=at)
    out = work / f"fault_{kind}_{at}"
    code = "completed"
    try:
        o = run_calibration(cfg, out_dir=out, progress=False, recording=False, cell=cell)
        code = f"completed, {o.verdict.verdict}"
    except HardwareFault:
        code = "HardwareFault (exit 3)"
    import yaml

    doc = yaml.safe_load((out / "session.yaml").read_text())  # also with no frame at all
    kinds = [e["kind"] for e in doc["events"]]
    kept = len(doc["frames"])
    resumed = ""
    if doc["status"] != "complete":
        r = run_calibration(cfg, resume=out, progress=False)
        resumed = f"{r.n_frames} frames, {r.verdict.verdict}"
    where = "move" if kind in ("protective_stop", "timeout") else "capture"
    where = f"{where} {at}" + (
        " (the via pose, before any frame)" if where == "move" and at == 0 else ""
    )
    return (
        f"| {kind} at {where} | {code} | {'yes' if cell.robot.stopped else 'no (not needed)'} "
        f"| {kept} | {', '.join(kinds) or '-'} | {resumed or '-'} |"
    )


def part_faults(work: Path) -> list[str]:
    t0 = time.monotonic()
    lines = [
        "Signals sent to a `slidecal run` subprocess (default cell, seed 1) after the given "
        "frame was done, then `slidecal run --resume SESSION`. 'robot stopped': the session's "
        "event says so (it is written after the robot's stop() returned); the in-process "
        "rows below check the simulated robot's stopped flag itself.",
        "",
        "| signal | exit | robot stopped | frames kept | event | resume: exit, frames, verdict |",
        "|---|---|---|---|---|---|",
    ]
    for sig, name, after in [
        (signal.SIGTERM, "SIGTERM", 2),
        (signal.SIGHUP, "SIGHUP", 5),
        (signal.SIGINT, "Ctrl-C (SIGINT)", 7),
    ]:
        lines.append(_signal_row(sig, name.split()[0], after, work))
    lines += [
        "",
        "Faults injected in the simulated cell (in-process), then `run_calibration(resume=...)`:",
        "",
        "| fault | run | robot stopped | frames kept | events | resume |",
        "|---|---|---|---|---|---|",
    ]
    for kind, at in [
        ("protective_stop", 0),
        ("protective_stop", 3),
        ("protective_stop", 8),
        ("timeout", 6),
        ("no_frame", 2),
        ("disconnect", 5),
        ("camera lost for good", 4),
    ]:
        lines.append(_fault_row(kind, at, work))
    lines += ["", f"Took {time.monotonic() - t0:.0f} s."]
    return lines


def write_section(part: str, lines: list[str], command: str) -> None:
    """Replace the section of ``part`` in docs/VERDICT.md (created when missing)."""
    head = f"<!-- part: {part} -->"
    tail = f"<!-- end: {part} -->"
    body = "\n".join([head, f"Produced by `{command}`.", "", *lines, tail])
    text = DOC.read_text() if DOC.is_file() else "# Verdict figures\n"
    if head in text:
        text = re.sub(re.escape(head) + r".*?" + re.escape(tail), lambda _m: body, text, flags=re.S)
    else:
        text = text.rstrip("\n") + "\n\n" + body + "\n"
    DOC.write_text(text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--part", required=True, choices=("gate", "garbage", "check", "faults"))
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--real-changes", type=int, default=1)
    args = ap.parse_args(argv)
    os.environ.setdefault("SLIDECAL_LOCK_DIR", tempfile.gettempdir())
    work = Path(tempfile.mkdtemp(prefix="slidecal_bench_verdict_"))
    try:
        if args.part == "gate":
            lines = part_gate(args.seeds, args.real_changes, work)
            cmd = f"{COMMAND} --part gate --seeds {args.seeds} --real-changes {args.real_changes}"
        elif args.part == "garbage":
            lines, cmd = part_garbage(work), f"{COMMAND} --part garbage"
        elif args.part == "check":
            lines, cmd = (
                part_check(args.seeds, work),
                f"{COMMAND} --part check --seeds {args.seeds}",
            )
        else:
            lines, cmd = part_faults(work), f"{COMMAND} --part faults"
    finally:
        shutil.rmtree(work, ignore_errors=True)
    write_section(args.part, lines, cmd)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
