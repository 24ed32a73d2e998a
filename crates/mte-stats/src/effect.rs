//! Effect sizes: the recovered fraction of a defence, and AUROC of a detector score.

use std::cmp::Ordering;

use crate::error::{Result, StatsError, check_finite, check_sample};

/// Fraction of the attack's damage that a defence recovers:
/// `(defended - undefended) / (clean - undefended)`.
///
/// `1` means the defence restores clean performance, `0` means it does nothing, negative
/// values mean it makes things worse, and values above `1` mean it beats the clean
/// baseline. Works for metrics in either direction (success rate or error), since numerator
/// and denominator flip sign together.
///
/// ```
/// // clean 0.80, attacked 0.20, defended 0.65: 75 % of the damage recovered.
/// let f = mte_stats::recovered_fraction(0.80, 0.20, 0.65)?;
/// assert!((f - 0.75).abs() < 1e-12);
/// # Ok::<(), mte_stats::StatsError>(())
/// ```
///
/// # Errors
///
/// [`StatsError::NonFinite`] naming the argument (with `index` 0),
/// [`StatsError::UndefinedRecovery`] when `clean == undefended`.
pub fn recovered_fraction(clean: f64, undefended: f64, defended: f64) -> Result<f64> {
    check_finite("clean", &[clean])?;
    check_finite("undefended", &[undefended])?;
    check_finite("defended", &[defended])?;
    if clean == undefended {
        return Err(StatsError::UndefinedRecovery { clean, undefended });
    }
    Ok((defended - undefended) / (clean - undefended))
}

/// The recovered fraction of paired samples with its jackknife standard error: `clean[i]`,
/// `undefended[i]` and `defended[i]` are one seed's values (the same reset seed in the clean
/// cell, the corrupted baseline and the corrupted defended arm). The estimate is
/// [`recovered_fraction`] of the three means; the standard error is the delete-one
/// jackknife's, `sqrt((n − 1) / n · Σ (R₋ᵢ − R̄)²)` over the `n` fractions that leave one seed
/// out. It needs no random draws, and it is the paired standard error of the mean difference
/// divided by the denominator when `clean` and `undefended` are constant (the delta method's
/// answer for a ratio of means).
///
/// ```
/// let (f, se) = mte_stats::recovered_fraction_jackknife(
///     &[0.8, 0.8, 0.8], &[0.2, 0.2, 0.2], &[0.5, 0.6, 0.7])?;
/// assert!((f - 2.0 / 3.0).abs() < 1e-12);
/// // sd(defended) / sqrt(3) / (0.8 - 0.2)
/// assert!((se - 0.1 / 3f64.sqrt() / 0.6).abs() < 1e-12);
/// # Ok::<(), mte_stats::StatsError>(())
/// ```
///
/// # Errors
///
/// [`StatsError::LengthMismatch`] when the three differ in length,
/// [`StatsError::TooFewSamples`] below 2 seeds, [`StatsError::NonFinite`] naming the
/// argument, [`StatsError::UndefinedRecovery`] when the full-sample or a leave-one-out
/// denominator is 0.
pub fn recovered_fraction_jackknife(
    clean: &[f64],
    undefended: &[f64],
    defended: &[f64],
) -> Result<(f64, f64)> {
    let n = clean.len();
    for other in [undefended.len(), defended.len()] {
        if other != n {
            return Err(StatsError::LengthMismatch {
                left: n,
                right: other,
            });
        }
    }
    if n < 2 {
        return Err(StatsError::TooFewSamples {
            argument: "clean",
            needed: 2,
            got: n,
        });
    }
    check_finite("clean", clean)?;
    check_finite("undefended", undefended)?;
    check_finite("defended", defended)?;
    let sum = |v: &[f64]| v.iter().sum::<f64>();
    let (sc, su, sd) = (sum(clean), sum(undefended), sum(defended));
    let nf = n as f64;
    let full = recovered_fraction(sc / nf, su / nf, sd / nf)?;
    let loo = (0..n)
        .map(|i| {
            let m = nf - 1.0;
            recovered_fraction(
                (sc - clean[i]) / m,
                (su - undefended[i]) / m,
                (sd - defended[i]) / m,
            )
        })
        .collect::<Result<Vec<f64>>>()?;
    let mean = loo.iter().sum::<f64>() / nf;
    let ss: f64 = loo.iter().map(|r| (r - mean).powi(2)).sum();
    Ok((full, ((nf - 1.0) / nf * ss).sqrt()))
}

