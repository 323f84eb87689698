"""How fast a session is read and solved, against OpenCV on the same session.

``python -m tests.bench speed [--frames 24 400 1000] [--repeats 3] [--out docs/results/SPEED.md]``
(or ``python tests/bench/speed.py ...``) writes simulated sessions of R1's eye-in-hand cell (its
20 poses repeated with fresh corner and arm noise until the session has the frames asked for)
with the session writer, then measures per size:

- whole process: ``slidecal solve SESSION`` against a script that reads the same session
  (``session.yaml`` with PyYAML's C loader, the corners from the file it names or inline) and
  runs ``cv2.calibrateCamera`` and ``cv2.calibrateHandEye`` (Park); median of ``--repeats``
  runs, the two interleaved;
- the session's load alone (``load_session``, in this process, median);
- in this process, the default solve (``calibrate``: the arm's accuracy learned) against
  ``cv2.calibrateCamera`` on the same detections (medians, interleaved).

The report (markdown) gives each figure beside its target.
"""

from __future__ import annotations

import argparse
import os
import pstats
import resource
import statistics
import subprocess
import sys
import tempfile
import textwrap
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

import slidecal.routines
from slidecal.mocks.scenarios import r1
from slidecal.routines.session import load_session
from slidecal.solver.calibrate import calibrate
from slidecal.solver.problem import CalibrationProblem
from tests.session_io import write_session

#: Whole-process time of ``slidecal solve`` over the OpenCV script's, per frame count at most
WHOLE_TARGET = {24: 2.0, 400: 1.2, 1000: 1.0}
#: In-process default solve over ``cv2.calibrateCamera``, at most, at every size
SOLVE_TARGET = 2.0
#: Seconds a 1000-frame session may take to load
LOAD_TARGET_S = 0.5
#: The checkout's root (``routines/``, ``solver/`` ... beside each other): profiled files' names
ROOT = Path(slidecal.routines.__file__).resolve().parent.parent

#: The OpenCV side of the comparison: read the session as a user's script would, calibrate the
#: camera, then the hand-eye (Park). argv: the session directory.
OPENCV_SCRIPT = textwrap.dedent(
    """
    import sys
    from pathlib import Path

    import cv2
    import numpy as np
    import yaml

    d = Path(sys.argv[1])
    doc = yaml.load((d / "session.yaml").read_text(), Loader=yaml.CSafeLoader)
    t = doc["target"]
    cols, rows = t["squares_x"] - 1, t["squares_y"] - 1
    c, r = np.meshgrid(np.arange(cols), np.arange(rows))
    board = np.column_stack(
        [(c.ravel() + 1) * t["square_size_m"], (r.ravel() + 1) * t["square_size_m"],
         np.zeros(cols * rows)]
    ).astype(np.float32)
    cam = doc["cameras"][0]
    table = np.load(d / doc["detections_file"]) if doc.get("detections_file") else None
    if table is not None:  # the first camera's rows, grouped by frame
        table = table[table["camera"] == 0]
        table = table[np.argsort(table["frame"], kind="stable")]
        fids, starts = np.unique(table["frame"], return_index=True)
        at = dict(zip(fids.tolist(), zip(starts, np.r_[starts[1:], len(table)])))
    obj, img, R_g, t_g = [], [], [], []
    for f in doc["frames"]:
        det = f["detections"][cam["name"]]
        if isinstance(det, dict):
            ids, px = np.array(det["ids"], int), np.array(det["px"], np.float32)
        else:
            rows_f = table[slice(*at.get(f["id"], (0, 0)))]
            ids, px = rows_f["id"], np.column_stack([rows_f["u"], rows_f["v"]])
        if len(ids) < 6:
            continue
        obj.append(board[ids])
        img.append(px.astype(np.float32))
        p = np.array(f["T_base_tool"], float)
        R_g.append(cv2.Rodrigues(p[3:])[0])
        t_g.append(p[:3])
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        obj, img, (cam["width"], cam["height"]), None, None
    )
    R_c = [cv2.Rodrigues(v)[0] for v in rvecs]
    R, tv = cv2.calibrateHandEye(R_g, t_g, R_c, tvecs, method=cv2.CALIB_HAND_EYE_PARK)
    print(rms, K[0, 0], tv.ravel())
    """
)


