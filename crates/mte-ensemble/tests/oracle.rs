//! The streaming ensembler against a naive offline computation over the
//! (query x chunk index) grid, for every aggregator, on random streams.
//!
//! The oracle knows every query of the episode up front, finds the covering set of each
//! control time by scanning all of them, reads the candidate rows by index arithmetic,
//! and aggregates with straightforward f64 implementations written independently of the
//! library (sorting instead of networks, no caches, no ring).
#![allow(clippy::unwrap_used)]

use mte_ensemble::{
    Aggregator, ChunkGeometry, EnsembleError, MedianTie, QueryMeta, TemporalEnsembler, WeightOrder,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

struct Query {
    t: u64,
    chunk: Vec<f32>,
    corrupted: bool,
}

fn sorted(mut v: Vec<f64>) -> Vec<f64> {
    v.sort_by(f64::total_cmp);
    v
}

fn column(c: &[Vec<f64>], j: usize) -> Vec<f64> {
    c.iter().map(|r| r[j]).collect()
}

fn dist(a: &[f64], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).powi(2))
        .sum::<f64>()
        .sqrt()
}

fn naive_median(v: Vec<f64>, tie: MedianTie) -> f64 {
    let v = sorted(v);
    let n = v.len();
    if n % 2 == 1 {
        return v[n / 2];
    }
    match tie {
        MedianTie::Average => 0.5 * (v[n / 2 - 1] + v[n / 2]),
        MedianTie::Lower => v[n / 2 - 1],
        MedianTie::Upper => v[n / 2],
        MedianTie::DropOldest => unreachable!("handled by the caller"),
    }
}

fn exp_weights(n: usize, m: f64, order: WeightOrder) -> Vec<f64> {
    (0..n)
        .map(|i| {
            let k = match order {
                WeightOrder::OldestFirst => i,
                WeightOrder::NewestFirst => n - 1 - i,
            };
            (-m * k as f64).exp()
        })
        .collect()
}

fn weighted_mean(c: &[Vec<f64>], w: &[f64]) -> Vec<f64> {
    let total: f64 = w.iter().sum();
    (0..c[0].len())
        .map(|j| c.iter().zip(w).map(|(r, wi)| wi * r[j]).sum::<f64>() / total)
        .collect()
}

/// Medoid of the candidates in `keep` by summed distance; ties go to the newest.
fn medoid_among(c: &[Vec<f64>], keep: &[usize]) -> Vec<f64> {
    let mut best = (f64::INFINITY, 0);
    for &i in keep {
        let s: f64 = keep.iter().map(|&j| dist(&c[i], &c[j])).sum();
        if s <= best.0 {
            best = (s, i);
        }
    }
    c[best.1].clone()
}

fn geo_objective(c: &[Vec<f64>], y: &[f64]) -> f64 {
    c.iter().map(|r| dist(r, y)).sum()
}

/// The oracle's aggregate. Geometric median returns `None`: it is checked by objective.
fn naive(agg: Aggregator, c: &[Vec<f64>]) -> Option<Vec<f64>> {
    let (n, d) = (c.len(), c[0].len());
    Some(match agg {
        Aggregator::ExpWeightedMean { m, order } => weighted_mean(c, &exp_weights(n, m, order)),
        Aggregator::Mean => weighted_mean(c, &vec![1.0; n]),
        Aggregator::Latest => c[n - 1].clone(),
        Aggregator::Median {
            tie: MedianTie::DropOldest,
        } => {
            let rest = if n % 2 == 0 { &c[1..] } else { c };
            (0..d)
                .map(|j| naive_median(column(rest, j), MedianTie::Average))
                .collect()
        }
        Aggregator::Median { tie } => (0..d).map(|j| naive_median(column(c, j), tie)).collect(),
        Aggregator::BlockMedoid => medoid_among(c, &(0..n).collect::<Vec<_>>()),
        Aggregator::TrimmedMedoid { q } => {
            let score: Vec<f64> = (0..n)
                .map(|i| c.iter().map(|r| dist(&c[i], r)).sum())
                .collect();
            let mut order: Vec<usize> = (0..n).collect();
            // Largest score first; equal scores: oldest first.
            order.sort_by(|&a, &b| score[b].total_cmp(&score[a]).then(a.cmp(&b)));
            let mut keep: Vec<usize> = order[q.min(n - 1)..].to_vec();
            keep.sort();
            medoid_among(c, &keep)
        }
        Aggregator::TrimmedMean { k } => {
            let r = k.min((n - 1) / 2);
            (0..d)
                .map(|j| {
                    let v = sorted(column(c, j));
                    let kept = &v[r..n - r];
                    kept.iter().sum::<f64>() / kept.len() as f64
                })
                .collect()
        }
        Aggregator::RecencyMedian { m } => {
            let w = exp_weights(n, m, WeightOrder::NewestFirst);
            let total: f64 = w.iter().sum();
            (0..d)
                .map(|j| {
                    let mut p: Vec<(f64, f64)> = c.iter().map(|r| r[j]).zip(w.clone()).collect();
                    p.sort_by(|a, b| a.0.total_cmp(&b.0));
                    let mut cum = 0.0;
                    for (i, &(v, wi)) in p.iter().enumerate() {
                        cum += wi;
                        if cum >= total / 2.0 {
                            if (cum - total / 2.0).abs() <= 1e-12 * total && i + 1 < n {
                                return 0.5 * (v + p[i + 1].0);
                            }
                            return v;
                        }
                    }
                    p[n - 1].0
                })
                .collect()
        }
        Aggregator::GeometricMedian { .. } => return None,
    })
}

