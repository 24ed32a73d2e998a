//! Sweeps: a TOML grid of policy x corruption x q x h (arms within each cell), run in
//! parallel into a [`RunDir`], resumable and shardable.
//!
//! ```toml
//! name = "blank-burst"
//! policies = ["assets/policies/pusht_keypoints_cpu"]
//! arms = ["ewm:0.01", "median"]      # compared on the same episodes
//! h = [2]
//! seeds = { first = 100000, count = 20 }
//! max_steps = 300                     # default 300 (gym-pusht's limit)
//! noise_seed = 0                      # per-query sampling noise, shared by the arms
//! stream = "legacy"                   # reset stream
//!
//! [[corruptions]]
//! fault = { kind = "blank" }
//! q = [0, 1, 2, 3]                    # burst schedule; q = 0 is the clean cell
//!
//! [[corruptions]]
//! fault = { kind = "occluder", size = 24 }
//! schedules = [{ kind = "dense", start = 40, end = 80 }]
//! ```
//!
//! A clean cell (q = 0, or fault `none`) is made once per policy and `h`, however many
//! corruption entries ask for it. `--shard i/n` runs cells `i, i + n, ...` of the grid; the
//! shards may share one directory (cells have separate files) or write several that
//! [`crate::store::load_runs`] merges.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use mte_sim::ResetStream;
use serde::{Deserialize, Serialize};

use crate::Reporter;
use crate::corruption::{CorruptionSpec, Fault, Schedule, SensorFault};
use crate::environment::{EnvTarget, Environment};
use crate::expert_policy::{PushTExpertPolicy, is_expert_policy};
use crate::label::{policy_label, slug, span_suffix};
use crate::lockstep::run_lockstep;
use crate::pusht::{EpisodeSpec, Execution, RolloutError, run_episode};
use crate::record::{CellSpec, ErrorRecord, Line, Manifest, RUN_FORMAT};
use crate::store::{CellWriter, RunDir, StoreError};
use mte_policy::{ChunkPolicy, PolicyError};

/// Episode seeds: a range or an explicit list.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Seeds {
    /// `first, first + 1, ..., first + count - 1`.
    Range {
        /// First seed.
        first: u64,
        /// How many.
        count: usize,
    },
    /// These seeds.
    List(Vec<u64>),
}

/// The most episode seeds one cell may list: 10^6, far beyond any protocol (the paper's is
/// 50 per cell), so that a mistyped `count` is an error, not an allocation that aborts.
pub const MAX_SEEDS: usize = 1_000_000;

impl Seeds {
    /// Checks the count (1..=[`MAX_SEEDS`]) and that a range does not pass `u64::MAX`.
    pub fn validate(&self) -> Result<(), SweepError> {
        let n = match self {
            Self::Range { count, .. } => *count,
            Self::List(v) => v.len(),
        };
        if n == 0 || n > MAX_SEEDS {
            return Err(field("seeds", n, format!("1..={MAX_SEEDS} seeds")));
        }
        if let Self::Range { first, count } = *self
            && first.checked_add(count as u64 - 1).is_none()
        {
            return Err(field(
                "seeds",
                format!("{{ first = {first}, count = {count} }}"),
                "a range that ends at or below 2^64 - 1",
            ));
        }
        Ok(())
    }

    /// The seeds in order (call [`Seeds::validate`] first).
    pub fn to_vec(&self) -> Vec<u64> {
        match self {
            Self::Range { first, count } => (0..*count as u64).map(|i| first + i).collect(),
            Self::List(v) => v.clone(),
        }
    }
}

/// One corruption entry of a sweep.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CorruptionEntry {
    /// The fault.
    pub fault: Fault,
    /// Burst lengths (burst schedule with period `M_min`); 0 = clean.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub q: Vec<usize>,
    /// Burst phase.
    #[serde(default)]
    pub phase: usize,
    /// Explicit schedules (instead of, or besides, `q`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub schedules: Vec<Schedule>,
}

