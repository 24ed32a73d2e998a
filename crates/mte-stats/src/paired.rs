//! Paired comparisons: exact McNemar, the Wilcoxon signed-rank test, and the standard error
//! of a mean paired difference.

use serde::{Deserialize, Serialize};

use crate::binomial::{MAX_TRIALS, binom_test_two_sided_ln};
use crate::error::{Result, StatsError, check_finite, check_sample};
use crate::normal::norm_sf;

/// Result of [`mcnemar_exact`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct McNemarResult {
    /// Discordant pairs where only the first condition succeeded.
    pub b: u64,
    /// Discordant pairs where only the second condition succeeded.
    pub c: u64,
    /// Two-sided exact p-value, in `[0, 1]`.
    pub p_value: f64,
    /// Natural log of the p-value; finite even where `p_value` underflows to `0.0`.
    pub ln_p_value: f64,
}

/// Exact McNemar test on the discordant pairs of a paired binary outcome.
///
/// Under `H0` each of the `b + c` discordant pairs falls either way with probability 1/2,
/// so the p-value is the two-sided exact binomial test of `b` successes in `b + c` trials
/// at `p = 0.5` ([`binom_test_two_sided`](crate::binom_test_two_sided), the definition of
/// `scipy.stats.binomtest`). With no discordant pairs (`b = c = 0`) there is no evidence
/// of a difference and the p-value is `1`.
///
/// ```
/// let r = mte_stats::mcnemar_exact(12, 48)?;
/// assert_eq!(format!("{:.1e}", r.p_value), "3.2e-6");
/// # Ok::<(), mte_stats::StatsError>(())
/// ```
///
/// # Errors
///
/// [`StatsError::TooManyTrials`] if `b + c` exceeds 2^53.
pub fn mcnemar_exact(b: u64, c: u64) -> Result<McNemarResult> {
    let n = b.saturating_add(c);
    if n > MAX_TRIALS {
        return Err(StatsError::TooManyTrials { n, max: MAX_TRIALS });
    }
    let ln_p_value = if n == 0 {
        0.0
    } else {
        binom_test_two_sided_ln(b, n, 0.5)?
    };
    Ok(McNemarResult {
        b,
        c,
        p_value: libm::exp(ln_p_value).min(1.0),
        ln_p_value,
    })
}

/// Which McNemar test a comparison of paired successes uses.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum McNemarTest {
    /// [`mcnemar_exact`]: the exact binomial test on the discordant pairs (the default).
    #[default]
    Exact,
    /// [`mcnemar_chi2_corrected`]: the chi-square approximation with Edwards' continuity
    /// correction, the textbook large-sample form.
    Chi2Corrected,
}

impl McNemarTest {
    /// Runs the test on `b:c` discordant pairs.
    ///
    /// # Errors
    ///
    /// As [`mcnemar_exact`].
    pub fn run(self, b: u64, c: u64) -> Result<McNemarResult> {
        match self {
            Self::Exact => mcnemar_exact(b, c),
            Self::Chi2Corrected => mcnemar_chi2_corrected(b, c),
        }
    }
}

/// A McNemar test name that is not `exact` or `chi2-cc`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown McNemar test `{0}`: expected `exact` or `chi2-cc`")]
pub struct UnknownMcNemarTest(pub String);

impl std::str::FromStr for McNemarTest {
    type Err = UnknownMcNemarTest;
    fn from_str(s: &str) -> std::result::Result<Self, Self::Err> {
        match s {
            "exact" => Ok(Self::Exact),
            "chi2-cc" | "chi2-corrected" => Ok(Self::Chi2Corrected),
            _ => Err(UnknownMcNemarTest(s.into())),
        }
    }
}

