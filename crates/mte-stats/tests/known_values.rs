//! Hand-checkable values: the paper's test vectors, worked examples and edge cases.

#![allow(clippy::unwrap_used)]

use mte_stats::{
    StatsError, WilcoxonMethod, auroc, binom_test_two_sided, binomial_se, holm, mcnemar_exact,
    mean_and_paired_se, paired_se, recovered_fraction, two_proportion_ztest, wilcoxon_signed_rank,
    wilcoxon_signed_rank_diffs, wilson_interval,
};

/// Two significant figures, as the paper prints them.
fn sig2(x: f64) -> String {
    format!("{x:.1e}")
}

#[test]
fn mcnemar_paper_vectors() {
    // (b, c, p as printed in the paper)
    let vectors = [
        (12, 48, 3.2e-6),
        (2, 16, 1.3e-3),
        (2, 19, 2.2e-4),
        (1, 19, 4.0e-5),
        (10, 4, 0.18),
        (3, 3, 1.00),
        (21, 6, 5.9e-3),
        (54, 17, 1.3e-5),
        (34, 18, 0.036),
        (9, 15, 0.31),
    ];
    for (b, c, printed) in vectors {
        let r = mcnemar_exact(b, c).unwrap();
        assert_eq!(
            sig2(r.p_value),
            sig2(printed),
            "{b}:{c} gave {:e}",
            r.p_value
        );
        assert_eq!((r.b, r.c), (b, c));
        assert!((r.ln_p_value - r.p_value.ln()).abs() < 1e-12);
    }
    assert_eq!(mcnemar_exact(3, 3).unwrap().p_value, 1.0);
}

#[test]
fn mcnemar_is_symmetric_and_handles_no_discordant_pairs() {
    let r = mcnemar_exact(0, 0).unwrap();
    assert_eq!((r.p_value, r.ln_p_value), (1.0, 0.0));
    for (b, c) in [(0, 7), (5, 9), (100, 3)] {
        assert_eq!(
            mcnemar_exact(b, c).unwrap().p_value,
            mcnemar_exact(c, b).unwrap().p_value
        );
    }
    // 0:7 -> 2 * 2^-7
    assert!((mcnemar_exact(0, 7).unwrap().p_value - 2.0 / 128.0).abs() < 1e-16);
}

#[test]
fn mcnemar_large_n() {
    // 10^6 discordant pairs, 18 standard deviations from even: tiny but representable.
    let r = mcnemar_exact(482_000, 518_000).unwrap();
    assert!(r.p_value.is_finite() && r.p_value > 0.0 && r.p_value < 1e-280);
    // scipy.stats.binomtest(482000, 10**6).pvalue = 7.538991619464022e-284
    assert!((r.p_value / 7.538_991_619_464_022e-284 - 1.0).abs() < 1e-9);

    // 400000:600000 is ~1e-8747: below the smallest f64, so p_value underflows to 0.0
    // (as in scipy), while the log stays exact. mpmath (40 digits): -20140.83494711660115.
    let r = mcnemar_exact(400_000, 600_000).unwrap();
    assert_eq!(r.p_value, 0.0);
    assert!((r.ln_p_value / -20_140.834_947_116_6 - 1.0).abs() < 1e-12);

    for (b, c) in [
        (500_000, 500_000),
        (499_999, 500_001),
        (500_300, 499_700),
        (1, 999_999),
    ] {
        let r = mcnemar_exact(b, c).unwrap();
        assert!((0.0..=1.0).contains(&r.p_value), "{b}:{c} -> {}", r.p_value);
        assert!(r.ln_p_value <= 0.0);
    }
    assert_eq!(mcnemar_exact(500_000, 500_000).unwrap().p_value, 1.0);
    assert!(matches!(
        mcnemar_exact(u64::MAX, 1),
        Err(StatsError::TooManyTrials { .. })
    ));
}

#[test]
fn binomial_test_never_exceeds_one() {
    for n in [1_u64, 2, 7, 30, 101] {
        for k in 0..=n {
            for p in [0.0, 0.01, 0.3, 0.5, 0.77, 1.0] {
                let v = binom_test_two_sided(k, n, p).unwrap();
                assert!((0.0..=1.0).contains(&v), "k={k} n={n} p={p}: {v}");
            }
        }
    }
}

