//! Attack calibration: how strong must PGD be before it stops getting stronger?
//!
//! The paper calibrates its attack by sweeping the budget (iterations) and the step size
//! and reporting the *undefended* outcome (the deployed exp-weighted mean) until the attack
//! stops improving. [`calibrate`] does the same on PushT: for each step size it runs the
//! budgets in increasing order on the same paired episodes (same seeds, sampling noise and
//! burst schedule) and stops that step size once a larger budget lowers the mean max
//! coverage by less than `tolerance`.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::Reporter;
use crate::corruption::{CorruptionSpec, Fault, QueryAttack, Schedule};
use crate::pusht::{EpisodeSpec, Execution, ObsNeeds, RolloutError, run_episode};
use mte_policy::{ChunkPolicy, PgdConfig};
use mte_sim::ResetStream;

/// What to sweep. Defaults: the paper's budgets and step, bursts of 2 at h = 2 against the
/// exp-weighted mean, 10 episodes.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrationSpec {
    /// The undefended arm.
    pub arm: Execution,
    /// Query stride.
    pub h: usize,
    /// Burst length (corrupted queries per `M_min`).
    pub q: usize,
    /// Episode seeds.
    pub seeds: Vec<u64>,
    /// Budgets, tried in increasing order.
    pub iterations: Vec<usize>,
    /// Step sizes.
    pub steps: Vec<f64>,
    /// L-infinity radius.
    pub eps: f64,
    /// Stop a step size when a larger budget lowers the mean max coverage by less than this.
    pub tolerance: f64,
    /// Step limit per episode.
    pub max_steps: usize,
    /// Seed of the per-query noise streams.
    pub noise_seed: u64,
}

impl Default for CalibrationSpec {
    fn default() -> Self {
        Self {
            arm: Execution::Ensemble(mte_ensemble::Aggregator::ExpWeightedMean {
                m: mte_ensemble::DEFAULT_EWM_M,
                order: mte_ensemble::WeightOrder::OldestFirst,
            }),
            h: 2,
            q: 2,
            seeds: (100_000..100_010).collect(),
            iterations: vec![5, 20, 50, 200, 500],
            steps: vec![0.001_875],
            eps: 0.03,
            tolerance: 0.01,
            max_steps: 300,
            noise_seed: 0,
        }
    }
}

/// One (step, budget) point; `iterations = 0` is the clean reference.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CalibrationRow {
    /// Step size (0 for the clean row).
    pub step: f64,
    /// Budget.
    pub iterations: usize,
    /// Episodes.
    pub n: usize,
    /// Mean max coverage.
    pub mean_coverage: f64,
    /// Success rate.
    pub success_rate: f64,
    /// Whether the sweep of this step size stopped here (no further improvement).
    pub stopped: bool,
}

fn cell(
    policy: &(dyn ChunkPolicy + Sync),
    needs: ObsNeeds,
    spec: &CalibrationSpec,
    corruption: &CorruptionSpec,
    reporter: &dyn Reporter,
) -> Result<(f64, f64), RolloutError> {
    let outcomes: Vec<Result<(f64, bool), RolloutError>> = spec
        .seeds
        .par_iter()
        .map(|&seed| {
            let ep = EpisodeSpec {
                needs,
                seed,
                stream: ResetStream::Legacy,
                h: spec.h,
                max_steps: spec.max_steps,
                execution: spec.arm,
                corruption,
                noise_seed: spec.noise_seed,
                sampling: Default::default(),
                monitors: &[],
                span: None,
            };
            let r = run_episode(policy, &ep)?;
            reporter.advance(1);
            Ok((r.max_coverage, r.success))
        })
        .collect();
    let mut cov = 0.0;
    let mut succ = 0.0;
    for o in outcomes {
        let (c, s) = o?;
        cov += c;
        succ += f64::from(u8::from(s));
    }
    let n = spec.seeds.len() as f64;
    Ok((cov / n, succ / n))
}

/// Runs the calibration sweep.
pub fn calibrate(
    policy: &(dyn ChunkPolicy + Sync),
    needs: ObsNeeds,
    spec: &CalibrationSpec,
    reporter: &dyn Reporter,
) -> Result<Vec<CalibrationRow>, RolloutError> {
    let bad = |field: &'static str, value: String, expected: &str| RolloutError::Config {
        field,
        value,
        expected: expected.into(),
    };
    if spec.seeds.is_empty() {
        return Err(bad("seeds", "[]".into(), "at least one seed"));
    }
    if spec.iterations.is_empty() || spec.steps.is_empty() {
        return Err(bad("iterations/steps", "[]".into(), "at least one of each"));
    }
    let mut budgets = spec.iterations.clone();
    budgets.sort_unstable();
    budgets.dedup();
    let total = spec.seeds.len() * (1 + budgets.len() * spec.steps.len());
    reporter.start("calibration episodes", total as u64);
    let (clean_cov, clean_succ) = cell(policy, needs, spec, &CorruptionSpec::CLEAN, reporter)?;
    let mut rows = vec![CalibrationRow {
        step: 0.0,
        iterations: 0,
        n: spec.seeds.len(),
        mean_coverage: clean_cov,
        success_rate: clean_succ,
        stopped: false,
    }];
    for &step in &spec.steps {
        let mut previous = clean_cov;
        for &iterations in &budgets {
            let corruption = CorruptionSpec {
                fault: Fault::Query(QueryAttack::Pgd(PgdConfig {
                    eps: spec.eps,
                    step,
                    iterations,
                    ..PgdConfig::default()
                })),
                schedule: Schedule::Burst {
                    q: spec.q,
                    phase: 0,
                    period: None,
                },
            };
            corruption.validate()?;
            let (cov, succ) = cell(policy, needs, spec, &corruption, reporter)?;
            let stopped = iterations != budgets[0] && previous - cov < spec.tolerance;
            rows.push(CalibrationRow {
                step,
                iterations,
                n: spec.seeds.len(),
                mean_coverage: cov,
                success_rate: succ,
                stopped,
            });
            if stopped {
                break;
            }
            previous = cov;
        }
    }
    reporter.finish();
    Ok(rows)
}
