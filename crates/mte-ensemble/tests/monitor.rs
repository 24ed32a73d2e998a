//! The monitors against naive offline oracles (every score recomputed from the whole
//! history), their translation properties, and the calibration ranks.
#![allow(clippy::unwrap_used)]

use mte_ensemble::ChunkGeometry;
use mte_ensemble::monitor::{
    Acc, AccConfig, CalibrationRule, Monitor, Tide, TideConfig, TideReference, calibrate,
};
use proptest::prelude::*;

/// Candidate of chunk `c` (queried at `t`) for control time `tau`, if it covers it.
fn candidate<'a>(g: &ChunkGeometry, t: u64, c: &'a [f32], d: usize, tau: u64) -> Option<&'a [f32]> {
    let age = tau.checked_sub(t)? as usize;
    (age <= g.t_p - g.t_o).then(|| &c[(age + g.t_o - 1) * d..(age + g.t_o) * d])
}

/// TIDE recomputed for query `i` from all chunks (plan: every earlier covering query,
/// weights exp(-m age), age 0 the newest; or the previous chunk alone).
fn tide_oracle(
    g: &ChunkGeometry,
    d: usize,
    cfg: TideConfig,
    chunks: &[(u64, Vec<f32>)],
    i: usize,
) -> Option<f64> {
    if i == 0 {
        return None;
    }
    let (t, new) = (&chunks[i].0, &chunks[i].1);
    let prev_t = chunks[i - 1].0;
    let (mut total, mut count) = (0.0, 0);
    for tau in *t..=prev_t + (g.t_p - g.t_o) as u64 {
        let a = candidate(g, *t, new, d, tau)?;
        let earlier: Vec<&[f32]> = match cfg.reference {
            TideReference::EnsembledPlan => (0..i)
                .rev()
                .filter_map(|j| candidate(g, chunks[j].0, &chunks[j].1, d, tau))
                .collect(),
            TideReference::PreviousChunk => candidate(g, prev_t, &chunks[i - 1].1, d, tau)
                .into_iter()
                .collect(),
        };
        if earlier.is_empty() {
            continue;
        }
        let w: Vec<f64> = (0..earlier.len())
            .map(|age| (-cfg.m * age as f64).exp())
            .collect();
        let ws: f64 = w.iter().sum();
        for k in 0..d {
            let plan: f64 = earlier
                .iter()
                .zip(&w)
                .map(|(c, w)| w * f64::from(c[k]))
                .sum::<f64>()
                / ws;
            total += (plan - f64::from(a[k])).powi(2);
        }
        count += 1;
    }
    (count > 0).then(|| total / (count * d) as f64)
}

/// ACC's raw score for query `i` against query `i - 1`.
fn acc_raw_oracle(
    g: &ChunkGeometry,
    d: usize,
    v_min: f64,
    chunks: &[(u64, Vec<f32>)],
    i: usize,
) -> Option<f64> {
    let (t, new) = (chunks[i].0, &chunks[i].1);
    let (pt, prev) = (chunks[i - 1].0, &chunks[i - 1].1);
    let taus: Vec<u64> = (t..=pt + (g.t_p - g.t_o) as u64)
        .filter(|&tau| {
            candidate(g, pt, prev, d, tau).is_some() && candidate(g, t, new, d, tau).is_some()
        })
        .collect();
    if taus.is_empty() {
        return None;
    }
    let mut total = 0.0;
    for k in 0..d {
        let vals: Vec<f64> = taus
            .iter()
            .map(|&tau| f64::from(candidate(g, t, new, d, tau).unwrap()[k]))
            .collect();
        let range = vals.iter().cloned().fold(f64::MIN, f64::max)
            - vals.iter().cloned().fold(f64::MAX, f64::min);
        let mae: f64 = taus
            .iter()
            .map(|&tau| {
                (f64::from(candidate(g, pt, prev, d, tau).unwrap()[k])
                    - f64::from(candidate(g, t, new, d, tau).unwrap()[k]))
                .abs()
            })
            .sum();
        total += mae / range.max(v_min);
    }
    Some(total / (taus.len() * d) as f64)
}

