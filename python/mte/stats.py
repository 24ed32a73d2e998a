"""Paired statistics of mte (the Rust ``mte-stats`` crate), checked against scipy.

- ``mcnemar(b, c, method="exact")``: two-sided p-value on ``b:c`` discordant pairs; the
  exact binomial test, or ``"chi2-cc"`` (continuity-corrected chi-square).
- ``wilcoxon(x, y)``: two-sided signed-rank test with scipy's rules; a dict with
  ``statistic``, ``pvalue``, ``method``, ``n``, ``zeros``.
- ``two_proportion_z(x1, n1, x2, n2)``: pooled z-test, ``(z, pvalue)``.
- ``holm(pvalues)``: Holm-adjusted p-values in input order.
- ``auroc(positive, negative)``: P(positive > negative), ties 1/2.
- ``wilson(successes, n, confidence=0.95)``: Wilson score interval ``(low, high)``.
"""

from ._native import auroc, holm, mcnemar, two_proportion_z, wilcoxon, wilson

__all__ = ["auroc", "holm", "mcnemar", "two_proportion_z", "wilcoxon", "wilson"]
