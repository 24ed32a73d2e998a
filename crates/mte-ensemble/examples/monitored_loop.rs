//! A control loop that ensembles, monitors and reacts to an alarm: the median ensembler
//! executes, TIDE scores every query against the earlier queries' plan, and an alarm (a
//! score above the threshold calibrated on clean episodes by `mte monitor calibrate`)
//! clears the ensembler, as Rewind-IL does, so the next query starts a fresh plan.
//!
//! `cargo run --example monitored_loop -p mte-ensemble [-- thresholds.json]`

use mte_ensemble::monitor::{Monitor, Tide, TideConfig};
use mte_ensemble::{Aggregator, ChunkGeometry, QueryMeta, TemporalEnsembler, Threshold};

/// A stand-in policy: a smooth chunk, with a jump at query 20 (a corrupted observation).
fn policy(t: u64) -> Vec<f32> {
    let jump = if t / 2 == 20 { 80.0 } else { 0.0 };
    (0..16)
        .flat_map(|r| {
            let x = (t + r) as f32;
            [200.0 + x + jump, 300.0 - 0.5 * x]
        })
        .collect()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let g = ChunkGeometry::new(16, 2, 2)?;
    let mut ens = TemporalEnsembler::new(g, 2, "median".parse::<Aggregator>()?)?;
    let mut tide = Tide::new(g, 2, TideConfig::default())?;
    // A thresholds file from `mte monitor calibrate`, or a stand-in threshold.
    let threshold: Option<f64> = match std::env::args().nth(1) {
        Some(path) => {
            let file: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path)?)?;
            let t: Threshold = serde_json::from_value(file["monitors"]["tide"].clone())?;
            t.value // None: this rule can never fire with that calibration set
        }
        None => Some(25.0),
    };
    let mut alarms = Vec::new();
    for tau in 0..100u64 {
        if tau % 2 == 0 {
            let chunk = policy(tau);
            let score = tide.observe(tau, &chunk)?;
            if let (Some(s), Some(th)) = (score, threshold)
                && s > th
            {
                alarms.push((tau, s));
                // React: forget the plan (a real system might also stop or ask for help).
                ens.reset();
                tide.reset();
                tide.observe(tau, &chunk)?;
            }
            ens.insert(tau, &chunk, QueryMeta::CLEAN)?;
        }
        let action = ens.action(tau)?.action;
        assert!(action.iter().all(|v| v.is_finite()));
    }
    #[allow(clippy::print_stdout)]
    {
        println!("alarms (control time, TIDE score): {alarms:?}");
    }
    Ok(())
}