/// McNemar's chi-square test with Edwards' continuity correction: the statistic
/// `(|b - c| - 1)^2 / (b + c)` against a chi-square with one degree of freedom, so
/// `p = P(chi2_1 > stat) = 2 P(Z > sqrt(stat))`. A large-sample approximation of
/// [`mcnemar_exact`]; with no discordant pairs the p-value is `1`.
///
/// ```
/// // 78:10 discordant pairs: 9.2e-13 (the exact test gives 3.3e-14).
/// let r = mte_stats::mcnemar_chi2_corrected(78, 10)?;
/// assert_eq!(format!("{:.1e}", r.p_value), "9.2e-13");
/// # Ok::<(), mte_stats::StatsError>(())
/// ```
///
/// # Errors
///
/// [`StatsError::TooManyTrials`] if `b + c` exceeds 2^53.
pub fn mcnemar_chi2_corrected(b: u64, c: u64) -> Result<McNemarResult> {
    let n = b.saturating_add(c);
    if n > MAX_TRIALS {
        return Err(StatsError::TooManyTrials { n, max: MAX_TRIALS });
    }
    if n == 0 {
        return Ok(McNemarResult {
            b,
            c,
            p_value: 1.0,
            ln_p_value: 0.0,
        });
    }
    let diff = (b as f64 - c as f64).abs() - 1.0;
    let z = (diff * diff / n as f64).sqrt();
    let p_value = (2.0 * crate::norm_sf(z)).min(1.0);
    let ln_p_value = if p_value > 0.0 {
        libm::log(p_value)
    } else {
        // Far tail, where the sf underflows: ln 2 + ln Q(z), Q(z) ~ phi(z)/z (1 - 1/z^2).
        std::f64::consts::LN_2 - 0.5 * z * z - libm::log(z * (2.0 * std::f64::consts::PI).sqrt())
            + libm::log1p(-1.0 / (z * z))
    };
    Ok(McNemarResult {
        b,
        c,
        p_value,
        ln_p_value,
    })
}

/// How [`wilcoxon_signed_rank`] computed its p-value.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum WilcoxonMethod {
    /// Exact null distribution of `r_plus` over all `2^n` sign assignments of the
    /// (mid)ranks, by dynamic programming over subset sums.
    Exact,
    /// Normal approximation with tie-corrected variance and no continuity correction.
    Normal,
}

/// Result of [`wilcoxon_signed_rank`] / [`wilcoxon_signed_rank_diffs`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WilcoxonResult {
    /// `min(r_plus, r_minus)`, scipy's two-sided statistic (a multiple of 1/2 with ties).
    pub statistic: f64,
    /// Sum of the ranks of the positive differences (`x > y`).
    pub r_plus: f64,
    /// Two-sided p-value, in `[0, 1]`.
    pub p_value: f64,
    /// Number of non-zero differences (the pairs that were ranked).
    pub n: usize,
    /// Number of zero differences, dropped before ranking.
    pub zeros: usize,
    /// Which null distribution gave the p-value.
    pub method: WilcoxonMethod,
    /// Signed standardised `r_plus`, `(r_plus - n(n+1)/4) / se`, for
    /// [`WilcoxonMethod::Normal`] only; positive when `x` tends to exceed `y`. (scipy's
    /// `zstatistic` reports `-|z|` instead.)
    pub z: Option<f64>,
}

/// Largest number of pairs (zeros included) for which the automatic method can be exact:
/// scipy switches to the normal approximation when `len(d) > 50`.
pub const WILCOXON_EXACT_MAX_PAIRS: usize = 50;

/// Largest number of pairs (zeros included) for which ties or zeros still allow an exact
/// p-value: scipy runs a permutation test over all `2^n` sign flips when `len(d) <= 13`.
pub const WILCOXON_PERMUTATION_MAX_PAIRS: usize = 13;

/// Two-sided Wilcoxon signed-rank test of paired samples `x` and `y` (differences
/// `x[i] - y[i]`); see [`wilcoxon_signed_rank_diffs`] for the rules.
///
/// # Errors
///
/// [`StatsError::LengthMismatch`], [`StatsError::EmptySample`],
/// [`StatsError::NonFinite`] (for an input, or for a difference that overflows), and
/// [`StatsError::AllZeroDifferences`].
pub fn wilcoxon_signed_rank(x: &[f64], y: &[f64]) -> Result<WilcoxonResult> {
    let d = differences(x, y)?;
    wilcoxon_signed_rank_diffs(&d)
}

