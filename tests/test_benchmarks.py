"""``slidecal bench NAME``: one command for every benchmark, one report header without paths."""

import importlib
import os

from slidecal.routines.benchmarks import BENCHMARKS, report_header
from slidecal.routines.cli import main


def test_every_benchmark_module_has_a_main():
    for name, (module, _) in BENCHMARKS.items():
        assert callable(importlib.import_module(module).main), name


def test_list_names_every_benchmark(capsys):
    assert main(["bench", "--list"]) == 0
    out = capsys.readouterr().out
    for name in BENCHMARKS:
        assert name in out


def test_header_names_versions_and_machine_but_no_path():
    lines = report_header("A title", "run", ["--seeds", "3"], 12.0)
    text = "\n".join(lines)
    assert lines[0] == "# A title"
    assert "`slidecal bench run --seeds 3`" in text
    assert "numpy" in text and "opencv" in text and "cores" in text
    assert os.getcwd() not in text and "/" not in text.replace("slidecal bench", "")


def test_scale_session_has_the_requested_frames_and_cameras():
    from slidecal.routines.bench_scale import session

    p = session(45, 2)
    assert len(p.frames) == 45 and [f.id for f in p.frames] == list(range(45))
    assert {c.name for c in p.cameras} == {"left", "right"}