def simulated_problem(n_frames: int, seed: int = 7) -> CalibrationProblem:
    """R1's eye-in-hand session with ``n_frames`` frames: its 20 poses repeated, fresh corner
    and arm noise each time (the default model: the arm's accuracy is learned)."""
    rng = np.random.default_rng(seed)
    frames: list = []
    base = None
    while len(frames) < n_frames:
        s = r1(rng)
        base = base or s.problem
        for f in s.problem.frames[: n_frames - len(frames)]:
            frames.append(replace(f, id=len(frames)))
    assert base is not None
    return replace(base, frames=tuple(frames))


#: The processes' environment: Python's bytecode cached as an installed package has it (a
#: PYTHONDONTWRITEBYTECODE environment would compile every module of slidecal at each start)
ENV = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def _run_s(argv: list[str]) -> tuple[float, float]:
    """Wall and CPU seconds (user + system) of a process."""
    cpu = _children_cpu_s()
    t = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, env=ENV)
    dt = time.perf_counter() - t
    if done.returncode not in (0, 1):  # 1: solved but not accepted by the verdict
        raise RuntimeError(f"{' '.join(argv)} failed ({done.returncode}): {done.stderr[-400:]}")
    return dt, _children_cpu_s() - cpu


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _opencv_s(problem: CalibrationProblem) -> tuple[float, float, float]:
    """Seconds of ``cv2.calibrateCamera`` on the first camera's detections, and of
    ``cv2.calibrateHandEye`` (Park) on its board poses and the robot's; then the CPU seconds
    of ``cv2.calibrateCamera``."""
    name = problem.cameras[0].name
    obj, img, R_g, t_g = [], [], [], []
    for f in problem.frames:
        d = f.detections.get(name)
        if d is not None and len(d.ids) >= 6:
            obj.append(problem.target.points_m[d.ids].astype(np.float32))
            img.append(d.px.astype(np.float32))
            R_g.append(f.T_base_tool[:3, :3])
            t_g.append(f.T_base_tool[:3, 3])
    spec = problem.cameras[0]
    t, cpu = time.perf_counter(), time.process_time()
    _, _, _, rvecs, tvecs = cv2.calibrateCamera(obj, img, (spec.width, spec.height), None, None)
    camera_s, camera_cpu_s = time.perf_counter() - t, time.process_time() - cpu
    R_c = [cv2.Rodrigues(v)[0] for v in rvecs]
    t = time.perf_counter()
    cv2.calibrateHandEye(R_g, t_g, R_c, tvecs, method=cv2.CALIB_HAND_EYE_PARK)
    return camera_s, time.perf_counter() - t, camera_cpu_s


def measure(n_frames: int, work: Path, repeats: int) -> dict[str, float]:
    """Every figure of one session size (seconds, medians of ``repeats``)."""
    session = work / f"session_{n_frames}"
    t = time.perf_counter()
    write_session(session, simulated_problem(n_frames), overwrite=True)
    written_s = time.perf_counter() - t
    session_mb = sum(p.stat().st_size for p in session.iterdir() if p.is_file()) / 1e6
    script = work / "opencv_script.py"
    script.write_text(OPENCV_SCRIPT)
    solve = [
        sys.executable, "-m", "slidecal.routines.cli", "solve", str(session),
        "--out", str(work / f"result_{n_frames}.yaml"), "--force",
    ]  # fmt: skip
    ours, theirs, loads, solves, cvs, hes, solve_cpu, cv_cpu = [], [], [], [], [], [], [], []
    _run_s(solve)  # writes the bytecode caches, once
    for _ in range(repeats):
        ours.append(_run_s(solve))
        theirs.append(_run_s([sys.executable, str(script), str(session)]))
    (ours, ours_cpu), (theirs, theirs_cpu) = zip(*ours, strict=True), zip(*theirs, strict=True)
    for _ in range(repeats):
        t = time.perf_counter()
        problem = load_session(session).problem
        loads.append(time.perf_counter() - t)
    calibrate(problem)  # warm caches alike for both
    for _ in range(repeats):
        t, cpu = time.perf_counter(), time.process_time()
        calibrate(problem)
        solves.append(time.perf_counter() - t)
        solve_cpu.append(time.process_time() - cpu)
        camera_s, hand_eye_s, camera_cpu_s = _opencv_s(problem)
        cvs.append(camera_s)
        hes.append(hand_eye_s)
        cv_cpu.append(camera_cpu_s)
    med = statistics.median
    return {
        "frames": n_frames,
        "write_s": written_s,
        "session_mb": session_mb,
        "slidecal_s": med(ours),
        "opencv_script_s": med(theirs),
        "slidecal_cpu_s": med(ours_cpu),
        "opencv_script_cpu_s": med(theirs_cpu),
        "load_s": med(loads),
        "calibrate_s": med(solves),
        "calibrate_camera_s": med(cvs),
        "hand_eye_s": med(hes),
        "calibrate_cpu_s": med(solve_cpu),
        "calibrate_camera_cpu_s": med(cv_cpu),
    }


