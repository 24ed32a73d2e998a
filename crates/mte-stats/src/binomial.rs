//! The binomial distribution in log space, and the exact two-sided binomial test.
//!
//! The log-pmf uses Loader's saddle-point form (the one behind R's `dbinom`): Stirling
//! remainders plus a deviance term `bd0` evaluated without cancellation, accurate to a few
//! ulps of the *log* even for `n = 10^6` and outcomes hundreds of standard deviations from
//! the mean. A tail is the log-sum-exp of its terms, starting at the term nearest the mode
//! (the largest) and walking outwards until a term is below `e^-50` of the running sum;
//! the pmf is log-concave, so the ignored remainder is negligible. The tail that contains
//! the mode is never summed: it is one minus the other tail (which is then at most about
//! one half, so nothing is lost). Cost: `O(sqrt(n p (1 - p)))` pmf evaluations at worst.
//!
//! Because everything stays in log space, a p-value of `1e-300` is exact to ~1e-13
//! relative, and one below the smallest `f64` is still available as a finite log
//! ([`binom_test_two_sided_ln`], [`McNemarResult::ln_p_value`](crate::McNemarResult)).
//!
//! Counts are `u64`; the number of trials must not exceed [`MAX_TRIALS`] = 2^53 so that
//! every count is exact as an `f64`.

use crate::error::{Result, StatsError, check_probability};

/// Largest number of trials accepted (2^53): every count up to it is exact as an `f64`.
pub const MAX_TRIALS: u64 = 1 << 53;

/// Relative tolerance scipy's `binomtest` uses to decide that two outcomes are equally
/// likely (`rerr = 1 + 1e-7` in `scipy/stats/_binomtest.py`).
const SCIPY_RERR: f64 = 1e-7;

/// A term below `exp(STOP) *` running sum ends a tail summation.
const STOP: f64 = -50.0;

const LN_2PI: f64 = 1.837_877_066_409_345_5;

fn check_trials(n: u64) -> Result<()> {
    if n > MAX_TRIALS {
        Err(StatsError::TooManyTrials { n, max: MAX_TRIALS })
    } else {
        Ok(())
    }
}

/// `ln(x!) - ln(sqrt(2 pi x) (x/e)^x)`, the remainder of Stirling's formula, for `x >= 1`.
fn stirlerr(x: f64) -> f64 {
    const S0: f64 = 1.0 / 12.0;
    const S1: f64 = 1.0 / 360.0;
    const S2: f64 = 1.0 / 1260.0;
    const S3: f64 = 1.0 / 1680.0;
    const S4: f64 = 1.0 / 1188.0;
    if x <= 15.0 {
        // Direct: absolute error ~ ulp(lgamma(16)) ~ 4e-15, an absolute error on the log.
        return libm::lgamma(x + 1.0) - (x + 0.5) * libm::log(x) + x - 0.5 * LN_2PI;
    }
    let xx = x * x;
    if x > 500.0 {
        (S0 - S1 / xx) / x
    } else if x > 80.0 {
        (S0 - (S1 - S2 / xx) / xx) / x
    } else if x > 35.0 {
        (S0 - (S1 - (S2 - S3 / xx) / xx) / xx) / x
    } else {
        (S0 - (S1 - (S2 - (S3 - S4 / xx) / xx) / xx) / xx) / x
    }
}

/// Deviance term `x ln(x / np) + np - x`, computed without cancellation near `x = np`.
fn bd0(x: f64, np: f64) -> f64 {
    if (x - np).abs() < 0.1 * (x + np) {
        let mut v = (x - np) / (x + np);
        let mut s = (x - np) * v;
        let mut ej = 2.0 * x * v;
        v *= v;
        let mut j = 1.0_f64;
        // The series converges geometrically (|v| < 0.1): 1000 terms is far beyond need.
        while j < 1000.0 {
            ej *= v;
            let s1 = s + ej / (2.0 * j + 1.0);
            if s1 == s {
                return s1;
            }
            s = s1;
            j += 1.0;
        }
        s
    } else {
        x * libm::log(x / np) + np - x
    }
}

