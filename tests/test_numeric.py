"""solver.numeric against scipy, whose functions it stands in for on the command's path."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import least_squares as scipy_least_squares
from scipy.special import chdtrc, fdtrc

from slidecal.solver.numeric import chi2_tail, f_tail, least_squares, median


def _rel(a: float, b: float) -> float:
    return abs(a - b) / a if a > 1e-250 else abs(a - b)


@pytest.mark.parametrize("dof", [1, 2, 3, 6, 30, 1000, 40000])
def test_chi2_tail_is_scipys(dof):
    for v in np.r_[0.0, np.geomspace(1e-3, 1e5, 40)]:
        assert _rel(chdtrc(dof, v), chi2_tail(dof, v)) < 1e-9


@pytest.mark.parametrize("d1", [1, 3, 12, 300])
@pytest.mark.parametrize("d2", [1, 5, 100, 20000])
def test_f_tail_is_scipys(d1, d2):
    for v in np.r_[0.0, np.geomspace(1e-3, 1e4, 40)]:
        assert _rel(fdtrc(d1, d2, v), f_tail(d1, d2, v)) < 1e-8


def test_least_squares_reaches_scipys_minimum():
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 4.0, 60)
    y = 2.5 * np.exp(-1.3 * t) * np.cos(3.0 * t + 0.4) + 0.01 * rng.normal(size=t.size)

    def f(p):
        return p[0] * np.exp(-p[1] * t) * np.cos(p[2] * t + p[3]) - y

    x0 = np.array([2.0, 1.0, 2.8, 0.0])
    ours, theirs = least_squares(f, x0), scipy_least_squares(f, x0)
    assert ours.fun @ ours.fun <= (theirs.fun @ theirs.fun) * (1 + 1e-9)
    np.testing.assert_allclose(ours.x, theirs.x, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(ours.jac, theirs.jac, rtol=1e-4, atol=1e-6)


def test_a_solve_imports_no_scipy():
    # scipy's import costs a small session's whole solve (see solver/numeric.py)
    code = "import sys, slidecal.routines.solve; print([m for m in sys.modules if 'scipy' in m])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_median_is_numpys_without_importing_numpy_ma():
    # np.median imports numpy.ma at its first call, which a command's start pays for
    rng = np.random.default_rng(0)
    cases = [rng.normal(size=n) for n in (1, 2, 7, 50, 51)] + [[3, 1, 2, 8], [1.0, np.nan, 2.0]]
    for x in cases:
        np.testing.assert_equal(median(x), np.median(x))  # bit for bit, NaN as NaN
    code = "import sys; from slidecal.solver.numeric import median; median([2, 1]); "
    code += "print('numpy.ma' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_a_solve_imports_no_numpy_ma(tmp_path):
    # np.median and a plain np.unique import numpy.ma at their first call (solver/numeric.py)
    session = tmp_path / "r1_session"
    shutil.copytree(Path(__file__).parent / "data" / "r1_session", session)
    code = (
        "import runpy, sys; sys.argv = ['slidecal', 'solve', sys.argv[1]]\n"
        "try:\n    runpy.run_module('slidecal.routines.cli', run_name='__main__')\n"
        "except SystemExit:\n    pass\n"
        "print('numpy.ma' in sys.modules, file=sys.stderr)"
    )
    out = subprocess.run([sys.executable, "-c", code, str(session)], capture_output=True, text=True)
    assert out.stderr.strip().splitlines()[-1] == "False"