#[test]
fn ztest_paper_vector() {
    // 0.185 vs 0.025 at n = 200 each.
    let r = two_proportion_ztest(37, 200, 5, 200).unwrap();
    assert_eq!(format!("{:.2}", r.z), "5.22");
    assert_eq!(sig2(r.p_value), "1.8e-7");
    let swapped = two_proportion_ztest(5, 200, 37, 200).unwrap();
    assert_eq!(swapped.z, -r.z);
    assert_eq!(swapped.p_value, r.p_value);
}

#[test]
fn ztest_degenerate_and_invalid() {
    let r = two_proportion_ztest(0, 50, 0, 80).unwrap();
    assert_eq!((r.z, r.p_value), (0.0, 1.0));
    let r = two_proportion_ztest(50, 50, 80, 80).unwrap();
    assert_eq!((r.z, r.p_value), (0.0, 1.0));
    assert_eq!(
        two_proportion_ztest(5, 4, 1, 10),
        Err(StatsError::CountExceedsTotal {
            successes: 5,
            total: 4
        })
    );
    assert!(matches!(
        two_proportion_ztest(0, 0, 1, 10),
        Err(StatsError::ZeroTrials { .. })
    ));
}

#[test]
fn holm_hand_example() {
    // m = 4, sorted 0.005, 0.01, 0.03, 0.04 -> 4*0.005 = 0.02, 3*0.01 = 0.03,
    // 2*0.03 = 0.06, max(0.06, 1*0.04) = 0.06; reported in input order.
    let adj = holm(&[0.01, 0.04, 0.03, 0.005]).unwrap();
    let expected = [0.03, 0.06, 0.06, 0.02];
    for (a, e) in adj.iter().zip(expected) {
        assert!((a - e).abs() < 1e-15, "{adj:?}");
    }
    // Capped at 1.
    assert_eq!(holm(&[0.5, 0.6]).unwrap(), vec![1.0, 1.0]);
    // Ties get equal adjusted values.
    let adj = holm(&[0.02, 0.02, 0.5]).unwrap();
    assert_eq!(adj[0], adj[1]);
    // A single test is unchanged; an empty family is empty.
    assert_eq!(holm(&[0.042]).unwrap(), vec![0.042]);
    assert!(holm(&[]).unwrap().is_empty());
    assert_eq!(
        holm(&[0.1, 1.5]),
        Err(StatsError::InvalidPValue {
            index: 1,
            value: 1.5
        })
    );
    assert!(matches!(
        holm(&[f64::NAN]),
        Err(StatsError::InvalidPValue { index: 0, .. })
    ));
}

#[test]
fn recovered_fraction_values_and_errors() {
    assert!((recovered_fraction(0.8, 0.2, 0.65).unwrap() - 0.75).abs() < 1e-12);
    assert_eq!(recovered_fraction(0.8, 0.2, 0.8).unwrap(), 1.0);
    assert_eq!(recovered_fraction(0.8, 0.2, 0.2).unwrap(), 0.0);
    assert!(recovered_fraction(0.8, 0.2, 0.1).unwrap() < 0.0);
    // Error metric (lower is better): same formula, same meaning.
    assert!((recovered_fraction(0.1, 0.5, 0.2).unwrap() - 0.75).abs() < 1e-12);
    assert_eq!(
        recovered_fraction(0.4, 0.4, 0.5),
        Err(StatsError::UndefinedRecovery {
            clean: 0.4,
            undefended: 0.4
        })
    );
    assert!(matches!(
        recovered_fraction(0.4, 0.1, f64::INFINITY),
        Err(StatsError::NonFinite {
            argument: "defended",
            index: 0,
            ..
        })
    ));
}

#[test]
fn auroc_edge_cases() {
    assert_eq!(auroc(&[1.0, 1.0, 1.0], &[1.0, 1.0]).unwrap(), 0.5);
    assert_eq!(auroc(&[2.0, 3.0], &[-1.0, 0.0, 1.0]).unwrap(), 1.0);
    assert_eq!(auroc(&[-1.0, 0.0], &[2.0, 3.0]).unwrap(), 0.0);
    assert_eq!(auroc(&[0.0], &[-0.0]).unwrap(), 0.5);
    // One positive tied with one of two negatives, above the other: (1 + 0.5) / 2.
    assert_eq!(auroc(&[1.0], &[1.0, 0.0]).unwrap(), 0.75);
    assert_eq!(
        auroc(&[], &[1.0]),
        Err(StatsError::EmptySample {
            argument: "positive_scores"
        })
    );
    assert!(matches!(
        auroc(&[1.0], &[0.5, f64::NAN]),
        Err(StatsError::NonFinite {
            argument: "negative_scores",
            index: 1,
            ..
        })
    ));
}

