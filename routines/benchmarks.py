"""Run a benchmark: ``slidecal bench NAME [options]`` (``slidecal bench --list`` names them).

Every benchmark is a module with ``main(argv) -> int`` that writes a markdown report; this command
dispatches to it and gives every report the same header: the command that regenerates it, the
versions of slidecal and of the libraries that decide the figures, and the kind of machine
(architecture, cores, operating system), never a path of this machine.
"""

from __future__ import annotations

import argparse
import importlib
import os
import platform
import sys
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path

#: benchmark name -> (module, what it measures)
BENCHMARKS: dict[str, tuple[str, str]] = {
    "solver": (
        "slidecal.routines.bench",
        "Monte Carlo S1-S4 and R1 against the Cramer-Rao bound; solve time against OpenCV",
    ),
    "run": ("slidecal.routines.bench_run", "slidecal run on a simulated cell over many seeds"),
    "planner": ("slidecal.routines.bench_planner", "the planner's prediction against Monte Carlo"),
    "stereo": ("slidecal.routines.bench_stereo", "S5: the linear stereo method, joint vs alone"),
    "rig": ("slidecal.routines.bench_rig", "rig maximum likelihood against the bound; OAK cell"),
    "handeye": (
        "slidecal.routines.bench_handeye",
        "classic hand-eye sessions against the bound and cv2.calibrateHandEye",
    ),
    "detect": (
        "slidecal.routines.bench_detect",
        "detection paths: corner bias and rms on rendered images, time per 2 MP image",
    ),
    "reality": (
        "slidecal.routines.bench_reality",
        "coverage of the reported std on a simulated real arm; clean efficiency; speed",
    ),
    "faults": ("slidecal.routines.faults", "each injected hardware fault in run and rehearse"),
    "verdict": (
        "slidecal.routines.bench_verdict",
        "the verdict's gate, garbage sessions, slidecal check, signals and faults",
    ),
    "scale": ("slidecal.routines.bench_scale", "solve time from 20 to 1000 frames, 1-3 cameras"),
    "public": (
        "slidecal.routines.bench_public",
        "real robot data: the public KUKA sessions (data not shipped: --data DIR)",
    ),
}

help = "run a benchmark and write its report (slidecal bench --list names them)"

#: the libraries whose versions a report names
_LIBRARIES = ("numpy", "scipy", "opencv-python-headless")


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "absent"


def shown_out(out: str | os.PathLike[str]) -> str:
    """A report's ``--out`` as its header shows it: a path inside the project as given, any
    other (a scratch folder, a home directory) as the report's place under ``docs/``, so no
    path of this machine reaches a committed report."""
    text = os.fspath(out)
    parts = Path(text).parts
    if not Path(text).is_absolute() and ".." not in parts and not text.startswith("~"):
        return text
    return "docs/" + ("" if text.endswith(("/", os.sep)) else Path(text).name)


def bench_command(name: str, argv: Sequence[str] | None) -> str:
    """The command line that regenerates benchmark ``name`` with these options (an ``--out``
    outside the project shown as its place under ``docs/``: :func:`shown_out`)."""
    args = list(sys.argv[1:] if argv is None else argv)
    for i, a in enumerate(args):
        if a.startswith("--out="):
            args[i] = "--out=" + shown_out(a.removeprefix("--out="))
        elif i > 0 and args[i - 1] == "--out":
            args[i] = shown_out(a)
    return " ".join(["slidecal bench", name, *args])


def report_header(title: str, name: str, argv: Sequence[str] | None, elapsed_s: float) -> list[str]:
    """The first lines of every benchmark report (markdown): title, command, versions, machine."""
    libs = ", ".join(f"{d.removesuffix('-python-headless')} {_version(d)}" for d in _LIBRARIES)
    machine = (
        f"{platform.machine()}, {os.cpu_count()} cores, {platform.system()}, "
        f"Python {platform.python_version()}"
    )
    return [
        f"# {title}",
        "",
        f"Regenerate with `{bench_command(name, argv)}` (slidecal {_version('slidecal')}; "
        f"{libs}; {machine}; this run took {elapsed_s:.0f} s).",
        "",
    ]


def publish_report(text: str, out: str | os.PathLike[str] | None) -> int:
    """Print a benchmark's report and, when ``out`` is given, write it there (its folder made
    if missing); the benchmark's exit status (0)."""
    print(text)
    if out:
        path = Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    return 0


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``slidecal bench``."""
    p.add_argument("name", nargs="?", choices=sorted(BENCHMARKS), help="the benchmark to run")
    p.add_argument("--list", action="store_true", help="list the benchmarks and what they measure")
    p.add_argument(
        "options", nargs=argparse.REMAINDER, help="the benchmark's own options (NAME --help)"
    )


def main(args: argparse.Namespace) -> int:
    """Entry point of ``slidecal bench``."""
    if args.list or not args.name:
        width = max(len(n) for n in BENCHMARKS)
        for n, (_, what) in sorted(BENCHMARKS.items()):
            print(f"{n:<{width}}  {what}")
        return 0
    module = importlib.import_module(BENCHMARKS[args.name][0])
    return int(module.main(list(args.options)) or 0)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(prog="slidecal bench", description=__doc__.splitlines()[0])
    add_arguments(ap)
    sys.exit(main(ap.parse_args()))
