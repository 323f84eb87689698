"""Upper tails of the chi-square and F distributions, the p-values of the solver's tests.

The values of ``scipy.special.chdtrc`` and ``fdtrc``, whose import costs a small solve more than
the solve: the regularised incomplete gamma and beta functions by their series and continued
fractions (modified Lentz; Numerical Recipes, Secs. 6.2 and 6.4).
"""

from __future__ import annotations

import math

_EPS = 1e-16  # relative size of the last term or factor
_TINY = 1e-300  # a zero denominator's stand-in (Lentz)
_MAX_TERMS = 1_000_000  # the series and fractions need O(sqrt(dof)) terms


def _guard(v: float) -> float:
    return v if abs(v) > _TINY else _TINY


def chi2_tail(dof: float, x: float) -> float:
    """``P(chi2(dof) > x)``: the regularised upper incomplete gamma ``Q(dof / 2, x / 2)``."""
    a, x = 0.5 * dof, 0.5 * x
    if x <= 0.0:
        return 1.0
    front = math.exp(a * math.log(x) - x - math.lgamma(a))
    if x < a + 1.0:  # the series of P = 1 - Q
        term = total = 1.0 / a
        n = a
        for _ in range(_MAX_TERMS):
            n += 1.0
            term *= x / n
            total += term
            if abs(term) < abs(total) * _EPS:
                break
        return max(1.0 - front * total, 0.0)
    b = x + 1.0 - a
    c, d = 1.0 / _TINY, 1.0 / b
    h = d
    for i in range(1, _MAX_TERMS):
        an = -i * (i - a)
        b += 2.0
        d = 1.0 / _guard(an * d + b)
        c = _guard(b + an / c)
        h *= d * c
        if abs(d * c - 1.0) < _EPS:
            break
    return front * h


def _beta_fraction(a: float, b: float, x: float) -> float:
    """The continued fraction of ``I_x(a, b)`` (``front * fraction / a``)."""
    c, d = 1.0, 1.0 / _guard(1.0 - (a + b) * x / (a + 1.0))
    h = d
    for m in range(1, _MAX_TERMS):
        m2 = 2 * m
        for aa in (
            m * (b - m) * x / ((a - 1.0 + m2) * (a + m2)),
            -(a + m) * (a + b + m) * x / ((a + m2) * (a + 1.0 + m2)),
        ):
            d = 1.0 / _guard(1.0 + aa * d)
            c = _guard(1.0 + aa / c)
            h *= d * c
        if abs(d * c - 1.0) < _EPS:
            break
    return h


def f_tail(d1: float, d2: float, f: float) -> float:
    """``P(F(d1, d2) > f)``: ``I_x(d2 / 2, d1 / 2)`` at ``x = d2 / (d2 + d1 f)``."""
    if f <= 0.0:
        return 1.0
    a, b, x = 0.5 * d2, 0.5 * d1, d2 / (d2 + d1 * f)
    lbeta = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b)
    front = math.exp(lbeta + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):
        return front * _beta_fraction(a, b, x) / a
    return max(1.0 - front * _beta_fraction(b, a, 1.0 - x) / b, 0.0)