/// A sweep spec (see the module docs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SweepSpec {
    /// Run name.
    pub name: String,
    /// Policy checkpoint directories.
    pub policies: Vec<String>,
    /// Arms compared in every cell.
    pub arms: Vec<String>,
    /// Query strides.
    pub h: Vec<usize>,
    /// Episode seeds (Diffusion Policy's PushT test seeds are 100000..100049).
    pub seeds: Seeds,
    /// Step limit per episode.
    #[serde(default = "default_max_steps")]
    pub max_steps: usize,
    /// Seed of the per-query sampling noise and corruption streams.
    #[serde(default)]
    pub noise_seed: u64,
    /// Reset stream.
    #[serde(default)]
    pub stream: ResetStream,
    /// Corruptions.
    pub corruptions: Vec<CorruptionEntry>,
    /// Runtime monitors scoring every query of every episode (`["tide", "acc"]`); their
    /// scores go into the records, thresholds come from calibration afterwards.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub monitors: Vec<mte_ensemble::MonitorKind>,
    /// Where the episodes run: `pusht` (native, the default), or a bridge target
    /// (`gym:<module>/<EnvId>`, `robomimic:<task>`) with one worker process per episode of
    /// a lockstep group (`mte_eval::bridge`; the worker's Python from `MTE_PYTHON` or
    /// `tools/env-setup`).
    #[serde(default, skip_serializing_if = "EnvTarget::is_pusht")]
    pub env: EnvTarget,
    /// Spans: executable rows of each chunk the runner uses, counted from row `T_o - 1`
    /// ([`crate::pusht::EpisodeSpec::span`]), one cell per span (ids get `-span<N>`);
    /// empty (the default): all `T_p - T_o + 1` rows.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub span: Vec<usize>,
}

fn default_max_steps() -> usize {
    300
}

/// Errors of a sweep.
#[derive(Debug, thiserror::Error)]
pub enum SweepError {
    /// The spec did not parse.
    #[error("sweep spec: {0}")]
    Toml(String),
    /// A spec value is out of range.
    #[error("sweep spec: `{field}` = {value}: expected {expected}")]
    Field {
        /// Field.
        field: &'static str,
        /// Value.
        value: String,
        /// Expectation.
        expected: String,
    },
    /// The results store failed.
    #[error(transparent)]
    Store(#[from] StoreError),
}

fn field(f: &'static str, v: impl ToString, e: impl Into<String>) -> SweepError {
    SweepError::Field {
        field: f,
        value: v.to_string(),
        expected: e.into(),
    }
}

impl SweepSpec {
    /// Parses TOML.
    pub fn from_toml(text: &str) -> Result<Self, SweepError> {
        let s: Self = toml::from_str(text).map_err(|e| SweepError::Toml(e.to_string()))?;
        s.validate()?;
        Ok(s)
    }

    /// The spec with every default written out.
    pub fn to_toml(&self) -> Result<String, SweepError> {
        toml::to_string(self).map_err(|e| SweepError::Toml(e.to_string()))
    }

    /// Checks the grid.
    pub fn validate(&self) -> Result<(), SweepError> {
        if self.policies.is_empty() {
            return Err(field("policies", "[]", "at least one checkpoint directory"));
        }
        if self.arms.is_empty() {
            return Err(field("arms", "[]", "at least one arm"));
        }
        for a in &self.arms {
            Execution::from_str(a)
                .map_err(|e| field("arms", a, format!("open-loop or an aggregator ({e})")))?;
        }
        if self.h.is_empty() || self.h.contains(&0) {
            return Err(field("h", format!("{:?}", self.h), "strides >= 1"));
        }
        self.seeds.validate()?;
        if self.max_steps == 0 {
            return Err(field("max_steps", 0, "at least 1"));
        }
        let longest = self.h.iter().copied().max().unwrap_or(1);
        if let Some(s) = self.span.iter().find(|&&s| s < longest) {
            return Err(field(
                "span",
                s,
                format!("at least every stride (the longest is {longest}; no uncovered time)"),
            ));
        }
        if self.corruptions.is_empty() {
            return Err(field("corruptions", "[]", "at least one entry"));
        }
        for c in &self.corruptions {
            c.fault
                .validate()
                .map_err(|e| field("corruptions.fault", &c.fault, e.to_string()))?;
            for s in &c.schedules {
                s.validate()
                    .map_err(|e| field("corruptions.schedules", format!("{s:?}"), e.to_string()))?;
            }
            if c.q.is_empty() && c.schedules.is_empty() {
                return Err(field("corruptions.q", "[]", "burst lengths or `schedules`"));
            }
        }
        self.check_cell_ids()
    }

