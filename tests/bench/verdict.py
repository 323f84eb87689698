"""Figures of the unattended verdict on the simulated cell (``docs/results/VERDICT.md``).

``python -m tests.bench verdict --part gate|garbage|check|faults [--seeds N]``
runs one part and rewrites its section of ``docs/results/VERDICT.md`` (between ``<!-- part: X -->``
and ``<!-- end: X -->``), so that each part stays under a few minutes of a shared machine:

- ``gate``: ``N`` simulated cells (cell seeds 1..N, each its own arm error and board pose;
  see :func:`same_cell`). Per cell an installed run, then new runs of the same cell (same arm,
  same board, same plan, fresh noise): unchanged (anything but ``accepted`` is a false reject)
  and with the camera changed by a 0.3 % focal length, a 1 px principal point or a 0.1 deg
  hand-eye rotation (``accepted`` is a false accept); each judged against the installed run
  with its session (the paired comparison and the parameter test).
- ``garbage``: the issue's garbage calibrations (recorded session, edited), their verdicts.
- ``check``: per cell (seeds 1..N) one install, then ``slidecal check`` on the same cell
  unchanged and with each of the three changes.
- ``mistakes``: issue 39's user mistakes on good runs, the verdict before and after its tests.
- ``faults``: SIGTERM, SIGHUP and Ctrl-C sent to a ``slidecal run`` subprocess after a given
  frame, and faults injected in-process at several frames: robot stopped, frames kept, event
  recorded, ``--resume`` completes with an accepted verdict.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from slidecal.drivers.ur_pose import T_from_ur_pose, ur_pose_from_T
from slidecal.mocks import scenarios as sc
from slidecal.mocks.cell import SimulatedCell
from slidecal.mocks.scenarios import cell_overrides, same_cell
from slidecal.routines.config import load_config, load_packaged_cell
from slidecal.routines.ops.check import run_check
from slidecal.routines.ops.install import install
from slidecal.routines.ops.verdict import Limits, judge
from slidecal.routines.planner import make_plan
from slidecal.routines.run import RunRequest, run_calibration
from slidecal.routines.session import load_session
from slidecal.routines.solve import solve_session
from slidecal.solver.adequacy import LEFT_OUT
from slidecal.solver.calibrate import calibrate
from slidecal.solver.drift import Z_LIMIT, chain_rms_px
from slidecal.solver.errors import HardwareFault, InputError
from tests.bench.report import RESULTS
from tests.session_io import (
    centre_only,
    copy_session,
    edit_session,
    focus_changed,
    rotations_in_degrees,
    square_size,
    swap_cameras,
)
from tests.unattended_helpers import record_without_translation, simulated_run_command

DOC = RESULTS / "VERDICT.md"
COMMAND = "python -m tests.bench verdict"

CHANGES = {
    "focal length +0.3 %": {"fx_rel": 0.003},
    "principal point +1 px": {"cx_px": 1.0},
    "hand-eye rotation 0.1 deg": {"he_deg": 0.1},
}


# ----------------------------------------------------------------------------- garbage makers


def pose_glitch(frame: int, dt_mm: tuple[float, float, float]):  # noqa: ANN201
    """One frame's recorded robot position off by ``dt_mm`` (a pose read before the arm
    settled)."""

    def edit(doc: dict) -> None:
        p = doc["frames"][frame]["T_base_tool"]
        doc["frames"][frame]["T_base_tool"] = [
            v + d / 1000.0 for v, d in zip(p[:3], dt_mm, strict=True)
        ] + p[3:]

    return edit


def poses_one_frame_late(doc: dict) -> None:
    """From the second frame on, each image paired with the previous frame's robot pose: a
    logger that fell one frame behind."""
    frames = doc["frames"]
    poses = [f["T_base_tool"] for f in frames]
    for k in range(len(frames) - 1, 0, -1):
        frames[k]["T_base_tool"] = poses[k - 1]


def poses_inverted(doc: dict) -> None:
    """The robot poses written as ``T_tool_base`` where ``T_base_tool`` is meant."""
    for f in doc["frames"]:
        f["T_base_tool"] = ur_pose_from_T(np.linalg.inv(T_from_ur_pose(f["T_base_tool"])))


def quaternions_scalar_last(doc: dict) -> None:
    """The robot poses given as quaternions in ROS's order [x, y, z, w] under ``q_wxyz``."""
    for f in doc["frames"]:
        T = T_from_ur_pose(f["T_base_tool"])
        xyzw = Rotation.from_matrix(T[:3, :3]).as_quat()
        f["T_base_tool"] = {"q_wxyz": xyzw.tolist(), "t_m": T[:3, 3].tolist()}


