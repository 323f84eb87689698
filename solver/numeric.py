"""Routines slidecal would otherwise take from scipy (the chi-square's and F's upper tails, a
small Levenberg-Marquardt fit) and from numpy without its import of numpy.ma (median, unique).

Why not scipy: importing ``scipy.special`` or ``scipy.optimize`` costs a command more than its
whole solve on a small session. The textbook methods: series and Lentz's continued fractions
for the incomplete gamma and beta functions, Marquardt's damping with forward differences.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

_EPS = 1e-15  # relative accuracy of the series and continued fractions
_TINY = 1e-300  # Lentz's guard against a zero denominator
_MAX_TERMS = 100_000  # the expansions converge in O(sqrt(a)) terms; a bound, never reached


def _lentz(a_n: Callable[[int], float], b_n: Callable[[int], float], b0: float) -> float:
    """The continued fraction ``b0 + a_1 / (b_1 + a_2 / (b_2 + ...))`` (modified Lentz)."""
    f = b0 if abs(b0) > _TINY else _TINY
    c, d = f, 0.0
    for n in range(1, _MAX_TERMS):
        d = b_n(n) + a_n(n) * d
        c = b_n(n) + a_n(n) / c
        d = 1.0 / (d if abs(d) > _TINY else _TINY)
        c = c if abs(c) > _TINY else _TINY
        f *= c * d
        if abs(c * d - 1.0) < _EPS:
            break
    return f


def _gamma_q(a: float, x: float) -> float:
    """The regularised upper incomplete gamma function ``Q(a, x)``."""
    if x <= 0.0:
        return 1.0
    front = math.exp(a * math.log(x) - x - math.lgamma(a))
    if x < a + 1.0:  # the series of P converges fast here, and P is not close to 1
        term = total = 1.0 / a
        n = a
        while term > total * _EPS:  # every term is positive (x, a > 0)
            n += 1.0
            term *= x / n
            total += term
        return max(1.0 - front * total, 0.0)
    return front / _lentz(lambda n: -n * (n - a), lambda n: x + 1.0 - a + 2.0 * n, x + 1.0 - a)


def _beta_i(a: float, b: float, x: float) -> float:
    """The regularised incomplete beta function ``I_x(a, b)``."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    if x > (a + 1.0) / (a + b + 2.0):  # the fraction converges fast on the other side
        return 1.0 - _beta_i(b, a, 1.0 - x)
    front = math.exp(
        math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x)
    )

    def a_n(n: int) -> float:
        m = n // 2
        if n % 2:
            return -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))
        return m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m))

    return front / (a * _lentz(a_n, lambda n: 1.0, 1.0))


def chi2_tail(dof: float, value: float) -> float:
    """``P(X >= value)`` for ``X`` chi-square with ``dof`` degrees of freedom."""
    return _gamma_q(0.5 * dof, 0.5 * value)


def f_tail(dof_num: float, dof_den: float, value: float) -> float:
    """``P(X >= value)`` for ``X`` F-distributed with ``(dof_num, dof_den)`` degrees of freedom."""
    if value <= 0.0:
        return 1.0
    return _beta_i(0.5 * dof_den, 0.5 * dof_num, dof_den / (dof_den + dof_num * value))


@dataclass(frozen=True)
class LeastSquaresFit:
    """The minimiser ``x``, its residuals ``fun`` and their Jacobian ``jac`` at ``x``."""

    x: np.ndarray
    fun: np.ndarray
    jac: np.ndarray


def _jacobian(f: Callable[[np.ndarray], np.ndarray], x: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Forward differences, each step relative to its parameter's size."""
    h = np.sqrt(np.finfo(float).eps) * np.maximum(1.0, np.abs(x))
    J = np.empty((len(r), len(x)))
    for i in range(len(x)):
        xi = x.copy()
        xi[i] += h[i]
        J[:, i] = (f(xi) - r) / h[i]
    return J


def least_squares(
    f: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, max_iter: int = 100
) -> LeastSquaresFit:
    """Minimise ``|f(x)|^2`` from ``x0`` by Levenberg-Marquardt (damping scaled by the normal
    matrix's diagonal, so each parameter's own scale does not matter)."""
    x = np.asarray(x0, dtype=float).copy()
    r = np.asarray(f(x), dtype=float)
    cost, lam = float(r @ r), 1e-3
    J = _jacobian(f, x, r)
    for _ in range(max_iter):
        A, g = J.T @ J, J.T @ r
        d = np.diag(A).copy()
        d[d <= 0] = 1.0
        while lam < 1e16:
            try:
                step = np.linalg.solve(A + lam * np.diag(d), -g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            r_new = np.asarray(f(x + step), dtype=float)
            cost_new = float(r_new @ r_new)
            if cost_new <= cost:
                break
            lam *= 10.0
        else:
            break  # no step lowers the cost: a minimum
        x, r, lam = x + step, r_new, max(lam / 10.0, 1e-12)
        done = cost - cost_new <= 1e-12 * cost or np.linalg.norm(step) <= 1e-12 * (
            np.linalg.norm(x) + 1e-12
        )
        cost = cost_new
        J = _jacobian(f, x, r)
        if done:
            break
    return LeastSquaresFit(x, r, J)


def median(x: np.ndarray | list[float]) -> float:
    """``np.median`` of all of ``x`` (NaN if one is) without numpy's import of numpy.ma."""
    a = np.sort(np.asarray(x, float), axis=None)  # one flattened copy
    if not len(a) or np.isnan(a[-1]):
        return float("nan")
    return float(a[(len(a) - 1) // 2] + a[len(a) // 2]) / 2


def distinct(x: np.ndarray) -> np.ndarray:
    """``np.unique(x)``, its sorted distinct values, without numpy's import of numpy.ma."""
    return np.unique(x, return_counts=True)[0]
