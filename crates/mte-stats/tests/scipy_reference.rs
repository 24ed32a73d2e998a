//! Parity with scipy: every value in `fixtures/scipy_reference.json` was computed by
//! `tools/reference/stats_reference.py` with the scipy / numpy versions recorded in the
//! fixture (see `fixtures/README.md`).
//!
//! Tolerances are relative unless stated, chosen per family with the reason next to each
//! constant; all are far tighter than anything a report prints (2 significant figures).

#![allow(clippy::unwrap_used)]

use mte_stats::{
    WilcoxonMethod, auroc, binom_cdf, binom_sf, binom_test_two_sided, mcnemar_exact, norm_cdf,
    norm_pdf, norm_ppf, norm_sf, two_proportion_ztest, wilcoxon_signed_rank,
    wilcoxon_signed_rank_diffs, wilson_interval,
};
use serde::Deserialize;

/// Exact binomial tails (binomtest, binom.cdf/sf, McNemar). Both sides compute the same
/// exact sums, scipy via Boost's incomplete beta, this crate via Loader's log-pmf summed in
/// log space. Observed agreement is ~1e-14 to 7e-13 relative (the latter at p ~ 1e-284),
/// except binomtest(12, 987654, 2.5e-5) at 2.3e-11: 50-digit mpmath gives
/// 0.0084168377780217095, which this crate matches to 2e-15 and scipy misses by 2.3e-11
/// (its binom.cdf is off by 5e-11 there). 1e-9 leaves room for such library error while
/// any wrong term or off-by-one in a tail moves the value by far more.
const EXACT_TAIL: f64 = 1e-9;

/// Exact Wilcoxon p-values are dyadic rationals (count / 2^n) that both sides compute
/// exactly; the only rounding is scipy's `1 - sf` branch near p = 1.
const WILCOXON_EXACT: f64 = 1e-13;

/// Normal-approximation p-values and |z|: same formula on both sides, differing only in
/// the erfc implementation (musl's via libm vs cephes) and summation order of the ranks.
const NORMAL_FORMULA: f64 = 1e-12;

/// Normal cdf/sf/pdf: same erfc-based formula as `scipy.special.ndtr`; the implementations
/// of erfc differ by a few ulps, amplified in the far tail by the argument scaling x/sqrt 2
/// (relative error ~ x^2 * 2^-53, i.e. ~2e-13 at x = 37).
const NORMAL_CDF: f64 = 1e-12;

/// Normal quantile: Acklam + two Halley steps vs cephes `ndtri`. Both are accurate to the
/// CDF's precision; the tail limits are set by the CDF (see [`NORMAL_CDF`]).
const NORMAL_PPF: f64 = 1e-12;

/// Wilson bounds: closed form around the quantile, so the quantile's tolerance.
const WILSON: f64 = 1e-12;

/// AUROC is a ratio of integers (doubled midrank sums): exact up to the final division.
const AUROC: f64 = 1e-15;

/// Below this both values are treated as zero (scipy underflows tails such as
/// P(X <= 2 | 1000, 0.9) ~ 1e-993 to 0.0, and so does an `f64`).
const TINY: f64 = 1e-305;

#[derive(Deserialize)]
struct Fixture {
    versions: serde_json::Value,
    binomtest: Vec<BinomTest>,
    binom_tails: Vec<BinomTail>,
    mcnemar: Vec<McNemar>,
    mcnemar_cc: Vec<McNemar>,
    wilcoxon: Vec<Wilcoxon>,
    ztest: Vec<ZTest>,
    norm: Vec<NormPoint>,
    norm_ppf: Vec<NormPpf>,
    wilson: Vec<Wilson>,
    auroc: Vec<Auroc>,
}

#[derive(Deserialize)]
struct BinomTest {
    k: u64,
    n: u64,
    p: f64,
    pvalue: f64,
}

#[derive(Deserialize)]
struct BinomTail {
    k: u64,
    n: u64,
    p: f64,
    cdf: f64,
    sf: f64,
}