/// Two-sided Wilcoxon signed-rank test of the paired differences `d`, replicating
/// `scipy.stats.wilcoxon(d)` with its defaults (scipy 1.17: `zero_method='wilcox'`,
/// `correction=False`, `method='auto'`).
///
/// The rules, from scipy's `_wilcoxon.py`:
///
/// - Zero differences are dropped (`'wilcox'`); the rest are ranked by `|d|` with midranks
///   for ties. `n` is the number of non-zero differences, `r_plus` / `r_minus` the rank
///   sums of the positive / negative ones, and the statistic is `min(r_plus, r_minus)`.
/// - `'auto'` decides on `N = d.len()`, **zeros included**:
///   - `N > 50`: normal approximation;
///   - `N <= 50` with no ties among `|d|` and no zeros: exact distribution;
///   - `N <= 13` with ties or zeros: scipy's permutation test, which enumerates all `2^N`
///     sign flips and is therefore exact; here it is the same subset-sum distribution
///     over the midranks (flipping a zero changes nothing), reported as
///     [`WilcoxonMethod::Exact`];
///   - otherwise (`14 <= N <= 50` with ties or zeros): normal approximation.
/// - Exact p-value: `min(1, 2 min(P(R+ <= r_plus), P(R+ >= r_plus)))` under the null where
///   each rank's sign is a fair coin (exact rational arithmetic in `u64`).
/// - Normal p-value: `z = (r_plus - n(n+1)/4) / se` with
///   `se^2 = n(n+1)(2n+1)/24 - sum(t^3 - t)/48` over the tie groups `t`, no continuity
///   correction, `p = min(1, 2 sf(|z|))`.
///
/// When every difference is zero, scipy returns `p = 1` for `N <= 13` and NaN (from
/// `0/0`) above; this function returns [`StatsError::AllZeroDifferences`] for every `N`.
///
/// ```
/// let d = [1.5, -0.5, 2.0, 3.0, 0.7, 4.1];
/// let r = mte_stats::wilcoxon_signed_rank_diffs(&d)?;
/// assert_eq!(r.statistic, 1.0);
/// assert!((r.p_value - 0.0625).abs() < 1e-15); // 2 * 2 / 64
/// # Ok::<(), mte_stats::StatsError>(())
/// ```
///
/// # Errors
///
/// [`StatsError::EmptySample`], [`StatsError::NonFinite`],
/// [`StatsError::AllZeroDifferences`].
pub fn wilcoxon_signed_rank_diffs(d: &[f64]) -> Result<WilcoxonResult> {
    check_sample("d", d)?;
    let total = d.len();
    let mut nonzero: Vec<f64> = d.iter().copied().filter(|&v| v != 0.0).collect();
    let n = nonzero.len();
    let zeros = total - n;
    if n == 0 {
        return Err(StatsError::AllZeroDifferences { n: total });
    }
    nonzero.sort_by(|a, b| a.abs().total_cmp(&b.abs()));

    // Doubled midranks are integers: a tie group at sorted positions s..e (0-based) has
    // midrank (s + 1 + e) / 2.
    let mut ranks2: Vec<u64> = Vec::with_capacity(n);
    let mut r_plus2: u128 = 0;
    let mut r_minus2: u128 = 0;
    let mut tie_sum = 0.0_f64;
    let mut has_ties = false;
    let mut s = 0;
    while s < n {
        let mut e = s + 1;
        while e < n && nonzero[e].abs() == nonzero[s].abs() {
            e += 1;
        }
        let t = (e - s) as f64;
        if e - s > 1 {
            has_ties = true;
            tie_sum += t * t * t - t;
        }
        let rank2 = (s + 1 + e) as u64;
        for v in &nonzero[s..e] {
            ranks2.push(rank2);
            if *v > 0.0 {
                r_plus2 += u128::from(rank2);
            } else {
                r_minus2 += u128::from(rank2);
            }
        }
        s = e;
    }
    let r_plus = r_plus2 as f64 / 2.0;
    let r_minus = r_minus2 as f64 / 2.0;

    let exact = if total > WILCOXON_EXACT_MAX_PAIRS {
        false
    } else {
        !(has_ties || zeros > 0) || total <= WILCOXON_PERMUTATION_MAX_PAIRS
    };

    let (p_value, method, z) = if exact {
        (exact_p(&ranks2, r_plus2), WilcoxonMethod::Exact, None)
    } else {
        let nf = n as f64;
        let mean = nf * (nf + 1.0) * 0.25;
        let var = (nf * (nf + 1.0) * (2.0 * nf + 1.0) - tie_sum / 2.0) / 24.0;
        let z = (r_plus - mean) / var.sqrt();
        (
            (2.0 * norm_sf(z.abs())).min(1.0),
            WilcoxonMethod::Normal,
            Some(z),
        )
    };
    Ok(WilcoxonResult {
        statistic: r_plus.min(r_minus),
        r_plus,
        p_value,
        n,
        zeros,
        method,
        z,
    })
}

