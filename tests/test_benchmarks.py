"""``python -m tests.bench NAME``: one command, run from a checkout, for every benchmark (the
studies of tests/bench/; no test imports them, they run here as a user runs them)."""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
NAMES = ("bad_input", "detect", "faults", "handeye", "planner", "public", "reality", "rig", "run",
         "scale", "solver", "split_half", "stereo", "verdict")


def bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tests.bench", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)


def test_list_names_every_benchmark():
    o = bench("--list")
    assert o.returncode == 0, o.stderr
    for name in NAMES:
        assert f"\n{name} " in "\n" + o.stdout


#: Every benchmark's ``--help`` through ``python -m tests.bench``'s own entry point, in one
#: interpreter: each process mostly imported numpy, scipy and OpenCV again.
HELP_ALL = textwrap.dedent(
    """
    import contextlib, io, json, sys
    from tests.bench.__main__ import main
    out = {}
    for name in sys.argv[1:]:
        text = io.StringIO()
        try:
            with contextlib.redirect_stdout(text):
                code = main([name, "--help"])
        except SystemExit as e:
            code = e.code
        out[name] = [code, text.getvalue()]
    print(json.dumps(out))
    """
)


def test_every_benchmark_takes_help():
    o = subprocess.run([sys.executable, "-c", HELP_ALL, *NAMES], cwd=ROOT, capture_output=True,
                       text=True, timeout=120)
    assert o.returncode == 0, o.stderr
    helps = json.loads(o.stdout)
    for name in NAMES:
        code, out = helps[name]
        assert code == 0 and "usage" in out, (name, out, o.stderr)


def test_public_data_bench_names_missing_data_in_one_line(tmp_path):
    # the public KUKA data is not shipped: a folder without it is refused with what to give
    o = bench("public", "--data", str(tmp_path))
    assert o.returncode == 2 and "Traceback" not in o.stderr
    assert "kuka_1, kuka_2 and kuka_3" in o.stderr and len(o.stderr.strip().splitlines()) == 1


def test_split_half_runs_on_a_session_and_reports_without_local_paths(tmp_path):
    # a simulated session with robot poses: z per intrinsic and per hand-eye axis, OpenCV's beside
    out = tmp_path / "SPLIT.md"
    o = bench("split_half", "tests/data/r1_session", "--seeds", "2", "--out", str(out))
    assert o.returncode == 0, o.stderr
    text = out.read_text()
    assert "`python -m tests.bench split_half tests/data/r1_session --seeds 2 --out " \
           "docs/results/SPLIT.md`" in text
    assert str(tmp_path) not in text
    for row in ("| fx |", "| cy |", "| hand-eye rx |", "| hand-eye tz |"):
        assert row in text
    assert "0 split(s) where a half did not solve" in text