#[test]
fn wilson_at_the_boundaries() {
    let (lo, hi) = wilson_interval(0, 50, 0.95).unwrap();
    assert_eq!(lo, 0.0);
    assert!(hi > 0.0 && hi < 0.1);
    let (lo, hi) = wilson_interval(50, 50, 0.95).unwrap();
    assert_eq!(hi, 1.0);
    assert!(lo > 0.9 && lo < 1.0);
    // Symmetric: k/n mirrors (n-k)/n.
    let (lo_a, hi_a) = wilson_interval(7, 40, 0.9).unwrap();
    let (lo_b, hi_b) = wilson_interval(33, 40, 0.9).unwrap();
    assert!((lo_a - (1.0 - hi_b)).abs() < 1e-15 && (hi_a - (1.0 - lo_b)).abs() < 1e-15);
    for bad in [0.0, 1.0, -0.5, f64::NAN] {
        assert!(matches!(
            wilson_interval(1, 10, bad),
            Err(StatsError::InvalidConfidence { .. })
        ));
    }
    assert!(matches!(
        wilson_interval(11, 10, 0.95),
        Err(StatsError::CountExceedsTotal { .. })
    ));
    assert!(matches!(
        wilson_interval(0, 0, 0.95),
        Err(StatsError::ZeroTrials { .. })
    ));
}

#[test]
fn binomial_and_paired_se() {
    assert!((binomial_se(0.2, 100).unwrap() - 0.04).abs() < 1e-15);
    assert_eq!(binomial_se(0.0, 10).unwrap(), 0.0);
    assert!(matches!(
        binomial_se(1.2, 10),
        Err(StatsError::InvalidProbability { .. })
    ));
    assert!(matches!(
        binomial_se(0.5, 0),
        Err(StatsError::ZeroTrials { .. })
    ));

    // diffs 1, 2, 3, 4: sd^2 = 5/3, se = sqrt(5/12).
    assert!((paired_se(&[1.0, 2.0, 3.0, 4.0]).unwrap() - (5.0_f64 / 12.0).sqrt()).abs() < 1e-15);
    assert_eq!(paired_se(&[3.0, 3.0, 3.0]).unwrap(), 0.0);
    // Huge but finite differences do not overflow.
    let se = paired_se(&[1e300, -1e300]).unwrap();
    assert!((se / 1e300 - 1.0).abs() < 1e-15, "{se}");
    assert_eq!(
        paired_se(&[1.0]),
        Err(StatsError::TooFewSamples {
            argument: "diffs",
            needed: 2,
            got: 1
        })
    );
    assert_eq!(
        paired_se(&[]),
        Err(StatsError::EmptySample { argument: "diffs" })
    );

    let s = mean_and_paired_se(&[2.0, 4.0, 6.0, 8.0], &[1.0, 2.0, 3.0, 4.0]).unwrap();
    assert_eq!(s.n, 4);
    assert!((s.mean_diff - 2.5).abs() < 1e-15);
    assert!((s.se - (5.0_f64 / 12.0).sqrt()).abs() < 1e-15);
    assert_eq!(
        mean_and_paired_se(&[1.0, 2.0], &[1.0]),
        Err(StatsError::LengthMismatch { left: 2, right: 1 })
    );
    assert!(matches!(
        mean_and_paired_se(&[1.0, 2.0], &[1.0, f64::NAN]),
        Err(StatsError::NonFinite {
            argument: "y",
            index: 1,
            ..
        })
    ));
    assert!(matches!(
        mean_and_paired_se(&[f64::MAX, 0.0], &[-f64::MAX, 0.0]),
        Err(StatsError::NonFinite {
            argument: "x - y",
            index: 0,
            ..
        })
    ));
}

