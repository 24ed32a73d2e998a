//! Multiple-comparison adjustment.

use crate::error::{Result, StatsError};

/// Holm–Bonferroni adjusted p-values, returned in the input order.
///
/// With the `m` p-values sorted ascending, `p_(1) <= ... <= p_(m)`, the adjusted value of
/// `p_(i)` is `min(1, max_{j <= i} (m - j + 1) p_(j))`. Rejecting every hypothesis whose
/// adjusted p-value is `<= alpha` controls the family-wise error rate at `alpha`. The
/// adjusted values are `>= ` the raw ones, at most 1, and monotone in the raw order (a
/// smaller raw p-value never gets a larger adjusted one); equal raw values get equal
/// adjusted values. Same as `statsmodels.stats.multitest.multipletests(p, method='holm')`.
/// An empty family gives an empty vector.
///
/// ```
/// let adj = mte_stats::holm(&[0.01, 0.04, 0.03])?;
/// // sorted: 0.01 * 3 = 0.03, 0.03 * 2 = 0.06, max(0.06, 0.04 * 1) = 0.06
/// let expected = [0.03, 0.06, 0.06];
/// assert!(adj.iter().zip(expected).all(|(a, e)| (a - e).abs() < 1e-15));
/// # Ok::<(), mte_stats::StatsError>(())
/// ```
///
/// # Errors
///
/// [`StatsError::InvalidPValue`] for a NaN or a value outside `[0, 1]`.
pub fn holm(p_values: &[f64]) -> Result<Vec<f64>> {
    if let Some(index) = p_values.iter().position(|p| !(0.0..=1.0).contains(p)) {
        return Err(StatsError::InvalidPValue {
            index,
            value: p_values[index],
        });
    }
    let m = p_values.len();
    let mut order: Vec<usize> = (0..m).collect();
    order.sort_by(|&a, &b| p_values[a].total_cmp(&p_values[b]));
    let mut adjusted = vec![0.0; m];
    let mut running = 0.0_f64;
    for (rank, &i) in order.iter().enumerate() {
        let candidate = ((m - rank) as f64 * p_values[i]).min(1.0);
        running = running.max(candidate);
        adjusted[i] = running;
    }
    Ok(adjusted)
}