    /// Two different cells must not share an id: a run keeps one file per id.
    fn check_cell_ids(&self) -> Result<(), SweepError> {
        match self.unique_cells().1 {
            Some((kept, clash)) => Err(field(
                "corruptions",
                &clash.id,
                format!(
                    "cells with different ids; `{}` and `{}` ({}, {}) both name it",
                    kept.corruption.fault, clash.corruption.fault, kept.policy, clash.policy
                ),
            )),
            None => Ok(()),
        }
    }

    /// The grid's cells, in a stable order (policy, h, corruption entry, q / schedule).
    pub fn cells(&self) -> Vec<CellSpec> {
        self.unique_cells().0
    }

    /// The grid's cells, each id once (the first of identical cells kept), and the first
    /// cell that differs from a kept one with its id (with that kept cell), if any.
    fn unique_cells(&self) -> (Vec<CellSpec>, Option<(CellSpec, CellSpec)>) {
        let mut cells: Vec<CellSpec> = Vec::new();
        let mut clash = None;
        for c in self.cells_with_repeats() {
            match cells.iter().find(|k| k.id == c.id) {
                None => cells.push(c),
                Some(k) if k.corruption != c.corruption || k.policy != c.policy => {
                    clash = clash.or_else(|| Some((k.clone(), c)));
                }
                Some(_) => {}
            }
        }
        (cells, clash)
    }

    /// Every (policy, h, corruption) of the grid in order, repeats included.
    fn cells_with_repeats(&self) -> Vec<CellSpec> {
        let seeds = self.seeds.to_vec();
        let mut cells: Vec<CellSpec> = Vec::new();
        for p in &self.policies {
            let label = policy_label(p).to_string();
            for (span, &h) in self
                .spans()
                .into_iter()
                .flat_map(|s| self.h.iter().map(move |h| (s, h)))
            {
                let mut push = |corruption: CorruptionSpec| {
                    cells.push(CellSpec {
                        id: slug(&format!("{label}-{corruption}-h{h}{}", span_suffix(span))),
                        policy: p.clone(),
                        corruption,
                        h,
                        arms: self.arms.clone(),
                        seeds: seeds.clone(),
                        max_steps: self.max_steps,
                        span,
                    });
                };
                for c in &self.corruptions {
                    for &q in &c.q {
                        push(if q == 0 || c.fault == Fault::None {
                            CorruptionSpec::CLEAN
                        } else {
                            CorruptionSpec {
                                fault: c.fault.clone(),
                                schedule: Schedule::Burst {
                                    q,
                                    phase: c.phase,
                                    period: None,
                                },
                            }
                        });
                    }
                    for s in &c.schedules {
                        push(CorruptionSpec {
                            fault: c.fault.clone(),
                            schedule: s.clone(),
                        });
                    }
                }
            }
        }
        cells
    }

    /// The spans of the grid: `None` (every executable row) when the spec names none.
    fn spans(&self) -> Vec<Option<usize>> {
        if self.span.is_empty() {
            vec![None]
        } else {
            self.span.iter().copied().map(Some).collect()
        }
    }

