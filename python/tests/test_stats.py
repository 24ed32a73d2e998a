"""mte.stats against scipy."""

import math

import numpy as np
import pytest
from scipy import stats as sp

import mte
from mte import stats


@pytest.mark.parametrize("b, c", [(0, 0), (1, 0), (12, 48), (78, 10), (30, 30), (5, 200)])
def test_mcnemar_exact_is_scipys_binomial_test(b, c):
    want = 1.0 if b + c == 0 else sp.binomtest(b, b + c, 0.5).pvalue
    assert stats.mcnemar(b, c) == pytest.approx(want, rel=1e-9, abs=1e-300)


@pytest.mark.parametrize("b, c", [(78, 10), (12, 48), (30, 31)])
def test_mcnemar_corrected_chi_square(b, c):
    want = sp.chi2.sf((abs(b - c) - 1) ** 2 / (b + c), 1)
    assert stats.mcnemar(b, c, method="chi2-cc") == pytest.approx(want, rel=1e-9)


@pytest.mark.parametrize("n, seed", [(10, 0), (30, 1), (80, 2)])
def test_wilcoxon_matches_scipy(n, seed):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    x[:3] = y[:3] + 0.25  # some structure
    got = stats.wilcoxon(list(x), list(y))
    want = sp.wilcoxon(x, y)
    assert got["statistic"] == pytest.approx(want.statistic, rel=1e-12)
    assert got["pvalue"] == pytest.approx(want.pvalue, rel=1e-9)


def test_two_proportion_z():
    z, p = stats.two_proportion_z(37, 200, 5, 200)
    pooled = 42 / 400
    want_z = (37 / 200 - 5 / 200) / math.sqrt(pooled * (1 - pooled) * (2 / 200))
    assert z == pytest.approx(want_z, rel=1e-12)
    assert p == pytest.approx(2 * sp.norm.sf(abs(want_z)), rel=1e-9)


def test_holm_against_a_direct_computation():
    p = [0.01, 0.04, 0.03, 0.005]
    order = np.argsort(p)
    adjusted = np.empty(4)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (4 - rank) * p[i]))
        adjusted[i] = running
    np.testing.assert_allclose(stats.holm(p), adjusted, rtol=1e-12)


def test_auroc_is_the_mann_whitney_u_fraction():
    pos, neg = [0.9, 0.8, 0.8, 0.3], [0.1, 0.8, 0.2]
    u = sp.mannwhitneyu(pos, neg).statistic
    assert stats.auroc(pos, neg) == pytest.approx(u / (len(pos) * len(neg)), rel=1e-12)


@pytest.mark.parametrize("k, n", [(0, 10), (7, 50), (50, 50), (4, 200)])
def test_wilson_interval(k, n):
    ci = sp.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    lo, hi = stats.wilson(k, n)
    assert lo == pytest.approx(ci.low, abs=1e-12) and hi == pytest.approx(ci.high, abs=1e-12)


def test_bad_input_is_a_typed_error():
    with pytest.raises(mte.MteError, match="chi3"):
        stats.mcnemar(1, 2, method="chi3")
    with pytest.raises(mte.MteError):
        stats.two_proportion_z(5, 4, 1, 2)
    with pytest.raises(mte.MteError):
        stats.wilcoxon([1.0, 2.0], [1.0])