#[test]
fn wilcoxon_auto_rule_boundaries() {
    // No ties, no zeros: exact up to 50 pairs, normal from 51.
    let d: Vec<f64> = (1..=50)
        .map(|i| {
            if i % 3 == 0 {
                -f64::from(i)
            } else {
                f64::from(i)
            }
        })
        .collect();
    assert_eq!(
        wilcoxon_signed_rank_diffs(&d).unwrap().method,
        WilcoxonMethod::Exact
    );
    let mut d51 = d.clone();
    d51.push(51.0);
    let r = wilcoxon_signed_rank_diffs(&d51).unwrap();
    assert_eq!(r.method, WilcoxonMethod::Normal);
    assert!(r.z.is_some());

    // Ties: exact (full enumeration) up to 13 pairs, normal from 14.
    let t13 = [
        1.0, 1.0, -2.0, 3.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0,
    ];
    assert_eq!(
        wilcoxon_signed_rank_diffs(&t13).unwrap().method,
        WilcoxonMethod::Exact
    );
    let mut t14 = t13.to_vec();
    t14.push(12.0);
    assert_eq!(
        wilcoxon_signed_rank_diffs(&t14).unwrap().method,
        WilcoxonMethod::Normal
    );

    // Zeros count towards the pair count: 13 non-zero + 1 zero = 14 pairs -> normal.
    let mut z14: Vec<f64> = (1..=13).map(f64::from).collect();
    z14.push(0.0);
    let r = wilcoxon_signed_rank_diffs(&z14).unwrap();
    assert_eq!((r.method, r.n, r.zeros), (WilcoxonMethod::Normal, 13, 1));

    // All 50 positive: p = 2 / 2^50.
    let pos: Vec<f64> = (1..=50).map(f64::from).collect();
    let r = wilcoxon_signed_rank_diffs(&pos).unwrap();
    assert_eq!(r.p_value, 2.0 / 2f64.powi(50));
    assert_eq!(r.statistic, 0.0);
}

#[test]
fn wilcoxon_errors_and_pairing() {
    assert_eq!(
        wilcoxon_signed_rank_diffs(&[0.0, -0.0, 0.0]),
        Err(StatsError::AllZeroDifferences { n: 3 })
    );
    assert_eq!(
        wilcoxon_signed_rank(&[1.0, 2.0], &[1.0, 2.0]),
        Err(StatsError::AllZeroDifferences { n: 2 })
    );
    assert_eq!(
        wilcoxon_signed_rank(&[1.0], &[1.0, 2.0]),
        Err(StatsError::LengthMismatch { left: 1, right: 2 })
    );
    assert_eq!(
        wilcoxon_signed_rank_diffs(&[]),
        Err(StatsError::EmptySample { argument: "d" })
    );
    assert!(matches!(
        wilcoxon_signed_rank_diffs(&[1.0, f64::NAN]),
        Err(StatsError::NonFinite { index: 1, .. })
    ));
    let x = [3.1, 2.0, 5.5, 4.0, 1.0, 7.25];
    let y = [2.0, 2.5, 3.0, 4.0, 0.0, 6.0];
    let d: Vec<f64> = x.iter().zip(&y).map(|(a, b)| a - b).collect();
    assert_eq!(
        wilcoxon_signed_rank(&x, &y).unwrap(),
        wilcoxon_signed_rank_diffs(&d).unwrap()
    );
    // Swapping x and y mirrors r_plus and keeps the two-sided p-value.
    let a = wilcoxon_signed_rank(&x, &y).unwrap();
    let b = wilcoxon_signed_rank(&y, &x).unwrap();
    assert_eq!(a.p_value, b.p_value);
    assert_eq!(a.statistic, b.statistic);
}

#[test]
fn results_round_trip_through_serde() {
    let r = wilcoxon_signed_rank_diffs(&(1..=60).map(f64::from).collect::<Vec<_>>()).unwrap();
    let json = serde_json::to_string(&r).unwrap();
    let back: mte_stats::WilcoxonResult = serde_json::from_str(&json).unwrap();
    assert_eq!(back, r);
    let m = mcnemar_exact(12, 48).unwrap();
    let back: mte_stats::McNemarResult =
        serde_json::from_str(&serde_json::to_string(&m).unwrap()).unwrap();
    assert_eq!(back, m);
}

/// Far in the tail the corrected chi-square p-value underflows, and its logarithm stays
/// finite and close to the normal tail's leading term `ln 2 - z^2 / 2`.
#[test]
fn mcnemar_chi2_corrected_keeps_a_finite_log_p_where_p_underflows() {
    let r = mte_stats::mcnemar_chi2_corrected(1_000_000, 0).expect("test");
    assert_eq!(r.p_value, 0.0);
    let z2 = (999_999.0f64).powi(2) / 1e6;
    assert!(r.ln_p_value.is_finite());
    assert!((r.ln_p_value - (std::f64::consts::LN_2 - z2 / 2.0)).abs() < 10.0);
    // No discordant pairs: no evidence.
    assert_eq!(
        mte_stats::mcnemar_chi2_corrected(0, 0)
            .expect("test")
            .p_value,
        1.0
    );
}