fn all_aggregators() -> Vec<Aggregator> {
    let mut v = Aggregator::catalogue();
    v.extend([
        Aggregator::ExpWeightedMean {
            m: -0.2,
            order: WeightOrder::OldestFirst,
        },
        Aggregator::ExpWeightedMean {
            m: 0.7,
            order: WeightOrder::NewestFirst,
        },
        Aggregator::TrimmedMedoid { q: 3 },
        Aggregator::TrimmedMean { k: 3 },
        Aggregator::RecencyMedian { m: 0.0 },
        Aggregator::RecencyMedian { m: -0.3 },
        Aggregator::GeometricMedian { max_iter: 500 },
    ]);
    v
}

/// A random episode: query times with strides in `1..=h_max` (so the stride varies), some
/// queries skipped, random chunks, some corrupted, a few with non-finite values.
fn random_episode(rng: &mut ChaCha8Rng, g: ChunkGeometry, d: usize, len: u64) -> Vec<Query> {
    let mut queries = Vec::new();
    let mut t = 0u64;
    while t < len {
        if queries.is_empty() || rng.random_bool(0.9) {
            let mut chunk: Vec<f32> = (0..g.t_p * d)
                .map(|_| rng.random_range(-10.0f32..10.0))
                .collect();
            if rng.random_bool(0.05) {
                let i = rng.random_range(0..chunk.len());
                chunk[i] = if rng.random_bool(0.5) {
                    f32::NAN
                } else {
                    f32::INFINITY
                };
            }
            queries.push(Query {
                t,
                chunk,
                corrupted: rng.random_bool(0.3),
            });
        }
        t += rng.random_range(1..=g.h as u64);
    }
    queries
}