    /// The manifest of a new run of this spec.
    pub fn manifest(&self, git_commit: Option<String>, created_unix_s: u64) -> Manifest {
        Manifest {
            format: RUN_FORMAT.into(),
            name: self.name.clone(),
            git_commit,
            mte_version: env!("CARGO_PKG_VERSION").into(),
            created_unix_s,
            noise_seed: self.noise_seed,
            cells: self.cells(),
            machines: vec![crate::machine::Machine::detect()],
        }
    }
}

/// Which part of the grid this process runs: cells `index, index + count, ...`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    /// 0-based shard index.
    pub index: usize,
    /// Number of shards.
    pub count: usize,
}

impl Default for Shard {
    fn default() -> Self {
        Self { index: 0, count: 1 }
    }
}

impl FromStr for Shard {
    type Err = SweepError;
    /// `i/n` with `0 <= i < n`.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let bad = || field("shard", s, "i/n with 0 <= i < n (e.g. 0/4)");
        let (i, n) = s.split_once('/').ok_or_else(bad)?;
        let (index, count) = (
            i.trim().parse().map_err(|_| bad())?,
            n.trim().parse().map_err(|_| bad())?,
        );
        if count == 0 || index >= count {
            return Err(bad());
        }
        Ok(Self { index, count })
    }
}

/// A policy the runner can load by its spec string.
pub trait PolicySource: Sync {
    /// Loads (or returns a cached) policy.
    fn load(&self, path: &str) -> Result<Box<dyn ChunkPolicy + Send + Sync>, PolicyError>;
}

/// Loads a policy by name: [`EXPERT_POLICY`](crate::expert_policy::EXPERT_POLICY) (with
/// optional settings) is the scripted PushT expert
/// ([`PushTExpertPolicy`], always on the CPU); anything else is a checkpoint directory of a
/// known policy type, loaded onto `device` ([`mte_policy::load_policy_on`]).
pub fn load_named_policy(
    path: &Path,
    device: &candle_core::Device,
) -> Result<Box<dyn ChunkPolicy + Send + Sync>, PolicyError> {
    if let Some(name) = path.to_str().filter(|n| is_expert_policy(n)) {
        return Ok(Box::new(name.parse::<PushTExpertPolicy>()?));
    }
    mte_policy::load_policy_on(path, device)
}

/// Loads checkpoint directories of any known policy type ([`mte_policy::load_policy`], CPU),
/// and [`EXPERT_POLICY`](crate::expert_policy::EXPERT_POLICY).
#[derive(Debug, Clone, Copy, Default)]
pub struct CheckpointSource;

impl PolicySource for CheckpointSource {
    fn load(&self, path: &str) -> Result<Box<dyn ChunkPolicy + Send + Sync>, PolicyError> {
        load_named_policy(Path::new(path), &candle_core::Device::Cpu)
    }
}

/// Loads checkpoint directories with their weights on one device
/// ([`mte_policy::load_policy_on`]): a sweep's policy forwards (and PGD's backward passes)
/// then run there, in lockstep batches; environments and ensemblers stay on the CPU.
#[derive(Debug, Clone)]
pub struct CheckpointSourceOn(pub candle_core::Device);

impl PolicySource for CheckpointSourceOn {
    fn load(&self, path: &str) -> Result<Box<dyn ChunkPolicy + Send + Sync>, PolicyError> {
        load_named_policy(Path::new(path), &self.0)
    }
}

/// What [`run`] did.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SweepSummary {
    /// Cells in this shard.
    pub cells: usize,
    /// Episodes run now.
    pub episodes_run: usize,
    /// Episodes skipped as already finished.
    pub episodes_skipped: usize,
    /// Errors recorded.
    pub errors: usize,
    /// Ids of the cells that recorded errors in this run, in cell order.
    #[serde(default)]
    pub failed_cells: Vec<String>,
}

/// One unit of work: episodes of one cell (seed, arm) still to run, run together in
/// lockstep ([`crate::lockstep`]) or one after the other.
struct Task {
    cell: usize,
    episodes: Vec<(u64, Execution)>,
}