/// `ln P(X = k)` for `X ~ Binomial(n, p)`, without argument checks (`k <= n`, `p` valid).
fn ln_pmf_raw(k: u64, n: u64, p: f64) -> f64 {
    let q = 1.0 - p;
    if p == 0.0 {
        return if k == 0 { 0.0 } else { f64::NEG_INFINITY };
    }
    if q == 0.0 {
        return if k == n { 0.0 } else { f64::NEG_INFINITY };
    }
    let nf = n as f64;
    if k == 0 {
        return if p < 0.1 {
            -bd0(nf, nf * q) - nf * p
        } else {
            nf * libm::log1p(-p)
        };
    }
    if k == n {
        return if q < 0.1 {
            -bd0(nf, nf * p) - nf * q
        } else {
            nf * libm::log(p)
        };
    }
    let kf = k as f64;
    let mf = (n - k) as f64;
    let lc = stirlerr(nf) - stirlerr(kf) - stirlerr(mf) - bd0(kf, nf * p) - bd0(mf, nf * q);
    let lf = LN_2PI + libm::log(kf) + libm::log1p(-kf / nf);
    lc - 0.5 * lf
}

/// `ln(e^a + e^b)` without overflow; `-inf` is the neutral element.
fn ln_add_exp(a: f64, b: f64) -> f64 {
    let (hi, lo) = if a >= b { (a, b) } else { (b, a) };
    if hi == f64::NEG_INFINITY {
        return f64::NEG_INFINITY;
    }
    hi + libm::log1p(libm::exp(lo - hi))
}

/// `ln(1 - e^a)` for `a <= 0`, accurate for `a` near 0 and for `a` very negative.
fn ln_one_minus_exp(a: f64) -> f64 {
    if a > -std::f64::consts::LN_2 {
        libm::log(-libm::expm1(a))
    } else {
        libm::log1p(-libm::exp(a))
    }
}

/// The lower mode `floor((n + 1) p)`, clamped to `n`: the pmf is non-decreasing up to it
/// and non-increasing from it.
fn mode(n: u64, p: f64) -> u64 {
    let m = ((n as f64 + 1.0) * p).floor();
    if m >= n as f64 { n } else { m as u64 }
}

/// `ln sum_{i in from..=to} pmf(i)` walking from `from` towards `to` (either direction),
/// stopping once terms are negligible. `from` must be the term nearest the mode.
fn ln_sum_outwards(from: u64, to: u64, n: u64, p: f64) -> f64 {
    let l0 = ln_pmf_raw(from, n, p);
    if l0 == f64::NEG_INFINITY {
        // The pmf is log-concave: the terms further out are impossible too.
        return f64::NEG_INFINITY;
    }
    // Sum of exp(l_i - l0); every ratio is <= 1 because terms shrink away from the mode.
    let mut acc = 1.0_f64;
    let mut i = from;
    while i != to {
        i = if to > from { i + 1 } else { i - 1 };
        let r = ln_pmf_raw(i, n, p) - l0;
        acc += libm::exp(r);
        if r - libm::log(acc) < STOP {
            break;
        }
    }
    l0 + libm::log(acc)
}

/// `ln P(X <= k)` without argument checks.
fn ln_cdf_raw(k: u64, n: u64, p: f64) -> f64 {
    if k >= n {
        return 0.0;
    }
    if k < mode(n, p) {
        ln_sum_outwards(k, 0, n, p)
    } else {
        ln_one_minus_exp(ln_sf_raw(k, n, p))
    }
}

/// `ln P(X > k)` without argument checks.
fn ln_sf_raw(k: u64, n: u64, p: f64) -> f64 {
    if k >= n {
        return f64::NEG_INFINITY;
    }
    if k >= mode(n, p) {
        ln_sum_outwards(k + 1, n, n, p)
    } else {
        ln_one_minus_exp(ln_cdf_raw(k, n, p))
    }
}

fn check_args(n: u64, p: f64) -> Result<()> {
    check_probability(p)?;
    check_trials(n)
}

/// `ln P(X = k)` for `X ~ Binomial(n, p)`.
///
/// # Errors
///
/// [`StatsError::InvalidProbability`] if `p` is not in `[0, 1]`,
/// [`StatsError::CountExceedsTotal`] if `k > n`, [`StatsError::TooManyTrials`] if
/// `n > 2^53`.
pub fn binom_ln_pmf(k: u64, n: u64, p: f64) -> Result<f64> {
    check_args(n, p)?;
    if k > n {
        return Err(StatsError::CountExceedsTotal {
            successes: k,
            total: n,
        });
    }
    Ok(ln_pmf_raw(k, n, p))
}

/// `P(X = k)` for `X ~ Binomial(n, p)` (`scipy.stats.binom.pmf`).
///
/// # Errors
///
/// As [`binom_ln_pmf`].
pub fn binom_pmf(k: u64, n: u64, p: f64) -> Result<f64> {
    binom_ln_pmf(k, n, p).map(libm::exp)
}