def kuka_angles_as_rpy(doc: dict) -> None:
    """The robot poses given as a KUKA's [A, B, C] (yaw, pitch, roll) under ``rpy_deg``."""
    for f in doc["frames"]:
        T = T_from_ur_pose(f["T_base_tool"])
        abc = Rotation.from_matrix(T[:3, :3]).as_euler("ZYX", degrees=True)
        f["T_base_tool"] = {"rpy_deg": abc.tolist(), "t_m": T[:3, 3].tolist()}


def mount_eye_to_hand(doc: dict) -> None:
    """An eye-in-hand session declared eye-to-hand."""
    doc["mount"] = "eye_to_hand"


def _run(cfg, work: Path, cell_seed: int, run_seed: int, plan=None):  # noqa: ANN001, ANN202
    """A run of the cell ``cell_seed`` (see :func:`same_cell`) and its session's problem;
    ``plan``: the plan (default: the planner's for ``cfg``)."""
    o = run_calibration(
        RunRequest(
            cfg,
            plan=plan,
            out_dir=work / f"run{cell_seed}_{run_seed}_{len(list(work.iterdir()))}",
            progress=False,
            recording=False,
            cell=same_cell(cfg, cell_seed, run_seed),
        )
    )
    return o, load_session(o.session_dir).problem


def _runs(n: int, work: Path, overrides: dict | None = None, first: int = 1):
    """``n`` runs with seeds ``first``.. (each its own arm and board pose)."""
    cfg = load_config(overrides=overrides)
    out = []
    for seed in range(first, first + n):
        o = run_calibration(
            RunRequest(
                cfg,
                out_dir=work / f"run{seed}_{len(list(work.iterdir()))}",
                progress=False,
                recording=False,
                seed=seed,
            )
        )
        out.append((o, load_session(o.session_dir).problem))
    return out


def _rate(k: int, n: int) -> str:
    return f"{k} / {n} ({100.0 * k / n:.1f} %)" if n else "0 / 0"


def _paired(v) -> tuple[bool, float, float]:  # noqa: ANN001
    """(paired test flagged, largest px, largest z) of a verdict's paired comparison."""
    info = v.installed.get("paired") if v.installed else None
    if not info or not info.get("usable"):
        return False, float("nan"), float("nan")
    cams = info["cameras"].values()
    flagged = any(c.test == "paired" and not c.passed for c in v.checks)
    return flagged, max(c["max_px"] for c in cams), max(c["max_z"] for c in cams)


def _span(xs: list[float], fmt: str) -> str:
    xs = [x for x in xs if np.isfinite(x)]
    return f"{min(xs):{fmt}}-{max(xs):{fmt}}" if xs else "-"


CASES = [("unchanged cell", {})] + list(CHANGES.items())
#: Not a camera change: the board moved since the install (a paired comparison flags it and
#: says that the camera changed or the board moved).
BOARD_MOVED = "board moved 1 mm, 0.2 deg"


def board_moved_overrides(mm: float = 1.0, deg: float = 0.2) -> dict:
    """The default cell with its board moved by ``mm`` along the base x and turned by ``deg``
    about its y axis (the default cell's true ``T_base_board`` changed)."""
    return {
        "simulation": {
            "T_base_board": {
                "rpy_deg": [180.0, 0.3 + deg, 2.0],
                "t_m": [-0.5609 + mm / 1000.0, 0.1262, 0.002],
            }
        }
    }