/// How a sweep spends the machine; the records do not depend on it (only their timings).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RunOptions {
    /// Worker threads (tasks run in parallel).
    pub workers: usize,
    /// Episodes of a cell run in lockstep, at most (the policy answers their queries in
    /// one batch); 1 runs every episode alone.
    pub batch: usize,
}

impl RunOptions {
    /// Lockstep groups of at most this many episodes by default: large enough to amortise
    /// the policy's per-call overhead, small enough to keep a group's memory modest (a
    /// keypoint group's activations are a few MB; an image group under PGD a few hundred).
    pub const DEFAULT_BATCH: usize = 64;

    /// `workers` threads with the default lockstep group size.
    pub fn new(workers: usize) -> Self {
        RunOptions {
            workers,
            batch: Self::DEFAULT_BATCH,
        }
    }
}

/// Largest lockstep group for bridged environments: each episode of a group has its own
/// worker process (a robosuite worker with cameras holds a few hundred MB).
pub const BRIDGE_GROUP: usize = 4;

/// A loaded policy, or why it could not be loaded (its cells fail, not the sweep).
type Loaded = Result<Box<dyn ChunkPolicy + Send + Sync>, String>;

/// The cell files of a shard, written by many workers: one lock per cell, and the error
/// records counted per cell.
struct Writers {
    files: Vec<Mutex<CellWriter>>,
    errors: Mutex<Vec<usize>>,
}

impl Writers {
    fn append(&self, cell: usize, line: &Line) -> Result<(), SweepError> {
        if matches!(line, Line::Error(_)) {
            self.errors.lock().map_err(|_| poisoned())?[cell] += 1;
        }
        self.files[cell]
            .lock()
            .map_err(|_| poisoned())?
            .append(line)
            .map_err(SweepError::from)
    }
}

/// Runs this shard of the grid into `run` on `options.workers` threads, episodes of a cell
/// in lockstep groups of at most `options.batch`, skipping finished (arm, seed) pairs. Each
/// finished episode is appended and synced at once.
pub fn run(
    spec: &SweepSpec,
    manifest: &Manifest,
    run: &RunDir,
    shard: Shard,
    options: RunOptions,
    policies: &dyn PolicySource,
    reporter: &dyn Reporter,
) -> Result<SweepSummary, SweepError> {
    let cells: Vec<&CellSpec> = manifest
        .cells
        .iter()
        .enumerate()
        .filter(|(i, _)| i % shard.count == shard.index)
        .map(|(_, c)| c)
        .collect();
    let options = if spec.env.is_pusht() {
        options
    } else {
        // One worker process per episode of a group: keep the groups small.
        RunOptions {
            batch: options.batch.min(BRIDGE_GROUP),
            ..options
        }
    };
    let (tasks, skipped, writers) = plan(&cells, run, options)?;
    reporter.start(
        "episodes",
        tasks.iter().map(|t| t.episodes.len() as u64).sum(),
    );
    let loaded = load_policies(&cells, policies)?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(options.workers.max(1))
        .build()
        .map_err(|e| field("workers", options.workers, format!("a thread pool ({e})")))?;
    let ctx = TaskContext {
        spec,
        noise_seed: manifest.noise_seed,
        cells: &cells,
        loaded: &loaded,
        writers: &writers,
        reporter,
    };
    let results = run_in_order(&pool, options.workers.max(1), &tasks, |t| {
        ctx.run(t, options.batch)
    });
    reporter.finish();
    let mut episodes_run = 0;
    for r in results {
        episodes_run += r.ok_or_else(poisoned)??;
    }
    let errors = writers.errors.into_inner().map_err(|_| poisoned())?;
    Ok(SweepSummary {
        cells: cells.len(),
        episodes_run,
        episodes_skipped: skipped,
        errors: errors.iter().sum(),
        failed_cells: cells
            .iter()
            .zip(&errors)
            .filter(|(_, n)| **n > 0)
            .map(|(c, _)| c.id.clone())
            .collect(),
    })
}

