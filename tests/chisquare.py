"""A chi-square goodness-of-fit p-value without SciPy (the project's packages do not include it): the
upper regularized incomplete gamma function Q(df/2, x/2), by its series below a + 1 and its continued
fraction above (the usual split; both converge fast there)."""

import math

import numpy as np


def upper_gamma_q(a: float, x: float) -> float:
    """Q(a, x) = Gamma(a, x) / Gamma(a)."""
    if x <= 0:
        return 1.0
    log_prefactor = a * math.log(x) - x - math.lgamma(a)
    if x < a + 1:  # P(a, x) by its series, then Q = 1 - P
        term = total = 1.0 / a
        for n in range(1, 1000):
            term *= x / (a + n)
            total += term
            if abs(term) < abs(total) * 1e-15:
                break
        return 1.0 - total * math.exp(log_prefactor)
    b, c, d = x + 1 - a, 1e300, 1 / (x + 1 - a)  # Q(a, x) by Lentz's continued fraction
    h = d
    for n in range(1, 1000):
        an = -n * (n - a)
        b += 2
        d = an * d + b
        d = 1e-300 if abs(d) < 1e-300 else d
        c = b + an / c
        c = 1e-300 if abs(c) < 1e-300 else c
        d = 1 / d
        h *= d * c
        if abs(d * c - 1) < 1e-15:
            break
    return math.exp(log_prefactor) * h


def uniform_pvalue(counts) -> float:
    """p-value of the counts under 'every outcome equally likely' (Pearson's chi-square test)."""
    counts = np.asarray(counts, dtype=float)
    expected = counts.sum() / len(counts)
    statistic = float(((counts - expected) ** 2 / expected).sum())
    return upper_gamma_q((len(counts) - 1) / 2, statistic / 2)
