//! Chunked execution of a policy on PushT, clean or corrupted.
//!
//! The policy is queried every `h` control steps (query `i` at `t_i = i h`) with the last
//! `T_o` control-rate observations (the first repeated at episode start, as Diffusion
//! Policy's env wrapper does). Its chunk is either executed open loop (`h` actions of the
//! latest chunk from row `T_o - 1`: Diffusion Policy's and LeRobot's default) or fed to a
//! [`TemporalEnsembler`] with any aggregator (`latest` is the non-ensembling baseline).
//!
//! ## Pairing
//!
//! Every arm of a cell sees the same reset seed, and query `i` of episode `seed` draws its
//! sampling noise from a stream seeded by `(noise_seed, seed, i)` and its corruption
//! randomness from another stream seeded the same way, so arms differ only in how chunks
//! become actions. The corruption schedule is a function of the query index, identical for
//! every arm.
//!
//! ## Corruption
//!
//! Observation faults go through [`ObservationCorruptor`] (stage *corrupt*); PGD replaces
//! the query of a corrupted window (stage *query*); candidate faults act on the real
//! ensembler's candidates through its [`CandidateHook`] (stage *ensemble*): oracle bracket
//! attacks rewrite the corrupted candidates of each control time from the clean bracket,
//! and common-mode bias `b(tau)` shifts every covering candidate while the newest query
//! covering `tau` is corrupted (in open loop, the executed row). `q(tau)` and `M(tau)` are
//! measured and recorded at every step. [`crate::episode`] names the stages and the
//! observer interface ([`run_episode_observed`]).

use std::fmt;
use std::str::FromStr;
use std::time::Instant;

use mte_ensemble::{
    Aggregator, BracketAccumulator, CandidateHook, Candidates, CandidatesMut, ChunkGeometry,
    EnsembleError, EnsemblerOptions, Monitor, MonitorKind, NoHook, QueryMeta, TemporalEnsembler,
};
use mte_policy::{ChunkPolicy, Observation, PgdConfig, PolicyError};
use mte_sim::{ResetStream, SimError};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::corruption::{
    BiasDirection, CandidateCorruption, CorruptionSpec, Fault, ObservationCorruptor, OracleMode,
    SensorFault,
};
use crate::environment::{Environment, PushTEnv};
use crate::episode::{EpisodeObserver, NoObserver, QueryEvent, Stage, StageTimer, StepEvent};
use crate::record::{EpisodeRecord, MonitorTrace};

/// How chunks become actions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Execution {
    /// Execute `h` actions of the latest chunk.
    OpenLoop,
    /// Aggregate every covering chunk with an ensembler.
    Ensemble(Aggregator),
}

impl fmt::Display for Execution {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::OpenLoop => f.write_str("open-loop"),
            Self::Ensemble(a) => write!(f, "{a}"),
        }
    }
}

impl FromStr for Execution {
    type Err = mte_ensemble::ParseAggregatorError;
    /// `open-loop`, or an aggregator's text form (`ewm:0.01`, `median`, `latest`, ...).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if s.trim() == "open-loop" {
            Ok(Self::OpenLoop)
        } else {
            s.parse().map(Self::Ensemble)
        }
    }
}

/// Which observations the policy reads (moved to the policy seam).
pub use mte_policy::ObsNeeds;