/// A geometry, a dimension and an episode of chunks at stride h (integer-valued, so sums
/// are exact in f64).
fn episode() -> impl Strategy<Value = (ChunkGeometry, usize, Vec<(u64, Vec<f32>)>)> {
    (2usize..20, 1usize..4, 1usize..5)
        .prop_flat_map(|(t_p, t_o, d)| {
            let t_o = t_o.min(t_p);
            (Just(t_p), Just(t_o), 1..=t_p - t_o + 1, Just(d), 2usize..12)
        })
        .prop_flat_map(|(t_p, t_o, h, d, n)| {
            let g = ChunkGeometry::new(t_p, t_o, h).unwrap();
            let chunks = prop::collection::vec(prop::collection::vec(-50i32..50, t_p * d), n);
            (Just(g), Just(d), chunks)
        })
        .prop_map(|(g, d, raw)| {
            let chunks = raw
                .into_iter()
                .enumerate()
                .map(|(i, c)| {
                    (
                        (i * g.h) as u64 + 3,
                        c.into_iter().map(|v| v as f32).collect(),
                    )
                })
                .collect();
            (g, d, chunks)
        })
}

fn close(a: Option<f64>, b: Option<f64>) -> bool {
    match (a, b) {
        (None, None) => true,
        (Some(x), Some(y)) => (x - y).abs() <= 1e-9 * (1.0 + x.abs().max(y.abs())),
        _ => false,
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    #[test]
    fn tide_matches_the_offline_oracle((g, d, chunks) in episode(), prev in any::<bool>()) {
        let cfg = TideConfig {
            reference: if prev { TideReference::PreviousChunk } else { TideReference::EnsembledPlan },
            ..TideConfig::default()
        };
        let mut m = Tide::new(g, d, cfg).unwrap();
        for (i, (t, c)) in chunks.iter().enumerate() {
            let got = m.observe(*t, c).unwrap();
            let want = tide_oracle(&g, d, cfg, &chunks, i);
            prop_assert!(close(got, want), "query {i}: {got:?} vs {want:?}");
        }
    }

    #[test]
    fn acc_matches_the_offline_oracle((g, d, chunks) in episode(), v_min in 0.01f64..5.0) {
        let cfg = AccConfig { v_min, ..AccConfig::default() };
        let mut m = Acc::new(g, d, cfg).unwrap();
        let mut s: Option<f64> = None;
        for (i, (t, c)) in chunks.iter().enumerate() {
            let got = m.observe(*t, c).unwrap();
            let want = if i == 0 { None } else {
                acc_raw_oracle(&g, d, v_min, &chunks, i).map(|raw| {
                    let v = s.map_or(raw, |s| 0.9 * s + 0.1 * raw);
                    s = Some(v);
                    v
                })
            };
            prop_assert!(close(got, want), "query {i}: {got:?} vs {want:?}");
        }
    }

    /// Common-mode bias: every candidate covering control time tau moves by the same b(tau)
    /// (constant or drifting). TIDE's score does not change; ACC's numerator does not, and its
    /// per-coordinate range moves by at most the bias's own range over the overlap.
    #[test]
    fn common_mode_bias_is_invisible_to_tide_and_bounded_for_acc(
        (g, d, chunks) in episode(), slope in -3i32..4, offset in -40i32..40,
    ) {
        let bias = |tau: u64, k: usize| (offset + slope * tau as i32 + k as i32) as f32;
        let shifted: Vec<(u64, Vec<f32>)> = chunks
            .iter()
            .map(|(t, c)| {
                let mut c = c.clone();
                for (r, row) in c.chunks_mut(d).enumerate() {
                    let tau = (*t + r as u64 + 1).saturating_sub(g.t_o as u64);
                    for (k, v) in row.iter_mut().enumerate() {
                        *v += bias(tau, k);
                    }
                }
                (*t, c)
            })
            .collect();
        let mut a = Tide::new(g, d, TideConfig::default()).unwrap();
        let mut b = Tide::new(g, d, TideConfig::default()).unwrap();
        for ((t, c), (_, s)) in chunks.iter().zip(&shifted) {
            let (x, y) = (a.observe(*t, c).unwrap(), b.observe(*t, s).unwrap());
            prop_assert!(close(x, y), "TIDE moved: {x:?} vs {y:?}");
        }
        // ACC, first scored query (no smoothing): mae / max(range', v) with
        // |range' - range| <= |slope| * (L - 1).
        if chunks.len() >= 2 {
            let v_min = 0.5;
            let raw = acc_raw_oracle(&g, d, v_min, &chunks, 1);
            let mut m = Acc::new(g, d, AccConfig { v_min, ..AccConfig::default() }).unwrap();
            m.observe(shifted[0].0, &shifted[0].1).unwrap();
            let got = m.observe(shifted[1].0, &shifted[1].1).unwrap();
            prop_assert_eq!(raw.is_some(), got.is_some());
            if let (Some(raw), Some(got)) = (raw, got) {
                let l = (g.t_p - g.t_o + 1) as f64;
                let spread = f64::from(slope.unsigned_abs()) * (l - 1.0);
                if slope == 0 {
                    prop_assert!(close(Some(raw), Some(got)), "a constant shift moved ACC");
                } else {
                    // Each term's denominator moves from max(r, v) to max(r', v), |r' - r| <= spread.
                    let hi = raw * (1.0 + spread / v_min);
                    prop_assert!(got <= hi + 1e-9, "{got} > {hi}");
                }
            }
        }
    }
}

#[test]
fn calibration_ranks_follow_each_rule() {
    // 500 episodes of 10 scores each: score = episode + query / 100.
    let eps: Vec<Vec<f64>> = (0..500)
        .map(|e| (0..10).map(|q| e as f64 + q as f64 / 100.0).collect())
        .collect();
    // TIDE per-episode maxima at alpha = 0.001: rank 501 > 500, can never fire.
    let t = calibrate(CalibrationRule::EpisodeMaxConformal { alpha: 0.001 }, &eps).unwrap();
    assert_eq!((t.n, t.k, t.value), (500, 501, None));
    assert!(!t.fires(1e300));
    // Pooled: n = 5000, k = ceil(5001 * 0.999) = 4996, the 4996th smallest: episode 499,
    // query 5.
    let t = calibrate(CalibrationRule::PooledConformal { alpha: 0.001 }, &eps).unwrap();
    assert_eq!((t.n, t.k), (5000, 4996));
    assert_eq!(t.value, Some(499.05));
    assert!(t.fires(499.06) && !t.fires(499.05), "strictly above");
    // ACC: k = min(500, ceil(501 * 0.95)) = 476: the 476th smallest maximum.
    let t = calibrate(CalibrationRule::EpisodeMaxCapped { delta: 0.05 }, &eps).unwrap();
    assert_eq!((t.n, t.k, t.value), (500, 476, Some(475.09)));
    assert!(t.fires(475.09), "at least the threshold");
    assert_eq!(t.first_alarm(&[1.0, 475.09, 500.0]), Some(1));
    // Capped at n for tiny n.
    let t = calibrate(CalibrationRule::EpisodeMaxCapped { delta: 0.05 }, &eps[..3]).unwrap();
    assert_eq!((t.k, t.value), (3, Some(2.09)));
    // Errors name the problem.
    assert!(calibrate(CalibrationRule::PooledConformal { alpha: 0.0 }, &eps).is_err());
    assert!(calibrate(CalibrationRule::PooledConformal { alpha: 0.1 }, &[vec![]]).is_err());
    let e = calibrate(
        CalibrationRule::PooledConformal { alpha: 0.1 },
        &[vec![f64::NAN]],
    )
    .unwrap_err();
    assert!(e.to_string().contains("finite"), "{e}");
    // Round trip through JSON (the threshold file).
    let json = serde_json::to_string(&t).unwrap();
    assert_eq!(
        serde_json::from_str::<mte_ensemble::Threshold>(&json).unwrap(),
        t
    );
}

#[test]
fn bad_settings_and_chunks_are_typed_errors() {
    let g = ChunkGeometry::new(16, 2, 2).unwrap();
    assert!(Tide::new(g, 0, TideConfig::default()).is_err());
    assert!(
        Tide::new(
            g,
            2,
            TideConfig {
                m: f64::NAN,
                ..TideConfig::default()
            }
        )
        .is_err()
    );
    assert!(
        Acc::new(
            g,
            2,
            AccConfig {
                v_min: 0.0,
                ..AccConfig::default()
            }
        )
        .is_err()
    );
    assert!(
        Acc::new(
            g,
            2,
            AccConfig {
                ema: 1.0,
                ..AccConfig::default()
            }
        )
        .is_err()
    );
    let mut m = Tide::new(g, 2, TideConfig::default()).unwrap();
    let mut c = vec![0.0f32; 32];
    assert!(m.observe(0, &c[..31]).is_err());
    c[5] = f32::NAN;
    let e = m.observe(0, &c).unwrap_err().to_string();
    assert!(e.contains("row 2") && e.contains("coordinate 1"), "{e}");
}