fn check_episode(agg: Aggregator, g: ChunkGeometry, d: usize, queries: &[Query], len: u64) {
    let mut ens = TemporalEnsembler::new(g, d, agg).unwrap();
    let mut next = 0;
    let span = g.span() as u64;
    for tau in 0..len {
        while next < queries.len() && queries[next].t == tau {
            let q = &queries[next];
            ens.insert(
                q.t,
                &q.chunk,
                QueryMeta {
                    corrupted: q.corrupted,
                },
            )
            .unwrap();
            next += 1;
        }
        // Oracle: scan every query of the episode.
        let covering: Vec<&Query> = queries
            .iter()
            .filter(|q| q.t <= tau && tau < q.t + span)
            .collect();
        let rows: Vec<Vec<f64>> = covering
            .iter()
            .map(|q| {
                let r = (tau - q.t) as usize + g.t_o - 1;
                q.chunk[r * d..(r + 1) * d]
                    .iter()
                    .map(|&v| v as f64)
                    .collect()
            })
            .collect();
        let finite: Vec<Vec<f64>> = rows
            .iter()
            .filter(|r| r.iter().all(|v| v.is_finite()))
            .cloned()
            .collect();
        let result = ens.action(tau);
        if covering.is_empty() {
            assert!(
                matches!(result, Err(EnsembleError::NoCandidates { .. })),
                "tau {tau}"
            );
            continue;
        }
        if finite.is_empty() {
            assert!(matches!(
                result,
                Err(EnsembleError::NoFiniteCandidates { .. })
            ));
            continue;
        }
        let step = result.unwrap();
        assert_eq!(step.report.m, covering.len());
        assert_eq!(
            step.report.q,
            covering.iter().filter(|q| q.corrupted).count()
        );
        assert_eq!(step.report.excluded, rows.len() - finite.len());
        let got: Vec<f64> = step.action.iter().map(|&v| v as f64).collect();
        let scale = finite.iter().flatten().fold(1.0f64, |a, v| a.max(v.abs()));
        match naive(agg, &finite) {
            Some(expect) => {
                for (j, (a, e)) in got.iter().zip(&expect).enumerate() {
                    // f32 output of an f64 computation (one rounding, plus summation order
                    // for the means): 1e-6 of the values' scale is ~10 f32 ulps.
                    assert!(
                        (a - e).abs() <= 1e-6 * scale,
                        "{agg} {g:?} d={d} tau={tau} coord {j}: got {a}, oracle {e}"
                    );
                }
            }
            None => {
                // Geometric median: the objective at our point must be as low as that of a
                // long independent Weiszfeld run (relative 1e-6), from the mean.
                let mut y = weighted_mean(&finite, &vec![1.0; finite.len()]);
                for _ in 0..2000 {
                    let w: Vec<f64> = finite
                        .iter()
                        .map(|r| 1.0 / dist(r, &y).max(1e-12))
                        .collect();
                    y = weighted_mean(&finite, &w);
                }
                let (ours, theirs) = (geo_objective(&finite, &got), geo_objective(&finite, &y));
                let Aggregator::GeometricMedian { max_iter } = agg else {
                    unreachable!()
                };
                // The default bound (64 iterations) trades accuracy for worst-case latency:
                // on these streams it leaves a relative objective gap up to ~1e-5 (seen at
                // small M, where Weiszfeld converges slowest), so it gets 1e-4; 500
                // iterations converge to the oracle's 1e-6.
                let tol = if max_iter >= 500 { 1e-6 } else { 1e-4 };
                assert!(
                    ours <= theirs * (1.0 + tol) + 1e-9,
                    "{agg} tau={tau}: {ours} > {theirs}"
                );
            }
        }
    }
}

#[test]
fn streaming_equals_offline_oracle_for_every_aggregator() {
    let mut rng = ChaCha8Rng::seed_from_u64(20261122);
    let aggs = all_aggregators();
    let mut episodes = 0;
    for case in 0..60 {
        let t_p = if case % 5 == 0 {
            rng.random_range(60..=100)
        } else {
            rng.random_range(8..=32)
        };
        let t_o = rng.random_range(1..=3.min(t_p));
        let h = rng.random_range(1..=4usize.min(t_p - t_o + 1));
        let g = ChunkGeometry::new(t_p, t_o, h).unwrap();
        let d = rng.random_range(1..=14);
        let len = 2 * t_p as u64 + 10;
        let queries = random_episode(&mut rng, g, d, len);
        for &agg in &aggs {
            // Large chunks with every aggregator would be slow in debug builds; cover them
            // with a rotating subset.
            if t_p > 32 && (case + aggs.iter().position(|a| *a == agg).unwrap()) % 4 != 0 {
                continue;
            }
            check_episode(agg, g, d, &queries, len);
            episodes += 1;
        }
    }
    assert!(episodes > 500, "only {episodes} episodes checked");
}

#[test]
fn regular_strides_one_to_four_match_the_oracle() {
    // Fixed strides (no skipped queries) at the paper's geometries.
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for (t_p, t_o) in [(16, 2), (10, 2), (100, 1)] {
        for h in 1..=4 {
            let g = ChunkGeometry::new(t_p, t_o, h).unwrap();
            let d = 7;
            let len = 3 * t_p as u64;
            let queries: Vec<Query> = (0..len)
                .step_by(h)
                .map(|t| Query {
                    t,
                    chunk: (0..t_p * d)
                        .map(|_| rng.random_range(-1.0f32..1.0))
                        .collect(),
                    corrupted: rng.random_bool(0.25),
                })
                .collect();
            for agg in [
                Aggregator::default(),
                Aggregator::MEDIAN,
                Aggregator::TrimmedMedoid { q: 2 },
            ] {
                check_episode(agg, g, d, &queries, len);
            }
        }
    }
}

