"""The solver's chi-square and F tails against scipy.special's."""

import numpy as np
from scipy.special import chdtrc, fdtrc

from slidecal.solver.tails import chi2_tail, f_tail


def test_tails_match_scipy():
    rng = np.random.default_rng(0)
    for _ in range(400):
        d1, d2 = int(rng.integers(1, 3000)), int(rng.integers(1, 200000))
        f = float(np.exp(rng.normal(0.0, 0.5)))
        assert np.isclose(f_tail(d1, d2, f), fdtrc(d1, d2, f), rtol=1e-8, atol=1e-300)
        v = int(rng.integers(1, 50000))
        x = float(v * np.exp(rng.normal(0.0, 0.3)))
        assert np.isclose(chi2_tail(v, x), chdtrc(v, x), rtol=1e-8, atol=1e-300)
    assert f_tail(3, 10, 0.0) == 1.0 and chi2_tail(3, 0.0) == 1.0
