"""Reference values from scipy for mte-stats' parity test (tests/scipy_reference.rs).

Every value comes from scipy (pinned in requirements-stats.txt) with fixed inputs or
fixed seeds, so the fixture is reproducible byte for byte.

Usage (from the repository root):
    python3 -m venv /tmp/venv-stats
    /tmp/venv-stats/bin/pip install -r tools/reference/requirements-stats.txt
    /tmp/venv-stats/bin/python tools/reference/stats_reference.py \
        > crates/mte-stats/tests/fixtures/scipy_reference.json
"""
import json
import math
import sys
from importlib.metadata import version

import numpy as np
import scipy
from scipy import stats

# (k, n, p): small and large n, p != 0.5, both sides of the mode, k == n p, far tails.
BINOMTEST = [
    (3, 15, 0.1), (0, 10, 0.3), (10, 10, 0.3), (7, 20, 0.35), (13, 20, 0.35),
    (1, 100, 0.01), (5, 100, 0.01), (0, 100, 0.01), (50, 100, 0.5), (49, 100, 0.5),
    (45, 100, 0.45), (60, 100, 0.45), (2, 1000, 0.9), (999, 1000, 0.9),
    (880, 1000, 0.9), (4990, 10000, 0.5), (4700, 10000, 0.5), (1, 7, 0.999),
    (497000, 1000000, 0.5), (482000, 1000000, 0.5), (1000, 1000000, 0.001),
    (1100, 1000000, 0.001), (900, 1000000, 0.001), (300000, 1000000, 0.3),
    (301000, 1000000, 0.3), (123456, 1000000, 0.123), (0, 1000000, 1e-6),
    (5, 1000000, 1e-6), (999990, 1000000, 0.99999), (12, 987654, 2.5e-5),
]

# (k, n, p) for binom.cdf / binom.sf (sf is P(X > k)).
BINOM_TAILS = [
    (0, 10, 0.5), (2, 10, 0.5), (5, 10, 0.5), (9, 10, 0.5), (3, 40, 0.3),
    (20, 40, 0.3), (30, 40, 0.3), (100, 1000, 0.2), (200, 1000, 0.2),
    (300, 1000, 0.2), (480000, 1000000, 0.5), (500000, 1000000, 0.5),
    (520000, 1000000, 0.5), (50, 1000000, 1e-4), (150, 1000000, 1e-4),
    (5, 500, 0.97), (490, 500, 0.97), (499, 500, 0.97),
]

# Discordant pairs b:c, the paper's ten plus edge and large cases.
MCNEMAR = [
    (12, 48), (2, 16), (2, 19), (1, 19), (10, 4), (3, 3), (21, 6), (54, 17),
    (34, 18), (9, 15), (0, 5), (5, 0), (0, 1), (100, 130), (1000, 1100),
    (497000, 503000), (482000, 518000),
]

# The paper's 78:10 (chi-square 9.2e-13, exact 3.3e-14) and a far tail.
MCNEMAR_CC_EXTRA = [(78, 10), (400, 100), (30, 30), (31, 30)]

ZTEST = [
    (37, 200, 5, 200), (10, 50, 20, 60), (0, 100, 3, 100), (500, 1000, 520, 1000),
    (1, 10, 9, 10), (150, 300, 150, 300), (999, 1000, 900, 1000),
]

NORM_X = [-40.0, -38.0, -30.0, -20.0, -10.0, -8.0, -5.0, -3.0, -1.96, -1.0, -0.5,
          -1e-5, 0.0, 1e-8, 0.3, 0.7, 1.0, 2.0, 5.0, 8.0, 10.0, 20.0, 37.0]
NORM_P = [1e-300, 1e-100, 1e-20, 1e-10, 1e-5, 0.001, 0.01, 0.02425, 0.025, 0.1, 0.3,
          0.4999, 0.5, 0.5001, 0.7, 0.9, 0.95, 0.97575, 0.975, 0.99, 0.999, 1 - 1e-10]

WILSON = [
    (0, 20, 0.95), (20, 20, 0.95), (1, 20, 0.95), (37, 200, 0.95), (5, 200, 0.95),
    (50, 100, 0.9), (3, 10, 0.99), (999, 1000, 0.95), (1, 1, 0.5), (0, 1, 0.95),
    (12345, 100000, 0.999), (7, 13, 0.6827),
]


def f(x):
    """A Python float (JSON writes the shortest repr, which round-trips exactly)."""
    return float(x)


