"""What every benchmark report shares: where it goes (``docs/results/``) and its header (the
command that regenerates it, the versions of slidecal and of the libraries that decide the
figures, and the kind of machine: architecture, cores, operating system; never a path of this
machine). The benchmarks are studies run from a checkout (``python -m tests.bench NAME``); the
package never imports them.
"""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path

#: The folder the reports go to unless ``--out`` says otherwise.
RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results"

#: benchmark name (its module in this folder) -> what it measures
BENCHMARKS: dict[str, str] = {
    "solver": "Monte Carlo S1-S4 and R1 against the Cramer-Rao bound; solve time against OpenCV",
    "run": "slidecal run on a simulated cell over many seeds",
    "planner": "the planner's prediction against Monte Carlo",
    "stereo": "S5: the linear stereo method, joint vs alone",
    "rig": "rig maximum likelihood against the bound; OAK cell",
    "handeye": "classic hand-eye sessions against the bound and cv2.calibrateHandEye",
    "detect": "detection paths: corner bias and rms on rendered images, time per 2 MP image",
    "reality": "coverage of the reported std on a simulated real arm; clean efficiency; speed",
    "faults": "each injected hardware fault in run and rehearse",
    "verdict": "the verdict's gate, garbage sessions, slidecal check, signals and faults",
    "scale": "solve time from 20 to 1000 frames, 1-3 cameras",
    "public": "real robot data: the public KUKA sessions (data not shipped: --data DIR)",
    "bad_input": "every malformed file and option: refused in one line naming file and field",
    "split_half": "honesty on real images: split a session at random, z of the halves' difference",
    "speed": "slidecal solve against an OpenCV script, whole process and in process; load time",
}


#: the libraries whose versions a report names
_LIBRARIES = ("numpy", "scipy", "opencv-python-headless")


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "absent"


def shown_out(out: str | os.PathLike[str]) -> str:
    """A report's ``--out`` as its header shows it: a path inside the project as given, any
    other (a scratch folder, a home directory) as the report's place under ``docs/results/``, so
    no path of this machine reaches a committed report."""
    text = os.fspath(out)
    parts = Path(text).parts
    if not Path(text).is_absolute() and ".." not in parts and not text.startswith("~"):
        return text
    return "docs/results/" + ("" if text.endswith(("/", os.sep)) else Path(text).name)


def bench_command(name: str, argv: Sequence[str] | None) -> str:
    """The command line that regenerates benchmark ``name`` with these options (an ``--out``
    outside the project shown as its place under ``docs/results/``: :func:`shown_out`)."""
    args = list(sys.argv[1:] if argv is None else argv)
    for i, a in enumerate(args):
        if a.startswith("--out="):
            args[i] = "--out=" + shown_out(a.removeprefix("--out="))
        elif i > 0 and args[i - 1] == "--out":
            args[i] = shown_out(a)
    return " ".join(["python -m tests.bench", name, *args])


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
    """Print a benchmark's report and, when ``out`` is given (every benchmark's default is its
    page in :data:`RESULTS`), write it there (its folder made if missing); exit status 0."""
    print(text)
    if out:
        path = Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
    return 0
