"""The morning report: self-contained HTML and a PNG, rendered in a real headless browser."""

from __future__ import annotations

import dataclasses
import re
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from slidecal.routines.ops.report import residual_vectors, uncertainty_map, write_report
from slidecal.routines.ops.verdict import judge
from slidecal.routines.session import load_session
from slidecal.routines.solve import solve_session
from slidecal.solver.result import RobotAccuracy

DATA = Path(__file__).parent / "data"
CHROMIUM = next(
    (shutil.which(n) for n in ("chromium", "chromium-browser") if shutil.which(n)), None
)


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    d = tmp_path_factory.mktemp("rep") / "s"
    shutil.copytree(DATA / "r1_session", d)
    return solve_session(d), load_session(d).problem


def test_report_is_self_contained(solved) -> None:
    o, _ = solved
    text = o.report_path.read_text()
    assert o.report_path == o.session_dir / "report.html"
    assert "ACCEPTED" in text and "Every test" in text
    # no network, no files beside it: every image inline, no external reference at all
    assert not re.search(r"(src|href)\s*=\s*['\"](?!data:)", text)
    assert "http://" not in text and "https://" not in text
    assert text.count("data:image/png;base64,") >= 2
    png = cv2.imread(str(o.session_dir / "report.png"))
    assert png is not None and png.shape[1] == 1120


def test_residuals_match_the_solver(solved) -> None:
    o, problem = solved
    at, res = residual_vectors(o.result, problem, "cam")
    n = sum(len(f.detections["cam"].ids) for f in problem.frames)
    assert at.shape == (n, 2)
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    # the chain includes the measured robot poses' noise (0.05 mm, 0.005 deg at 0.5 m: about
    # 0.1 px) on top of the detector's; far below a pixel, far above zero
    assert 0.02 < rms < 0.5


def test_uncertainty_map_grows_towards_the_corners(solved) -> None:
    o, _ = solved
    m = uncertainty_map(o.result, "cam")
    assert m is not None and m.shape == (20, 32)
    assert m[0, 0] > 2 * m[10, 16] > 0  # extrapolated distortion at the corners


def test_report_with_reasons_robot_accuracy_and_installed(solved, tmp_path: Path) -> None:
    o, problem = solved
    ra = RobotAccuracy(0.06, 0.006, ((3, 0.12, 0.01), (0, 0.05, 0.004)), True)
    r = dataclasses.replace(o.result, converged=False, robot_accuracy=ra)
    v = judge(r, problem=problem, installed=o.result)
    path = write_report(tmp_path, r, v, problem, o.result, "summary text")
    text = path.read_text()
    assert "REJECTED" in text and "did NOT converge" in text
    assert "Robot accuracy per frame" in text and "Against the installed calibration" in text


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium binary (CI: apt-get install chromium)")
def test_report_renders_in_headless_chromium(solved, tmp_path: Path) -> None:
    o, _ = solved
    shot = tmp_path / "shot.png"
    p = subprocess.run(
        [
            CHROMIUM,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-dev-shm-usage",
            "--user-data-dir=" + str(tmp_path / "profile"),
            f"--screenshot={shot}",
            "--window-size=1200,1400",
            o.report_path.resolve().as_uri(),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert shot.is_file(), p.stderr[-2000:]
    img = cv2.imread(str(shot))
    assert img.shape[:2] == (1400, 1200)
    # the verdict banner is drawn (the accepted green across the top) and images rendered
    # (many colours: the residual plot and the viridis map), not a blank or error page
    banner = img[30:60, 40:1100].reshape(-1, 3).mean(axis=0)
    assert banner[1] > 140 and banner[0] < 100 and banner[2] < 100, banner
    colours = len(np.unique((img // 16).reshape(-1, 3), axis=0))
    assert colours > 40
    shutil.copy(shot, o.session_dir / "report_screenshot.png")