def binomtest_cases():
    return [{"k": k, "n": n, "p": p, "pvalue": f(stats.binomtest(k, n, p).pvalue)}
            for k, n, p in BINOMTEST]


def binom_tail_cases():
    return [{"k": k, "n": n, "p": p, "cdf": f(stats.binom.cdf(k, n, p)),
             "sf": f(stats.binom.sf(k, n, p))} for k, n, p in BINOM_TAILS]


def mcnemar_cases():
    return [{"b": b, "c": c, "pvalue": f(stats.binomtest(b, b + c, 0.5).pvalue)}
            for b, c in MCNEMAR]


def mcnemar_cc_cases():
    """McNemar's chi-square with Edwards' continuity correction: chi2.sf((|b-c|-1)^2/(b+c), 1)."""
    return [{"b": b, "c": c,
             "pvalue": f(stats.chi2.sf((abs(b - c) - 1) ** 2 / (b + c), 1))}
            for b, c in MCNEMAR + MCNEMAR_CC_EXTRA if b + c > 0]


def wilcoxon_samples():
    """(name, x, y or None, intended: 'exact' | 'normal'), fixed seeds."""
    out = []
    r = np.random.default_rng(20240611)

    def rnd(a, decimals=6):
        return np.round(a, decimals)

    x = rnd(r.normal(size=10)); y = rnd(x + r.normal(0.4, 1.0, 10))
    out.append(("small_n10_no_ties", x, y, "exact"))
    x = rnd(r.normal(size=20)); y = rnd(x + r.normal(-0.6, 1.0, 20))
    out.append(("n20_no_ties", x, y, "exact"))
    x = rnd(r.normal(size=50)); y = rnd(x + r.normal(0.3, 1.0, 50))
    out.append(("n50_no_ties_boundary_exact", x, y, "exact"))
    x = rnd(r.normal(size=51)); y = rnd(x + r.normal(0.3, 1.0, 51))
    out.append(("n51_no_ties_boundary_normal", x, y, "normal"))
    x = rnd(r.normal(size=80)); y = rnd(x + r.normal(0.2, 1.0, 80))
    out.append(("n80_no_ties", x, y, "normal"))
    d = np.round(r.normal(0.3, 1.0, 30), 1)
    d[d == 0] = 0.1
    out.append(("n30_ties", d, None, "normal"))
    d = np.round(r.normal(0.5, 1.0, 12), 0)
    d[d == 0] = 1.0
    out.append(("n12_ties_permutation", d, None, "exact"))
    d = np.array([1.0, 2.0, 2.0, -2.0, 3.0, 3.0, 3.0, -1.0, 4.0, 5.0, 5.0, 6.0, 7.0])
    out.append(("n13_ties_permutation_boundary", d, None, "exact"))
    d = np.append(d, 8.0)
    out.append(("n14_ties_boundary_normal", d, None, "normal"))
    d = rnd(r.normal(0.8, 1.0, 10)); d[[2, 7]] = 0.0
    out.append(("n10_zeros_permutation", d, None, "exact"))
    d = rnd(r.normal(0.2, 1.0, 25)); d[[0, 5, 11]] = 0.0
    out.append(("n25_zeros_normal", d, None, "normal"))
    x = rnd(r.normal(size=60)); y = x.copy(); y[::4] = rnd(y[::4] + r.normal(0, 1, 15))
    out.append(("n60_many_zeros", x, y, "normal"))
    d = np.round(r.normal(0.1, 1.0, 200), 1)
    out.append(("n200_ties_and_zeros", d, None, "normal"))
    d = np.array([0.1] * 20 + [-0.1] * 3)
    out.append(("near_constant_all_tied", d, None, "normal"))
    x = 5.0 + rnd(r.normal(0.0, 1e-9, 40), 15); y = np.full(40, 5.0)
    out.append(("near_constant_tiny_spread", x, y, "exact"))
    d = rnd(np.abs(r.normal(1.0, 1.0, 50)) + 0.01)
    out.append(("n50_all_positive", d, None, "exact"))
    out.append(("n1", np.array([2.5]), None, "exact"))
    out.append(("n2_tie_opposite_signs", np.array([-1.0, 1.0]), None, "exact"))
    out.append(("n3_two_zeros", np.array([0.0, 0.0, 1.0]), None, "exact"))
    return out


