//! Proportions: the pooled two-proportion z-test, the Wilson score interval, and the
//! binomial standard error.

use serde::{Deserialize, Serialize};

use crate::error::{Result, StatsError, check_probability};
use crate::normal::{norm_ppf, norm_sf};

/// Result of [`two_proportion_ztest`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ZTestResult {
    /// `(p1 - p2) / se_pooled`; positive when the first proportion is larger.
    pub z: f64,
    /// Two-sided p-value `2 sf(|z|)`, in `[0, 1]`.
    pub p_value: f64,
}

fn check_count(successes: u64, total: u64, argument: &'static str) -> Result<()> {
    if total == 0 {
        return Err(StatsError::ZeroTrials { argument });
    }
    if successes > total {
        return Err(StatsError::CountExceedsTotal { successes, total });
    }
    Ok(())
}

/// Two-sided z-test for equal proportions of two independent samples (`x1` successes of
/// `n1`, `x2` of `n2`), with the pooled variance
/// `p (1 - p) (1/n1 + 1/n2)`, `p = (x1 + x2) / (n1 + n2)`.
///
/// When the pooled proportion is 0 or 1 (no successes, or no failures, in either sample)
/// the two observed proportions are equal and the variance is zero: the result is then
/// `z = 0`, `p = 1` (no evidence of a difference) rather than `0/0`.
///
/// ```
/// // 18.5 % vs 2.5 % at n = 200 each.
/// let r = mte_stats::two_proportion_ztest(37, 200, 5, 200)?;
/// assert_eq!(format!("{:.2}", r.z), "5.22");
/// assert_eq!(format!("{:.1e}", r.p_value), "1.8e-7");
/// # Ok::<(), mte_stats::StatsError>(())
/// ```
///
/// # Errors
///
/// [`StatsError::ZeroTrials`] if `n1` or `n2` is 0, [`StatsError::CountExceedsTotal`] if
/// a count of successes exceeds its total.
pub fn two_proportion_ztest(x1: u64, n1: u64, x2: u64, n2: u64) -> Result<ZTestResult> {
    check_count(x1, n1, "n1")?;
    check_count(x2, n2, "n2")?;
    let (x1f, n1f, x2f, n2f) = (x1 as f64, n1 as f64, x2 as f64, n2 as f64);
    let pooled = (x1f + x2f) / (n1f + n2f);
    let se = (pooled * (1.0 - pooled) * (1.0 / n1f + 1.0 / n2f)).sqrt();
    if se == 0.0 {
        return Ok(ZTestResult {
            z: 0.0,
            p_value: 1.0,
        });
    }
    let z = (x1f / n1f - x2f / n2f) / se;
    Ok(ZTestResult {
        z,
        p_value: (2.0 * norm_sf(z.abs())).min(1.0),
    })
}

/// Wilson score interval `(lo, hi)` for a binomial proportion after `successes` in `n`
/// trials, at two-sided confidence level `confidence` (e.g. `0.95`).
///
/// Same formula as `scipy.stats.binomtest(k, n).proportion_ci(confidence, 'wilson')`
/// (Newcombe 1998, no continuity correction): with `z = ppf((1 + confidence) / 2)`,
/// `center = (2 n p + z^2) / (2 (n + z^2))` and
/// `delta = z / (2 (n + z^2)) sqrt(4 n p (1 - p) + z^2)`, the interval is
/// `center -/+ delta`, except that `lo = 0` exactly when `successes = 0` and `hi = 1`
/// exactly when `successes = n`.
///
/// ```
/// let (lo, hi) = mte_stats::wilson_interval(0, 20, 0.95)?;
/// assert_eq!(lo, 0.0);
/// assert!((hi - 0.161_125_158_052_819_35).abs() < 1e-12);
/// # Ok::<(), mte_stats::StatsError>(())
/// ```
///
/// # Errors
///
/// [`StatsError::ZeroTrials`] if `n = 0`, [`StatsError::CountExceedsTotal`] if
/// `successes > n`, [`StatsError::InvalidConfidence`] unless `0 < confidence < 1`.
pub fn wilson_interval(successes: u64, n: u64, confidence: f64) -> Result<(f64, f64)> {
    check_count(successes, n, "n")?;
    if !(confidence > 0.0 && confidence < 1.0) {
        return Err(StatsError::InvalidConfidence { value: confidence });
    }
    let z = norm_ppf(0.5 + 0.5 * confidence)?;
    let nf = n as f64;
    let p = successes as f64 / nf;
    let q = 1.0 - p;
    let denom = 2.0 * (nf + z * z);
    let center = (2.0 * nf * p + z * z) / denom;
    let delta = z / denom * (4.0 * nf * p * q + z * z).sqrt();
    let lo = if successes == 0 { 0.0 } else { center - delta };
    let hi = if successes == n { 1.0 } else { center + delta };
    Ok((lo.max(0.0), hi.min(1.0)))
}

/// Standard error of a binomial proportion, `sqrt(p (1 - p) / n)`.
///
/// # Errors
///
/// [`StatsError::InvalidProbability`] unless `0 <= p <= 1`, [`StatsError::ZeroTrials`] if
/// `n = 0`.
pub fn binomial_se(p: f64, n: u64) -> Result<f64> {
    check_probability(p)?;
    if n == 0 {
        return Err(StatsError::ZeroTrials { argument: "n" });
    }
    Ok((p * (1.0 - p) / n as f64).sqrt())
}
