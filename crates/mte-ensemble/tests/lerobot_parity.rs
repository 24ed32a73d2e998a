//! Parity of `ewm:<m>` (oldest-first exp-weighted mean) with LeRobot's
//! `ACTTemporalEnsembler.update()`, on streams recorded by
//! `tools/reference/lerobot_ensembler.py` (see `fixtures/README.md`).
//!
//! ACT with temporal ensembling queries every control step with a chunk whose row 0 is the
//! current step: in mte terms `t_o = 1`, `h = 1`, `t_p = chunk_size`.
#![allow(clippy::unwrap_used)]

use mte_ensemble::{Aggregator, ChunkGeometry, QueryMeta, TemporalEnsembler, WeightOrder};
use serde::Deserialize;

#[derive(Deserialize)]
struct Fixture {
    cases: Vec<Case>,
}

#[derive(Deserialize)]
struct Case {
    coeff: f64,
    chunk_size: usize,
    action_dim: usize,
    chunks: Vec<Vec<Vec<f32>>>,
    actions: Vec<Vec<f32>>,
}

fn fixture() -> Fixture {
    serde_json::from_str(include_str!("fixtures/lerobot_act_ensembler.json")).unwrap()
}

/// Replays one recorded stream with `ewm:<coeff>` in the given order and returns the
/// largest absolute difference from LeRobot's actions.
fn max_gap(case: &Case, order: WeightOrder) -> f32 {
    let g = ChunkGeometry::new(case.chunk_size, 1, 1).unwrap();
    let agg = Aggregator::ExpWeightedMean {
        m: case.coeff,
        order,
    };
    let mut ens = TemporalEnsembler::new(g, case.action_dim, agg).unwrap();
    let mut worst = 0.0f32;
    for (t, (chunk, expected)) in case.chunks.iter().zip(&case.actions).enumerate() {
        let flat: Vec<f32> = chunk.iter().flatten().copied().collect();
        ens.insert(t as u64, &flat, QueryMeta::CLEAN).unwrap();
        let step = ens.action(t as u64).unwrap();
        assert_eq!(step.report.m, (t + 1).min(case.chunk_size));
        for (a, e) in step.action.iter().zip(expected) {
            worst = worst.max((a - e).abs());
        }
    }
    worst
}

#[test]
fn oldest_first_ewm_matches_lerobot_act_temporal_ensembler() {
    let fixture = fixture();
    assert_eq!(fixture.cases.len(), 4);
    for case in &fixture.cases {
        let worst = max_gap(case, WeightOrder::OldestFirst);
        // LeRobot updates a float32 running average (one multiply-add and divide per step,
        // up to chunk_size times per slot), mte sums the weights in f64 once: the gap is a
        // few float32 ulps of values in [-1, 1], far below 1e-5. A wrong convention (newest
        // first) or off-by-one row moves outputs by more than 1e-2 on these streams.
        assert!(
            worst < 1e-5,
            "coeff {}: max abs difference {worst}",
            case.coeff
        );
    }
}

#[test]
fn the_opposite_convention_does_not_match() {
    // Guards the test above against passing vacuously: newest-first weights must differ.
    let worst = max_gap(&fixture().cases[1], WeightOrder::NewestFirst); // coeff 0.5
    assert!(worst > 1e-2, "newest-first unexpectedly matched: {worst}");
}