/// Errors of a rollout.
#[derive(Debug, thiserror::Error)]
pub enum RolloutError {
    /// The simulator failed.
    #[error(transparent)]
    Sim(#[from] SimError),
    /// The policy failed.
    #[error(transparent)]
    Policy(#[from] PolicyError),
    /// The ensembler refused a chunk or a time.
    #[error(transparent)]
    Ensemble(#[from] EnsembleError),
    /// An aggregator refused a candidate set.
    #[error(transparent)]
    Aggregate(#[from] mte_ensemble::AggregateError),
    /// Rendering failed.
    #[error(transparent)]
    Render(#[from] mte_sim::render::RenderError),
    /// A corruption parameter was out of range.
    #[error(transparent)]
    Corruption(#[from] crate::corruption::CorruptionError),
    /// The environment failed.
    #[error(transparent)]
    Env(#[from] crate::environment::EnvError),
    /// A bad setting.
    #[error("`{field}` = {value}: expected {expected}")]
    Config {
        /// Field.
        field: &'static str,
        /// Value.
        value: String,
        /// Expectation.
        expected: String,
    },
}

/// Everything that defines one episode of one arm.
#[derive(Clone, Debug, PartialEq)]
pub struct EpisodeSpec<'a> {
    /// Observations the policy reads.
    pub needs: ObsNeeds,
    /// Reset seed.
    pub seed: u64,
    /// Reset stream.
    pub stream: ResetStream,
    /// Query stride `h`.
    pub h: usize,
    /// Step limit.
    pub max_steps: usize,
    /// Arm.
    pub execution: Execution,
    /// Corruption of the cell.
    pub corruption: &'a CorruptionSpec,
    /// Seed of the per-query sampling and corruption streams (shared by the arms).
    pub noise_seed: u64,
    /// How the policy's sampling noise varies across queries.
    pub sampling: Sampling,
    /// Runtime monitors scoring every query (passive: they never change an action).
    pub monitors: &'a [MonitorKind],
    /// Executable rows of each chunk the runner uses, counted from row `T_o - 1`; `None`:
    /// all `T_p - T_o + 1` of them. Fewer rows means fewer candidates per control step
    /// (`M_min = floor(span / h)`), as for a policy predicting only `T_o - 1 + span` rows:
    /// the control that separates a longer observation history (which shortens the span)
    /// from the candidate count it brings.
    pub span: Option<usize>,
}

/// ACC's range floor for PushT, in pixels: the spec's 1e-3 in LeRobot's normalised action
/// units, where PushT's 512 px span [−1, 1] (so 1e-3 x 256 px).
pub const PUSHT_ACC_V_MIN_PX: f64 = 0.256;

/// How a stochastic policy's sampling noise is drawn across the queries of an episode.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Sampling {
    /// A fresh noise stream per query, as deployed (every experiment's default).
    #[default]
    Independent,
    /// The same noise stream at every query of an episode, so a chunk is a deterministic
    /// function of its observation window: an analysis control that removes the
    /// between-query sampling variability and keeps only what the observation changes.
    Fixed,
}

impl Sampling {
    /// The noise stream index of query `i`.
    fn stream_of(self, i: u64) -> u64 {
        match self {
            Self::Independent => i,
            Self::Fixed => 0,
        }
    }
}

/// SplitMix64 finaliser: decorrelates structured seeds.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The RNG of query `i` of episode `seed`: `purpose` 0 = sampling noise, 1 = corruption,
/// 2 = per-episode attack state.
pub fn query_rng(noise_seed: u64, seed: u64, i: u64, purpose: u64) -> ChaCha8Rng {
    let mut r = ChaCha8Rng::seed_from_u64(mix(mix(noise_seed) ^ mix(seed).rotate_left(21) ^ i));
    r.set_stream(purpose);
    r
}

/// A fault that rewrites the candidates of the real ensembler through its candidate hook.
#[derive(Debug)]
enum CandidateFault {
    /// Candidates are left as the policy made them.
    None(NoHook),
    /// Corrupted candidates are rewritten from the clean bracket (oracle attacks).
    Oracle(OracleHook),
    /// Every candidate is shifted by the same bias while the newest query is corrupted.
    CommonMode(ShiftHook),
}

/// The oracle bracket attack: per coordinate, every corrupted candidate is set to one end
/// of the clean candidates' range (`Drift`: the end given by a per-episode direction;
/// `Instant`: the end that moves the median farthest), when `0 < q < M`.
#[derive(Debug)]
struct OracleHook {
    mode: OracleMode,
    /// Per coordinate: +1 pushes towards the bracket's top, -1 towards its bottom (drift).
    direction: Vec<f32>,
    clean: Vec<f32>,
    with: Vec<f32>,
    scratch: Vec<f32>,
}

impl CandidateHook for OracleHook {
    fn rewrite(&mut self, set: &mut CandidatesMut<'_>) {
        let m = set.len();
        let q = (0..m).filter(|&i| set.corrupted(i)).count();
        if q == 0 || q == m {
            return;
        }
        for j in 0..set.dim() {
            self.clean.clear();
            self.clean
                .extend((0..m).filter(|&i| !set.corrupted(i)).map(|i| set.get(i, j)));
            let target = self.target(j, q);
            for i in 0..m {
                if set.corrupted(i) {
                    set.row_mut(i)[j] = target;
                }
            }
        }
    }
}

impl OracleHook {
    /// The value every corrupted candidate takes in coordinate `j` (`clean` holds the clean
    /// candidates' values there).
    fn target(&mut self, j: usize, q: usize) -> f32 {
        let lo = self.clean.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = self.clean.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        match self.mode {
            OracleMode::Drift if self.direction[j] >= 0.0 => hi,
            OracleMode::Drift => lo,
            OracleMode::Instant => {
                // The end that moves the coordinate-wise median farthest from the clean
                // candidates' median.
                let base = median(&self.clean, &mut self.scratch);
                let mut median_with = |v: f32| {
                    self.with.clear();
                    self.with.extend_from_slice(&self.clean);
                    self.with.extend(std::iter::repeat_n(v, q));
                    median(&self.with, &mut self.scratch)
                };
                let (up, down) = (median_with(hi), median_with(lo));
                if (up - base).abs() >= (down - base).abs() {
                    hi
                } else {
                    lo
                }
            }
        }
    }
}

/// Common-mode bias on the candidates: while `on`, every candidate's first two coordinates
/// are shifted by `bias` (px).
#[derive(Debug)]
struct ShiftHook {
    bias: [f32; 2],
    on: bool,
    /// Length (px).
    magnitude: f64,
    /// Direction at control time 0 (radians).
    angle: f64,
    /// Turn per control step (radians).
    rate: f64,
}

impl ShiftHook {
    /// `magnitude` px at `angle_deg`, turning as `direction` says; a random direction is
    /// drawn from the episode's per-episode attack stream.
    fn new(
        magnitude: f64,
        angle_deg: f64,
        direction: BiasDirection,
        spec: &EpisodeSpec<'_>,
    ) -> Self {
        let (offset, rate) = match direction {
            BiasDirection::Constant => (0.0, 0.0),
            BiasDirection::Drift { deg_per_step } => (0.0, deg_per_step),
            BiasDirection::Random => {
                let mut r = query_rng(spec.noise_seed, spec.seed, 0, 2);
                (r.random_range(0.0..360.0), 0.0)
            }
        };
        let mut hook = Self {
            bias: [0.0; 2],
            on: false,
            magnitude,
            angle: (angle_deg + offset).to_radians(),
            rate: rate.to_radians(),
        };
        hook.at(0);
        hook
    }

    /// Points the bias where it is at control time `tau`.
    fn at(&mut self, tau: u64) {
        let a = self.angle + self.rate * tau as f64;
        self.bias = [
            (self.magnitude * a.cos()) as f32,
            (self.magnitude * a.sin()) as f32,
        ];
    }

    /// Adds the bias to one action (its first two coordinates).
    fn shift(&self, action: &mut [f32]) {
        for (x, b) in action.iter_mut().zip(self.bias) {
            *x += b;
        }
    }
}

impl CandidateHook for ShiftHook {
    fn active(&self) -> bool {
        self.on
    }
    fn rewrite(&mut self, set: &mut CandidatesMut<'_>) {
        for i in 0..set.len() {
            self.shift(set.row_mut(i));
        }
    }
}

impl CandidateFault {
    fn new(spec: &EpisodeSpec<'_>, d: usize, clean: bool) -> Result<Self, RolloutError> {
        Ok(match (&spec.corruption.fault, spec.execution) {
            _ if clean => Self::None(NoHook),
            (Fault::Candidates(CandidateCorruption::Oracle { .. }), Execution::OpenLoop) => {
                return Err(RolloutError::Config {
                    field: "arm",
                    value: "open-loop".into(),
                    expected: "an aggregator: oracle attacks rewrite an ensembler's candidates"
                        .into(),
                });
            }
            (Fault::Candidates(CandidateCorruption::Oracle { mode }), Execution::Ensemble(_)) => {
                let mut r = query_rng(spec.noise_seed, spec.seed, 0, 2);
                Self::Oracle(OracleHook {
                    mode: *mode,
                    direction: (0..d)
                        .map(|_| if r.random_bool(0.5) { 1.0 } else { -1.0 })
                        .collect(),
                    clean: Vec::new(),
                    with: Vec::new(),
                    scratch: Vec::new(),
                })
            }
            (
                Fault::Candidates(CandidateCorruption::CommonMode {
                    magnitude,
                    angle_deg,
                    direction,
                }),
                _,
            ) => Self::CommonMode(ShiftHook::new(*magnitude, *angle_deg, *direction, spec)),
            _ => Self::None(NoHook),
        })
    }

    /// Whether a corrupted query's candidates count as corrupted: not under common-mode
    /// bias, which shifts every candidate alike (no clean bracket to measure against).
    fn flags_corrupted(&self) -> bool {
        !matches!(self, Self::CommonMode(_))
    }

    /// The ensembler's hook.
    fn hook(&mut self) -> &mut dyn CandidateHook {
        match self {
            Self::Oracle(h) => h,
            Self::CommonMode(h) => h,
            Self::None(h) => h,
        }
    }
}

fn median(v: &[f32], s: &mut Vec<f32>) -> f32 {
    s.clear();
    s.extend_from_slice(v);
    s.sort_by(f32::total_cmp);
    let n = s.len();
    if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    }
}

fn bump(counts: &mut Vec<u64>, k: usize) {
    if counts.len() <= k {
        counts.resize(k + 1, 0);
    }
    counts[k] += 1;
}

/// The record-keeping observer: query counts, `M(tau)` and `q(tau)` histograms, bracket
/// accounting.
#[derive(Debug, Default)]
struct Recorder {
    queries: usize,
    corrupted_queries: usize,
    m_counts: Vec<u64>,
    q_counts: Vec<u64>,
    bracket: BracketAccumulator,
}

impl EpisodeObserver for Recorder {
    fn on_query(&mut self, e: &QueryEvent<'_>) {
        self.queries += 1;
        self.corrupted_queries += usize::from(e.corrupted);
    }
    fn on_step(&mut self, e: &StepEvent<'_>) {
        bump(&mut self.m_counts, e.m);
        bump(&mut self.q_counts, e.q);
        if let (Some(r), Some(b)) = (e.report, e.bracket) {
            self.bracket.record(&r, &b);
        }
    }
}

/// The runner's own observers (the record, the stage timer) and the caller's, told alike.
pub(crate) struct Watchers<'o> {
    rec: Recorder,
    timer: StageTimer,
    monitors: Monitors,
    user: &'o mut dyn EpisodeObserver,
}

/// The episode's monitors and their traces.
#[derive(Default)]
struct Monitors {
    running: Vec<(MonitorKind, Box<dyn Monitor + Send>, MonitorTrace)>,
}

impl Monitors {
    fn new(kinds: &[MonitorKind], geometry: ChunkGeometry, d: usize) -> Result<Self, RolloutError> {
        let running = kinds
            .iter()
            .map(|&k| {
                let m =
                    k.build(geometry, d, PUSHT_ACC_V_MIN_PX)
                        .map_err(|e| RolloutError::Config {
                            field: "monitors",
                            value: k.to_string(),
                            expected: format!("a monitor this geometry supports ({e})"),
                        })?;
                Ok((k, m, MonitorTrace::default()))
            })
            .collect::<Result<_, RolloutError>>()?;
        Ok(Self { running })
    }

    fn on_query(&mut self, e: &QueryEvent<'_>) {
        for (_, m, trace) in &mut self.running {
            if trace.error.is_some() {
                continue;
            }
            match m.observe(e.t, e.chunk) {
                Ok(Some(score)) => {
                    if trace.scores.is_empty() {
                        trace.first_query = e.index;
                    }
                    trace.scores.push(score);
                }
                Ok(None) => {}
                Err(err) => trace.error = Some(err.to_string()),
            }
        }
    }

    fn traces(self) -> std::collections::BTreeMap<String, MonitorTrace> {
        self.running
            .into_iter()
            .map(|(k, _, t)| (k.to_string(), t))
            .collect()
    }
}

impl<'o> Watchers<'o> {
    /// Fresh record and timer, and the caller's observer.
    pub(crate) fn new(user: &'o mut dyn EpisodeObserver) -> Self {
        Watchers {
            rec: Recorder::default(),
            timer: StageTimer::default(),
            monitors: Monitors::default(),
            user,
        }
    }
}

impl EpisodeObserver for Watchers<'_> {
    fn on_query(&mut self, e: &QueryEvent<'_>) {
        self.monitors.on_query(e);
        self.rec.on_query(e);
        self.user.on_query(e);
    }
    fn on_step(&mut self, e: &StepEvent<'_>) {
        self.rec.on_step(e);
        self.user.on_step(e);
    }
    fn on_stage(&mut self, stage: Stage, seconds: f64) {
        self.timer.on_stage(stage, seconds);
        self.user.on_stage(stage, seconds);
    }
}

/// How the arm turns chunks into actions.
enum Executor {
    /// `h` actions of the latest chunk.
    OpenLoop,
    /// The streaming ensembler (boxed: it is large and built once per episode).
    Ensemble(Box<TemporalEnsembler<Aggregator>>),
}

/// One episode of one arm, between stages.
pub(crate) struct Episode<'e, 's> {
    spec: &'s EpisodeSpec<'s>,
    geometry: ChunkGeometry,
    env: &'e mut dyn Environment,
    corruptor: Option<ObservationCorruptor>,
    candidate_fault: CandidateFault,
    executor: Executor,
    /// The last `keep` observations, oldest first.
    frames: Vec<Observation>,
    keep: usize,
    chunk: Vec<f32>,
    out: Vec<f32>,
    /// Whether the newest query's candidates are flagged corrupted.
    newest_flag: [bool; 1],
    steps: usize,
    max_coverage: f64,
    success: bool,
}

/// Run one episode of one arm. The returned record's `cell` is empty (the caller names it).
pub fn run_episode(
    policy: &dyn ChunkPolicy,
    spec: &EpisodeSpec<'_>,
) -> Result<EpisodeRecord, RolloutError> {
    run_episode_observed(policy, spec, &mut NoObserver)
}

/// [`run_episode`], telling `observer` every query and every control step
/// ([`crate::episode`] gives the stages).
pub fn run_episode_observed(
    policy: &dyn ChunkPolicy,
    spec: &EpisodeSpec<'_>,
    observer: &mut dyn EpisodeObserver,
) -> Result<EpisodeRecord, RolloutError> {
    let mut env = PushTEnv::new(spec.stream);
    run_episode_in(&mut env, policy, spec, observer)
}

/// One episode of one arm in any [`Environment`] (reset here from `spec.seed`; `spec.stream`
/// is PushT's and unused by other environments).
pub fn run_episode_in(
    env: &mut dyn Environment,
    policy: &dyn ChunkPolicy,
    spec: &EpisodeSpec<'_>,
    observer: &mut dyn EpisodeObserver,
) -> Result<EpisodeRecord, RolloutError> {
    let t_start = Instant::now();
    let mut w = Watchers::new(observer);
    let mut ep = Episode::new(env, policy, spec, &mut w)?;
    while !ep.over() {
        ep.observe(&mut w)?;
        if let Some(p) = ep.prepare(&mut w)? {
            let t = Instant::now();
            let chunk = p.answer_alone(policy)?;
            w.on_stage(p.stage(), t.elapsed().as_secs_f64());
            let event = ep.accept(&p, chunk, &mut w)?;
            w.on_query(&event);
        }
        ep.act(&mut w)?;
    }
    Ok(ep.record(w, t_start.elapsed().as_secs_f64()))
}

/// A query made ready by stage *corrupt*: the window the policy sees, whether the query is
/// corrupted, PGD's settings when it attacks it, and the query's two streams as they stand
/// after the corruption drew from them.
pub(crate) struct Pending {
    index: u64,
    window: Vec<Observation>,
    corrupted: bool,
    attack: Option<PgdConfig>,
    crng: ChaCha8Rng,
    srng: ChaCha8Rng,
}

impl Pending {
    /// The stage its answer is timed under: PGD is corruption, a plain query is *query*.
    pub(crate) fn stage(&self) -> Stage {
        if self.attack.is_some() {
            Stage::Corrupt
        } else {
            Stage::Query
        }
    }

    /// Whether the schedule corrupted this query.
    pub(crate) fn corrupted(&self) -> bool {
        self.corrupted
    }

    /// PGD's settings, when PGD attacks this query.
    pub(crate) fn attack(&self) -> Option<&PgdConfig> {
        self.attack.as_ref()
    }

    /// The window the policy sees.
    pub(crate) fn window(&self) -> &[Observation] {
        &self.window
    }

    /// Copies of the (attack, sampling) streams: the batch and the single answer both start
    /// from them, so a failed batch can be answered again query by query.
    pub(crate) fn streams(&self) -> (ChaCha8Rng, ChaCha8Rng) {
        (self.crng.clone(), self.srng.clone())
    }

    /// The chunk this query gets asked alone.
    pub(crate) fn answer_alone(&self, policy: &dyn ChunkPolicy) -> Result<Vec<f32>, PolicyError> {
        let (mut crng, mut srng) = self.streams();
        match &self.attack {
            Some(cfg) => mte_policy::attackable(policy)?.predict_chunk_attacked(
                &self.window,
                cfg,
                &mut crng,
                &mut srng,
            ),
            None => policy.predict_chunk(&self.window, &mut srng),
        }
    }
}

/// The rows of each chunk an episode uses: `T_o - 1 + span` of the policy's `t_p`.
///
/// # Errors
/// [`RolloutError::Config`] naming `span` unless `1 <= span <= t_p - t_o + 1`.
pub fn used_horizon(t_p: usize, t_o: usize, span: Option<usize>) -> Result<usize, RolloutError> {
    let full = (t_p + 1).saturating_sub(t_o);
    match span {
        None => Ok(t_p),
        Some(s) if (1..=full).contains(&s) => Ok(t_o - 1 + s),
        Some(s) => Err(RolloutError::Config {
            field: "span",
            value: s.to_string(),
            expected: format!("1..={full} (the policy's executable rows, T_p - T_o + 1)"),
        }),
    }
}

impl<'e, 's> Episode<'e, 's> {
    /// Checks the spec, resets the environment and builds the arm's executor.
    pub(crate) fn new(
        env: &'e mut dyn Environment,
        policy: &dyn ChunkPolicy,
        spec: &'s EpisodeSpec<'s>,
        w: &mut Watchers<'_>,
    ) -> Result<Self, RolloutError> {
        let (t_o, d) = (policy.n_obs_steps(), policy.action_dim());
        let t_p = used_horizon(policy.horizon(), t_o, spec.span)?;
        let h = spec.h;
        if h == 0 || h + t_o > t_p + 1 {
            return Err(RolloutError::Config {
                field: "h",
                value: h.to_string(),
                expected: format!("1..={} (T_p - T_o + 1)", t_p + 1 - t_o),
            });
        }
        spec.corruption.validate()?;
        let geometry = ChunkGeometry { t_p, t_o, h };
        let clean = spec.corruption.is_clean();
        if env.action_dim() != d {
            return Err(RolloutError::Config {
                field: "policy",
                value: format!("action dimension {d}"),
                expected: format!("the environment's action dimension {}", env.action_dim()),
            });
        }
        let t = Instant::now();
        let score = env.reset(spec.seed)?;
        w.on_stage(Stage::Step, t.elapsed().as_secs_f64());
        let candidate_fault = CandidateFault::new(spec, d, clean)?;
        let executor = match spec.execution {
            Execution::OpenLoop => Executor::OpenLoop,
            Execution::Ensemble(a) => {
                Executor::Ensemble(Box::new(TemporalEnsembler::with_options(
                    geometry,
                    d,
                    a,
                    EnsemblerOptions {
                        lookahead: None,
                        bracket_diagnostics: !clean,
                    },
                )?))
            }
        };
        let corruptor = observation_corruptor(spec)?;
        w.monitors = Monitors::new(spec.monitors, geometry, d)?;
        let keep = corruptor
            .as_ref()
            .map_or(t_o, |c| c.frames_needed(t_o))
            .max(t_o + 1);
        Ok(Self {
            spec,
            geometry,
            max_coverage: score,
            env,
            corruptor,
            candidate_fault,
            executor,
            frames: Vec::with_capacity(keep + 1),
            keep,
            chunk: Vec::new(),
            out: vec![0f32; d],
            newest_flag: [false],
            steps: 0,
            success: false,
        })
    }

    /// The newest `T_o` observations as the sensors gave them, before any fault.
    pub(crate) fn clean_window(&self) -> &[Observation] {
        &self.frames[self.frames.len() - self.geometry.t_o..]
    }

    /// Stage *observe*: the current observation joins the history.
    pub(crate) fn observe(&mut self, w: &mut dyn EpisodeObserver) -> Result<(), RolloutError> {
        let t = Instant::now();
        let o = self.env.observe(self.spec.needs)?;
        w.on_stage(Stage::Observe, t.elapsed().as_secs_f64());
        if self.frames.is_empty() {
            self.frames = vec![o; self.keep];
        } else {
            self.frames.remove(0);
            self.frames.push(o);
        }
        Ok(())
    }

    /// Whether the episode is over (solved, or at its step limit).
    pub(crate) fn over(&self) -> bool {
        self.success || self.steps >= self.spec.max_steps
    }

    /// Stage *corrupt* at a query time (`steps` a multiple of `h`): query `i = steps / h`'s
    /// schedule decision and window, ready for the policy; `None` between queries.
    pub(crate) fn prepare(
        &mut self,
        w: &mut dyn EpisodeObserver,
    ) -> Result<Option<Pending>, RolloutError> {
        let spec = self.spec;
        let (steps, t_o) = (self.steps, self.geometry.t_o);
        if steps % spec.h != 0 {
            return Ok(None);
        }
        let i = (steps / spec.h) as u64;
        let t = Instant::now();
        let mut crng = query_rng(spec.noise_seed, spec.seed, i, 1);
        let corrupted = !spec.corruption.is_clean()
            && spec
                .corruption
                .schedule
                .corrupts(i, steps as u64, self.geometry.m_min(), &mut crng);
        let window = match &mut self.corruptor {
            Some(c) => c.window(&self.frames, t_o, corrupted, spec.needs.image, &mut crng),
            None => self.frames[self.frames.len() - t_o..].to_vec(),
        };
        w.on_stage(Stage::Corrupt, t.elapsed().as_secs_f64());
        let attack = spec.corruption.fault.pgd().filter(|_| corrupted).cloned();
        Ok(Some(Pending {
            index: i,
            window,
            corrupted,
            attack,
            crng,
            srng: query_rng(spec.noise_seed, spec.seed, spec.sampling.stream_of(i), 0),
        }))
    }

    /// The rest of stage *query*: `chunk`, the policy's answer to `p`, into the executor.
    pub(crate) fn accept(
        &mut self,
        p: &Pending,
        chunk: Vec<f32>,
        w: &mut dyn EpisodeObserver,
    ) -> Result<QueryEvent<'_>, RolloutError> {
        let (steps, corrupted) = (self.steps, p.corrupted);
        self.chunk = chunk;
        // A shortened span keeps the chunk's first rows (a shorter chunk is left as it is:
        // a wrong length stays the ensembler's typed error).
        self.chunk.truncate(self.geometry.t_p * self.out.len());
        // Common-mode bias acts while the newest query is corrupted.
        if let CandidateFault::CommonMode(s) = &mut self.candidate_fault {
            s.on = corrupted;
        }
        self.newest_flag = [corrupted && self.candidate_fault.flags_corrupted()];
        let t = Instant::now();
        if let Executor::Ensemble(e) = &mut self.executor {
            let meta = QueryMeta {
                corrupted: self.newest_flag[0],
            };
            e.insert(steps as u64, &self.chunk, meta)?;
        }
        w.on_stage(Stage::Ensemble, t.elapsed().as_secs_f64());
        Ok(QueryEvent {
            index: p.index,
            t: steps as u64,
            chunk: &self.chunk,
            corrupted,
        })
    }

    /// Stages *ensemble*, *act* and *step*: control time `steps`'s action, told to the
    /// observers, executed.
    pub(crate) fn act(&mut self, w: &mut dyn EpisodeObserver) -> Result<(), RolloutError> {
        let event = self.decide(w)?;
        w.on_step(&event);
        self.step(w)
    }

    /// The episode's record (its `cell` empty: the caller names it); `total_s` is the
    /// wall time this episode's own work took (s).
    pub(crate) fn record(&self, w: Watchers<'_>, total_s: f64) -> EpisodeRecord {
        let spec = self.spec;
        let (rec, mut times, monitors) = (w.rec, w.timer.times, w.monitors.traces());
        times.total_s = total_s;
        let ensembled = matches!(spec.execution, Execution::Ensemble(_));
        EpisodeRecord {
            cell: String::new(),
            arm: spec.execution.to_string(),
            seed: spec.seed,
            success: self.success,
            max_coverage: self.max_coverage,
            steps: self.steps,
            queries: rec.queries,
            corrupted_queries: rec.corrupted_queries,
            m_counts: rec.m_counts,
            q_counts: rec.q_counts,
            bracket: (!spec.corruption.is_clean() && ensembled).then_some(rec.bracket),
            times,
            monitors,
        }
    }

    /// Stages *ensemble* and *act*: the action of control time `steps`.
    fn decide(&mut self, w: &mut dyn EpisodeObserver) -> Result<StepEvent<'_>, RolloutError> {
        let tau = self.steps as u64;
        let d = self.out.len();
        if let CandidateFault::CommonMode(s) = &mut self.candidate_fault {
            s.at(tau);
        }
        let t = Instant::now();
        let event = match &mut self.executor {
            Executor::Ensemble(e) => {
                let s = e.action_with(tau, self.candidate_fault.hook())?;
                self.out.copy_from_slice(s.action);
                let (report, bracket) = (s.report, s.bracket);
                let (candidates, corrupted) = e.last_candidates();
                StepEvent {
                    tau,
                    candidates,
                    corrupted,
                    action: &self.out,
                    m: report.m,
                    q: report.q,
                    report: Some(report),
                    bracket,
                }
            }
            Executor::OpenLoop => {
                let r = self.geometry.t_o - 1 + self.steps % self.spec.h;
                self.out.copy_from_slice(&self.chunk[r * d..(r + 1) * d]);
                if let CandidateFault::CommonMode(s) = &self.candidate_fault
                    && s.on
                {
                    s.shift(&mut self.out);
                }
                StepEvent {
                    tau,
                    candidates: Candidates::new(&self.chunk[r * d..(r + 1) * d], d)?,
                    corrupted: &self.newest_flag,
                    action: &self.out,
                    m: 1,
                    q: usize::from(self.newest_flag[0]),
                    report: None,
                    bracket: None,
                }
            }
        };
        w.on_stage(Stage::Ensemble, t.elapsed().as_secs_f64());
        Ok(event)
    }