def part_gate(n: int, work: Path) -> list[str]:
    lim = Limits()
    t0 = time.monotonic()
    rows: dict[str, list] = {name: [] for name, _ in CASES}
    alone = alone_ext = 0
    plan = make_plan(load_config())  # the same for every run (the cell's plan: block)
    for seed in range(1, n + 1):
        inst, inst_problem = _run(load_config(), work, seed, 1, plan)
        alone += inst.verdict.verdict != "accepted"
        alone_ext += _extended(inst)
        for k, (name, ch) in enumerate(CASES):
            cfg = load_config(overrides=cell_overrides(**ch)) if ch else load_config()
            o, p = _run(cfg, work, seed, 2 + k, plan)
            v = judge(
                o.result,
                problem=p,
                installed=inst.result,
                installed_problem=inst_problem,
            )
            param = any(c.test == "installed" and not c.passed for c in v.checks)
            rows[name].append((v.verdict != "accepted", param, *_paired(v), _extended(o)))
    lines = [
        f"{n} simulated cells (cell seeds 1..{n}: each its own arm error and board pose). Per "
        "cell: an installed run, then a new run of the same cell (same arm, same board, same "
        "plan; fresh repeatability, image and detector noise) unchanged and with each change "
        "of the camera (the simulated truth changed); the new run's verdict against the "
        "installed one. 'paired': the corner-by-corner comparison at the poses both runs "
        f"share (drift: beyond {Z_LIMIT:g} sigma and {lim.max_change_px:g} px); 'parameters': "
        "the change of the parameters in combined sigmas (and px); 'extended': runs that "
        "missed a one-sigma limit with the plan's frames and extended their plan "
        "(docs/UNATTENDED.md).",
        "",
        "| case | flagged (drifted or rejected) | paired flagged | parameters flagged | "
        "paired px (min-max) | paired sigma (min-max) | extended |",
        "|---|---|---|---|---|---|---|",
        f"| installed run alone | {_rate(alone, n)} | - | - | - | - | {alone_ext} |",
    ]
    for name, ch in CASES:
        r = rows[name]
        flagged = sum(x[0] for x in r)
        what = (
            f"false rejects {_rate(flagged, n)}"
            if not ch
            else f"false accepts {_rate(n - flagged, n)}"
        )
        lines.append(
            f"| {name} | {_rate(flagged, n)}: {what} | {_rate(sum(x[2] for x in r), n)} | "
            f"{_rate(sum(x[1] for x in r), n)} | {_span([x[3] for x in r], '.2f')} | "
            f"{_span([x[4] for x in r], '.1f')} | {sum(x[5] for x in r)} |"
        )
    lines += ["", f"Took {time.monotonic() - t0:.0f} s ({5 * n} runs)."]
    return lines


def _extended(o) -> bool:  # noqa: ANN001 - a RunOutcome
    """Whether the run extended its plan (its verdict says so)."""
    return any(n.startswith("extending the plan") for n in o.verdict.notes)