/// Both samples checked (non-empty, finite) and pooled as `(score, is_positive)`, lowest
/// score first.
fn sorted_pool(positive_scores: &[f64], negative_scores: &[f64]) -> Result<Vec<(f64, bool)>> {
    check_sample("positive_scores", positive_scores)?;
    check_sample("negative_scores", negative_scores)?;
    let mut pooled: Vec<(f64, bool)> = positive_scores
        .iter()
        .map(|&s| (s, true))
        .chain(negative_scores.iter().map(|&s| (s, false)))
        .collect();
    // Finite values only: partial_cmp never fails, and treats -0.0 == 0.0.
    pooled.sort_by(|a, b| a.0.partial_cmp(&b.0).unwrap_or(Ordering::Equal));
    Ok(pooled)
}

/// The empirical ROC curve of a detector score: `(false positive rate, true positive rate)`
/// at every threshold between distinct pooled scores, from `(0, 0)` (nothing flagged) to
/// `(1, 1)` (everything flagged), "flagged" meaning `score >= threshold`. Tied scores move
/// both rates in one diagonal step, so the trapezoidal area under these points is exactly
/// [`auroc`] (ties counting 1/2).
///
/// ```
/// let roc = mte_stats::roc_curve(&[0.9, 0.4], &[0.4, 0.1])?;
/// assert_eq!(roc, vec![(0.0, 0.0), (0.0, 0.5), (0.5, 1.0), (1.0, 1.0)]);
/// # Ok::<(), mte_stats::StatsError>(())
/// ```
///
/// # Errors
///
/// As [`auroc`]: an empty side, or a NaN or infinite score.
pub fn roc_curve(positive_scores: &[f64], negative_scores: &[f64]) -> Result<Vec<(f64, f64)>> {
    let (n1, n0) = (positive_scores.len() as f64, negative_scores.len() as f64);
    let mut pooled = sorted_pool(positive_scores, negative_scores)?;
    pooled.reverse(); // highest first
    let mut points = vec![(0.0, 0.0)];
    let (mut tp, mut fp) = (0usize, 0usize);
    let mut s = 0;
    while s < pooled.len() {
        let mut e = s;
        while e < pooled.len() && pooled[e].0 == pooled[s].0 {
            if pooled[e].1 {
                tp += 1;
            } else {
                fp += 1;
            }
            e += 1;
        }
        points.push((fp as f64 / n0, tp as f64 / n1));
        s = e;
    }
    Ok(points)
}

