//! Property tests: invariants that must hold for any valid input.

#![allow(clippy::unwrap_used)]

use mte_stats::{
    auroc, binom_cdf, binom_pmf, binom_sf, binom_test_two_sided, holm, mcnemar_exact, norm_cdf,
    norm_ppf, two_proportion_ztest, wilcoxon_signed_rank_diffs, wilson_interval,
};
use proptest::prelude::*;

/// Scores on a coarse grid so that ties are common.
fn scores(max_len: usize) -> impl Strategy<Value = Vec<f64>> {
    prop::collection::vec((-20_i32..20).prop_map(|v| f64::from(v) / 4.0), 1..max_len)
}

proptest! {
    // No regression files: this crate keeps no proptest-regressions directory.
    #![proptest_config(ProptestConfig {
        cases: 256,
        failure_persistence: None,
        ..ProptestConfig::default()
    })]

    #[test]
    fn binomial_test_p_in_unit_interval(n in 1_u64..2_000, frac in 0.0..=1.0_f64, p in 0.0..=1.0_f64) {
        let k = ((n as f64) * frac).floor() as u64;
        let v = binom_test_two_sided(k.min(n), n, p).unwrap();
        prop_assert!((0.0..=1.0).contains(&v));
    }

    /// The two-sided definition, summed by brute force over all outcomes.
    #[test]
    fn binomial_test_matches_brute_force(n in 1_u64..120, frac in 0.0..=1.0_f64, p in 0.0..=1.0_f64) {
        let k = ((n as f64) * frac).floor() as u64;
        let observed = binom_pmf(k, n, p).unwrap();
        let brute: f64 = (0..=n)
            .map(|i| binom_pmf(i, n, p).unwrap())
            .filter(|&q| q <= observed * (1.0 + 1e-7))
            .sum();
        let expected = if (k as f64) == p * n as f64 { 1.0 } else { brute.min(1.0) };
        let ours = binom_test_two_sided(k, n, p).unwrap();
        prop_assert!(
            (ours - expected).abs() <= 1e-12 * expected.max(1e-300),
            "k={k} n={n} p={p}: {ours:e} vs brute force {expected:e}"
        );
    }

    #[test]
    fn binomial_tails_are_complementary(n in 0_u64..5_000, frac in 0.0..=1.0_f64, p in 0.0..=1.0_f64) {
        let k = ((n as f64) * frac).floor() as u64;
        let c = binom_cdf(k, n, p).unwrap();
        let s = binom_sf(k, n, p).unwrap();
        prop_assert!((0.0..=1.0).contains(&c) && (0.0..=1.0).contains(&s));
        prop_assert!((c + s - 1.0).abs() < 1e-12, "cdf {c} + sf {s}");
    }

    #[test]
    fn mcnemar_p_in_unit_interval(b in 0_u64..100_000, c in 0_u64..100_000) {
        let r = mcnemar_exact(b, c).unwrap();
        prop_assert!((0.0..=1.0).contains(&r.p_value));
        prop_assert!(r.ln_p_value <= 0.0);
    }

    #[test]
    fn wilcoxon_p_in_unit_interval(d in prop::collection::vec((-8_i32..8).prop_map(f64::from), 1..80)) {
        match wilcoxon_signed_rank_diffs(&d) {
            Ok(r) => {
                prop_assert!((0.0..=1.0).contains(&r.p_value));
                prop_assert!(r.statistic >= 0.0);
                let nf = r.n as f64;
                prop_assert!(r.statistic <= nf * (nf + 1.0) / 4.0);
            }
            Err(e) => prop_assert!(d.iter().all(|&v| v == 0.0), "{e}"),
        }
    }

    #[test]
    fn ztest_p_in_unit_interval(n1 in 1_u64..500, n2 in 1_u64..500, f1 in 0.0..=1.0_f64, f2 in 0.0..=1.0_f64) {
        let x1 = ((n1 as f64) * f1).floor() as u64;
        let x2 = ((n2 as f64) * f2).floor() as u64;
        let r = two_proportion_ztest(x1, n1, x2, n2).unwrap();
        prop_assert!((0.0..=1.0).contains(&r.p_value));
    }

    #[test]
    fn wilson_contains_the_estimate(n in 1_u64..10_000, frac in 0.0..=1.0_f64, conf in 0.01..0.999_f64) {
        let k = ((n as f64) * frac).floor() as u64;
        let (lo, hi) = wilson_interval(k, n, conf).unwrap();
        let phat = k as f64 / n as f64;
        prop_assert!(0.0 <= lo && lo <= phat + 1e-12 && phat <= hi + 1e-12 && hi <= 1.0);
    }

    #[test]
    fn holm_adjusted_at_least_raw_and_monotone(p in prop::collection::vec(0.0..=1.0_f64, 0..40)) {
        let adj = holm(&p).unwrap();
        prop_assert_eq!(adj.len(), p.len());
        for i in 0..p.len() {
            prop_assert!(adj[i] >= p[i] && adj[i] <= 1.0);
            for j in 0..p.len() {
                if p[i] <= p[j] {
                    prop_assert!(adj[i] <= adj[j], "raw {} <= {} but adjusted {} > {}", p[i], p[j], adj[i], adj[j]);
                }
            }
        }
    }

    #[test]
    fn auroc_is_antisymmetric(pos in scores(60), neg in scores(60)) {
        let a = auroc(&pos, &neg).unwrap();
        let b = auroc(&neg, &pos).unwrap();
        prop_assert!((0.0..=1.0).contains(&a));
        prop_assert!((a + b - 1.0).abs() < 1e-14, "{a} + {b}");
    }

    #[test]
    fn auroc_matches_pairwise_definition(pos in scores(30), neg in scores(30)) {
        let mut wins = 0.0;
        for &p in &pos {
            for &n in &neg {
                wins += if p > n { 1.0 } else if p == n { 0.5 } else { 0.0 };
            }
        }
        let expected = wins / (pos.len() * neg.len()) as f64;
        prop_assert!((auroc(&pos, &neg).unwrap() - expected).abs() < 1e-14);
    }

    /// Lower half only: above the median `cdf(x)` rounds to a multiple of 2^-53 and loses
    /// the information needed to recover `x` (the upper tail is the mirror image).
    #[test]
    fn norm_ppf_inverts_cdf(x in -37.0..0.5_f64) {
        let p = norm_cdf(x);
        let back = norm_ppf(p).unwrap();
        prop_assert!((back - x).abs() <= 1e-13 * (1.0 + x.abs()), "x {x} -> p {p} -> {back}");
    }
}