def part_garbage(work: Path) -> list[str]:
    ((o, _),) = _runs(1, work)
    cases = [
        ("robot rotations in degrees", rotations_in_degrees),
        ("square size 0.025 m for a 0.030 m board", square_size(0.025)),
        ("square size 0.036 m for 0.030 m (= 0.025 given as 0.030)", square_size(0.036)),
        ("one robot pose 6 mm off (read before the arm settled)", pose_glitch(3, (5.0, 0.0, -3.0))),
        ("from frame 1 on, each image paired with the previous pose", poses_one_frame_late),
        ("robot poses written as T_tool_base", poses_inverted),
        ("quaternions in ROS's order [x, y, z, w] given as q_wxyz", quaternions_scalar_last),
        ("a KUKA's angles [A, B, C] given as rpy_deg", kuka_angles_as_rpy),
        ("eye-in-hand session declared eye_to_hand", mount_eye_to_hand),
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
    return lines + ["", *classic_square_rows()]


#: The tests issue 39 added: the verdict before them is the verdict of the others
NEW_TESTS = ("stereo", "intrinsics", "arm", "projection")


def _mistake_row(name: str, v) -> str:  # noqa: ANN001 - a Verdict
    old = [c for c in v.checks if c.test not in NEW_TESTS]
    quality = [c for c in old if c.test not in ("installed", "paired")]
    before = (
        "rejected"
        if not all(c.passed for c in quality)
        else ("drifted" if not all(c.passed for c in old) else "accepted")
    )
    why = "; ".join(c.message for c in v.reasons[:2]) or "; ".join(
        n for n in v.notes if "beyond the image area" in n
    )
    return f"| {name} | {before} | {v.verdict} | {why.replace('|', '/')} |"


def part_mistakes(work: Path, seeds: int) -> list[str]:
    """Issue 39's mistakes on good runs of the eye-to-hand cell (seeds 1..N) and the OAK-like
    stereo head (projected corners): the verdict without the tests the issue added, and now."""
    lines = [
        "Each mistake made on a good run (eye-to-hand cell, seeds 1..N; the stereo head: "
        "`oak_rig`, projected corners), judged as `slidecal solve` judges it. 'before': the "
        f"verdict without the tests issue 39 added ({', '.join(NEW_TESTS)}); 'now': with them.",
        "",
        "| mistake | before | now | first reasons (or the note on the image's corners) |",
        "|---|---|---|---|",
    ]
    cfg = load_packaged_cell("eye_to_hand_cell.yaml")
    sockets = {"left": "CAM_B", "right": "CAM_C"}
    for seed in range(1, seeds + 1):
        o = run_calibration(
            RunRequest(cfg, out_dir=work / f"m{seed}", progress=False, recording=False, seed=seed)
        )
        p = load_session(o.session_dir).problem
        K = o.result.cameras["cam"].K
        cases = [("none (the good run)", p)]
        cases += [
            (
                f"fx {100 * (f - 1):g} % longer from the middle frame on",
                focus_changed(p, "cam", K, f, len(p.frames) // 2),
            )
            for f in (1.01, 1.003)
        ]
        cases.append(("corners only in the central 35 % of the image", centre_only(p, 0.35)))
        for name, q in cases:
            lines.append(_mistake_row(f"{name}, seed {seed}", judge(calibrate(q), problem=q)))
        rig = sc.oak_rig(np.random.default_rng(seed)).problem
        for name, q in (
            ("stereo head, seed", rig),
            ("left and right swapped, seed", swap_cameras(rig, "left", "right")),
        ):
            lines.append(
                _mistake_row(f"{name} {seed}", judge(calibrate(q), problem=q, sockets=sockets))
            )
    return lines


def classic_square_rows() -> list[str]:
    """A classic hand-eye session (28 frames, each at its own orientation, on a simulated real
    arm: ``classic_real_arm``, seed 2001) solved and judged as ``slidecal solve`` does, its
    board described 2 % too small or too large: the hand-eye's error against the truth the
    session can know, in mm and in its reported standard deviations."""
    lines = [
        "A classic hand-eye session (28 frames, each at its own orientation, a simulated real "
        "arm: `classic_real_arm`, seed 2001), its board described 2 % too small or too large, "
        "solved and judged as `slidecal solve` does. Hand-eye error: its translation's "
        "distance from the truth the session can know (`effective_truth`), in mm and in its "
        "reported one-sigma.",
        "",
        "| session | board | verdict | exit | hand-eye error | first reasons |",
        "|---|---|---|---|---|---|",
    ]
    for mount in ("eye_in_hand", "eye_to_hand"):
        s = sc.classic_real_arm(np.random.default_rng(2001), eye_in_hand=mount == "eye_in_hand")
        t = s.problem.target
        for scale, board in ((1.0, "as printed"), (0.98, "2 % too small"), (1.02, "2 % too large")):
            problem = replace(
                s.problem,
                target=replace(
                    t, points_m=t.points_m * scale, square_size_m=t.square_size_m * scale
                ),
            )
            res = calibrate(problem)
            v = judge(res, problem=problem, command="solve")
            ra = res.robot_accuracy
            X, _ = sc.effective_truth(s, max(ra.rotation_deg, 1e-4), max(ra.translation_mm, 1e-3))
            err_mm = 1000.0 * float(np.linalg.norm(res.hand_eye.t_m - X[:3, 3]))
            why = "; ".join(c.message for c in v.reasons[:2]).replace("|", "/")
            lines.append(
                f"| classic {mount.replace('_', '-')} | {board} | {v.verdict} | {v.exit_code} | "
                f"{err_mm:.1f} mm ({err_mm / res.hand_eye.std_t_mm:.1f} sigma) | {why} |"
            )
    return lines


def _garbage_row(name: str, o) -> str:  # noqa: ANN001
    fx = float(next(iter(o.result.cameras.values())).K[0, 0])
    why = "; ".join(c.message for c in o.verdict.reasons[:2]).replace("|", "/")
    if not why:  # accepted: what it left out, if anything
        why = "; ".join(n for n in o.verdict.notes if LEFT_OUT in n).replace("|", "/")
    return f"| {name} | {o.verdict.verdict} | {o.exit_code} | {fx:.0f} | {why} |"


def part_check(n: int, work: Path) -> list[str]:
    t0 = time.monotonic()
    cases = [(name, cell_overrides(**ch) if ch else {}) for name, ch in CASES]
    cases.append((BOARD_MOVED, board_moved_overrides()))
    rows: dict[str, list] = {name: [] for name, _ in cases}
    plan = make_plan(load_config())
    not_installed: list[str] = []
    for seed in range(1, n + 1):
        o, p = _run(load_config(), work, seed, 1, plan)
        if o.verdict.verdict == "rejected":  # nothing to install, nothing to check against
            why = "; ".join(c.message for c in o.verdict.reasons[:1])
            not_installed.append(f"cell {seed}: {why}")
            continue
        store = work / f"store{seed}"
        info = {"chain_rms_px": chain_rms_px(o.result, p)}
        install(store, o.session_dir, o.result, o.verdict.verdict, info=info)
        for k, (name, ov) in enumerate(cases):
            cfg = load_config(overrides=ov)
            v, _ = run_check(
                cfg,
                store,
                work / f"chk_{len(list(work.iterdir()))}",
                progress=False,
                cell=same_cell(cfg, seed, 100 + k),
            )
            c = v.extra["check"]
            pi = (c.get("paired") or {}).get("cameras") or {}
            rows[name].append(
                (
                    v.verdict == "drifted",
                    bool(pi),
                    max((x["max_px"] for x in pi.values()), default=float("nan")),
                    max((x["max_z"] for x in pi.values()), default=float("nan")),
                    c["robot_time_s"],
                    c["frames"],
                )
            )
    lim = Limits()
    n_all, n = n, len(rows["unchanged cell"])
    lines = [
        f"{n_all} simulated cells (cell seeds 1..{n_all}). Per cell: one run installed, then "
        "`slidecal check` on the same cell (same arm, same board; fresh noise) unchanged, "
        "with each change of the camera, and with the board moved instead (a paired "
        "comparison cannot tell that from a camera change and says so). The check revisits "
        "poses of the installed session and compares corner by corner (drift: beyond "
        f"{Z_LIMIT:g} sigma and {lim.check_max_px:g} px).",
        "",
        "| case | verdict drifted | paired comparison made | paired px (min-max) | "
        "paired sigma (min-max) | frames | robot time (max) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, _ in cases:
        r = rows[name]
        drifted = sum(x[0] for x in r)
        what = {
            "unchanged cell": f"false rejects {drifted}",
            BOARD_MOVED: "not a camera change: reported as the camera or the board moved",
        }.get(name, f"false accepts {n - drifted}")
        lines.append(
            f"| {name} | {_rate(drifted, n)} ({what}) | {_rate(sum(x[1] for x in r), n)} | "
            f"{_span([x[2] for x in r], '.2f')} | {_span([x[3] for x in r], '.1f')} | "
            f"{max(x[5] for x in r)} | {max(x[4] for x in r):.1f} s |"
        )
    if not_installed:
        lines += [
            "",
            f"Not installed, so not checked: {len(not_installed)} of {n_all} cells whose "
            "installed run was itself rejected (the rates above are over the other "
            f"{n}): " + "; ".join(not_installed) + ".",
        ]
    lines += [
        "",
        f"Took {time.monotonic() - t0:.0f} s ({n_all} runs and {len(cases) * n} checks).",
    ]
    return lines


def _signal_row(sig: int, name: str, after: int, work: Path) -> str:
    out = work / f"sig_{name}_{after}"
    env = {**os.environ, "SLIDECAL_LOCK_DIR": str(work)}
    cmd = simulated_run_command(out)
    # a benchmark started in the background (no job control) hands its children SIGINT
    # ignored: slidecal's run installs its own Ctrl-C handler, so the row measures it either way
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
        o = run_calibration(
            RunRequest(cfg, out_dir=out, progress=False, recording=False, cell=cell)
        )
        code = f"completed, {o.verdict.verdict}"
    except HardwareFault:
        code = "HardwareFault (exit 3)"

    doc = yaml.safe_load((out / "session.yaml").read_text())  # also with no frame at all
    kinds = [e["kind"] for e in doc["events"]]
    kept = len(doc["frames"])
    resumed = ""
    if doc["status"] != "complete":
        r = run_calibration(RunRequest(cfg, resume=out, progress=False))
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
        "Faults injected in the simulated cell (in-process), then "
        "`run_calibration(RunRequest(resume=...))`:",
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
    """Replace the section of ``part`` in docs/results/VERDICT.md (created when missing)."""
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
    ap.add_argument(
        "--part", required=True, choices=("gate", "garbage", "check", "faults", "mistakes")
    )
    ap.add_argument("--seeds", type=int, default=10)
    args = ap.parse_args(argv)
    os.environ.setdefault("SLIDECAL_LOCK_DIR", tempfile.gettempdir())
    work = Path(tempfile.mkdtemp(prefix="slidecal_bench_verdict_"))
    try:
        if args.part == "gate":
            lines, cmd = part_gate(args.seeds, work), f"{COMMAND} --part gate --seeds {args.seeds}"
        elif args.part == "garbage":
            lines, cmd = part_garbage(work), f"{COMMAND} --part garbage"
        elif args.part == "check":
            lines, cmd = (
                part_check(args.seeds, work),
                f"{COMMAND} --part check --seeds {args.seeds}",
            )
        elif args.part == "mistakes":
            lines = part_mistakes(work, args.seeds)
            cmd = f"{COMMAND} --part mistakes --seeds {args.seeds}"
        else:
            lines, cmd = part_faults(work), f"{COMMAND} --part faults"
    finally:
        shutil.rmtree(work, ignore_errors=True)
    write_section(args.part, lines, cmd)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