#: The parts of a solve the profile reports whole (cumulative seconds): file, function
PHASES = (
    ("<frozen importlib._bootstrap>", "_find_and_load", "imports (all, lazy ones included)"),
    ("routines/session.py", "load_session", "load_session"),
    ("routines/schema.py", "load_yaml", "load_yaml (every YAML file read)"),
    ("solver/calibrate.py", "calibrate", "calibrate"),
    ("solver/refine.py", "refine", "calibrate: refine"),
    ("solver/adequacy.py", "free_pose_fit", "calibrate: free_pose_fit"),
    ("routines/run.py", "finish_solve", "finish_solve"),
    ("routines/ops/report.py", "write_report", "finish_solve: write_report"),
    ("routines/results_io.py", "write_result", "finish_solve: write_result"),
    ("routines/exports.py", "write_all_exports", "finish_solve: write_all_exports"),
)


def profile(session: Path, out: Path, top: int = 20) -> str:
    """``slidecal solve`` of ``session`` as a whole process under cProfile, as markdown: the
    phases' cumulative seconds, then modules and functions by own seconds."""
    prof = out.with_suffix(".prof")
    _run_s(
        [sys.executable, "-m", "cProfile", "-o", str(prof), "-m", "slidecal.routines.cli",
         "solve", str(session), "--out", str(out), "--force"]
    )  # fmt: skip
    stats = pstats.Stats(str(prof)).stats  # type: ignore[attr-defined]
    by_module: dict[str, float] = {}
    phases: dict[str, float] = {}
    rows = []
    for (path, line, name), (_, _, own, cum, _) in stats.items():
        where = _short_path(path)
        by_module[where] = by_module.get(where, 0.0) + own
        rows.append((own, cum, f"{where}:{line}({name})"))
        for file, function, label in PHASES:
            if where == file and name == function:
                phases[label] = phases.get(label, 0.0) + cum
    total = sum(by_module.values())
    lines = [
        f"cProfile of `slidecal solve` on the {session.name[8:]}-frame session (seconds; the "
        "phases overlap: an import inside a phase counts in both):",
        "",
    ]
    lines += ["| phase | cumulative s |", "| --- | ---: |", f"| whole process | {total:.2f} |"]
    lines += [f"| {label} | {phases.get(label, 0.0):.3f} |" for _, _, label in PHASES]
    lines += ["", "| module | own s |", "| --- | ---: |"]
    for where, sec in sorted(by_module.items(), key=lambda kv: -kv[1])[:top]:
        lines.append(f"| {where} | {sec:.3f} |")
    lines += ["", "| function | own s | cumulative s |", "| --- | ---: | ---: |"]
    for own, cum, name in sorted(rows, reverse=True)[:top]:
        lines.append(f"| {name} | {own:.3f} | {cum:.3f} |")
    return "\n".join(lines) + "\n"


def _short_path(path: str) -> str:
    """A profiled file as ``routines/run.py`` or ``numpy/linalg/_linalg.py``; C functions
    (NumPy's, OpenCV's, Python's built-ins) as ``C code``."""
    p = Path(path)
    if path == "~":
        return "C code"
    if "site-packages" in p.parts:
        return "/".join(p.parts[p.parts.index("site-packages") + 1 :])
    if p.is_relative_to(ROOT):
        return p.relative_to(ROOT).as_posix()
    return "/".join(p.parts[-2:]) if p.is_absolute() else path