/// Runs `tasks` on `workers` threads of `pool`, each thread taking the next task in list
/// order when it is free, so that the cells of a sweep start in the order its spec gives
/// them (rayon's `par_iter` would split the list in halves and start the second half at
/// once). Results in list order; `None` only where a task panicked.
fn run_in_order<T: Sync, R: Send>(
    pool: &rayon::ThreadPool,
    workers: usize,
    tasks: &[T],
    f: impl Fn(&T) -> R + Sync,
) -> Vec<Option<R>> {
    let next = AtomicUsize::new(0);
    let slots: Vec<Mutex<Option<R>>> = tasks.iter().map(|_| Mutex::new(None)).collect();
    pool.scope(|s| {
        for _ in 0..workers.min(tasks.len()) {
            s.spawn(|_| {
                loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(t) = tasks.get(i) else { break };
                    let r = f(t);
                    if let Ok(mut slot) = slots[i].lock() {
                        *slot = Some(r);
                    }
                }
            });
        }
    });
    slots
        .into_iter()
        .map(|m| m.into_inner().ok().flatten())
        .collect()
}

/// The work list of `cells` (finished (arm, seed) pairs skipped and counted) and their
/// open cell files. A cell's remaining episodes (seed-major, the arms of a seed together)
/// are cut into tasks of at most `options.batch`, and small enough that every worker gets
/// one (a shard of one big cell still fills the machine).
fn plan(
    cells: &[&CellSpec],
    run: &RunDir,
    options: RunOptions,
) -> Result<(Vec<Task>, usize, Writers), SweepError> {
    let mut todo: Vec<Vec<(u64, Execution)>> = Vec::new();
    let mut skipped = 0;
    let mut files = Vec::new();
    for c in cells {
        let done = run.finished(&c.id)?;
        files.push(Mutex::new(run.writer(&c.id)?));
        let mut episodes = Vec::new();
        for &seed in &c.seeds {
            for a in &c.arms {
                if done.contains(&(a.clone(), seed)) {
                    skipped += 1;
                } else {
                    let arm =
                        Execution::from_str(a).map_err(|e| field("arms", a, e.to_string()))?;
                    episodes.push((seed, arm));
                }
            }
        }
        todo.push(episodes);
    }
    let total: usize = todo.iter().map(Vec::len).sum();
    let size = total
        .div_ceil(options.workers.max(1))
        .clamp(1, options.batch.max(1));
    let mut tasks = Vec::new();
    for (ci, episodes) in todo.into_iter().enumerate() {
        for group in episodes.chunks(size) {
            tasks.push(Task {
                cell: ci,
                episodes: group.to_vec(),
            });
        }
    }
    let errors = Mutex::new(vec![0; cells.len()]);
    Ok((tasks, skipped, Writers { files, errors }))
}

/// Loads each policy of `cells` once, and checks every cell's burst against its policy.
fn load_policies<'c>(
    cells: &[&'c CellSpec],
    policies: &dyn PolicySource,
) -> Result<HashMap<&'c str, Loaded>, SweepError> {
    let mut loaded: HashMap<&str, Loaded> = HashMap::new();
    for c in cells {
        loaded.entry(c.policy.as_str()).or_insert_with(|| {
            policies
                .load(&c.policy)
                .map_err(|e| format!("loading policy {}: {e}", c.policy))
        });
    }
    for c in cells {
        if let Some(Ok(p)) = loaded.get(c.policy.as_str()) {
            let t_p = crate::pusht::used_horizon(p.horizon(), p.n_obs_steps(), c.span)
                .map_err(|e| field("span", &c.id, e.to_string()))?;
            check_burst(c, t_p, p.n_obs_steps())?;
        }
    }
    Ok(loaded)
}

/// What every task of a sweep shares.
struct TaskContext<'a> {
    spec: &'a SweepSpec,
    noise_seed: u64,
    cells: &'a [&'a CellSpec],
    loaded: &'a HashMap<&'a str, Loaded>,
    writers: &'a Writers,
    reporter: &'a dyn Reporter,
}