    /// Stage *step*: the environment executes the action.
    fn step(&mut self, w: &mut dyn EpisodeObserver) -> Result<(), RolloutError> {
        let t = Instant::now();
        let outcome = self.env.step(&self.out)?;
        w.on_stage(Stage::Step, t.elapsed().as_secs_f64());
        self.steps += 1;
        self.max_coverage = self.max_coverage.max(outcome.score);
        self.success = outcome.success;
        Ok(())
    }
}

/// Whether a spec's declared patch step names the file's: equal to a relative 1e-9, so a
/// spec may write the step as a decimal (`1.5e-3`) that round-trips through JSON.
fn same_step(declared: f64, file: f64) -> bool {
    (declared - file).abs() <= 1e-9 * declared.abs().max(file.abs())
}

/// The arm's observation corruptor, if its fault is a sensor fault (a patch is loaded and
/// checked against the frame here, not per frame).
fn observation_corruptor(
    spec: &EpisodeSpec<'_>,
) -> Result<Option<ObservationCorruptor>, RolloutError> {
    let Some(fault) = spec.corruption.fault.sensor() else {
        return Ok(None);
    };
    let SensorFault::Patch { path, step } = fault else {
        return Ok(Some(ObservationCorruptor::new(fault.clone())));
    };
    let Some((w, h)) = spec.needs.image else {
        return Err(RolloutError::Config {
            field: "fault",
            value: fault.to_string(),
            expected: "an image policy (a patch is drawn into camera frames)".into(),
        });
    };
    let bad_path = |e: String| RolloutError::Config {
        field: "fault.path",
        value: path.display().to_string(),
        expected: e,
    };
    let (meta, patch) =
        crate::patch_file::load(path).map_err(|e| bad_path(format!("a patch directory ({e})")))?;
    patch.origin(w, h).map_err(|e| bad_path(e.to_string()))?;
    if let Some(step) = *step
        && !same_step(step, meta.step)
    {
        return Err(RolloutError::Config {
            field: "fault.step",
            value: step.to_string(),
            expected: format!(
                "the step size {} that {} was trained with (patch.json)",
                meta.step,
                path.display()
            ),
        });
    }
    Ok(Some(ObservationCorruptor::with_patch(fault.clone(), patch)))
}