def report(rows: list[dict[str, float]], repeats: int) -> str:
    """The markdown report of ``rows`` (one per session size)."""
    lines = [
        "# Speed: reading and solving a session, against OpenCV",
        "",
        "Generated by `python -m tests.bench speed` (tests/bench/speed.py): R1's eye-in-hand "
        "cell, one camera, sessions written by the session writer; medians of "
        f"{repeats} runs, slidecal and OpenCV interleaved. Whole process: `slidecal solve "
        "SESSION` against a script that reads the same session (PyYAML C loader) and runs "
        "`cv2.calibrateCamera` + `cv2.calibrateHandEye` (Park). In process: the default "
        "solve (`calibrate`, the arm's accuracy learned) against `cv2.calibrateCamera` on the "
        "same detections; `cv2.calibrateHandEye` s: in process, the script's hand-eye alone "
        "(OpenCV's Park takes every pair of frames: it grows as frames squared). The machine "
        "the figures come from may be shared: compare figures of one run; CPU: the whole "
        "processes' CPU seconds (user + system), and in process the CPU seconds of `calibrate` "
        "and of `cv2.calibrateCamera`, steadier than wall time on a busy machine.",
        "",
        "| frames | session MB | slidecal solve s | OpenCV script s | ratio (target) "
        "| load s (target) | calibrate s | cv2.calibrateCamera s | ratio (target) "
        "| cv2.calibrateHandEye s | CPU s: slidecal / script (ratio) "
        "| in-process CPU s: calibrate / cv2.calibrateCamera (ratio) |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        n = int(r["frames"])
        whole = r["slidecal_s"] / r["opencv_script_s"]
        inproc = r["calibrate_s"] / r["calibrate_camera_s"]
        load_target = f" (<= {LOAD_TARGET_S})" if n >= 1000 else ""
        lines.append(
            f"| {n} | {r['session_mb']:.2f} | {r['slidecal_s']:.2f} | "
            f"{r['opencv_script_s']:.2f} | {whole:.2f} (<= {WHOLE_TARGET.get(n, '-')}) | "
            f"{r['load_s']:.3f}{load_target} | {r['calibrate_s']:.2f} | "
            f"{r['calibrate_camera_s']:.2f} | {inproc:.2f} (<= {SOLVE_TARGET}) | "
            f"{r['hand_eye_s']:.2f} | {r['slidecal_cpu_s']:.2f} / {r['opencv_script_cpu_s']:.2f} "
            f"({r['slidecal_cpu_s'] / r['opencv_script_cpu_s']:.2f}) | "
            f"{r['calibrate_cpu_s']:.2f} / {r['calibrate_camera_cpu_s']:.2f} "
            f"({r['calibrate_cpu_s'] / r['calibrate_camera_cpu_s']:.2f}) |"
        )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Measure, print and write the report; 0 when every target holds, else 1."""
    ap = argparse.ArgumentParser(prog="speed", description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[24, 400, 1000])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("docs/results/SPEED.md"))
    ap.add_argument(
        "--profile", action="store_true", help="add a cProfile of the largest session's solve"
    )
    a = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in a.frames:
            rows.append(measure(n, Path(tmp), a.repeats))
            print(rows[-1], flush=True)
        text = report(rows, a.repeats)
        if a.profile:
            n = max(a.frames)
            text += "\n" + profile(Path(tmp) / f"session_{n}", Path(tmp) / "profiled.yaml")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(text)
    print(text)
    held = all(
        r["slidecal_s"] / r["opencv_script_s"] <= WHOLE_TARGET.get(int(r["frames"]), np.inf)
        and r["calibrate_s"] / r["calibrate_camera_s"] <= SOLVE_TARGET
        and (r["frames"] < 1000 or r["load_s"] <= LOAD_TARGET_S)
        for r in rows
    )
    return 0 if held else 1


if __name__ == "__main__":
    sys.exit(main())