/// Exact two-sided p-value of the doubled rank sum `obs2` when each of `ranks2` (doubled
/// ranks, at most 50 of them) is added with probability 1/2.
fn exact_p(ranks2: &[u64], obs2: u128) -> f64 {
    let max: usize = ranks2.iter().map(|&r| r as usize).sum();
    // counts[s] = number of sign assignments with doubled r_plus = s; at most 2^50.
    let mut counts = vec![0_u64; max + 1];
    counts[0] = 1;
    let mut reach = 0_usize;
    for &r in ranks2 {
        let r = r as usize;
        reach += r;
        for s in (r..=reach).rev() {
            counts[s] += counts[s - r];
        }
    }
    let obs = obs2 as usize;
    let le: u64 = counts[..=obs].iter().sum();
    let ge: u64 = counts[obs..].iter().sum();
    let total = (1_u64 << ranks2.len()) as f64;
    (2.0 * le.min(ge) as f64 / total).min(1.0)
}

/// Element-wise `x - y`, checked for equal lengths, emptiness and finiteness.
fn differences(x: &[f64], y: &[f64]) -> Result<Vec<f64>> {
    if x.len() != y.len() {
        return Err(StatsError::LengthMismatch {
            left: x.len(),
            right: y.len(),
        });
    }
    check_sample("x", x)?;
    check_finite("y", y)?;
    let d: Vec<f64> = x.iter().zip(y).map(|(a, b)| a - b).collect();
    check_finite("x - y", &d)?;
    Ok(d)
}

/// Standard error of the mean of paired differences: the sample standard deviation
/// (denominator `n - 1`) divided by `sqrt(n)`.
///
/// ```
/// let se = mte_stats::paired_se(&[1.0, 2.0, 3.0, 4.0])?;
/// assert!((se - (5.0_f64 / 3.0 / 4.0).sqrt()).abs() < 1e-15);
/// # Ok::<(), mte_stats::StatsError>(())
/// ```
///
/// # Errors
///
/// [`StatsError::EmptySample`], [`StatsError::TooFewSamples`] for a single difference,
/// [`StatsError::NonFinite`].
pub fn paired_se(diffs: &[f64]) -> Result<f64> {
    check_sample("diffs", diffs)?;
    if diffs.len() < 2 {
        return Err(StatsError::TooFewSamples {
            argument: "diffs",
            needed: 2,
            got: diffs.len(),
        });
    }
    Ok(mean_and_se(diffs).1)
}

/// Mean and standard error of a finite sample of length `>= 2`, scaled to avoid overflow.
fn mean_and_se(d: &[f64]) -> (f64, f64) {
    let n = d.len() as f64;
    let max = d.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
    if max == 0.0 {
        return (0.0, 0.0);
    }
    // A power of two, so dividing by it is exact: same rounding as the unscaled formula.
    let scale = libm::ldexp(1.0, libm::frexp(max).1);
    let mean_s = d.iter().map(|v| v / scale).sum::<f64>() / n;
    let ss: f64 = d.iter().map(|v| (v / scale - mean_s).powi(2)).sum();
    (mean_s * scale, (ss / (n - 1.0) / n).sqrt() * scale)
}

/// Mean paired difference `x - y` with its standard error; see [`mean_and_paired_se`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PairedSummary {
    /// Number of pairs.
    pub n: usize,
    /// Mean of `x[i] - y[i]`.
    pub mean_diff: f64,
    /// Standard error of `mean_diff` ([`paired_se`] of the differences).
    pub se: f64,
}

/// Mean of the paired differences `x[i] - y[i]` and its standard error ([`paired_se`]).
///
/// # Errors
///
/// [`StatsError::LengthMismatch`], [`StatsError::EmptySample`],
/// [`StatsError::TooFewSamples`] for a single pair, [`StatsError::NonFinite`].
pub fn mean_and_paired_se(x: &[f64], y: &[f64]) -> Result<PairedSummary> {
    let d = differences(x, y)?;
    if d.len() < 2 {
        return Err(StatsError::TooFewSamples {
            argument: "x",
            needed: 2,
            got: d.len(),
        });
    }
    let (mean_diff, se) = mean_and_se(&d);
    Ok(PairedSummary {
        n: d.len(),
        mean_diff,
        se,
    })
}
