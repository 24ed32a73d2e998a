//! What a run directory holds: the cell definitions and one JSON line per episode.
//!
//! A run directory (`mte-run-v1`) is
//!
//! ```text
//! RUN_DIR/
//!   spec.toml          the resolved sweep spec (every default filled in)
//!   manifest.json      format, git commit, versions, start time, the cell list (CellSpec)
//!   cells/<id>.jsonl   one Line per finished episode and arm, appended and flushed
//! ```
//!
//! Lines are self-describing (`"kind": "episode"` or `"kind": "error"`) and carry the cell
//! id, so a report needs nothing but the files. Times are seconds, coverage is gym-pusht's
//! intersection over goal area in `[0, 1]`, actions are pixels of the 512 x 512 workspace.

use mte_ensemble::BracketAccumulator;
use serde::{Deserialize, Serialize};

use crate::corruption::CorruptionSpec;

/// The format tag written in every manifest.
pub const RUN_FORMAT: &str = "mte-run-v1";

/// One cell of a grid: a policy, a corruption, a stride and the arms compared on the same
/// episodes. Arms of a cell pair episode by episode (same seeds, same per-query sampling
/// noise, same corruption schedule).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CellSpec {
    /// File-name-safe identifier, unique in the run.
    pub id: String,
    /// Policy label (the checkpoint directory as given in the spec).
    pub policy: String,
    /// What corrupts which queries.
    pub corruption: CorruptionSpec,
    /// Query stride `h` (control steps between queries).
    pub h: usize,
    /// Arms in their text form: `open-loop` or an aggregator (`ewm:0.01`, `median`, ...).
    pub arms: Vec<String>,
    /// Episode reset seeds, in order.
    pub seeds: Vec<u64>,
    /// Step limit per episode.
    pub max_steps: usize,
    /// Executable rows of each chunk the runner uses ([`crate::pusht::EpisodeSpec::span`]);
    /// absent: all of them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub span: Option<usize>,
}

impl CellSpec {
    /// Nominal number of corrupted queries per period (`q` of the burst schedule; 0 when
    /// clean).
    pub fn q(&self) -> usize {
        self.corruption.q()
    }

    /// Strength of the corruption on its natural axis (PGD iterations, occluder size in
    /// pixels, noise standard deviation, bias magnitude), for plots against attack budget.
    pub fn budget(&self) -> Option<f64> {
        self.corruption.fault.budget()
    }

    /// Whether `other` runs the same checkpoint: the policy labels compared as lexically
    /// normalised paths, as in [`CellSpec::same_but_seeds`], so cells of runs made from specs in
    /// different folders (`sweeps/../assets/p`, `.scratch/../assets/p`) pair in reports.
    pub fn same_policy(&self, other: &CellSpec) -> bool {
        self.policy_key() == other.policy_key()
    }

    /// The policy label as a lexically normalised path: the key reports group cells by.
    pub fn policy_key(&self) -> String {
        normalise_label(&self.policy)
    }

    /// Whether `other` defines the same cell, its seeds aside: equal in every field, the
    /// policy compared as a lexically normalised path (`.` dropped, `dir/..` folded), so a
    /// spec moved to another folder that names the same checkpoint (`sweeps/../assets/p`
    /// and `.scratch/../assets/p`) still matches the run it grows.
    pub fn same_but_seeds(&self, other: &CellSpec) -> bool {
        let key = |c: &CellSpec| CellSpec {
            seeds: Vec::new(),
            policy: c.policy_key(),
            ..c.clone()
        };
        key(self) == key(other)
    }
}

/// A policy label as a path with `.` components dropped and `dir/..` pairs folded (purely
/// lexical: no file system, no symlinks resolved; a leading `..` stays): the form
/// [`CellSpec::policy_key`] gives, for matching a user-given policy path against cells.
pub(crate) fn normalise_label(label: &str) -> String {
    use std::path::{Component, Path};
    let mut parts: Vec<Component<'_>> = Vec::new();
    for c in Path::new(label).components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir if matches!(parts.last(), Some(Component::Normal(_))) => {
                parts.pop();
            }
            other => parts.push(other),
        }
    }
    parts
        .iter()
        .collect::<std::path::PathBuf>()
        .to_string_lossy()
        .into_owned()
}

/// Wall time spent per stage of an episode (seconds). `runner` is everything that is not
/// the policy, the simulator, rendering or the corruption itself: observation bookkeeping,
/// the ensembler, diagnostics, recording.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StageTimes {
    /// Policy queries (sampling a chunk).
    pub policy_s: f64,
    /// Physics steps.
    pub sim_s: f64,
    /// Rendering observations.
    pub render_s: f64,
    /// Corrupting observations or candidates (attacks included).
    pub corruption_s: f64,
    /// Ensembling and bracket diagnostics (part of the runner's overhead; for the oracle
    /// attack this also includes its candidate rewriting, which is counted as corruption).
    pub ensemble_s: f64,
    /// Whole episode.
    pub total_s: f64,
}

impl StageTimes {
    /// Time not accounted to the policy, simulator, renderer or corruption: the runner's
    /// own overhead (ensembler included).
    pub fn overhead_s(&self) -> f64 {
        (self.total_s - self.policy_s - self.sim_s - self.render_s - self.corruption_s).max(0.0)
    }
}

