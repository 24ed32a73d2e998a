//! `mte.stats`: the paired statistics of mte-stats (each checked against scipy in the
//! Python tests).

use mte_stats::McNemarTest;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::err;

/// McNemar's test on `b:c` discordant pairs; `method` is `"exact"` (the default) or
/// `"chi2-cc"` (continuity-corrected chi-square). Returns the two-sided p-value.
#[pyfunction]
#[pyo3(signature = (b, c, method = "exact"))]
fn mcnemar(b: u64, c: u64, method: &str) -> PyResult<f64> {
    let test: McNemarTest = method.parse().map_err(err)?;
    Ok(test.run(b, c).map_err(err)?.p_value)
}

/// Two-sided Wilcoxon signed-rank test of paired `x`, `y` (scipy's rules): a dict with
/// `statistic`, `pvalue`, `method` (`"exact"` or `"normal"`), `n`, `zeros`.
#[pyfunction]
fn wilcoxon<'py>(py: Python<'py>, x: Vec<f64>, y: Vec<f64>) -> PyResult<Bound<'py, PyDict>> {
    let r = mte_stats::wilcoxon_signed_rank(&x, &y).map_err(err)?;
    let d = PyDict::new(py);
    d.set_item("statistic", r.statistic)?;
    d.set_item("pvalue", r.p_value)?;
    let method = match r.method {
        mte_stats::WilcoxonMethod::Exact => "exact",
        mte_stats::WilcoxonMethod::Normal => "normal",
    };
    d.set_item("method", method)?;
    d.set_item("n", r.n)?;
    d.set_item("zeros", r.zeros)?;
    Ok(d)
}

/// Pooled two-proportion z-test: `(z, pvalue)`.
#[pyfunction]
fn two_proportion_z(x1: u64, n1: u64, x2: u64, n2: u64) -> PyResult<(f64, f64)> {
    let r = mte_stats::two_proportion_ztest(x1, n1, x2, n2).map_err(err)?;
    Ok((r.z, r.p_value))
}

/// Holm's step-down adjusted p-values, in input order.
#[pyfunction]
fn holm(pvalues: Vec<f64>) -> PyResult<Vec<f64>> {
    mte_stats::holm(&pvalues).map_err(err)
}

/// AUROC: the probability that a positive scores above a negative, ties counting 1/2.
#[pyfunction]
fn auroc(positive: Vec<f64>, negative: Vec<f64>) -> PyResult<f64> {
    mte_stats::auroc(&positive, &negative).map_err(err)
}

/// Wilson score interval of `successes` in `n` at `confidence`: `(low, high)`.
#[pyfunction]
#[pyo3(signature = (successes, n, confidence = 0.95))]
fn wilson(successes: u64, n: u64, confidence: f64) -> PyResult<(f64, f64)> {
    mte_stats::wilson_interval(successes, n, confidence).map_err(err)
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(mcnemar, m)?)?;
    m.add_function(wrap_pyfunction!(wilcoxon, m)?)?;
    m.add_function(wrap_pyfunction!(two_proportion_z, m)?)?;
    m.add_function(wrap_pyfunction!(holm, m)?)?;
    m.add_function(wrap_pyfunction!(auroc, m)?)?;
    m.add_function(wrap_pyfunction!(wilson, m)?)?;
    Ok(())
}
