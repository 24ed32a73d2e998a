//! Property tests of the aggregators (proptest).
#![allow(clippy::unwrap_used)]

use mte_ensemble::{Aggregate, Aggregator, Candidates, MedianTie, WeightOrder, Workspace, bracket};
use proptest::prelude::*;

fn agg(a: Aggregator, rows: &[f32], d: usize) -> Vec<f32> {
    let c = Candidates::new(rows, d).unwrap();
    let mut ws = Workspace::new(c.len(), d);
    let mut out = vec![0.0; d];
    a.aggregate(&c, &mut ws, &mut out).unwrap();
    out
}

/// `n` candidates of dimension `d`, finite.
fn candidate_sets(max_n: usize, max_d: usize) -> impl Strategy<Value = (Vec<f32>, usize)> {
    (1..=max_n, 1..=max_d)
        .prop_flat_map(|(n, d)| (prop::collection::vec(-1000.0f32..1000.0, n * d), Just(d)))
}

/// Integer-valued candidates, so that translating by an integer is exact in f32.
fn integer_sets(max_n: usize, max_d: usize) -> impl Strategy<Value = (Vec<f32>, usize)> {
    (1..=max_n, 1..=max_d).prop_flat_map(|(n, d)| {
        (
            prop::collection::vec((-500i32..500).prop_map(|v| v as f32), n * d),
            Just(d),
        )
    })
}

const TIES: [MedianTie; 4] = [
    MedianTie::Average,
    MedianTie::Lower,
    MedianTie::Upper,
    MedianTie::DropOldest,
];

/// A permutation of `0..n` from a seed (xorshift Fisher-Yates).
fn shuffle(n: usize, seed: u64) -> Vec<usize> {
    let mut perm: Vec<usize> = (0..n).collect();
    let mut s = seed | 1;
    for i in (1..n).rev() {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        perm.swap(i, (s % (i as u64 + 1)) as usize);
    }
    perm
}

