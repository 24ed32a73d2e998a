//! What an episode tells its observers: the seam through which recorders, diagnostics and
//! runtime monitors watch a chunked rollout without touching the runner.
//!
//! An episode runs in named stages, per control step `tau`:
//!
//! 1. **observe**: the environment's observation at `tau` joins the history;
//! 2. **corrupt** (query times only, `tau = i h`): the schedule decides whether query `i` is
//!    corrupted, and an observation fault rewrites its window;
//! 3. **query**: the policy maps the window to a `T_p x d` chunk (under PGD, the attacked
//!    observation's chunk); observers get [`QueryEvent`];
//! 4. **ensemble**: the covering candidates of `tau` are gathered, a candidate fault (oracle
//!    attack, common-mode bias) rewrites them through the ensembler's
//!    [`CandidateHook`](mte_ensemble::CandidateHook), and the aggregator makes the action;
//! 5. **act**: observers get [`StepEvent`] (the candidates as aggregated, the action, the
//!    step report);
//! 6. **step**: the environment advances.

use mte_ensemble::{BracketReport, Candidates, StepReport};

use crate::record::StageTimes;

/// A stage whose wall time an episode reports through [`EpisodeObserver::on_stage`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Rendering or reading the observation.
    Observe,
    /// The schedule, an observation fault, and an attacked query's optimisation (PGD).
    Corrupt,
    /// The policy's forward pass on a clean query.
    Query,
    /// Inserting chunks, gathering and aggregating candidates.
    Ensemble,
    /// The environment's reset and steps.
    Step,
}

/// A query has returned its chunk.
#[derive(Debug, Clone, Copy)]
pub struct QueryEvent<'a> {
    /// Query index `i`.
    pub index: u64,
    /// Control time the query fired, `i h`.
    pub t: u64,
    /// The chunk, `T_p x d` row-major; row `r` is for time `t - (T_o - 1) + r`.
    pub chunk: &'a [f32],
    /// Whether the schedule corrupted this query.
    pub corrupted: bool,
}

/// A control step's action is decided.
#[derive(Debug, Clone, Copy)]
pub struct StepEvent<'a> {
    /// Control time.
    pub tau: u64,
    /// The candidates as aggregated (after any candidate fault), oldest first, and whether
    /// each came from a corrupted query; open loop: the one executed row.
    pub candidates: Candidates<'a>,
    /// Corrupted flags of `candidates`.
    pub corrupted: &'a [bool],
    /// The action sent to the environment (after common-mode bias, in open loop).
    pub action: &'a [f32],
    /// `M(tau)` and the measured `q(tau)`.
    pub m: usize,
    /// Corrupted candidates among them.
    pub q: usize,
    /// The ensembler's report (ensemble arms).
    pub report: Option<StepReport>,
    /// Bracket diagnostics, when a corrupted candidate was present.
    pub bracket: Option<BracketReport>,
}

/// Watches an episode. Every method defaults to doing nothing; they are called on the
/// episode's thread, in time order.
pub trait EpisodeObserver {
    /// After each query.
    fn on_query(&mut self, _event: &QueryEvent<'_>) {}
    /// After each control step's action is decided, before the environment steps.
    fn on_step(&mut self, _event: &StepEvent<'_>) {}
    /// After each timed stage, with its wall time in seconds.
    fn on_stage(&mut self, _stage: Stage, _seconds: f64) {}
}

/// The observer that sums each stage's wall time into a record's [`StageTimes`] (PGD's
/// optimisation counts as corruption, not as the policy's time).
#[derive(Debug, Clone, Copy, Default)]
pub struct StageTimer {
    /// The sums so far (`total_s` is the caller's).
    pub times: StageTimes,
}

impl EpisodeObserver for StageTimer {
    fn on_stage(&mut self, stage: Stage, seconds: f64) {
        let t = &mut self.times;
        *match stage {
            Stage::Observe => &mut t.render_s,
            Stage::Corrupt => &mut t.corruption_s,
            Stage::Query => &mut t.policy_s,
            Stage::Ensemble => &mut t.ensemble_s,
            Stage::Step => &mut t.sim_s,
        } += seconds;
    }
}

/// An observer that watches nothing.
#[derive(Debug, Clone, Copy, Default)]
pub struct NoObserver;

impl EpisodeObserver for NoObserver {}