/// `ln P(X <= k)` for `X ~ Binomial(n, p)`; `k >= n` gives `0`.
///
/// # Errors
///
/// [`StatsError::InvalidProbability`] if `p` is not in `[0, 1]`,
/// [`StatsError::TooManyTrials`] if `n > 2^53`.
pub fn binom_ln_cdf(k: u64, n: u64, p: f64) -> Result<f64> {
    check_args(n, p)?;
    Ok(ln_cdf_raw(k, n, p).min(0.0))
}

/// `P(X <= k)` for `X ~ Binomial(n, p)` (`scipy.stats.binom.cdf`); `k >= n` gives `1`.
///
/// # Errors
///
/// As [`binom_ln_cdf`].
pub fn binom_cdf(k: u64, n: u64, p: f64) -> Result<f64> {
    binom_ln_cdf(k, n, p).map(libm::exp)
}

/// `ln P(X > k)` (strictly greater) for `X ~ Binomial(n, p)`; `k >= n` gives `-inf`.
///
/// # Errors
///
/// As [`binom_ln_cdf`].
pub fn binom_ln_sf(k: u64, n: u64, p: f64) -> Result<f64> {
    check_args(n, p)?;
    Ok(ln_sf_raw(k, n, p).min(0.0))
}

/// Survival function `P(X > k)` (**strictly** greater, the convention of
/// `scipy.stats.binom.sf`) for `X ~ Binomial(n, p)`. For `P(X >= k)` use
/// `binom_sf(k - 1, n, p)` (and `1` when `k = 0`).
///
/// # Errors
///
/// As [`binom_ln_cdf`].
pub fn binom_sf(k: u64, n: u64, p: f64) -> Result<f64> {
    binom_ln_sf(k, n, p).map(libm::exp)
}

/// Natural log of the two-sided p-value of [`binom_test_two_sided`]; finite even where the
/// p-value itself underflows to `0.0` (e.g. 400000 successes in 10^6 fair trials).
///
/// # Errors
///
/// As [`binom_test_two_sided`].
pub fn binom_test_two_sided_ln(k: u64, n: u64, p: f64) -> Result<f64> {
    check_args(n, p)?;
    if n == 0 {
        return Err(StatsError::ZeroTrials { argument: "n" });
    }
    if k > n {
        return Err(StatsError::CountExceedsTotal {
            successes: k,
            total: n,
        });
    }
    let np = p * n as f64;
    let kf = k as f64;
    if kf == np {
        return Ok(0.0);
    }
    // Outcomes at most (1 + 1e-7) times as likely as the observed one count as "as extreme".
    let threshold = ln_pmf_raw(k, n, p) + libm::log1p(SCIPY_RERR);
    let ln_p = if kf < np {
        // Other side: [ceil(np), n], pmf non-increasing. First index with pmf <= threshold.
        let (mut lo, mut hi) = (np.ceil() as u64, n + 1);
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            if ln_pmf_raw(mid, n, p) <= threshold {
                hi = mid;
            } else {
                lo = mid + 1;
            }
        }
        let lower = ln_cdf_raw(k, n, p);
        if lo > n {
            lower
        } else {
            // P(X >= lo) = P(X > lo - 1); lo >= ceil(np) >= 1 here.
            ln_add_exp(lower, ln_sf_raw(lo - 1, n, p))
        }
    } else {
        // Other side: [0, floor(np)], pmf non-decreasing. Count of indices with
        // pmf <= threshold (they form a prefix).
        let (mut lo, mut hi) = (0_u64, np.floor() as u64 + 1);
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            if ln_pmf_raw(mid, n, p) <= threshold {
                lo = mid + 1;
            } else {
                hi = mid;
            }
        }
        // P(X >= k) = P(X > k - 1); k > np >= 0 so k >= 1.
        let upper = ln_sf_raw(k - 1, n, p);
        if lo == 0 {
            upper
        } else {
            ln_add_exp(ln_cdf_raw(lo - 1, n, p), upper)
        }
    };
    Ok(ln_p.min(0.0))
}