/// The running sums of `ewm` and `mean` give the gathered path's results bit for bit (actions,
/// reports, errors and the candidates read afterwards), on random streams with varying
/// strides, skipped queries, non-finite rows, chunks inserted ahead, repeated steps and a
/// reset mid-episode, at small and ACT-sized chunks.
#[test]
fn running_sums_give_the_gathered_bits() {
    use mte_ensemble::{Aggregate, EnsemblerOptions, Gathered};
    let mut rng = ChaCha8Rng::seed_from_u64(20261127);
    let aggs = [
        Aggregator::default(),
        Aggregator::Mean,
        Aggregator::ExpWeightedMean {
            m: 0.3,
            order: WeightOrder::OldestFirst,
        },
        Aggregator::ExpWeightedMean {
            m: -0.2,
            order: WeightOrder::NewestFirst,
        },
    ];
    for agg in aggs {
        assert!(agg.running_weights().is_some(), "{agg}");
    }
    let mut steps = 0;
    for case in 0..80 {
        let t_p = if case % 4 == 0 {
            rng.random_range(60..=100)
        } else {
            rng.random_range(4..=32)
        };
        let t_o = rng.random_range(1..=2.min(t_p));
        let h = rng.random_range(1..=4usize.min(t_p - t_o + 1));
        let g = ChunkGeometry::new(t_p, t_o, h).unwrap();
        let d = [1, 2, 3, 7, 14][case % 5];
        let len = 2 * t_p as u64 + 10;
        let queries = random_episode(&mut rng, g, d, len);
        let agg = aggs[case % aggs.len()];
        let opts = EnsemblerOptions {
            lookahead: Some(h + 2),
            bracket_diagnostics: false,
        };
        let mut run = TemporalEnsembler::with_options(g, d, agg, opts).unwrap();
        let mut gat = TemporalEnsembler::with_options(g, d, Gathered(agg), opts).unwrap();
        let reset_at = (case % 3 == 0).then_some(len / 2);
        let mut next = 0;
        for tau in 0..len {
            if Some(tau) == reset_at {
                run.reset();
                gat.reset();
                // Start the rest of the episode afresh: skip queries already due.
                while next < queries.len() && queries[next].t < tau {
                    next += 1;
                }
            }
            // Insert up to two steps ahead (within the lookahead) some of the time.
            let ahead = if rng.random_bool(0.3) { 2 } else { 0 };
            while next < queries.len() && queries[next].t <= tau + ahead {
                let q = &queries[next];
                let meta = QueryMeta {
                    corrupted: q.corrupted,
                };
                let (a, b) = (
                    run.insert(q.t, &q.chunk, meta),
                    gat.insert(q.t, &q.chunk, meta),
                );
                assert_eq!(format!("{a:?}"), format!("{b:?}"), "insert at {tau}");
                next += 1;
            }
            for _ in 0..1 + usize::from(rng.random_bool(0.1)) {
                let a = run.action(tau).map(|s| (s.action.to_vec(), s.report));
                let b = gat.action(tau).map(|s| (s.action.to_vec(), s.report));
                match (&a, &b) {
                    (Ok((xa, ra)), Ok((xb, rb))) => {
                        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                        assert_eq!(bits(xa), bits(xb), "{agg} {g:?} d {d} tau {tau}");
                        assert_eq!(ra, rb, "{agg} tau {tau}");
                        steps += 1;
                    }
                    _ => assert_eq!(format!("{a:?}"), format!("{b:?}"), "tau {tau}"),
                }
                if rng.random_bool(0.5) {
                    let (ca, fa) = run.last_candidates();
                    let (ca, fa) = (ca.values().to_vec(), fa.to_vec());
                    let (cb, fb) = gat.last_candidates();
                    assert_eq!(ca, cb.values(), "candidates at {tau}");
                    assert_eq!(fa, fb, "flags at {tau}");
                }
            }
        }
    }
    assert!(steps > 5000, "only {steps} steps compared");
}