impl TaskContext<'_> {
    /// Runs the episodes of one task and appends a line per episode (its record or its
    /// error) as each finishes; returns the episodes run.
    fn run(&self, t: &Task, batch: usize) -> Result<usize, SweepError> {
        let c = self.cells[t.cell];
        // Every policy of the shard was loaded (or failed to) before the tasks ran.
        let Some(loaded) = self.loaded.get(c.policy.as_str()) else {
            return Ok(0);
        };
        let policy = match loaded {
            Ok(p) => p,
            Err(e) => {
                for &(seed, arm) in &t.episodes {
                    self.append(t.cell, seed, arm, Err(e.clone()))?;
                }
                return Ok(0);
            }
        };
        let specs: Vec<EpisodeSpec<'_>> = t
            .episodes
            .iter()
            .map(|&(seed, execution)| EpisodeSpec {
                needs: policy.needs(),
                seed,
                stream: self.spec.stream,
                h: c.h,
                max_steps: c.max_steps,
                execution,
                corruption: &c.corruption,
                noise_seed: self.noise_seed,
                sampling: Default::default(),
                monitors: &self.spec.monitors,
                span: c.span,
            })
            .collect();
        let mut ran = 0;
        let mut failure = None;
        let mut done = |i: usize, r: Result<crate::record::EpisodeRecord, RolloutError>| {
            let (seed, arm) = t.episodes[i];
            let r = r.map(|mut rec| {
                rec.cell = c.id.clone();
                rec
            });
            ran += usize::from(r.is_ok());
            if let Err(e) = self.append(t.cell, seed, arm, r.map_err(|e| e.to_string()))
                && failure.is_none()
            {
                failure = Some(e);
            }
        };
        if let EnvTarget::Bridge(target) = &self.spec.env {
            run_bridged(target, policy.as_ref(), &specs, &mut done);
        } else if batch > 1 {
            run_lockstep(policy.as_ref(), &specs, &mut done);
        } else {
            for (i, spec) in specs.iter().enumerate() {
                done(i, run_episode(policy.as_ref(), spec));
            }
        }
        match failure {
            Some(e) => Err(e),
            None => Ok(ran),
        }
    }

    /// Appends one episode's line (its record, or its error) and advances the progress.
    fn append(
        &self,
        cell: usize,
        seed: u64,
        arm: Execution,
        r: Result<crate::record::EpisodeRecord, String>,
    ) -> Result<(), SweepError> {
        let line = match r {
            Ok(rec) => Line::Episode(rec),
            Err(error) => Line::Error(ErrorRecord {
                cell: self.cells[cell].id.clone(),
                arm: Some(arm.to_string()),
                seed: Some(seed),
                error,
            }),
        };
        self.writers.append(cell, &line)?;
        self.reporter.advance(1);
        Ok(())
    }
}

thread_local! {
    /// Bridge workers kept between the lockstep groups this thread runs: a robosuite worker
    /// takes seconds to start, an episode as little as one. Seeded resets do not depend on
    /// what a worker ran before, so reuse changes no record. They close when the sweep's
    /// thread pool ends.
    static WORKERS: std::cell::RefCell<Vec<crate::bridge::BridgeEnv>> =
        const { std::cell::RefCell::new(Vec::new()) };
}

/// A worker for `target` observed with `needs`: one this thread kept, or a new one.
fn take_worker(
    target: &crate::bridge::Target,
    needs: mte_policy::ObsNeeds,
) -> Result<crate::bridge::BridgeEnv, crate::environment::EnvError> {
    let kept = WORKERS.with(|w| {
        let mut w = w.borrow_mut();
        let i = w
            .iter()
            .position(|e| e.target() == target && e.needs() == needs)?;
        Some(w.swap_remove(i))
    });
    match kept {
        Some(env) => Ok(env),
        None => crate::bridge::BridgeEnv::spawn(target, needs, &Default::default()),
    }
}