#[derive(Deserialize)]
struct McNemar {
    b: u64,
    c: u64,
    pvalue: f64,
}

#[derive(Deserialize)]
struct Wilcoxon {
    name: String,
    x: Vec<f64>,
    y: Option<Vec<f64>>,
    n_nonzero: usize,
    method: String,
    statistic: f64,
    pvalue: f64,
    abs_z: Option<f64>,
}

#[derive(Deserialize)]
struct ZTest {
    x1: u64,
    n1: u64,
    x2: u64,
    n2: u64,
    z: f64,
    pvalue: f64,
}

#[derive(Deserialize)]
struct NormPoint {
    x: f64,
    pdf: f64,
    cdf: f64,
    sf: f64,
}

#[derive(Deserialize)]
struct NormPpf {
    p: f64,
    x: f64,
}

#[derive(Deserialize)]
struct Wilson {
    k: u64,
    n: u64,
    confidence: f64,
    lo: f64,
    hi: f64,
}

#[derive(Deserialize)]
struct Auroc {
    name: String,
    pos: Vec<f64>,
    neg: Vec<f64>,
    auroc: f64,
}

fn fixture() -> Fixture {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/fixtures/scipy_reference.json"
    );
    let text = std::fs::read_to_string(path).unwrap();
    serde_json::from_str(&text).unwrap()
}

/// Relative closeness, with values both below [`TINY`] (or both exactly equal, including
/// both zero) accepted.
fn assert_close(actual: f64, expected: f64, rel: f64, what: &str) {
    if actual == expected || (actual.abs() < TINY && expected.abs() < TINY) {
        return;
    }
    let err = ((actual - expected) / expected).abs();
    assert!(
        err <= rel,
        "{what}: got {actual:e}, scipy {expected:e}, relative error {err:e} > {rel:e}"
    );
}

#[test]
fn fixture_records_pinned_versions() {
    let f = fixture();
    assert_eq!(f.versions["scipy"], "1.17.1");
    assert_eq!(f.versions["numpy"], "2.2.6");
}

#[test]
fn binomtest_two_sided_matches_scipy() {
    for c in fixture().binomtest {
        let ours = binom_test_two_sided(c.k, c.n, c.p).unwrap();
        let what = format!("binomtest({}, {}, {})", c.k, c.n, c.p);
        assert_close(ours, c.pvalue, EXACT_TAIL, &what);
    }
}

#[test]
fn binom_cdf_and_sf_match_scipy() {
    for c in fixture().binom_tails {
        let what = format!("({}, {}, {})", c.k, c.n, c.p);
        assert_close(
            binom_cdf(c.k, c.n, c.p).unwrap(),
            c.cdf,
            EXACT_TAIL,
            &format!("cdf{what}"),
        );
        assert_close(
            binom_sf(c.k, c.n, c.p).unwrap(),
            c.sf,
            EXACT_TAIL,
            &format!("sf{what}"),
        );
    }
}

#[test]
fn mcnemar_matches_scipy_binomtest() {
    for c in fixture().mcnemar {
        let r = mcnemar_exact(c.b, c.c).unwrap();
        assert_close(
            r.p_value,
            c.pvalue,
            EXACT_TAIL,
            &format!("mcnemar {}:{}", c.b, c.c),
        );
    }
}

/// The continuity-corrected chi-square McNemar: scipy's `chi2.sf(stat, 1)` and this crate's
/// `2 norm_sf(sqrt(stat))` are the same function (chi2 with one degree of freedom is a
/// squared normal), evaluated through different erfc implementations, so the tolerance is
/// that of the normal formulas.
#[test]
fn mcnemar_chi2_corrected_matches_scipy_chi2() {
    let f = fixture();
    assert!(f.mcnemar_cc.iter().any(|c| (c.b, c.c) == (78, 10)));
    for c in f.mcnemar_cc {
        let r = mte_stats::mcnemar_chi2_corrected(c.b, c.c).unwrap();
        assert_close(
            r.p_value,
            c.pvalue,
            NORMAL_FORMULA,
            &format!("mcnemar chi2-cc {}:{}", c.b, c.c),
        );
        assert!(
            (r.ln_p_value - c.pvalue.ln()).abs() < 1e-9,
            "ln p {}:{}",
            c.b,
            c.c
        );
        // Chosen by name, the same test.
        let by_name: mte_stats::McNemarTest = "chi2-cc".parse().unwrap();
        assert_eq!(by_name.run(c.b, c.c).unwrap(), r);
    }
    assert!("chi2".parse::<mte_stats::McNemarTest>().is_err());
}