fn permute(rows: &[f32], d: usize, perm: &[usize]) -> Vec<f32> {
    perm.iter()
        .flat_map(|&i| rows[i * d..(i + 1) * d].iter().copied())
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn median_lies_inside_min_max((rows, d) in candidate_sets(40, 6)) {
        for tie in TIES {
            let out = agg(Aggregator::Median { tie }, &rows, d);
            for (j, x) in out.iter().enumerate() {
                let col = rows.iter().skip(j).step_by(d);
                let lo = col.clone().copied().fold(f32::INFINITY, f32::min);
                let hi = col.copied().fold(f32::NEG_INFINITY, f32::max);
                prop_assert!(lo <= *x && *x <= hi, "{tie:?}: {x} not in [{lo}, {hi}]");
            }
        }
    }

    #[test]
    fn order_free_aggregators_are_permutation_invariant(
        (rows, d) in candidate_sets(20, 5),
        seed in any::<u64>(),
    ) {
        let perm = shuffle(rows.len() / d, seed);
        let shuffled = permute(&rows, d, &perm);
        for a in [
            Aggregator::MEDIAN,
            Aggregator::Median { tie: MedianTie::Lower },
            Aggregator::Median { tie: MedianTie::Upper },
            Aggregator::TrimmedMean { k: 2 },
        ] {
            prop_assert_eq!(agg(a, &rows, d), agg(a, &shuffled, d), "{}", a);
        }
        // Sums depend on order at the last f32 bit.
        for a in [Aggregator::Mean, Aggregator::GeometricMedian { max_iter: 200 }] {
            let (x, y) = (agg(a, &rows, d), agg(a, &shuffled, d));
            for (u, v) in x.iter().zip(&y) {
                prop_assert!((u - v).abs() <= 1e-3, "{a}: {u} vs {v}");
            }
        }
    }

    #[test]
    fn median_stays_in_clean_bracket_whenever_2q_below_m(
        (clean, d) in candidate_sets(12, 4),
        bad in prop::collection::vec(
            prop_oneof![Just(1e30f32), Just(-1e30f32), Just(f32::MAX), -1e6f32..1e6], 0..60),
        seed in any::<u64>(),
    ) {
        let n_clean = clean.len() / d;
        // Largest q with 2q < M = n_clean + q, i.e. q < n_clean.
        let q = (bad.len() / d).min(n_clean - 1);
        let mut rows = clean.clone();
        rows.extend_from_slice(&bad[..q * d]);
        let mut flags = vec![false; n_clean];
        flags.extend(std::iter::repeat_n(true, q));
        // Interleave corrupted and clean candidates in a random order.
        let n = n_clean + q;
        let perm = shuffle(n, seed);
        let rows = permute(&rows, d, &perm);
        let flags: Vec<bool> = perm.iter().map(|&i| flags[i]).collect();
        let c = Candidates::new(&rows, d).unwrap();
        let mut guaranteed: Vec<Aggregator> =
            TIES.iter().map(|&tie| Aggregator::Median { tie }).collect();
        guaranteed.push(Aggregator::TrimmedMean { k: q });
        for a in guaranteed {
            let out = agg(a, &rows, d);
            let b = bracket::diagnose(&c, &flags, &out).unwrap();
            prop_assert!(!b.outside, "{a}: left the bracket with q={q}, M={n}: {b:?}");
            prop_assert_eq!(b.excess, 0.0);
        }
    }

    #[test]
    fn translation_equivariance((rows, d) in integer_sets(15, 4), shift in -1000i32..1000) {
        let b = shift as f32;
        let moved: Vec<f32> = rows.iter().map(|v| v + b).collect();
        let exact = [
            Aggregator::MEDIAN,
            Aggregator::Median { tie: MedianTie::DropOldest },
            Aggregator::BlockMedoid,
            Aggregator::TrimmedMedoid { q: 2 },
            Aggregator::Latest,
        ];
        for a in exact {
            let (x, y) = (agg(a, &rows, d), agg(a, &moved, d));
            for (u, v) in x.iter().zip(&y) {
                prop_assert_eq!(u + b, *v, "{}", a);
            }
        }
        for a in [Aggregator::Mean, Aggregator::default(), Aggregator::TrimmedMean { k: 1 },
                  Aggregator::GeometricMedian { max_iter: 300 }] {
            let (x, y) = (agg(a, &rows, d), agg(a, &moved, d));
            for (u, v) in x.iter().zip(&y) {
                prop_assert!((u + b - v).abs() <= 1e-3, "{a}: {u} + {b} vs {v}");
            }
        }
    }

    #[test]
    fn ewm_with_zero_coefficient_is_the_mean((rows, d) in candidate_sets(30, 6)) {
        let mean = agg(Aggregator::Mean, &rows, d);
        for order in [WeightOrder::OldestFirst, WeightOrder::NewestFirst] {
            prop_assert_eq!(agg(Aggregator::ExpWeightedMean { m: 0.0, order }, &rows, d), mean.clone());
        }
    }

    #[test]
    fn recency_median_with_zero_coefficient_is_the_median((rows, d) in candidate_sets(30, 6)) {
        prop_assert_eq!(
            agg(Aggregator::RecencyMedian { m: 0.0 }, &rows, d),
            agg(Aggregator::MEDIAN, &rows, d)
        );
    }

    #[test]
    fn medoids_return_a_candidate((rows, d) in candidate_sets(20, 5), q in 0usize..5) {
        for a in [Aggregator::BlockMedoid, Aggregator::TrimmedMedoid { q }] {
            let out = agg(a, &rows, d);
            prop_assert!(rows.chunks(d).any(|r| r == out.as_slice()), "{a}");
        }
    }
}

#[test]
fn mean_is_dragged_where_the_median_is_not() {
    // Seven clean candidates near 0 and one at 1e30: the failure the median fixes.
    let mut rows = vec![0.0f32, 0.1, -0.1, 0.2, -0.2, 0.05, -0.05];
    rows.push(1e30);
    let mean = agg(Aggregator::default(), &rows, 1)[0];
    let median = agg(Aggregator::MEDIAN, &rows, 1)[0];
    assert!(mean > 1e28, "{mean}");
    assert!((-0.2..=0.2).contains(&median), "{median}");
}