def wilcoxon_cases():
    cases = []
    for name, x, y, intended in wilcoxon_samples():
        d = x if y is None else x - y
        nz = np.abs(d[d != 0])
        auto = stats.wilcoxon(x) if y is None else stats.wilcoxon(x, y)
        asym = (stats.wilcoxon(x, method="asymptotic") if y is None
                else stats.wilcoxon(x, y, method="asymptotic"))
        # Which branch 'auto' took, observed rather than restated: the asymptotic branch
        # gives the same p-value as method='asymptotic'. When both are exactly 1 the
        # branch cannot be told apart; the case then records the intended branch.
        ambiguous = auto.pvalue == asym.pvalue == 1.0
        observed = "normal" if auto.pvalue == asym.pvalue else "exact"
        if ambiguous:
            observed = intended
        assert observed == intended, (name, observed, intended)
        case = {
            "name": name,
            "x": [f(v) for v in x],
            "y": None if y is None else [f(v) for v in y],
            "n_nonzero": int(nz.size),
            "has_ties": bool(np.unique(nz).size < nz.size),
            "method": observed,
            "method_observed": not ambiguous,
            "statistic": f(auto.statistic),
            "pvalue": f(auto.pvalue),
            "abs_z": f(abs(asym.zstatistic)) if observed == "normal" else None,
        }
        cases.append(case)
    return cases


def ztest_cases():
    out = []
    for x1, n1, x2, n2 in ZTEST:
        pooled = (x1 + x2) / (n1 + n2)
        se = math.sqrt(pooled * (1 - pooled) * (1 / n1 + 1 / n2))
        z = (x1 / n1 - x2 / n2) / se
        out.append({"x1": x1, "n1": n1, "x2": x2, "n2": n2, "z": z,
                    "pvalue": f(2 * stats.norm.sf(abs(z)))})
    return out


def norm_cases():
    points = [{"x": x, "pdf": f(stats.norm.pdf(x)), "cdf": f(stats.norm.cdf(x)),
               "sf": f(stats.norm.sf(x))} for x in NORM_X]
    ppf = [{"p": p, "x": f(stats.norm.ppf(p))} for p in NORM_P]
    return points, ppf


def wilson_cases():
    out = []
    for k, n, conf in WILSON:
        ci = stats.binomtest(k, n).proportion_ci(confidence_level=conf, method="wilson")
        out.append({"k": k, "n": n, "confidence": conf, "lo": f(ci.low), "hi": f(ci.high)})
    return out


def auroc_cases():
    r = np.random.default_rng(7)
    samples = [
        ("integer_scores_ties", r.integers(0, 10, 30).astype(float),
         r.integers(0, 8, 25).astype(float)),
        ("continuous", np.round(r.normal(1.0, 1.0, 40), 6), np.round(r.normal(0, 1, 35), 6)),
        ("all_tied", np.ones(3), np.ones(2)),
        ("perfect_separation", np.array([2.0, 3.0, 4.0]), np.array([-1.0, 0.0, 1.0])),
        ("reversed_separation", np.array([-1.0, 0.0]), np.array([2.0, 3.0, 4.0])),
        ("single_each_tie", np.array([0.5]), np.array([0.5])),
        ("signed_zeros", np.array([-0.0, 1.0]), np.array([0.0, -1.0])),
        ("coarse_large", np.round(r.normal(0.5, 1.0, 500), 1),
         np.round(r.normal(0.0, 1.0, 400), 1)),
    ]
    out = []
    for name, pos, neg in samples:
        u = stats.mannwhitneyu(pos, neg).statistic
        out.append({"name": name, "pos": [f(v) for v in pos], "neg": [f(v) for v in neg],
                    "auroc": f(u / (pos.size * neg.size))})
    return out


def main():
    norm_points, norm_ppf = norm_cases()
    out = {
        "generator": "tools/reference/stats_reference.py",
        "versions": {"python": sys.version.split()[0], "numpy": version("numpy"),
                     "scipy": scipy.__version__},
        "binomtest": binomtest_cases(),
        "binom_tails": binom_tail_cases(),
        "mcnemar": mcnemar_cases(),
        "mcnemar_cc": mcnemar_cc_cases(),
        "wilcoxon": wilcoxon_cases(),
        "ztest": ztest_cases(),
        "norm": norm_points,
        "norm_ppf": norm_ppf,
        "wilson": wilson_cases(),
        "auroc": auroc_cases(),
    }
    json.dump(out, sys.stdout, indent=1, allow_nan=False)
    sys.stdout.write("\n")


if __name__ == "__main__":
    main()
