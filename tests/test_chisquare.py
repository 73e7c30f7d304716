"""tests/chisquare.py, the chi-square p-value the uniformity tests use, against printed tables and closed forms."""

import math

import pytest
from chisquare import uniform_pvalue, upper_gamma_q


@pytest.mark.parametrize("df, x, p", [(1, 3.841, 0.05), (10, 18.307, 0.05), (4, 13.277, 0.01), (2, 9.210, 0.01)])
def test_the_chi_square_tail_matches_the_printed_critical_values(df, x, p):
    assert upper_gamma_q(df / 2, x / 2) == pytest.approx(p, abs=2e-5)


@pytest.mark.parametrize("x", [0.01, 0.3, 0.9, 1.4, 1.6, 3.0, 9.0])
def test_the_tail_matches_closed_forms_on_both_sides_of_the_series_split(x):
    # x < a + 1 takes the series, above it the continued fraction. Q(1, x) = exp(-x) (2 degrees of freedom);
    # Q(1/2, x) = erfc(sqrt x) (1 degree of freedom).
    assert upper_gamma_q(1.0, x) == pytest.approx(math.exp(-x), rel=1e-10)
    assert upper_gamma_q(0.5, x) == pytest.approx(math.erfc(math.sqrt(x)), rel=1e-10)


def test_equal_counts_are_uniform_and_lopsided_ones_are_not():
    assert uniform_pvalue([50, 50, 50, 50]) == pytest.approx(1.0)
    assert uniform_pvalue([100, 10, 10, 10]) < 1e-6