/// Area under the ROC curve: the probability that a randomly drawn positive scores higher
/// than a randomly drawn negative, ties counting 1/2.
///
/// Computed as the Mann–Whitney `U` of the positives over `n1 n0`, from midranks of the
/// pooled scores after one sort: `O((n1 + n0) log(n1 + n0))`. This equals
/// `scipy.stats.mannwhitneyu(pos, neg).statistic / (n1 * n0)` and
/// `sklearn.metrics.roc_auc_score`. `-0.0` and `0.0` are the same score. All scores tied
/// gives `0.5`; complete separation gives `1` (or `0`), and
/// `auroc(a, b) + auroc(b, a) = 1`.
///
/// ```
/// let auc = mte_stats::auroc(&[0.9, 0.8, 0.4], &[0.1, 0.4, 0.3])?;
/// assert!((auc - 8.5 / 9.0).abs() < 1e-15);
/// # Ok::<(), mte_stats::StatsError>(())
/// ```
///
/// # Errors
///
/// [`StatsError::EmptySample`] if either side is empty, [`StatsError::NonFinite`] for a
/// NaN or infinite score.
pub fn auroc(positive_scores: &[f64], negative_scores: &[f64]) -> Result<f64> {
    let n1 = positive_scores.len();
    let n0 = negative_scores.len();
    let pooled = sorted_pool(positive_scores, negative_scores)?;
    // Sum of doubled midranks of the positives: integer arithmetic, exact.
    let mut rank_sum2: u128 = 0;
    let mut s = 0;
    while s < pooled.len() {
        let mut e = s + 1;
        while e < pooled.len() && pooled[e].0 == pooled[s].0 {
            e += 1;
        }
        let positives = pooled[s..e].iter().filter(|v| v.1).count() as u128;
        rank_sum2 += positives * (s + 1 + e) as u128;
        s = e;
    }
    // U = R1 - n1 (n1 + 1) / 2, doubled.
    let n1w = n1 as u128;
    let u2 = rank_sum2 - n1w * (n1w + 1);
    Ok(u2 as f64 / 2.0 / (n1 as f64 * n0 as f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roc_curve_area_is_the_auroc_and_ties_step_diagonally() -> Result<()> {
        let pos = [0.9, 0.8, 0.4, 0.4, 2.0];
        let neg = [0.1, 0.4, 0.3, 0.4, 0.85];
        let roc = roc_curve(&pos, &neg)?;
        assert_eq!(roc.first(), Some(&(0.0, 0.0)));
        assert_eq!(roc.last(), Some(&(1.0, 1.0)));
        assert!(roc.windows(2).all(|w| w[1].0 >= w[0].0 && w[1].1 >= w[0].1));
        let area: f64 = roc
            .windows(2)
            .map(|w| (w[1].0 - w[0].0) * (w[1].1 + w[0].1) / 2.0)
            .sum();
        assert!((area - auroc(&pos, &neg)?).abs() < 1e-12, "{area}");
        // The tie at 0.4 (two positives, two negatives) is one diagonal step of (0.4, 0.4).
        assert!(
            roc.contains(&(0.2, 0.6)) && roc.contains(&(0.6, 1.0)),
            "{roc:?}"
        );
        assert!(roc_curve(&[], &neg).is_err());
        assert!(roc_curve(&pos, &[f64::NAN]).is_err());
        Ok(())
    }

    /// The jackknife against its closed form for a mean (constant clean and undefended), a
    /// naive leave-one-out recomputation on uneven data, and its typed errors.
    #[test]
    fn jackknife_recovered_fraction() {
        let d = [0.31, 0.52, 0.48, 0.90, 0.12, 0.66];
        let (f, se) = recovered_fraction_jackknife(&[0.7; 6], &[0.1; 6], &d).unwrap();
        let m = d.iter().sum::<f64>() / 6.0;
        let sd = (d.iter().map(|x| (x - m).powi(2)).sum::<f64>() / 5.0).sqrt();
        assert!((f - (m - 0.1) / 0.6).abs() < 1e-12);
        assert!((se - sd / 6f64.sqrt() / 0.6).abs() < 1e-12, "{se}");
        let c = [0.9, 0.7, 0.8, 0.6, 0.95];
        let u = [0.1, 0.3, 0.2, 0.25, 0.05];
        let (f, se) = recovered_fraction_jackknife(&c, &u, &d[..5]).unwrap();
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        assert!((f - (mean(&d[..5]) - mean(&u)) / (mean(&c) - mean(&u))).abs() < 1e-12);
        let loo: Vec<f64> = (0..5)
            .map(|i| {
                let drop = |v: &[f64]| {
                    v.iter()
                        .enumerate()
                        .filter(|&(j, _)| j != i)
                        .map(|(_, x)| *x)
                        .collect::<Vec<_>>()
                };
                let (c, u, dd) = (drop(&c), drop(&u), drop(&d[..5]));
                (mean(&dd) - mean(&u)) / (mean(&c) - mean(&u))
            })
            .collect();
        let lm = mean(&loo);
        let want = (0.8 * loo.iter().map(|r| (r - lm).powi(2)).sum::<f64>()).sqrt();
        assert!((se - want).abs() < 1e-12, "{se} vs {want}");
        assert!(matches!(
            recovered_fraction_jackknife(&[0.5], &[0.1], &[0.3]),
            Err(StatsError::TooFewSamples { .. })
        ));
        assert!(matches!(
            recovered_fraction_jackknife(&[0.5, 0.5], &[0.1], &[0.3, 0.3]),
            Err(StatsError::LengthMismatch { .. })
        ));
        assert!(matches!(
            recovered_fraction_jackknife(&[0.2, 0.2], &[0.2, 0.2], &[0.3, 0.3]),
            Err(StatsError::UndefinedRecovery { .. })
        ));
    }
}