/// Runs `specs` in lockstep, each episode in its own worker for `target` (kept for the
/// thread's next group if it is still alive); an episode whose worker does not start is
/// recorded as failed with the reason.
fn run_bridged(
    target: &crate::bridge::Target,
    policy: &dyn ChunkPolicy,
    specs: &[EpisodeSpec<'_>],
    done: &mut crate::lockstep::OnDone<'_>,
) {
    let mut envs = Vec::new();
    let mut started = Vec::new();
    for (i, spec) in specs.iter().enumerate() {
        match take_worker(target, spec.needs) {
            Ok(env) => {
                envs.push(env);
                started.push(i);
            }
            Err(e) => done(i, Err(e.into())),
        }
    }
    let live: Vec<EpisodeSpec<'_>> = started.iter().map(|&i| specs[i].clone()).collect();
    let mut quiet = vec![crate::episode::NoObserver; live.len()];
    {
        let envs: Vec<&mut dyn Environment> =
            envs.iter_mut().map(|e| e as &mut dyn Environment).collect();
        let observers: Vec<&mut dyn crate::episode::EpisodeObserver> = quiet
            .iter_mut()
            .map(|o| o as &mut dyn crate::episode::EpisodeObserver)
            .collect();
        crate::lockstep::run_lockstep_in(envs, policy, &live, observers, &mut |j, r| {
            done(started[j], r)
        });
    }
    WORKERS.with(|w| {
        w.borrow_mut()
            .extend(envs.into_iter().filter(|e| e.is_alive()))
    });
}

/// [`CorruptionSpec::check_burst`] for cell `c` of a policy of `t_p`, `t_o`, naming the cell.
fn check_burst(c: &CellSpec, t_p: usize, t_o: usize) -> Result<(), SweepError> {
    c.corruption
        .check_burst(t_p, t_o, c.h)
        .map_err(|e| field(e.field, e.value, format!("{} (cell {})", e.expected, c.id)))
}

fn poisoned() -> SweepError {
    field("writer", "poisoned lock", "a worker that did not panic")
}

/// Resolves relative policy and patch paths against `base` (the spec file's directory),
/// where they do not exist relative to the working directory but do relative to `base`.
pub fn resolve_policies(spec: &mut SweepSpec, base: &Path) {
    let resolve = |path: &Path| -> Option<PathBuf> {
        (path.is_relative() && !path.exists() && base.join(path).exists()).then(|| base.join(path))
    };
    for p in &mut spec.policies {
        if let Some(r) = resolve(Path::new(&*p)) {
            *p = r.to_string_lossy().into_owned();
        }
    }
    for c in &mut spec.corruptions {
        if let Fault::Sensor(SensorFault::Patch { path, .. }) = &mut c.fault
            && let Some(r) = resolve(path)
        {
            *path = r;
        }
    }
}

#[cfg(test)]
mod order_tests {
    use super::*;

    /// Tasks start in list order: the task at position `k` of the start log was taken
    /// when it was among the first `k + workers` (a task can start only once those ahead
    /// of it are taken). Halving the list, as `par_iter` does, starts task `n / 2` second.
    #[test]
    fn tasks_start_in_list_order_and_results_keep_it() {
        for workers in [1, 2, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(workers)
                .build()
                .expect("pool");
            let tasks: Vec<usize> = (0..24).collect();
            let log = Mutex::new(Vec::new());
            let out = run_in_order(&pool, workers, &tasks, |&t| {
                log.lock().expect("log").push(t);
                std::thread::sleep(std::time::Duration::from_millis(1 + (t % 3) as u64));
                t * 10
            });
            let log = log.into_inner().expect("log");
            assert_eq!(log.len(), tasks.len(), "every task ran once");
            for (k, &t) in log.iter().enumerate() {
                assert!(
                    t < k + workers,
                    "workers {workers}: task {t} started {k}th: {log:?}"
                );
            }
            let want: Vec<Option<usize>> = tasks.iter().map(|t| Some(t * 10)).collect();
            assert_eq!(out, want);
        }
    }
}