#[test]
fn wilcoxon_matches_scipy_auto() {
    for c in fixture().wilcoxon {
        let r = match &c.y {
            Some(y) => wilcoxon_signed_rank(&c.x, y).unwrap(),
            None => wilcoxon_signed_rank_diffs(&c.x).unwrap(),
        };
        let expected_method = match c.method.as_str() {
            "exact" => WilcoxonMethod::Exact,
            "normal" => WilcoxonMethod::Normal,
            other => panic!("unknown method {other}"),
        };
        assert_eq!(r.method, expected_method, "{}: method", c.name);
        assert_eq!(r.n, c.n_nonzero, "{}: n", c.name);
        assert_eq!(r.zeros, c.x.len() - c.n_nonzero, "{}: zeros", c.name);
        // Rank sums are multiples of 1/2: exact on both sides.
        assert_eq!(r.statistic, c.statistic, "{}: statistic", c.name);
        let tol = match r.method {
            WilcoxonMethod::Exact => WILCOXON_EXACT,
            WilcoxonMethod::Normal => NORMAL_FORMULA,
        };
        assert_close(r.p_value, c.pvalue, tol, &c.name);
        match (r.z, c.abs_z) {
            (Some(z), Some(abs_z)) => assert_close(z.abs(), abs_z, NORMAL_FORMULA, &c.name),
            (None, None) => {}
            (z, abs_z) => panic!("{}: z {z:?} vs scipy {abs_z:?}", c.name),
        }
    }
}

#[test]
fn two_proportion_ztest_matches_formula() {
    for c in fixture().ztest {
        let r = two_proportion_ztest(c.x1, c.n1, c.x2, c.n2).unwrap();
        let what = format!("z-test {}/{} vs {}/{}", c.x1, c.n1, c.x2, c.n2);
        assert_close(r.z, c.z, NORMAL_FORMULA, &what);
        assert_close(r.p_value, c.pvalue, NORMAL_FORMULA, &what);
    }
}

#[test]
fn normal_distribution_matches_scipy() {
    let f = fixture();
    for c in f.norm {
        assert_close(norm_pdf(c.x), c.pdf, NORMAL_CDF, &format!("pdf({})", c.x));
        assert_close(norm_cdf(c.x), c.cdf, NORMAL_CDF, &format!("cdf({})", c.x));
        assert_close(norm_sf(c.x), c.sf, NORMAL_CDF, &format!("sf({})", c.x));
    }
    for c in f.norm_ppf {
        assert_close(
            norm_ppf(c.p).unwrap(),
            c.x,
            NORMAL_PPF,
            &format!("ppf({})", c.p),
        );
    }
}

#[test]
fn wilson_matches_scipy_proportion_ci() {
    for c in fixture().wilson {
        let (lo, hi) = wilson_interval(c.k, c.n, c.confidence).unwrap();
        let what = format!("wilson({}, {}, {})", c.k, c.n, c.confidence);
        assert_close(lo, c.lo, WILSON, &format!("{what} lo"));
        assert_close(hi, c.hi, WILSON, &format!("{what} hi"));
    }
}

#[test]
fn auroc_matches_mannwhitneyu() {
    for c in fixture().auroc {
        assert_close(auroc(&c.pos, &c.neg).unwrap(), c.auroc, AUROC, &c.name);
    }
}