/// One episode of one arm.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRecord {
    /// Cell id.
    pub cell: String,
    /// Arm text form.
    pub arm: String,
    /// Reset seed.
    pub seed: u64,
    /// Coverage above gym-pusht's 0.95 threshold was reached.
    pub success: bool,
    /// Largest coverage over the episode (Diffusion Policy's PushT score).
    pub max_coverage: f64,
    /// Control steps run.
    pub steps: usize,
    /// Policy queries made.
    pub queries: usize,
    /// Of those, how many were corrupted.
    pub corrupted_queries: usize,
    /// `m_counts[m]`: control steps whose covering set had `M(tau) = m` chunks (ensemble
    /// arms; open loop has `M = 1`).
    pub m_counts: Vec<u64>,
    /// `q_counts[q]`: control steps with `q(tau) = q` corrupted covering chunks, measured.
    pub q_counts: Vec<u64>,
    /// Bracket diagnostics of the steps with a corrupted candidate (ensemble arms).
    pub bracket: Option<BracketAccumulator>,
    /// Time per stage.
    pub times: StageTimes,
    /// Per monitor (`tide`, `acc`), its score of every query after the first, when the
    /// episode ran with monitors (thresholds are applied afterwards, from calibration).
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub monitors: std::collections::BTreeMap<String, MonitorTrace>,
}

/// One monitor's scores over an episode.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MonitorTrace {
    /// Index of the query `scores[0]` belongs to (1: the first query has no score).
    pub first_query: u64,
    /// The score of every query from `first_query` on, in order.
    pub scores: Vec<f64>,
    /// Why scoring stopped early, if it did (a chunk the monitor refused).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

impl MonitorTrace {
    /// The episode score: the largest query score (`None` without any).
    pub fn max(&self) -> Option<f64> {
        self.scores.iter().copied().reduce(f64::max)
    }
}

/// The most control steps an episode record may claim: 10^9 (gym-pusht's limit is 300), so
/// that sums over a run cannot overflow.
pub const MAX_RECORD_STEPS: usize = 1_000_000_000;

impl EpisodeRecord {
    /// Checks the record's counts against each other (a hand-edited or corrupted file is
    /// refused here, not turned into overflowing or meaningless tables): `steps` at most
    /// [`MAX_RECORD_STEPS`]; `m_counts` and `q_counts` each sum to `steps`; at most `steps`
    /// queries, of which at most all corrupted; coverage in `[0, 1]`; bracket tallies within
    /// `steps`. Returns what is wrong.
    pub fn check(&self) -> Result<(), String> {
        let steps = self.steps;
        if steps > MAX_RECORD_STEPS {
            return Err(format!(
                "steps = {steps}: expected at most {MAX_RECORD_STEPS}"
            ));
        }
        if !(0.0..=1.0).contains(&self.max_coverage) {
            return Err(format!(
                "max_coverage = {}: expected a value in [0, 1]",
                self.max_coverage
            ));
        }
        for (name, counts) in [("m_counts", &self.m_counts), ("q_counts", &self.q_counts)] {
            let total: u128 = counts.iter().map(|&c| u128::from(c)).sum();
            if total != steps as u128 {
                return Err(format!("{name} sum to {total}: expected steps = {steps}"));
            }
        }
        if self.queries > steps.max(1) || self.corrupted_queries > self.queries {
            return Err(format!(
                "{} queries ({} corrupted) in {steps} steps: expected at most one query per step \
                 and at most every query corrupted",
                self.queries, self.corrupted_queries
            ));
        }
        if let Some(b) = &self.bracket {
            let total: u128 = b.tallies.iter().map(|t| u128::from(t.steps)).sum();
            let bad = b.tallies.iter().any(|t| {
                t.outside > t.steps || t.zero_width_outside > t.steps || t.coincide > t.steps
            });
            if total > steps as u128 || bad {
                return Err(format!(
                    "bracket tallies ({total} steps) exceed the record's {steps} steps or their own"
                ));
            }
        }
        Ok(())
    }
}

/// A cell (or one episode of it) that failed; the sweep records it and goes on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ErrorRecord {
    /// Cell id.
    pub cell: String,
    /// Arm, when the failure belongs to one.
    pub arm: Option<String>,
    /// Seed, when the failure belongs to one episode.
    pub seed: Option<u64>,
    /// The error, as displayed.
    pub error: String,
}

/// One line of a cell file.
// Episodes are the common case and errors are rare, so boxing the large variant would only
// add an allocation per line.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Line {
    /// A finished episode.
    Episode(EpisodeRecord),
    /// A failure.
    Error(ErrorRecord),
}

/// The manifest of a run directory.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// [`RUN_FORMAT`].
    pub format: String,
    /// Run name (from the spec).
    pub name: String,
    /// `git rev-parse HEAD` of the source tree, when known.
    pub git_commit: Option<String>,
    /// mte's version.
    pub mte_version: String,
    /// When the run was created (seconds since the Unix epoch).
    pub created_unix_s: u64,
    /// Seed of the per-query sampling noise (shared by all arms).
    pub noise_seed: u64,
    /// Every cell of the grid (all shards).
    pub cells: Vec<CellSpec>,
    /// The machines that wrote records into the run: the creating one first, then each
    /// different machine that resumed it or ran a shard of it. Records are bit-identical
    /// only between runs on one CPU model (`crate::machine`). Absent in runs written before
    /// the field existed.
    #[serde(default)]
    pub machines: Vec<crate::machine::Machine>,
}
