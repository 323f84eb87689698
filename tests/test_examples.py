"""The shipped example scripts run as their docstrings say."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).parents[1] / "examples"


@pytest.mark.slow
def test_commissioning_example_reads_the_verdict_and_installs(tmp_path: Path) -> None:
    env = {**os.environ, "SLIDECAL_LOCK_DIR": str(tmp_path)}
    p = subprocess.run(
        [sys.executable, str(EXAMPLES / "commission.py"), "--out", str(tmp_path / "s"),
         "--install", str(tmp_path / "store")],
        capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300,
    )
    assert p.returncode == 0, p.stderr
    assert "verdict: accepted" in p.stdout and "installed:" in p.stdout
    assert (tmp_path / "store" / "current" / "result.yaml").is_file()
    assert (tmp_path / "s" / "verdict.yaml").is_file()