/// Exact two-sided binomial test of `H0: P(success) = p` after `k` successes in `n`
/// trials, with the definition of `scipy.stats.binomtest(k, n, p).pvalue`: the total
/// probability of all outcomes whose probability is at most `(1 + 1e-7)` times that of
/// the observed outcome (scipy's relative tolerance for "equally likely"). `k = n p`
/// gives exactly `1`, and the result is clamped to `<= 1`.
///
/// # Errors
///
/// [`StatsError::ZeroTrials`] if `n = 0`, [`StatsError::CountExceedsTotal`] if `k > n`,
/// [`StatsError::InvalidProbability`] if `p` is not in `[0, 1]`,
/// [`StatsError::TooManyTrials`] if `n > 2^53`.
pub fn binom_test_two_sided(k: u64, n: u64, p: f64) -> Result<f64> {
    binom_test_two_sided_ln(k, n, p).map(|l| libm::exp(l).min(1.0))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn rel(a: f64, b: f64) -> f64 {
        ((a - b) / b).abs()
    }

    #[test]
    fn pmf_matches_direct_formula_for_small_n() {
        for n in 1..40_u64 {
            for k in 0..=n {
                let p = 0.37;
                let direct = libm::lgamma(n as f64 + 1.0)
                    - libm::lgamma(k as f64 + 1.0)
                    - libm::lgamma((n - k) as f64 + 1.0)
                    + k as f64 * libm::log(p)
                    + (n - k) as f64 * libm::log1p(-p);
                let ours = binom_ln_pmf(k, n, p).unwrap();
                assert!((ours - direct).abs() < 1e-12, "n={n} k={k}");
            }
        }
    }

    #[test]
    fn pmf_sums_to_one() {
        for &(n, p) in &[(1_u64, 0.5), (17, 0.2), (200, 0.93), (1000, 0.5)] {
            let total: f64 = (0..=n).map(|k| binom_pmf(k, n, p).unwrap()).sum();
            assert!((total - 1.0).abs() < 1e-12);
            for k in [0, n / 3, n / 2, n] {
                let c = binom_cdf(k, n, p).unwrap();
                let s = binom_sf(k, n, p).unwrap();
                assert!((c + s - 1.0).abs() < 1e-13, "n={n} k={k}");
            }
        }
    }

    #[test]
    fn degenerate_probabilities() {
        assert_eq!(binom_cdf(0, 10, 0.0).unwrap(), 1.0);
        assert_eq!(binom_sf(0, 10, 0.0).unwrap(), 0.0);
        assert_eq!(binom_cdf(9, 10, 1.0).unwrap(), 0.0);
        assert_eq!(binom_sf(9, 10, 1.0).unwrap(), 1.0);
        assert_eq!(binom_test_two_sided(0, 10, 0.0).unwrap(), 1.0);
        assert_eq!(binom_test_two_sided(3, 10, 0.0).unwrap(), 0.0);
        assert_eq!(binom_test_two_sided(10, 10, 1.0).unwrap(), 1.0);
        assert_eq!(binom_test_two_sided(2, 10, 1.0).unwrap(), 0.0);
        assert_eq!(binom_cdf(0, 0, 0.5).unwrap(), 1.0);
    }

    #[test]
    fn small_exact_values() {
        // binomtest(3, 15, 0.1).pvalue from the scipy docs: 0.18406106910639114
        assert!(
            rel(
                binom_test_two_sided(3, 15, 0.1).unwrap(),
                0.184_061_069_106_391_14
            ) < 1e-12
        );
        // P(X <= 2 | 10, 0.5) = 56 / 1024
        assert!(rel(binom_cdf(2, 10, 0.5).unwrap(), 56.0 / 1024.0) < 1e-14);
        // P(X > 7 | 10, 0.5) = 56 / 1024
        assert!(rel(binom_sf(7, 10, 0.5).unwrap(), 56.0 / 1024.0) < 1e-14);
    }

    #[test]
    fn rejects_bad_arguments() {
        assert!(matches!(
            binom_test_two_sided(5, 4, 0.5),
            Err(StatsError::CountExceedsTotal {
                successes: 5,
                total: 4
            })
        ));
        assert!(matches!(
            binom_test_two_sided(0, 0, 0.5),
            Err(StatsError::ZeroTrials { .. })
        ));
        assert!(matches!(
            binom_cdf(1, 4, f64::NAN),
            Err(StatsError::InvalidProbability { .. })
        ));
        assert!(matches!(
            binom_sf(1, u64::MAX, 0.5),
            Err(StatsError::TooManyTrials { .. })
        ));
    }

    #[test]
    fn huge_n_stays_finite() {
        let l = binom_test_two_sided_ln(400_000, 1_000_000, 0.5).unwrap();
        // -n KL(0.4 || 0.5) + ln 2 - O(ln n) ~ -20135.
        assert!(l.is_finite() && l < -20_000.0 && l > -20_200.0, "{l}");
        let p = binom_test_two_sided(482_000, 1_000_000, 0.5).unwrap();
        assert!(p > 0.0 && p < 1e-280, "{p}");
    }
}
