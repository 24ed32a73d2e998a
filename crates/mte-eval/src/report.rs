//! The report of an evaluation run: paired tables, bracket diagnostics and plots, computed
//! from a run directory's files alone (protocol sections 3, 6 and 7).
//!
//! [`build`] takes the [`Manifest`] and every [`Line`] of the cell files and computes
//!
//! 1. the **main table**: one row per corrupted cell, the robust arm against the baseline
//!    arm on the seeds both ran (mean max coverage, paired difference, Wilcoxon signed-rank
//!    test on coverage, exact McNemar test on success, Holm over the rows), next to the
//!    baseline arm on the clean cell of the same policy and stride;
//! 2. the **aggregator table** of one cell: every arm against the baseline (Holm over arms);
//! 3. the **bracket table** by regime per arm, pooled over the corrupted cells and, where
//!    there are several, per corrupted cell (the pool mixes corruptions of different strength);
//! 4. the **recovered fraction** `(robust - baseline) / (clean - baseline)` per corrupted
//!    cell ("n/a" where undefined);
//! 5. the measured distributions of `M(tau)` and `q(tau)`;
//! 6. the runner's **overhead** per stage;
//! 7. the **failures** recorded by the sweep;
//! 8. **plots**: mean max coverage and success rate against `q` per (policy, fault,
//!    schedule kind, `h`), and the recovered fraction against the attack budget (or `q`).
//!
//! Layout: this module computes the tables as data ([`build`], one function per table);
//! `figures` computes the plots' series, `plot` draws them, `render` turns the tables into
//! blocks (one function per section) and renders Markdown and HTML, `defence` computes and
//! renders section 9.
//!
//! [`Report::markdown`] and [`Report::html`] render the same blocks (the HTML is
//! self-contained, with the plots inlined as SVG); [`Report::write`] writes both and every
//! plot as SVG and PNG. Output is deterministic: cells in manifest order, arms in the
//! cells' order, seeds in the cells' seed order, fixed decimals.
//!
//! Pairing: an arm is compared with the baseline on the seeds present for both in the same
//! cell; seeds present for one arm only are counted and reported as unpaired. A repeated
//! (cell, arm, seed) record is ignored after its first occurrence and counted.

use std::collections::{HashMap, HashSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use mte_ensemble::{BracketAccumulator, BracketRow};
use mte_stats::{
    McNemarResult, StatsError, binomial_se, holm, mean_and_paired_se, paired_se,
    recovered_fraction, wilcoxon_signed_rank, wilson_interval,
};
use serde::Serialize;

/// The McNemar test a report uses ([`ReportOptions::mcnemar`]).
pub use mte_stats::McNemarTest;

use crate::label::{policy_label, slug};
use crate::record::{CellSpec, EpisodeRecord, ErrorRecord, Line, Manifest, StageTimes};

mod control;
mod defence;
mod figures;
mod plot;
mod render;
mod roc;

use figures::plots;

use render::{Block, code, delta, est, est_rate, f3, fmt_p, fraction_se, opt_p, pct, table};

pub use control::{ControlPair, ControlRow, ControlTable};
pub use defence::{DefencePair, DefenceRow, DefenceTable};
pub use plot::Plot;
use plot::{PlotSpec, Point, Series};
pub use roc::roc_plots;

/// Arm text form of open-loop execution (no ensemble: excluded from `M`/`q` tables).
const OPEN_LOOP: &str = "open-loop";

/// Confidence level of the Wilson intervals.
const CONFIDENCE: f64 = 0.95;
/// How the report says that a cell has no episode yet (after "cell `id`" or "the cell").
const NOT_RUN: &str = "has not run: no episode recorded";

/// Which arms to compare and which cell to detail.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ReportOptions {
    /// Baseline arm; default: the first arm starting with `ewm` (else the first arm).
    pub baseline_arm: Option<String>,
    /// Robust arm; default: `median` (else the first arm that is not the baseline).
    pub robust_arm: Option<String>,
    /// Cell of the aggregator table; default: the corrupted cell with the most arms (the
    /// first on ties).
    pub focus_cell: Option<String>,
    /// Compare a defended policy with an undefended one (section 9); none by default.
    pub defence: Option<DefencePair>,
    /// Attack cells to read against their control cells (the section after the defence
    /// table); none by default.
    pub controls: Vec<ControlPair>,
    /// The McNemar test on paired success: exact by default; the continuity-corrected
    /// chi-square (the paper's tables appear to use it for n >= 100) by name.
    pub mcnemar: McNemarTest,
}

/// Why a report could not be built or written.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    /// The manifest lists no cell.
    #[error("the manifest of run `{run}` lists no cell")]
    NoCells {
        /// Run name.
        run: String,
    },
    /// Fewer than two arms: nothing to compare.
    #[error("the run has fewer than two arms ({arms}): nothing to compare")]
    TooFewArms {
        /// The arms found, comma separated.
        arms: String,
    },
    /// An arm given in the options is not an arm of any cell.
    #[error("{role} arm `{arm}` is not an arm of the run (arms: {available})")]
    UnknownArm {
        /// `baseline` or `robust`.
        role: &'static str,
        /// The arm given.
        arm: String,
        /// The arms of the run, comma separated.
        available: String,
    },
    /// Baseline and robust arm are the same.
    #[error("baseline and robust arm are both `{arm}`")]
    SameArm {
        /// The arm.
        arm: String,
    },
    /// A policy given for the defence table is not a policy of any cell.
    #[error("{role} policy `{policy}` is not a policy of the run (policies: {available})")]
    UnknownPolicy {
        /// `undefended` or `defended`.
        role: &'static str,
        /// The policy given.
        policy: String,
        /// The policies' labels, comma separated.
        available: String,
    },
    /// A cell named for the control table is not in the manifest.
    #[error(
        "{role} cell `{cell}` of the control table is not a cell of the run (cells: {available})"
    )]
    UnknownControlCell {
        /// `attack` or `control`.
        role: &'static str,
        /// The cell id given.
        cell: String,
        /// The run's cell ids, comma separated.
        available: String,
    },
    /// The focus cell given in the options is not in the manifest.
    #[error("focus cell `{cell}` is not a cell of the manifest")]
    UnknownFocusCell {
        /// The cell id given.
        cell: String,
    },
    /// An episode record names a cell the manifest does not list.
    #[error(
        "episode record of cell `{cell}` (arm `{arm}`, seed {seed}): no such cell in the manifest"
    )]
    RecordOutsideManifest {
        /// Cell id of the record.
        cell: String,
        /// Arm of the record.
        arm: String,
        /// Seed of the record.
        seed: u64,
    },
    /// An episode record's coverage is NaN or infinite.
    #[error(
        "episode record of cell `{cell}`, arm `{arm}`, seed {seed}: max_coverage = {value} is not finite"
    )]
    NonFiniteCoverage {
        /// Cell id.
        cell: String,
        /// Arm.
        arm: String,
        /// Seed.
        seed: u64,
        /// The value.
        value: f64,
    },
    /// An episode record's counts contradict each other.
    #[error("episode record of cell `{cell}`, arm `{arm}`, seed {seed}: {reason}")]
    InconsistentRecord {
        /// Cell id.
        cell: String,
        /// Arm.
        arm: String,
        /// Seed.
        seed: u64,
        /// What is wrong.
        reason: String,
    },
    /// A statistic failed on input that should have been valid.
    #[error("{what}: {source}")]
    Stats {
        /// What was being computed (cell and arms).
        what: String,
        /// The statistics error.
        #[source]
        source: StatsError,
    },
    /// Drawing or encoding a plot failed.
    #[error("plot `{plot}`: {reason}")]
    Plot {
        /// Plot name.
        plot: String,
        /// What went wrong.
        reason: String,
    },
    /// The bundled font could not be registered with the plotting library.
    #[error("the bundled plot font (DejaVu Sans) could not be loaded")]
    Font,
    /// Writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
}

fn stats_err(what: impl Into<String>) -> impl FnOnce(StatsError) -> ReportError {
    let what = what.into();
    move |source| ReportError::Stats { what, source }
}

/// A sample mean with its standard error (`None` below two observations).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Estimate {
    /// Observations.
    pub n: usize,
    /// Mean.
    pub mean: f64,
    /// Standard error of the mean.
    pub se: Option<f64>,
}

impl Estimate {
    /// Mean and standard error of `values` (`mte_stats::paired_se` of the sample); `None`
    /// for an empty sample.
    fn of(values: &[f64], what: &str) -> Result<Option<Self>, ReportError> {
        if values.is_empty() {
            return Ok(None);
        }
        let n = values.len();
        let mean = values.iter().sum::<f64>() / n as f64;
        let se = if n >= 2 {
            Some(paired_se(values).map_err(stats_err(what))?)
        } else {
            None
        };
        Ok(Some(Self { n, mean, se }))
    }
}

/// One arm against the baseline arm on the seeds both ran in one cell.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Comparison {
    /// The arm compared with the baseline.
    pub arm: String,
    /// Paired episodes (seeds present for both arms).
    pub n: usize,
    /// Seeds present for only one of the two arms (left out).
    pub unpaired: usize,
    /// Baseline mean max coverage over the paired seeds.
    pub baseline: Option<Estimate>,
    /// The arm's mean max coverage over the paired seeds.
    pub other: Option<Estimate>,
    /// Baseline success rate over the paired seeds.
    pub baseline_success: Option<f64>,
    /// The arm's success rate over the paired seeds.
    pub other_success: Option<f64>,
    /// Mean of `other - baseline` per seed, with its paired standard error.
    pub delta: Option<Estimate>,
    /// Two-sided Wilcoxon signed-rank p-value on paired max coverage (`None` when every
    /// difference is zero or there is no pair).
    pub wilcoxon_p: Option<f64>,
    /// Exact McNemar test on paired success (`b`: baseline-only, `c`: arm-only successes).
    pub mcnemar: Option<McNemarResult>,
}

/// Pairs `other` with `base` by seed (in `base`'s order) and compares them.
fn compare(
    base: &[&EpisodeRecord],
    other: &[&EpisodeRecord],
    arm: &str,
    what: &str,
    test: McNemarTest,
) -> Result<Comparison, ReportError> {
    let by_seed: HashMap<u64, &EpisodeRecord> = other.iter().map(|r| (r.seed, *r)).collect();
    let (mut xb, mut xo, mut sb, mut so) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for b in base {
        if let Some(o) = by_seed.get(&b.seed) {
            xb.push(b.max_coverage);
            xo.push(o.max_coverage);
            sb.push(b.success);
            so.push(o.success);
        }
    }
    let n = xb.len();
    let unpaired = base.len() + other.len() - 2 * n;
    let rate = |s: &[bool]| (n > 0).then(|| s.iter().filter(|&&x| x).count() as f64 / n as f64);
    let delta = match n {
        0 => None,
        1 => Some(Estimate {
            n,
            mean: xo[0] - xb[0],
            se: None,
        }),
        _ => {
            let d = mean_and_paired_se(&xo, &xb).map_err(stats_err(what))?;
            Some(Estimate {
                n,
                mean: d.mean_diff,
                se: Some(d.se),
            })
        }
    };
    let wilcoxon_p = if n == 0 {
        None
    } else {
        match wilcoxon_signed_rank(&xo, &xb) {
            Ok(w) => Some(w.p_value),
            Err(StatsError::AllZeroDifferences { .. }) => None,
            Err(e) => return Err(stats_err(what)(e)),
        }
    };
    let mcnemar = if n == 0 {
        None
    } else {
        let b = sb.iter().zip(&so).filter(|&(&b, &o)| b && !o).count() as u64;
        let c = sb.iter().zip(&so).filter(|&(&b, &o)| !b && o).count() as u64;
        Some(test.run(b, c).map_err(stats_err(what))?)
    };
    Ok(Comparison {
        arm: arm.to_string(),
        n,
        unpaired,
        baseline: Estimate::of(&xb, what)?,
        other: Estimate::of(&xo, what)?,
        baseline_success: rate(&sb),
        other_success: rate(&so),
        delta,
        wilcoxon_p,
        mcnemar,
    })
}

/// The baseline arm on the clean cell of a policy and stride.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CleanRef {
    /// Clean cell id.
    pub cell: String,
    /// Baseline mean max coverage over all its episodes there.
    pub coverage: Estimate,
    /// Baseline success rate there.
    pub success: f64,
}

/// Recovered fraction of one cell; `None` where undefined or not meaningful, with the
/// reason.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Recovered {
    /// On mean max coverage.
    pub coverage: Option<f64>,
    /// Paired jackknife standard error of `coverage` (leave one seed out); `None` where
    /// `coverage` is, or where a leave-one-out denominator is zero.
    pub coverage_se: Option<f64>,
    /// The seeds the fractions are computed on: those that ran the clean cell and both arms
    /// under the corruption (0 where undefined).
    pub seeds: usize,
    /// On success rate.
    pub success: Option<f64>,
    /// Against each arm's own clean value, on mean max coverage: the share of the
    /// baseline's loss (clean − corrupted) that the robust arm does not suffer on its own
    /// clean value, `1 − (robust clean − robust) / (baseline clean − baseline)`. Unlike the
    /// paper's definition it does not count a clean-data gap between the arms as recovery.
    /// Defined where `coverage` is.
    pub coverage_own: Option<f64>,
    /// Paired jackknife standard error of `coverage_own` (leave one seed out of the four
    /// cells' common seeds); `None` where it is undefined.
    pub coverage_own_se: Option<f64>,
    /// Why the coverage fraction is undefined, when it is.
    pub note: Option<String>,
    /// The test of the denominator: does the corruption lower the baseline at all?
    pub denominator: Option<Denominator>,
}

impl Recovered {
    /// No fraction: every value `None`, with the reason (if any) and the denominator's test.
    pub(crate) fn undefined(note: Option<String>, denominator: Option<Denominator>) -> Self {
        Self {
            coverage: None,
            coverage_se: None,
            seeds: 0,
            success: None,
            coverage_own: None,
            coverage_own_se: None,
            note,
            denominator,
        }
    }
}

/// Significance level of the denominator test.
pub const DENOMINATOR_ALPHA: f64 = 0.05;

/// The recovered fraction's denominator, `clean − corrupted` for the baseline arm, tested on
/// the seeds both cells ran (the same reset seeds, so paired): a fraction is a number only
/// where the corruption significantly lowers the baseline (two-sided paired Wilcoxon on max
/// coverage, exact McNemar on success, at [`DENOMINATOR_ALPHA`], and a positive
/// difference); otherwise it is "not meaningful" (dividing by noise).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Denominator {
    /// Paired seeds.
    pub n: usize,
    /// Mean clean − corrupted max coverage over them.
    pub coverage_delta: Option<f64>,
    /// Its two-sided paired Wilcoxon p-value.
    pub coverage_p: Option<f64>,
    /// Clean − corrupted success rate over them.
    pub success_delta: Option<f64>,
    /// Its exact McNemar p-value.
    pub success_p: Option<f64>,
}

impl Denominator {
    /// From the comparison of the corrupted baseline (`base`) with the clean one (`other`).
    fn of(c: &Comparison) -> Self {
        Self {
            n: c.n,
            coverage_delta: c.delta.map(|d| d.mean),
            coverage_p: c.wilcoxon_p,
            success_delta: c.baseline_success.zip(c.other_success).map(|(b, o)| o - b),
            success_p: c.mcnemar.map(|m| m.p_value),
        }
    }

    /// The coverage denominator is significantly above zero.
    pub fn coverage_meaningful(&self) -> bool {
        self.coverage_delta.is_some_and(|d| d > 0.0)
            && self.coverage_p.is_some_and(|p| p < DENOMINATOR_ALPHA)
    }

    /// The success denominator is significantly above zero.
    pub fn success_meaningful(&self) -> bool {
        self.success_delta.is_some_and(|d| d > 0.0)
            && self.success_p.is_some_and(|p| p < DENOMINATOR_ALPHA)
    }
}

/// The denominator test of a corrupted cell against its clean cell, for `arm`.
fn denominator(
    corrupted: &CellData<'_>,
    clean: Option<&CellData<'_>>,
    arm: &str,
) -> Result<Option<Denominator>, ReportError> {
    let Some(clean) = clean.filter(|c| c.has(arm) && corrupted.has(arm)) else {
        return Ok(None);
    };
    let what = format!(
        "denominator: cell `{}` vs clean `{}`, arm `{arm}`",
        corrupted.spec.id, clean.spec.id
    );
    let c = compare(
        corrupted.episodes(arm),
        clean.episodes(arm),
        arm,
        &what,
        corrupted.mcnemar,
    )?;
    Ok(Some(Denominator::of(&c)))
}

/// A row of the main table (one corrupted cell).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MainRow {
    /// Cell id.
    pub cell: String,
    /// Policy label.
    pub policy: String,
    /// The corruption's text form.
    pub corruption: String,
    /// Nominal `q`.
    pub q: usize,
    /// Query stride.
    pub h: usize,
    /// The baseline arm on the matching clean cell, if the run has one.
    pub clean: Option<CleanRef>,
    /// The robust arm on the same clean cell: with `clean`, the clean-data gap between the
    /// arms, a confound of every comparison under corruption.
    pub robust_clean: Option<CleanRef>,
    /// Robust against baseline on that clean cell, paired by seed: the clean-data gap's
    /// test, shown beside every corrupted comparison it confounds.
    pub clean_comparison: Option<Comparison>,
    /// Robust against baseline; `None` when the cell lacks one of the two arms.
    pub comparison: Option<Comparison>,
    /// Holm-adjusted Wilcoxon p over the rows of the table.
    pub holm_wilcoxon: Option<f64>,
    /// Holm-adjusted McNemar p over the rows of the table.
    pub holm_mcnemar: Option<f64>,
    /// Recovered fraction.
    pub recovered: Recovered,
}

/// A row of the aggregator table.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FocusRow {
    /// Arm.
    pub arm: String,
    /// Episodes of the arm in the cell.
    pub n: usize,
    /// Successful episodes.
    pub successes: usize,
    /// Wilson interval of the success rate.
    pub success_ci: Option<(f64, f64)>,
    /// Mean max coverage over the arm's episodes.
    pub coverage: Option<Estimate>,
    /// Against the baseline (`None` for the baseline itself, or when the cell lacks it).
    pub vs_baseline: Option<Comparison>,
    /// Holm-adjusted Wilcoxon p over the arms.
    pub holm_wilcoxon: Option<f64>,
    /// Holm-adjusted McNemar p over the arms.
    pub holm_mcnemar: Option<f64>,
}

/// The aggregator table of one cell.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FocusTable {
    /// Cell id.
    pub cell: String,
    /// The corruption's text form.
    pub corruption: String,
    /// One row per arm, in the cell's arm order.
    pub rows: Vec<FocusRow>,
}

/// Bracket diagnostics of one arm over the corrupted cells.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ArmBrackets {
    /// Arm.
    pub arm: String,
    /// Episodes that carried a bracket accumulator.
    pub episodes: usize,
    /// `BracketAccumulator::rows` of the merged accumulators.
    pub rows: Vec<BracketRow>,
}

/// Bracket diagnostics of one corrupted cell, per arm: the pooled table of section 3 mixes
/// corruptions of different strength, so each corrupted cell also gets its own.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CellBrackets {
    /// Cell id.
    pub cell: String,
    /// The corruption's text form.
    pub corruption: String,
    /// One entry per arm with bracket data, in the run's arm order.
    pub arms: Vec<ArmBrackets>,
}

/// Measured `M(tau)` and `q(tau)` counts of one arm.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Distribution {
    /// Arm.
    pub arm: String,
    /// `m[k]`: control steps with `M = k`, summed over episodes.
    pub m: Vec<u64>,
    /// `q[k]`: control steps with `q = k`, summed over episodes.
    pub q: Vec<u64>,
}

/// Wall time of one arm by stage, summed over its episodes.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Overhead {
    /// Arm.
    pub arm: String,
    /// Episodes.
    pub episodes: usize,
    /// Control steps.
    pub steps: u64,
    /// Stage times summed over episodes.
    pub times: StageTimes,
    /// `StageTimes::overhead_s` summed over episodes.
    pub runner_s: f64,
}

impl Overhead {
    /// Runner overhead per control step in microseconds.
    pub fn us_per_step(&self) -> Option<f64> {
        (self.steps > 0).then(|| 1e6 * self.runner_s / self.steps as f64)
    }
}

/// The report of a run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    /// Run name.
    pub name: String,
    /// The manifest's metadata line (format, versions, commit, seed).
    pub manifest: ManifestInfo,
    /// Cells in the manifest.
    pub cells: usize,
    /// Corrupted cells.
    pub corrupted_cells: usize,
    /// Episode records used (duplicates excluded).
    pub episodes: usize,
    /// Baseline arm.
    pub baseline: String,
    /// Robust arm.
    pub robust: String,
    /// Main table, corrupted cells in manifest order.
    pub main: Vec<MainRow>,
    /// Aggregator table.
    pub focus: FocusTable,
    /// Every clean cell's arms against the baseline, in manifest order: the clean-data
    /// differences that confound the comparisons under corruption.
    pub clean_cells: Vec<FocusTable>,
    /// The episode of the paper's Figure 2, if one was found.
    pub figure2: Option<Figure2>,
    /// The McNemar test of every comparison.
    pub mcnemar: McNemarTest,
    /// Bracket tables, arms in run order (arms without bracket data left out).
    pub brackets: Vec<ArmBrackets>,
    /// The same per corrupted cell, in run order; empty when the run has at most one
    /// corrupted cell (the pooled table is then that cell's).
    pub cell_brackets: Vec<CellBrackets>,
    /// `M`/`q` distributions of the ensemble arms.
    pub distributions: Vec<Distribution>,
    /// Stage times per arm.
    pub overhead: Vec<Overhead>,
    /// Error records, in file order.
    pub failures: Vec<ErrorRecord>,
    /// The defence table, when [`ReportOptions::defence`] asks for it.
    pub defence: Option<DefenceTable>,
    /// The control table, when [`ReportOptions::controls`] names pairs.
    pub controls: Option<ControlTable>,
    /// Remarks on the data (duplicates, unpaired seeds, missing arms).
    pub notes: Vec<String>,
    /// Plots.
    #[serde(skip)]
    pub plots: Vec<Plot>,
}

/// What the manifest says about the run itself.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ManifestInfo {
    /// Format tag.
    pub format: String,
    /// mte version.
    pub mte_version: String,
    /// Source commit, when known.
    pub git_commit: Option<String>,
    /// Creation time (Unix seconds).
    pub created_unix_s: u64,
    /// Seed of the per-query sampling noise.
    pub noise_seed: u64,
    /// The machines that wrote the records, one summary line each.
    pub machines: Vec<String>,
}

/// The records of one cell, per arm, in seed order.
struct CellData<'a> {
    spec: &'a CellSpec,
    /// The McNemar test of every comparison ([`ReportOptions::mcnemar`]).
    mcnemar: McNemarTest,
    /// The spec's arms, then arms only seen in records.
    arms: Vec<String>,
    eps: Vec<Vec<&'a EpisodeRecord>>,
    seen: HashSet<(usize, u64)>,
}

impl<'a> CellData<'a> {
    fn new(spec: &'a CellSpec, mcnemar: McNemarTest) -> Self {
        let mut arms: Vec<String> = Vec::new();
        for a in &spec.arms {
            if !arms.contains(a) {
                arms.push(a.clone());
            }
        }
        let eps = vec![Vec::new(); arms.len()];
        Self {
            spec,
            mcnemar,
            arms,
            eps,
            seen: HashSet::new(),
        }
    }

    /// Adds a record; `false` for a repeated (arm, seed).
    fn add(&mut self, r: &'a EpisodeRecord) -> bool {
        let ai = match self.arms.iter().position(|a| *a == r.arm) {
            Some(i) => i,
            None => {
                self.arms.push(r.arm.clone());
                self.eps.push(Vec::new());
                self.arms.len() - 1
            }
        };
        if !self.seen.insert((ai, r.seed)) {
            return false;
        }
        self.eps[ai].push(r);
        true
    }

    /// Orders every arm's records by the spec's seed order (unknown seeds last, ascending).
    fn sort(&mut self) {
        let mut pos: HashMap<u64, usize> = HashMap::new();
        for (i, &s) in self.spec.seeds.iter().enumerate() {
            pos.entry(s).or_insert(i);
        }
        for v in &mut self.eps {
            v.sort_by_key(|r| (pos.get(&r.seed).copied().unwrap_or(usize::MAX), r.seed));
        }
    }

    fn episodes(&self, arm: &str) -> &[&'a EpisodeRecord] {
        self.arms
            .iter()
            .position(|a| a == arm)
            .map_or(&[], |i| self.eps[i].as_slice())
    }

    fn has(&self, arm: &str) -> bool {
        self.arms.iter().any(|a| a == arm)
    }

    fn is_clean(&self) -> bool {
        self.spec.corruption.is_clean()
    }
}

/// A row's Holm-adjusted `(Wilcoxon, McNemar)` p-values.
type HolmPair = (Option<f64>, Option<f64>);

/// Holm over the rows' Wilcoxon p-values and, separately, their McNemar p-values (a row
/// without a comparison, or without a test, has none), per row as `(Wilcoxon, McNemar)`.
fn holm_both(rows: &[Option<&Comparison>], over: &str) -> Result<Vec<HolmPair>, ReportError> {
    let pw: Vec<Option<f64>> = rows.iter().map(|c| c.and_then(|c| c.wilcoxon_p)).collect();
    let pm: Vec<Option<f64>> = rows
        .iter()
        .map(|c| c.and_then(|c| c.mcnemar.map(|m| m.p_value)))
        .collect();
    let hw = holm_opt(&pw, &format!("Holm over {over} (Wilcoxon)"))?;
    let hm = holm_opt(&pm, &format!("Holm over {over} (McNemar)"))?;
    Ok(hw.into_iter().zip(hm).collect())
}

/// Holm over the defined p-values, scattered back.
fn holm_opt(ps: &[Option<f64>], what: &str) -> Result<Vec<Option<f64>>, ReportError> {
    let defined: Vec<f64> = ps.iter().flatten().copied().collect();
    let adj = holm(&defined).map_err(stats_err(what))?;
    let mut it = adj.into_iter();
    Ok(ps.iter().map(|p| p.and_then(|_| it.next())).collect())
}

fn coverages(eps: &[&EpisodeRecord]) -> Vec<f64> {
    eps.iter().map(|r| r.max_coverage).collect()
}

fn success_count(eps: &[&EpisodeRecord]) -> usize {
    eps.iter().filter(|r| r.success).count()
}

/// The serde `kind` tag of a tagged enum value (`blank`, `burst`, ...).
fn kind_tag<T: Serialize>(v: &T) -> String {
    serde_json::to_value(v)
        .ok()
        .and_then(|j| j.get("kind").and_then(|k| k.as_str()).map(str::to_string))
        .unwrap_or_default()
}

/// `base`, or `base-2`, `base-3`, ... if taken.
fn unique(taken: &mut HashSet<String>, base: String) -> String {
    let mut name = base.clone();
    let mut k = 2;
    while !taken.insert(name.clone()) {
        name = format!("{base}-{k}");
        k += 1;
    }
    name
}

/// Builds the report of a run from its manifest and the lines of its cell files.
///
/// # Errors
///
/// [`ReportError`] for an empty manifest, fewer than two arms, an unknown arm or focus cell
/// in `opts`, a record of a cell the manifest does not list or with a non-finite coverage,
/// and plots that cannot be drawn.
pub fn build(
    manifest: &Manifest,
    lines: &[Line],
    opts: &ReportOptions,
) -> Result<Report, ReportError> {
    if manifest.cells.is_empty() {
        return Err(ReportError::NoCells {
            run: manifest.name.clone(),
        });
    }
    let Loaded {
        cells,
        failures,
        episodes,
        mut notes,
    } = load_records(manifest, lines, opts.mcnemar)?;
    let all_arms = arms_in_order(&cells);
    let (baseline, robust) = choose_arms(&all_arms, opts)?;
    let corrupted: Vec<usize> = (0..cells.len()).filter(|&i| !cells[i].is_clean()).collect();
    let main = main_rows(&cells, &corrupted, (&baseline, &robust), &mut notes)?;
    let focus_ci = focus_cell(manifest, &cells, &corrupted, opts)?;
    let focus = focus_table(&cells[focus_ci], &baseline, &mut notes)?;
    let figure2 = figure2(&cells, &corrupted, (&baseline, &robust));
    let clean_cells = cells
        .iter()
        .filter(|c| c.is_clean())
        .map(|c| focus_table(c, &baseline, &mut notes))
        .collect::<Result<Vec<_>, _>>()?;
    let (brackets, distributions, overhead) = diagnostics(&cells, &corrupted, &all_arms);
    let cell_brackets = cell_brackets(&cells, &corrupted, &all_arms);
    let controls = if opts.controls.is_empty() {
        None
    } else {
        Some(control::build(&cells, &opts.controls, &mut notes)?)
    };
    let defence = match &opts.defence {
        Some(pair) => Some(defence::build(&cells, pair, &all_arms, &mut notes)?),
        None => None,
    };
    let plots = plots(&cells, &corrupted, &baseline, &main, defence.as_ref())?
        .into_iter()
        .map(Plot::new)
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Report {
        name: manifest.name.clone(),
        manifest: ManifestInfo::of(manifest),
        cells: cells.len(),
        corrupted_cells: corrupted.len(),
        episodes,
        baseline,
        robust,
        main,
        focus,
        clean_cells,
        figure2,
        mcnemar: opts.mcnemar,
        brackets,
        cell_brackets,
        distributions,
        overhead,
        failures,
        defence,
        controls,
        notes,
        plots,
    })
}

/// The arms of a run's cells, in order of first appearance.
fn arms_in_order(cells: &[CellData<'_>]) -> Vec<String> {
    let mut all: Vec<String> = Vec::new();
    for a in cells.iter().flat_map(|c| &c.arms) {
        if !all.contains(a) {
            all.push(a.clone());
        }
    }
    all
}

/// Every arm's bracket and distribution diagnostics over the corrupted cells and its
/// aggregation overhead, arm after arm.
#[allow(clippy::type_complexity)]
fn diagnostics(
    cells: &[CellData<'_>],
    corrupted: &[usize],
    arms: &[String],
) -> (Vec<ArmBrackets>, Vec<Distribution>, Vec<Overhead>) {
    let (mut brackets, mut distributions, mut overhead) = (Vec::new(), Vec::new(), Vec::new());
    for arm in arms {
        let (b, d) = arm_diagnostics(cells, corrupted, arm);
        brackets.extend(b);
        distributions.extend(d);
        overhead.extend(arm_overhead(cells, arm));
    }
    (brackets, distributions, overhead)
}

impl ManifestInfo {
    /// What a report repeats of the run's manifest.
    fn of(manifest: &Manifest) -> Self {
        Self {
            format: manifest.format.clone(),
            mte_version: manifest.mte_version.clone(),
            git_commit: manifest.git_commit.clone(),
            created_unix_s: manifest.created_unix_s,
            noise_seed: manifest.noise_seed,
            machines: manifest.machines.iter().map(|m| m.summary()).collect(),
        }
    }
}

/// The records of a run, by cell, checked; failures; notes on what was left out.
struct Loaded<'a> {
    cells: Vec<CellData<'a>>,
    failures: Vec<ErrorRecord>,
    episodes: usize,
    notes: Vec<String>,
}

/// Sorts `lines` into the manifest's cells, checking every episode record.
fn load_records<'a>(
    manifest: &'a Manifest,
    lines: &'a [Line],
    mcnemar: McNemarTest,
) -> Result<Loaded<'a>, ReportError> {
    let index: HashMap<&str, usize> = manifest
        .cells
        .iter()
        .enumerate()
        .map(|(i, c)| (c.id.as_str(), i))
        .collect();
    let mut cells: Vec<CellData<'_>> = manifest
        .cells
        .iter()
        .map(|c| CellData::new(c, mcnemar))
        .collect();
    let mut failures = Vec::new();
    let (mut episodes, mut duplicates) = (0usize, 0usize);
    for line in lines {
        match line {
            Line::Episode(r) => {
                let &ci = index.get(r.cell.as_str()).ok_or_else(|| {
                    ReportError::RecordOutsideManifest {
                        cell: r.cell.clone(),
                        arm: r.arm.clone(),
                        seed: r.seed,
                    }
                })?;
                check_record(r)?;
                if cells[ci].add(r) {
                    episodes += 1;
                } else {
                    duplicates += 1;
                }
            }
            Line::Error(e) => failures.push(e.clone()),
        }
    }
    for c in &mut cells {
        c.sort();
    }
    let mut notes = Vec::new();
    if duplicates > 0 {
        notes.push(format!(
            "{duplicates} repeated (cell, arm, seed) episode record(s) ignored after the first"
        ));
    }
    for c in &cells {
        for a in c.arms.iter().filter(|a| !c.spec.arms.contains(a)) {
            notes.push(format!(
                "cell `{}`: records of arm `{a}`, which the manifest does not list",
                c.spec.id
            ));
        }
    }
    Ok(Loaded {
        cells,
        failures,
        episodes,
        notes,
    })
}

/// A record's coverage is finite and its counts agree ([`EpisodeRecord::check`]).
fn check_record(r: &EpisodeRecord) -> Result<(), ReportError> {
    if !r.max_coverage.is_finite() {
        return Err(ReportError::NonFiniteCoverage {
            cell: r.cell.clone(),
            arm: r.arm.clone(),
            seed: r.seed,
            value: r.max_coverage,
        });
    }
    r.check().map_err(|reason| ReportError::InconsistentRecord {
        cell: r.cell.clone(),
        arm: r.arm.clone(),
        seed: r.seed,
        reason,
    })
}

/// Sections 1 and 4: one row per corrupted cell, Holm-adjusted over the rows.
fn main_rows(
    cells: &[CellData<'_>],
    corrupted: &[usize],
    (baseline, robust): (&str, &str),
    notes: &mut Vec<String>,
) -> Result<Vec<MainRow>, ReportError> {
    let mut main = Vec::new();
    // Each clean cell's robust-vs-baseline comparison: made (and its gap noted) once, not
    // once per row it is shown beside.
    let mut clean_tests: Vec<(usize, Option<Comparison>)> = Vec::new();
    for &ci in corrupted {
        let c = &cells[ci];
        let clean_at = clean_of(cells, ci);
        let clean_cell = clean_at.map(|cj| &cells[cj]);
        let clean = match clean_cell {
            Some(cc) => clean_ref(cc, baseline)?,
            None => None,
        };
        let den = denominator(c, clean_cell, baseline)?;
        let robust_clean = match clean_cell.filter(|cc| cc.has(robust)) {
            Some(cc) => clean_ref(cc, robust)?,
            None => None,
        };
        let clean_comparison = match clean_at {
            Some(cj) => clean_test(&cells[cj], cj, (baseline, robust), &mut clean_tests, notes)?,
            None => None,
        };
        let comparison = arm_comparison(c, (baseline, robust), notes)?;
        let no_eps: &[&EpisodeRecord] = &[];
        let on_clean = |arm: &str| clean_cell.map_or(no_eps, |cc| cc.episodes(arm));
        let recovered = recovered(
            RecoveryEpisodes {
                clean: on_clean(baseline),
                base: c.episodes(baseline),
                other: c.episodes(robust),
                other_clean: on_clean(robust),
            },
            den,
        );
        main.push(MainRow {
            cell: c.spec.id.clone(),
            policy: c.spec.policy.clone(),
            corruption: c.spec.corruption.to_string(),
            q: c.spec.q(),
            h: c.spec.h,
            clean,
            robust_clean,
            clean_comparison,
            comparison,
            holm_wilcoxon: None,
            holm_mcnemar: None,
            recovered,
        });
    }
    let comparisons: Vec<Option<&Comparison>> =
        main.iter().map(|r| r.comparison.as_ref()).collect();
    let adjusted = holm_both(&comparisons, "the main table")?;
    for (r, (w, m)) in main.iter_mut().zip(adjusted) {
        r.holm_wilcoxon = w;
        r.holm_mcnemar = m;
    }
    Ok(main)
}

/// Cell `c`'s robust-vs-baseline comparison; `None`, with a note, when the cell has not
/// run or lacks an arm. Seeds that ran only one arm are noted (they are left out).
fn arm_comparison(
    c: &CellData<'_>,
    (baseline, robust): (&str, &str),
    notes: &mut Vec<String>,
) -> Result<Option<Comparison>, ReportError> {
    if c.eps.iter().all(|v| v.is_empty()) {
        notes.push(format!(
            "cell `{}` {NOT_RUN} (a resumed sweep fills it)",
            c.spec.id
        ));
        return Ok(None);
    }
    if !(c.has(baseline) && c.has(robust)) {
        notes.push(format!(
            "cell `{}` lacks arm `{}`: no comparison",
            c.spec.id,
            if c.has(baseline) { robust } else { baseline }
        ));
        return Ok(None);
    }
    let what = format!("cell `{}`, `{robust}` vs `{baseline}`", c.spec.id);
    let cmp = compare(
        c.episodes(baseline),
        c.episodes(robust),
        robust,
        &what,
        c.mcnemar,
    )?;
    if cmp.unpaired > 0 {
        notes.push(format!(
            "cell `{}`: {} seed(s) ran only one of `{baseline}` and `{robust}` and are left out of the pairing",
            c.spec.id, cmp.unpaired
        ));
    }
    Ok(Some(cmp))
}

/// The robust-vs-baseline comparison on the clean cell `clean` (index `cj`), from `tests`
/// when it was made for an earlier row, else made, noted ([`clean_gap_note`]) and kept.
fn clean_test(
    clean: &CellData<'_>,
    cj: usize,
    (baseline, robust): (&str, &str),
    tests: &mut Vec<(usize, Option<Comparison>)>,
    notes: &mut Vec<String>,
) -> Result<Option<Comparison>, ReportError> {
    if let Some((_, c)) = tests.iter().find(|(j, _)| *j == cj) {
        return Ok(c.clone());
    }
    let gap = if clean.has(robust) && clean.has(baseline) {
        let what = format!(
            "clean gap: cell `{}`, `{robust}` vs `{baseline}`",
            clean.spec.id
        );
        let gap = compare(
            clean.episodes(baseline),
            clean.episodes(robust),
            robust,
            &what,
            clean.mcnemar,
        )?;
        clean_gap_note(clean, &gap, (baseline, robust), notes);
        Some(gap)
    } else {
        None
    };
    tests.push((cj, gap.clone()));
    Ok(gap)
}

/// A note when the two arms differ significantly (`gap`) on the clean cell `clean`: the
/// confound that every comparison and recovered fraction of that policy and h carries.
fn clean_gap_note(
    clean: &CellData<'_>,
    gap: &Comparison,
    (baseline, robust): (&str, &str),
    notes: &mut Vec<String>,
) {
    let (Some(d), Some(p)) = (gap.delta, gap.wilcoxon_p) else {
        return;
    };
    if p >= DENOMINATOR_ALPHA {
        return;
    }
    notes.push(format!(
        "clean-data confound: on the clean cell `{}`, `{robust}` − `{baseline}` = {} (paired \
         Wilcoxon p = {}, n = {}); every difference and recovered fraction of this policy and h \
         includes this gap, which is not robustness (a recovered fraction above 1 comes from it)",
        clean.spec.id,
        delta(Some(&d)),
        fmt_p(p),
        gap.n
    ));
}

/// Section 2's cell: the one asked for, else the corrupted cell with the most arms.
fn focus_cell(
    manifest: &Manifest,
    cells: &[CellData<'_>],
    corrupted: &[usize],
    opts: &ReportOptions,
) -> Result<usize, ReportError> {
    if let Some(id) = &opts.focus_cell {
        return manifest
            .cells
            .iter()
            .position(|c| &c.id == id)
            .ok_or_else(|| ReportError::UnknownFocusCell { cell: id.clone() });
    }
    let pool: Vec<usize> = if corrupted.is_empty() {
        (0..cells.len()).collect()
    } else {
        corrupted.to_vec()
    };
    let mut best = pool[0];
    for &i in &pool {
        if cells[i].arms.len() > cells[best].arms.len() {
            best = i;
        }
    }
    Ok(best)
}

/// Sections 3 and 5 for one arm: bracket diagnostics and the `M`, `q` distributions over
/// the corrupted cells.
fn arm_diagnostics(
    cells: &[CellData<'_>],
    corrupted: &[usize],
    arm: &str,
) -> (Option<ArmBrackets>, Option<Distribution>) {
    let (mut m, mut q) = (Vec::<u64>::new(), Vec::<u64>::new());
    for &ci in corrupted {
        for r in cells[ci].episodes(arm) {
            add_counts(&mut m, &r.m_counts);
            add_counts(&mut q, &r.q_counts);
        }
    }
    let shown = arm != OPEN_LOOP && (m.iter().any(|&k| k > 0) || q.iter().any(|&k| k > 0));
    let distribution = shown.then(|| Distribution {
        arm: arm.to_string(),
        m,
        q,
    });
    (arm_brackets(cells, corrupted, arm), distribution)
}

/// One arm's bracket accumulators merged over the episodes of `cells[i]` for `i` in `which`;
/// `None` when none carried one.
fn arm_brackets(cells: &[CellData<'_>], which: &[usize], arm: &str) -> Option<ArmBrackets> {
    let mut acc = BracketAccumulator::default();
    let mut episodes = 0;
    for &ci in which {
        for b in cells[ci]
            .episodes(arm)
            .iter()
            .filter_map(|r| r.bracket.as_ref())
        {
            acc.merge(b);
            episodes += 1;
        }
    }
    (episodes > 0).then(|| ArmBrackets {
        arm: arm.to_string(),
        episodes,
        rows: acc.rows(),
    })
}

/// Section 3's per-cell tables: one per corrupted cell when there are several.
fn cell_brackets(
    cells: &[CellData<'_>],
    corrupted: &[usize],
    arms: &[String],
) -> Vec<CellBrackets> {
    if corrupted.len() < 2 {
        return Vec::new();
    }
    corrupted
        .iter()
        .map(|&ci| CellBrackets {
            cell: cells[ci].spec.id.clone(),
            corruption: cells[ci].spec.corruption.to_string(),
            arms: arms
                .iter()
                .filter_map(|a| arm_brackets(cells, &[ci], a))
                .collect(),
        })
        .filter(|c| !c.arms.is_empty())
        .collect()
}

/// Section 6 for one arm: where its episodes' time went, over every cell.
fn arm_overhead(cells: &[CellData<'_>], arm: &str) -> Option<Overhead> {
    let mut o = Overhead {
        arm: arm.to_string(),
        episodes: 0,
        steps: 0,
        times: StageTimes::default(),
        runner_s: 0.0,
    };
    for c in cells {
        for r in c.episodes(arm) {
            o.episodes += 1;
            o.steps += r.steps as u64;
            o.times.policy_s += r.times.policy_s;
            o.times.sim_s += r.times.sim_s;
            o.times.render_s += r.times.render_s;
            o.times.corruption_s += r.times.corruption_s;
            o.times.ensemble_s += r.times.ensemble_s;
            o.times.total_s += r.times.total_s;
            o.runner_s += r.times.overhead_s();
        }
    }
    (o.episodes > 0).then_some(o)
}

/// Baseline and robust arm from the options or the defaults.
fn choose_arms(all: &[String], opts: &ReportOptions) -> Result<(String, String), ReportError> {
    let available = || all.join(", ");
    let check = |role: &'static str, a: &String| {
        if all.contains(a) {
            Ok(a.clone())
        } else {
            Err(ReportError::UnknownArm {
                role,
                arm: a.clone(),
                available: available(),
            })
        }
    };
    let too_few = || ReportError::TooFewArms { arms: available() };
    let baseline = match &opts.baseline_arm {
        Some(a) => check("baseline", a)?,
        None => all
            .iter()
            .find(|a| a.starts_with("ewm"))
            .or(all.first())
            .cloned()
            .ok_or_else(too_few)?,
    };
    let robust = match &opts.robust_arm {
        Some(a) => check("robust", a)?,
        None => all
            .iter()
            .find(|a| *a == "median" && **a != baseline)
            .or_else(|| all.iter().find(|a| **a != baseline))
            .cloned()
            .ok_or_else(too_few)?,
    };
    if baseline == robust {
        return Err(ReportError::SameArm { arm: baseline });
    }
    Ok((baseline, robust))
}

fn add_counts(acc: &mut Vec<u64>, counts: &[u64]) {
    if acc.len() < counts.len() {
        acc.resize(counts.len(), 0);
    }
    for (a, &k) in acc.iter_mut().zip(counts) {
        *a += k;
    }
}

/// `arm` on the clean cell `c` (`None` without episodes).
fn clean_ref(c: &CellData<'_>, arm: &str) -> Result<Option<CleanRef>, ReportError> {
    let eps = c.episodes(arm);
    let what = format!("cell `{}`, arm `{arm}`", c.spec.id);
    Ok(
        Estimate::of(&coverages(eps), &what)?.map(|coverage| CleanRef {
            cell: c.spec.id.clone(),
            coverage,
            success: success_count(eps) as f64 / eps.len() as f64,
        }),
    )
}

/// The episodes a recovered fraction is computed from, each one arm on one cell; an empty
/// list where the run has no such cell or arm.
#[derive(Clone, Copy)]
struct RecoveryEpisodes<'e, 'r> {
    /// The baseline on its clean cell.
    clean: &'e [&'r EpisodeRecord],
    /// The baseline under the corruption.
    base: &'e [&'r EpisodeRecord],
    /// The robust arm (or the defended policy) under the corruption.
    other: &'e [&'r EpisodeRecord],
    /// The robust arm (or the defended policy) on its own clean cell.
    other_clean: &'e [&'r EpisodeRecord],
}

/// Episodes of the same seed in each list, in the order of the second list: one entry per
/// seed that every list ran.
fn same_seeds<'r, const N: usize>(lists: [&[&'r EpisodeRecord]; N]) -> Vec<[&'r EpisodeRecord; N]> {
    let maps: Vec<HashMap<u64, &'r EpisodeRecord>> = lists
        .iter()
        .map(|l| l.iter().map(|r| (r.seed, *r)).collect())
        .collect();
    let Some(order) = lists.get(1).or(lists.first()) else {
        return Vec::new();
    };
    order
        .iter()
        .filter_map(|r| {
            let mut out = [*r; N];
            for (slot, m) in out.iter_mut().zip(&maps) {
                *slot = *m.get(&r.seed)?;
            }
            Some(out)
        })
        .collect()
}

/// Recovered fractions of a row, on the seeds that ran the clean cell and both arms under
/// the corruption (so a cell that has not run every seed is paired with the clean values of
/// the seeds it ran); `None` with the reason where undefined, or where the denominator is
/// not significantly above zero ("not meaningful").
fn recovered(eps: RecoveryEpisodes<'_, '_>, denominator: Option<Denominator>) -> Recovered {
    let undefined = |note: &str| Recovered::undefined(Some(note.into()), denominator);
    if eps.clean.is_empty() {
        return undefined("no clean cell with the baseline arm for this policy and h");
    }
    if eps.base.is_empty() && eps.other.is_empty() {
        return undefined(&format!("the cell {NOT_RUN}"));
    }
    if eps.base.is_empty() || eps.other.is_empty() {
        return undefined("no paired episodes: one arm has no episode recorded");
    }
    let Some(den) = denominator.filter(|d| d.n > 0) else {
        return undefined(
            "no seed ran both the clean and the corrupted cell: the denominator cannot be tested",
        );
    };
    let triples = same_seeds([eps.clean, eps.base, eps.other]);
    if triples.is_empty() {
        return undefined("no seed ran the clean cell and both arms under the corruption");
    }
    let column = |i: usize, f: fn(&EpisodeRecord) -> f64| -> Vec<f64> {
        triples.iter().map(|t| f(t[i])).collect()
    };
    let cov = |r: &EpisodeRecord| r.max_coverage;
    let (cl, b, o) = (column(0, cov), column(1, cov), column(2, cov));
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (coverage, coverage_se, note) = if !den.coverage_meaningful() {
        (None, None, Some(not_meaningful(&den)))
    } else {
        match recovered_fraction(mean(&cl), mean(&b), mean(&o)) {
            Ok(f) => {
                let se = mte_stats::recovered_fraction_jackknife(&cl, &b, &o).ok();
                (Some(f), se.map(|(_, se)| se), None)
            }
            Err(e) => (None, None, Some(e.to_string())),
        }
    };
    let won = |r: &EpisodeRecord| f64::from(u8::from(r.success));
    let success = den
        .success_meaningful()
        .then(|| {
            let (sc, sb, so) = (column(0, won), column(1, won), column(2, won));
            recovered_fraction(mean(&sc), mean(&sb), mean(&so)).ok()
        })
        .flatten();
    let (coverage_own, coverage_own_se) = coverage
        .and_then(|_| own_fraction(eps))
        .map_or((None, None), |(f, se)| (Some(f), se));
    Recovered {
        coverage,
        coverage_se,
        seeds: triples.len(),
        success,
        coverage_own,
        coverage_own_se,
        note,
        denominator,
    }
}

/// The note of a fraction whose denominator is not significantly above zero.
fn not_meaningful(den: &Denominator) -> String {
    format!(
        "not meaningful: the corruption does not lower the baseline's coverage \
         significantly (clean − corrupted {}, paired Wilcoxon p = {}, n = {})",
        den.coverage_delta
            .map_or_else(|| "n/a".into(), |d| format!("{d:+.3}")),
        den.coverage_p.map_or_else(|| "n/a".into(), fmt_p),
        den.n
    )
}

/// `1 − (robust clean − robust) / (clean − baseline)` on mean max coverage, on the seeds that
/// ran all four (both clean cells and both arms under the corruption), with its paired
/// jackknife standard error where defined; `None` without such seeds or with a zero
/// denominator. It is the paper's fraction with the robust arm's value shifted per seed by
/// the clean gap, `robust − robust clean + clean`, so the jackknife is the paper fraction's.
fn own_fraction(eps: RecoveryEpisodes<'_, '_>) -> Option<(f64, Option<f64>)> {
    let quads = same_seeds([eps.clean, eps.base, eps.other, eps.other_clean]);
    if quads.is_empty() {
        return None;
    }
    let n = quads.len() as f64;
    let mean = |i: usize| quads.iter().map(|q| q[i].max_coverage).sum::<f64>() / n;
    let base_loss = mean(0) - mean(1);
    if base_loss == 0.0 {
        return None;
    }
    let own = 1.0 - (mean(3) - mean(2)) / base_loss;
    let col = |i: usize| -> Vec<f64> { quads.iter().map(|q| q[i].max_coverage).collect() };
    let shifted: Vec<f64> = quads
        .iter()
        .map(|q| q[2].max_coverage - q[3].max_coverage + q[0].max_coverage)
        .collect();
    let se = mte_stats::recovered_fraction_jackknife(&col(0), &col(1), &shifted)
        .ok()
        .map(|(_, se)| se);
    Some((own, se))
}

fn focus_table(
    c: &CellData<'_>,
    baseline: &str,
    notes: &mut Vec<String>,
) -> Result<FocusTable, ReportError> {
    let id = &c.spec.id;
    if !c.has(baseline) {
        notes.push(format!(
            "focus cell `{id}` lacks the baseline arm `{baseline}`: no comparison"
        ));
    }
    let mut rows = Vec::new();
    for arm in &c.arms {
        let eps = c.episodes(arm);
        let what = format!("cell `{id}`, arm `{arm}`");
        let n = eps.len();
        let successes = success_count(eps);
        let success_ci = if n > 0 {
            Some(
                wilson_interval(successes as u64, n as u64, CONFIDENCE)
                    .map_err(stats_err(&what))?,
            )
        } else {
            None
        };
        let vs_baseline = if arm != baseline && c.has(baseline) {
            let what = format!("cell `{id}`, `{arm}` vs `{baseline}`");
            Some(compare(c.episodes(baseline), eps, arm, &what, c.mcnemar)?)
        } else {
            None
        };
        rows.push(FocusRow {
            arm: arm.clone(),
            n,
            successes,
            success_ci,
            coverage: Estimate::of(&coverages(eps), &what)?,
            vs_baseline,
            holm_wilcoxon: None,
            holm_mcnemar: None,
        });
    }
    let comparisons: Vec<Option<&Comparison>> =
        rows.iter().map(|r| r.vs_baseline.as_ref()).collect();
    let adjusted = holm_both(&comparisons, "arms")?;
    for (r, (w, m)) in rows.iter_mut().zip(adjusted) {
        r.holm_wilcoxon = w;
        r.holm_mcnemar = m;
    }
    Ok(FocusTable {
        cell: id.clone(),
        corruption: c.spec.corruption.to_string(),
        rows,
    })
}

/// The episode of the paper's Figure 2: among the corrupted cells' paired seeds, one the
/// robust arm solves and the baseline does not, the largest coverage difference first. Its
/// films (`files`) are made by whoever can run the policy (`mte report --figure2`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Figure2 {
    /// Cell id.
    pub cell: String,
    /// Policy label (the checkpoint as given in the spec).
    pub policy: String,
    /// Reset seed.
    pub seed: u64,
    /// Query stride.
    pub h: usize,
    /// Step limit.
    pub max_steps: usize,
    /// The cell's corruption.
    pub corruption: crate::corruption::CorruptionSpec,
    /// Baseline: success and max coverage as recorded.
    pub baseline: (bool, f64),
    /// Robust arm: success and max coverage as recorded.
    pub robust: (bool, f64),
    /// `(caption, path relative to the report)` of the rendered figures.
    pub files: Vec<(String, String)>,
}

fn figure2(
    cells: &[CellData<'_>],
    corrupted: &[usize],
    (baseline, robust): (&str, &str),
) -> Option<Figure2> {
    let mut best: Option<(f64, Figure2)> = None;
    for c in corrupted.iter().map(|&i| &cells[i]) {
        for b in c.episodes(baseline).iter().filter(|e| !e.success) {
            let Some(r) = c
                .episodes(robust)
                .iter()
                .find(|e| e.seed == b.seed && e.success)
            else {
                continue;
            };
            let gap = r.max_coverage - b.max_coverage;
            if best.as_ref().is_some_and(|(g, _)| *g >= gap) {
                continue;
            }
            best = Some((
                gap,
                Figure2 {
                    cell: c.spec.id.clone(),
                    policy: c.spec.policy.clone(),
                    seed: b.seed,
                    h: c.spec.h,
                    max_steps: c.spec.max_steps,
                    corruption: c.spec.corruption.clone(),
                    baseline: (b.success, b.max_coverage),
                    robust: (r.success, r.max_coverage),
                    files: Vec::new(),
                },
            ));
        }
    }
    best.map(|(_, f)| f)
}

/// The distinct `items`, each at its first occurrence (linear: the lists are short).
fn distinct<T: PartialEq>(items: impl IntoIterator<Item = T>) -> Vec<T> {
    let mut out: Vec<T> = Vec::new();
    for item in items {
        if !out.contains(&item) {
            out.push(item);
        }
    }
    out
}

/// Arms of `members`, in their order.
fn arms_of(cells: &[CellData<'_>], members: &[usize]) -> Vec<String> {
    let mut sorted = members.to_vec();
    sorted.sort_unstable();
    distinct(sorted.iter().flat_map(|&ci| cells[ci].arms.iter().cloned()))
}

/// The clean cell of the same policy and h as cell `ci`.
fn clean_of(cells: &[CellData<'_>], ci: usize) -> Option<usize> {
    let s = cells[ci].spec;
    cells.iter().position(|c| {
        c.is_clean() && c.spec.same_policy(s) && c.spec.h == s.h && c.spec.span == s.span
    })
}

#[cfg(test)]
mod tests {
    use super::render::{html_inline, s3};
    use super::*;
    use crate::corruption::{CorruptionSpec, Fault, Schedule, SensorFault};
    use crate::record::RUN_FORMAT;
    use mte_ensemble::bracket::RegimeTally;

    const EWM: &str = "ewm:0.01";
    const MEDIAN: &str = "median";
    const SEEDS: [u64; 8] = [100, 101, 102, 103, 104, 105, 106, 107];
    const CLEAN: &str = "pusht_keypoints-clean-h2";
    const Q1: &str = "pusht_keypoints-blank-burst-q1-h2";
    const Q2: &str = "pusht_keypoints-blank-burst-q2-h2";

    // Max coverage per seed (SEEDS order); `None`: the episode is missing.
    const CLEAN_EWM: [f64; 8] = [0.97, 0.92, 0.99, 0.88, 0.96, 0.90, 0.985, 0.93];
    const CLEAN_MEDIAN: [f64; 8] = [0.96, 0.93, 0.98, 0.89, 0.97, 0.91, 0.99, 0.92];
    const Q1_EWM: [f64; 8] = [0.60, 0.55, 0.70, 0.42, 0.65, 0.50, 0.75, 0.48];
    // Median wins every seed, by distinct margins.
    const Q1_MEDIAN: [f64; 8] = [0.96, 0.81, 0.97, 0.82, 0.95, 0.85, 0.99, 0.85];
    const Q2_EWM: [f64; 8] = [0.30, 0.35, 0.20, 0.45, 0.25, 0.40, 0.33, 0.28];
    // Seed 104 ties; seed 107 failed for the median (an error record).
    const Q2_MEDIAN: [Option<f64>; 7] = [
        Some(0.50),
        Some(0.30),
        Some(0.45),
        Some(0.60),
        Some(0.25),
        Some(0.55),
        Some(0.48),
    ];

    fn cell(id: &str, corruption: CorruptionSpec) -> CellSpec {
        CellSpec {
            id: id.into(),
            policy: "assets/policies/pusht_keypoints".into(),
            corruption,
            h: 2,
            arms: vec![EWM.into(), MEDIAN.into()],
            seeds: SEEDS.to_vec(),
            max_steps: 300,
            span: None,
        }
    }

    fn blank(q: usize) -> CorruptionSpec {
        CorruptionSpec {
            fault: SensorFault::Blank.into(),
            schedule: Schedule::Burst {
                q,
                phase: 0,
                period: None,
            },
        }
    }

    fn manifest() -> Manifest {
        Manifest {
            format: RUN_FORMAT.into(),
            name: "run-small".into(),
            git_commit: Some("0123456789abcdef0123456789abcdef01234567".into()),
            mte_version: "0.1.0".into(),
            created_unix_s: 1_700_000_000,
            noise_seed: 7,
            cells: vec![
                cell(CLEAN, CorruptionSpec::CLEAN),
                cell(Q1, blank(1)),
                cell(Q2, blank(2)),
            ],
            machines: vec![crate::machine::Machine {
                cpu_model: "Example CPU".into(),
                vector_extensions: vec!["avx2".into(), "fma".into()],
                logical_cpus: 2,
                target: "x86_64-linux".into(),
                accelerator: None,
            }],
        }
    }

    /// A bracket accumulator with `steps` steps in the guaranteed regime and `tie` in the
    /// tie regime, of which `outside` left the bracket (by `0.1 k` widths).
    fn bracket(steps: u64, tie: u64, outside: u64) -> BracketAccumulator {
        let tally = |steps: u64, outside: u64| RegimeTally {
            steps,
            outside,
            zero_width_outside: u64::from(outside > 2),
            coincide: steps / 4,
            excess: (0..steps)
                .map(|k| {
                    if k < outside {
                        0.1 * (k + 1) as f64
                    } else {
                        0.0
                    }
                })
                .collect(),
            nearest: (0..steps).map(|k| 0.05 + 0.01 * k as f64).collect(),
        };
        BracketAccumulator {
            tallies: [tally(steps, 0), tally(tie, outside), RegimeTally::default()],
        }
    }

    fn episode(cell: &str, arm: &str, seed: u64, cov: f64) -> Line {
        let corrupted = cell != CLEAN;
        let median = arm == MEDIAN;
        Line::Episode(EpisodeRecord {
            cell: cell.into(),
            arm: arm.into(),
            seed,
            success: cov >= 0.95,
            max_coverage: cov,
            steps: 150,
            queries: 75,
            corrupted_queries: if corrupted { 20 } else { 0 },
            m_counts: vec![0, 0, 0, 0, 0, 0, 0, 120, 30],
            q_counts: if !corrupted {
                vec![150]
            } else if cell == Q1 {
                vec![100, 50]
            } else {
                vec![60, 50, 40]
            },
            bracket: corrupted.then(|| {
                if median {
                    bracket(8, 2, 0)
                } else {
                    bracket(6, 4, 3)
                }
            }),
            times: StageTimes {
                policy_s: 1.5,
                sim_s: 0.3,
                render_s: 0.0,
                corruption_s: if corrupted { 0.02 } else { 0.0 },
                ensemble_s: if median { 0.012 } else { 0.006 },
                total_s: 1.9,
            },
            monitors: Default::default(),
        })
    }

    fn lines() -> Vec<Line> {
        let mut v = Vec::new();
        for (id, ewm, med) in [
            (CLEAN, CLEAN_EWM, CLEAN_MEDIAN.map(Some).to_vec()),
            (Q1, Q1_EWM, Q1_MEDIAN.map(Some).to_vec()),
            (Q2, Q2_EWM, Q2_MEDIAN.to_vec()),
        ] {
            for (i, &seed) in SEEDS.iter().enumerate() {
                v.push(episode(id, EWM, seed, ewm[i]));
                match med.get(i).copied().flatten() {
                    Some(c) => v.push(episode(id, MEDIAN, seed, c)),
                    None => v.push(Line::Error(ErrorRecord {
                        cell: id.into(),
                        arm: Some(MEDIAN.into()),
                        seed: Some(seed),
                        error: "policy returned a non-finite chunk | row 3".into(),
                    })),
                }
            }
        }
        v
    }

    /// The fixture's records without its error line, each episode of a cell named in `copies`
    /// written once under every id listed for it (under its own id only where that is listed).
    fn copied_episodes(copies: &[(&str, &[&str])]) -> Vec<Line> {
        let mut out = Vec::new();
        for l in lines().into_iter().filter(|l| !matches!(l, Line::Error(_))) {
            let ids = match &l {
                Line::Episode(e) => copies.iter().find(|(from, _)| *from == e.cell),
                _ => None,
            };
            match (ids, &l) {
                (Some((_, ids)), Line::Episode(e)) => out.extend(ids.iter().map(|id| {
                    let mut e = e.clone();
                    e.cell = (*id).into();
                    Line::Episode(e)
                })),
                _ => out.push(l),
            }
        }
        out
    }

    fn report() -> Report {
        build(&manifest(), &lines(), &ReportOptions::default()).unwrap_or_else(|e| panic!("{e}"))
    }

    /// Figure 2's episode: a corrupted cell's seed the median solves and the EWM does not,
    /// with the largest coverage difference of all such pairs.
    #[test]
    fn figure2_picks_the_widest_median_win_over_a_baseline_failure() {
        let r = report();
        let f = r.figure2.as_ref().unwrap();
        assert!(f.robust.0 && !f.baseline.0, "{f:?}");
        let gap = f.robust.1 - f.baseline.1;
        let eps: Vec<EpisodeRecord> = lines()
            .into_iter()
            .filter_map(|l| match l {
                Line::Episode(e) if e.cell != CLEAN => Some(e),
                _ => None,
            })
            .collect();
        let mut pairs = 0;
        for b in eps.iter().filter(|e| e.arm == EWM && !e.success) {
            let hit = eps
                .iter()
                .find(|e| e.arm == MEDIAN && e.cell == b.cell && e.seed == b.seed && e.success);
            if let Some(m) = hit {
                pairs += 1;
                assert!(m.max_coverage - b.max_coverage <= gap);
            }
        }
        assert!(pairs >= 1);
        let md = r.markdown();
        assert!(md.contains(&format!("seed {}", f.seed)), "{md}");
    }

    fn row<'a>(r: &'a Report, cell: &str) -> &'a MainRow {
        r.main
            .iter()
            .find(|x| x.cell == cell)
            .unwrap_or_else(|| panic!("no row {cell}"))
    }

    fn fixture_dir() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/run_small")
    }

    fn updating() -> bool {
        std::env::var_os("MTE_UPDATE_SNAPSHOTS").is_some_and(|v| v == "1")
    }

    /// Writes the fixture as a run directory.
    fn write_fixture(dir: &Path) {
        let m = manifest();
        std::fs::create_dir_all(dir.join("cells")).unwrap();
        let text = serde_json::to_string_pretty(&m).unwrap();
        std::fs::write(dir.join("manifest.json"), text + "\n").unwrap();
        let all = lines();
        for c in &m.cells {
            let mut out = String::new();
            for l in &all {
                let id = match l {
                    Line::Episode(e) => &e.cell,
                    Line::Error(e) => &e.cell,
                };
                if *id == c.id {
                    out.push_str(&serde_json::to_string(l).unwrap());
                    out.push('\n');
                }
            }
            std::fs::write(dir.join("cells").join(format!("{}.jsonl", c.id)), out).unwrap();
        }
    }

    /// Reads a run directory: the manifest, then every cell file in manifest order.
    fn read_run(dir: &Path) -> (Manifest, Vec<Line>) {
        let text = std::fs::read_to_string(dir.join("manifest.json")).unwrap();
        let m: Manifest = serde_json::from_str(&text).unwrap();
        let mut lines = Vec::new();
        for c in &m.cells {
            let path = dir.join("cells").join(format!("{}.jsonl", c.id));
            let text = std::fs::read_to_string(&path).unwrap();
            for l in text.lines().filter(|l| !l.trim().is_empty()) {
                lines.push(serde_json::from_str::<Line>(l).unwrap());
            }
        }
        (m, lines)
    }

    #[test]
    fn fixture_files_match_the_code_and_markdown_matches_the_snapshot() {
        let dir = fixture_dir();
        if updating() {
            write_fixture(&dir);
        }
        let (m, lines) = read_run(&dir);
        assert_eq!(m, manifest(), "manifest.json differs from the code fixture");
        let mut expected = lines_sorted(super::tests::lines());
        let mut got = lines_sorted(lines.clone());
        expected.dedup();
        got.dedup();
        assert_eq!(got, expected, "cell files differ from the code fixture");
        let md = build(&m, &lines, &ReportOptions::default())
            .unwrap()
            .markdown();
        let snap = dir.join("report.md");
        if updating() {
            std::fs::write(&snap, &md).unwrap();
        }
        let want = std::fs::read_to_string(&snap).unwrap_or_default();
        assert!(
            md == want,
            "markdown differs from {} (MTE_UPDATE_SNAPSHOTS=1 regenerates it):\n{md}",
            snap.display()
        );
    }

    fn lines_sorted(mut v: Vec<Line>) -> Vec<String> {
        let mut s: Vec<String> = v
            .drain(..)
            .map(|l| serde_json::to_string(&l).unwrap())
            .collect();
        s.sort();
        s
    }

    #[test]
    fn all_median_wins_give_the_exact_wilcoxon_p_and_the_mean_difference() {
        let r = report();
        let c = row(&r, Q1).comparison.as_ref().unwrap();
        assert_eq!((c.n, c.unpaired), (8, 0));
        let w = mte_stats::wilcoxon_signed_rank(&Q1_MEDIAN, &Q1_EWM).unwrap();
        assert_eq!(c.wilcoxon_p, Some(w.p_value));
        // Eight positive differences of distinct size: only the all-positive and the
        // all-negative sign patterns are as extreme, 2 / 2^8.
        assert!((w.p_value - 2.0 / 256.0).abs() < 1e-15);
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let d = c.delta.unwrap();
        assert!((d.mean - (mean(&Q1_MEDIAN) - mean(&Q1_EWM))).abs() < 1e-12);
        let se = mte_stats::mean_and_paired_se(&Q1_MEDIAN, &Q1_EWM)
            .unwrap()
            .se;
        assert_eq!(d.se, Some(se));
        assert!((c.baseline.unwrap().mean - mean(&Q1_EWM)).abs() < 1e-12);
        // Median succeeds on 4 seeds where the EWM does not, never the other way round.
        let mc = c.mcnemar.unwrap();
        assert_eq!((mc.b, mc.c), (0, 4));
        assert_eq!(mc.p_value, mte_stats::mcnemar_exact(0, 4).unwrap().p_value);
        // Holm over the two rows of the main table.
        let p2 = row(&r, Q2).comparison.as_ref().unwrap().wilcoxon_p.unwrap();
        let adj = mte_stats::holm(&[w.p_value, p2]).unwrap();
        assert_eq!(row(&r, Q1).holm_wilcoxon, Some(adj[0]));
        assert_eq!(row(&r, Q2).holm_wilcoxon, Some(adj[1]));
        let md = r.markdown();
        assert!(md.contains("| 0.0078 |"), "{md}");
        // Clean reference: the EWM on the clean cell.
        let clean = row(&r, Q1).clean.as_ref().unwrap();
        assert_eq!(clean.cell, CLEAN);
        assert!((clean.coverage.mean - mean(&CLEAN_EWM)).abs() < 1e-12);
        assert!((clean.success - 4.0 / 8.0).abs() < 1e-12);
        // Both arms' clean values: the clean-data gap is shown beside every comparison.
        let robust_clean = row(&r, Q1).robust_clean.as_ref().unwrap();
        assert!((robust_clean.coverage.mean - mean(&CLEAN_MEDIAN)).abs() < 1e-12);
        let f = row(&r, Q1).recovered.coverage.unwrap();
        let want = (mean(&Q1_MEDIAN) - mean(&Q1_EWM)) / (mean(&CLEAN_EWM) - mean(&Q1_EWM));
        assert!((f - want).abs() < 1e-12);
        // Against each arm's own clean value: the share of the baseline's loss avoided.
        let own = row(&r, Q1).recovered.coverage_own.unwrap();
        let want =
            1.0 - (mean(&CLEAN_MEDIAN) - mean(&Q1_MEDIAN)) / (mean(&CLEAN_EWM) - mean(&Q1_EWM));
        assert!((own - want).abs() < 1e-12, "{own} vs {want}");
        // Its jackknife error, leaving each seed out of all four cells.
        let loo: Vec<f64> = (0..8)
            .map(|i| {
                let m = |v: &[f64]| (v.iter().sum::<f64>() - v[i]) / 7.0;
                1.0 - (m(&CLEAN_MEDIAN) - m(&Q1_MEDIAN)) / (m(&CLEAN_EWM) - m(&Q1_EWM))
            })
            .collect();
        let lm = mean(&loo);
        let se = (7.0 / 8.0 * loo.iter().map(|x| (x - lm).powi(2)).sum::<f64>()).sqrt();
        let got = row(&r, Q1).recovered.coverage_own_se.unwrap();
        assert!(se > 0.0 && (got - se).abs() < 1e-12, "{got} vs {se}");
        // The paired clean test beside it: median vs EWM on the clean cell.
        let k = row(&r, Q1).clean_comparison.as_ref().unwrap();
        let w = mte_stats::wilcoxon_signed_rank(&CLEAN_MEDIAN, &CLEAN_EWM).unwrap();
        assert_eq!((k.n, k.wilcoxon_p), (8, Some(w.p_value)));
    }

    #[test]
    fn a_clean_data_gap_between_the_arms_is_named_as_a_confound() {
        let r = build(&manifest(), &lines(), &ReportOptions::default()).unwrap();
        assert!(
            !r.notes.iter().any(|n| n.contains("confound")),
            "{:?}",
            r.notes
        );
        let mut lines = lines();
        for l in &mut lines {
            if let Line::Episode(e) = l
                && e.cell == CLEAN
                && e.arm == MEDIAN
            {
                e.max_coverage = 1.0;
            }
        }
        let r = build(&manifest(), &lines, &ReportOptions::default()).unwrap();
        let notes: Vec<&String> = r.notes.iter().filter(|n| n.contains("confound")).collect();
        assert_eq!(notes.len(), 1, "{:?}", r.notes);
        assert!(
            notes[0].contains(CLEAN) && notes[0].contains("n = 8"),
            "{}",
            notes[0]
        );
    }

    #[test]
    fn a_clean_cell_pairs_with_the_same_checkpoint_however_its_path_is_spelled() {
        // Runs made from specs in two folders name one checkpoint two ways; a different
        // checkpoint of the same name does not pair.
        let clean_of_q1 = |policy: &str| {
            let mut m = manifest();
            let q1 = m.cells.iter_mut().find(|c| c.id == Q1).expect("cell Q1");
            q1.policy = policy.into();
            let r = build(&m, &lines(), &ReportOptions::default()).unwrap();
            row(&r, Q1).clean.as_ref().map(|c| c.coverage.mean)
        };
        let full: f64 = CLEAN_EWM.iter().sum::<f64>() / CLEAN_EWM.len() as f64;
        for same in [
            "assets/policies/pusht_keypoints",
            ".scratch/../assets/policies/pusht_keypoints",
            "./sweeps/../assets/./policies/pusht_keypoints",
        ] {
            let got = clean_of_q1(same).unwrap_or_else(|| panic!("{same}: no clean cell"));
            assert!((got - full).abs() < 1e-12, "{same}: {got}");
        }
        for other in ["runs/pusht_keypoints", "../assets/policies/pusht_keypoints"] {
            assert_eq!(clean_of_q1(other), None, "{other}");
        }
    }

    #[test]
    fn a_corrupted_cell_takes_the_clean_cell_of_its_own_span_and_spans_make_a_curve() {
        const CLEAN13: &str = "pusht_keypoints-clean-h2-span13";
        const Q1_13: &str = "pusht_keypoints-blank-burst-q1-h2-span13";
        let mut m = manifest();
        for (id, c) in [(CLEAN13, CorruptionSpec::CLEAN), (Q1_13, blank(1))] {
            m.cells.push(CellSpec {
                span: Some(13),
                ..cell(id, c)
            });
        }
        let mut l = lines();
        for x in lines() {
            if let Line::Episode(mut e) = x
                && (e.cell == CLEAN || e.cell == Q1)
            {
                // The shortened span's clean cell scores 0.1 less under every arm.
                let clean = e.cell == CLEAN;
                e.cell = if clean { CLEAN13 } else { Q1_13 }.into();
                e.max_coverage -= if clean { 0.1 } else { 0.0 };
                l.push(Line::Episode(e));
            }
        }
        let r = build(&m, &l, &ReportOptions::default()).unwrap();
        let clean_mean = |id: &str| row(&r, id).clean.as_ref().expect("clean").coverage.mean;
        let full: f64 = CLEAN_EWM.iter().sum::<f64>() / CLEAN_EWM.len() as f64;
        assert!((clean_mean(Q1) - full).abs() < 1e-12);
        assert!((clean_mean(Q1_13) - (full - 0.1)).abs() < 1e-12);
        // One span is no curve; a second clean span makes the clean-coverage-against-span
        // plot, one series per arm, points in span order.
        assert!(!r.plots.iter().any(|p| p.name.starts_with("span-")));
        m.cells.push(CellSpec {
            span: Some(6),
            ..cell("pusht_keypoints-clean-h2-span6", CorruptionSpec::CLEAN)
        });
        for x in lines() {
            if let Line::Episode(mut e) = x
                && e.cell == CLEAN
            {
                e.cell = "pusht_keypoints-clean-h2-span6".into();
                l.push(Line::Episode(e));
            }
        }
        let r = build(&m, &l, &ReportOptions::default()).unwrap();
        let spans: Vec<&Plot> = r
            .plots
            .iter()
            .filter(|p| p.name.starts_with("span-"))
            .collect();
        assert_eq!(
            spans.len(),
            1,
            "{:?}",
            r.plots.iter().map(|p| &p.name).collect::<Vec<_>>()
        );
        let ewm = spans[0]
            .spec
            .series
            .iter()
            .find(|s| s.label == EWM)
            .expect("ewm");
        let xy: Vec<(f64, f64)> = ewm.points.iter().map(|p| (p.x, p.y)).collect();
        assert_eq!(xy.len(), 2);
        assert_eq!((xy[0].0, xy[1].0), (6.0, 13.0));
        assert!((xy[0].1 - full).abs() < 1e-12 && (xy[1].1 - (full - 0.1)).abs() < 1e-12);
        assert_eq!(spans[0].spec.series.len(), 2, "both arms");
    }

    #[test]
    fn recovered_fraction_is_na_when_clean_equals_baseline() {
        let mut lines = lines();
        // The clean EWM episodes score exactly what the EWM scores under attack.
        for l in &mut lines {
            if let Line::Episode(e) = l
                && e.cell == CLEAN
                && e.arm == EWM
            {
                let i = SEEDS.iter().position(|&s| s == e.seed).unwrap();
                e.max_coverage = Q1_EWM[i];
                e.success = false;
            }
        }
        let r = build(&manifest(), &lines, &ReportOptions::default()).unwrap();
        let rec = &row(&r, Q1).recovered;
        assert_eq!(rec.coverage, None);
        // A zero denominator is not significantly above zero: "not meaningful", before
        // the fraction's own "undefined" could apply.
        assert!(
            rec.note.as_deref().unwrap().contains("not meaningful"),
            "{rec:?}"
        );
        assert!(!rec.denominator.unwrap().coverage_meaningful());
        let md = r.markdown();
        assert!(!md.contains("NaN") && !md.contains("inf"), "{md}");
        let line = md
            .lines()
            .find(|l| l.starts_with(&format!("| `{Q1}` | 0.581")))
            .unwrap_or_else(|| panic!("{md}"));
        assert!(line.ends_with("| n/a | n/a |"), "{line}");
        // Without a clean cell there is nothing to recover towards.
        let mut m = manifest();
        m.cells.remove(0);
        let lines: Vec<Line> = super::tests::lines()
            .into_iter()
            .filter(|l| !matches!(l, Line::Episode(e) if e.cell == CLEAN))
            .collect();
        let r = build(&m, &lines, &ReportOptions::default()).unwrap();
        assert!(
            r.main
                .iter()
                .all(|x| x.recovered.coverage.is_none() && x.clean.is_none())
        );
        assert!(!r.markdown().contains("NaN"));
    }

    #[test]
    fn unpaired_seeds_are_counted_and_reported() {
        let r = report();
        let c = row(&r, Q2).comparison.as_ref().unwrap();
        assert_eq!((c.n, c.unpaired), (7, 1));
        let paired_ewm = &Q2_EWM[..7];
        let med: Vec<f64> = Q2_MEDIAN.iter().flatten().copied().collect();
        let w = mte_stats::wilcoxon_signed_rank(&med, paired_ewm).unwrap();
        assert_eq!(c.wilcoxon_p, Some(w.p_value));
        assert_eq!(w.zeros, 1);
        assert!(
            r.notes
                .iter()
                .any(|n| n.contains(Q2) && n.contains("1 seed(s)")),
            "{:?}",
            r.notes
        );
        assert!(r.markdown().contains("1 seed(s) ran only one of"));
    }

    #[test]
    fn error_records_are_listed_under_failures() {
        let r = report();
        assert_eq!(r.failures.len(), 1);
        let md = r.markdown();
        let failures = md.split("## 7. Failures").nth(1).unwrap();
        assert!(
            failures.contains(&format!(
                "| `{Q2}` | `median` | 107 | policy returned a non-finite chunk \\| row 3 |"
            )),
            "{failures}"
        );
        let html = r.html();
        assert!(html.contains("policy returned a non-finite chunk | row 3"));
    }

    #[test]
    fn write_produces_markdown_html_png_and_svg() {
        let r = report();
        assert!(!r.plots.is_empty());
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("report");
        let files = r.write(&out).unwrap();
        assert_eq!(files[0], out.join("report.md"));
        assert_eq!(files[1], out.join("report.html"));
        assert_eq!(files[2], out.join("report.json"));
        assert_eq!(files.len(), 3 + 2 * r.plots.len());
        // The tables as data: the main table's recovered fraction and its denominator test.
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&files[2]).unwrap()).unwrap();
        let main = json["main"].as_array().unwrap();
        assert_eq!(main.len(), r.main.len());
        let rec = &main[0]["recovered"];
        assert_eq!(rec["coverage"].as_f64(), r.main[0].recovered.coverage);
        assert!(rec["denominator"]["coverage_p"].as_f64().is_some());
        assert_eq!(
            json["figure2"]["seed"].as_u64(),
            r.figure2.as_ref().map(|f| f.seed)
        );
        let (mut png, mut svg) = (0, 0);
        for f in &files {
            let bytes = std::fs::read(f).unwrap();
            assert!(!bytes.is_empty(), "{}", f.display());
            match f.extension().and_then(|e| e.to_str()) {
                Some("png") => {
                    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n", "{}", f.display());
                    png += 1;
                }
                Some("svg") => {
                    let text = String::from_utf8(bytes).unwrap();
                    assert!(text.contains("<svg") && text.contains("</svg>"));
                    // Text is drawn (axis labels, legend).
                    assert!(text.contains("<text"), "{}", f.display());
                    svg += 1;
                }
                _ => {}
            }
        }
        assert_eq!((png, svg), (r.plots.len(), r.plots.len()));
        let names: Vec<&str> = r.plots.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "coverage-pusht_keypoints-blank-burst-h2",
                "success-pusht_keypoints-blank-burst-h2",
                "recovered-pusht_keypoints-blank-h2"
            ]
        );
        // The PNG has text: not every row of the caption band is white.
        let html = std::fs::read_to_string(out.join("report.html")).unwrap();
        assert_eq!(html.matches("<svg").count(), r.plots.len());
        assert!(!html.contains("src=") && !html.contains("href=\"http"));
    }

    #[test]
    fn png_rasterises_text_with_the_bundled_font() {
        let r = report();
        let png = r.plots[0].png().unwrap();
        let dec = png::Decoder::new(std::io::Cursor::new(png));
        let mut reader = dec.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), plot::SIZE);
        // The caption band (top 30 rows) holds the title: some dark pixels.
        let row = info.width as usize * 3;
        let dark = buf[..30 * row]
            .chunks(3)
            .filter(|p| p.iter().all(|&c| c < 128))
            .count();
        assert!(dark > 50, "{dark} dark pixels in the caption band");
    }

    #[test]
    fn defaults_pick_ewm_median_and_the_first_widest_corrupted_cell() {
        let r = report();
        assert_eq!((r.baseline.as_str(), r.robust.as_str()), (EWM, MEDIAN));
        assert_eq!(r.focus.cell, Q1);
        assert_eq!(r.focus.rows.len(), 2);
        assert!(r.focus.rows[0].vs_baseline.is_none());
        let med = &r.focus.rows[1];
        assert_eq!((med.n, med.successes), (8, 4));
        let ci = mte_stats::wilson_interval(4, 8, 0.95).unwrap();
        assert_eq!(med.success_ci, Some(ci));
        // One arm against the baseline: Holm changes nothing.
        let p = med.vs_baseline.as_ref().unwrap().wilcoxon_p;
        assert_eq!(med.holm_wilcoxon, p);
        // Swapped roles through the options.
        let opts = ReportOptions {
            baseline_arm: Some(MEDIAN.into()),
            robust_arm: Some(EWM.into()),
            focus_cell: Some(Q2.into()),
            defence: None,
            controls: Vec::new(),
            mcnemar: McNemarTest::Exact,
        };
        let r = build(&manifest(), &lines(), &opts).unwrap();
        let c = row(&r, Q1).comparison.as_ref().unwrap();
        assert!(c.delta.unwrap().mean < 0.0);
        assert_eq!(r.focus.cell, Q2);
    }

    /// The McNemar test is chosen by name: chi-square with continuity correction on the same
    /// discordant pairs, named in the text.
    #[test]
    fn the_mcnemar_test_is_chosen_by_the_options() {
        let opts = ReportOptions {
            mcnemar: "chi2-cc".parse().unwrap(),
            ..ReportOptions::default()
        };
        let r = build(&manifest(), &lines(), &opts).unwrap();
        let m = row(&r, Q1).comparison.as_ref().unwrap().mcnemar.unwrap();
        assert_eq!(m, mte_stats::mcnemar_chi2_corrected(m.b, m.c).unwrap());
        let exact = report();
        let e = row(&exact, Q1)
            .comparison
            .as_ref()
            .unwrap()
            .mcnemar
            .unwrap();
        assert_eq!((e.b, e.c), (m.b, m.c));
        assert_ne!(e.p_value, m.p_value);
        assert!(
            r.markdown()
                .contains("chi-square test with continuity correction")
        );
    }

    /// The fixture run plus a defended policy `tuned`: clean and q = 1 cells only (no q = 2),
    /// ewm 0.03 lower on clean and `lift` higher under q = 1 on every seed; median unchanged.
    fn defended_run(lift: f64) -> (Manifest, Vec<Line>) {
        let mut m = manifest();
        let tuned = |id: &str, c: CorruptionSpec| CellSpec {
            policy: "runs/ft/tuned".into(),
            ..cell(id, c)
        };
        m.cells.push(tuned("tuned-clean-h2", CorruptionSpec::CLEAN));
        m.cells.push(tuned("tuned-blank-burst-q1-h2", blank(1)));
        let mut l = lines();
        for (i, &seed) in SEEDS.iter().enumerate() {
            l.push(episode("tuned-clean-h2", EWM, seed, CLEAN_EWM[i] - 0.03));
            l.push(episode("tuned-clean-h2", MEDIAN, seed, CLEAN_MEDIAN[i]));
            l.push(episode(
                "tuned-blank-burst-q1-h2",
                EWM,
                seed,
                Q1_EWM[i] + lift,
            ));
            l.push(episode(
                "tuned-blank-burst-q1-h2",
                MEDIAN,
                seed,
                Q1_MEDIAN[i],
            ));
        }
        (m, l)
    }

    /// Report options with the defence table of `defended_run`'s two policies.
    fn tuned_defence() -> ReportOptions {
        ReportOptions {
            defence: Some(DefencePair {
                undefended: "pusht_keypoints".into(),
                defended: "runs/ft/tuned".into(),
            }),
            ..Default::default()
        }
    }

    #[test]
    fn defence_table_pairs_cells_by_corruption_and_gives_the_recovered_fraction() {
        let (m, l) = defended_run(0.1);
        let r = build(&m, &l, &tuned_defence()).unwrap_or_else(|e| panic!("{e}"));
        let t = r.defence.as_ref().expect("defence table");
        assert_eq!(t.rows.len(), 2, "one pair of cells x two arms");
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let ewm = &t.rows[0];
        assert_eq!((ewm.arm.as_str(), ewm.h), (EWM, 2));
        assert_eq!(ewm.undefended_cell, Q1);
        assert_eq!(ewm.defended_cell, "tuned-blank-burst-q1-h2");
        assert_eq!(ewm.comparison.n, 8);
        let d = ewm.comparison.delta.expect("delta");
        assert!((d.mean - 0.1).abs() < 1e-12, "{d:?}");
        let clean = mean(&CLEAN_EWM);
        let want = 0.1 / (clean - mean(&Q1_EWM));
        let got = ewm.recovered.coverage.expect("defined");
        assert!((got - want).abs() < 1e-12, "{got} vs {want}");
        let clean_of = |k: Option<&CleanRef>| k.expect("clean cell").coverage.mean;
        assert!((clean_of(ewm.clean.as_ref()) - clean).abs() < 1e-12);
        let def_clean = clean_of(ewm.defended_clean.as_ref());
        assert!((def_clean - (clean - 0.03)).abs() < 1e-12);
        let offsets: Vec<f64> = Q1_EWM.iter().map(|x| x + 0.1).collect();
        let w = mte_stats::wilcoxon_signed_rank(&offsets, &Q1_EWM).expect("wilcoxon");
        assert_eq!(ewm.comparison.wilcoxon_p, Some(w.p_value));
        // No success under q = 1 either way: the z-test has nothing to separate.
        assert_eq!(
            (ewm.undefended_success, ewm.defended_success),
            ((0, 8), (0, 8))
        );
        assert_eq!(ewm.ztest_p, Some(1.0));
        // The median is unchanged by the defence: every difference is zero.
        let med = &t.rows[1];
        assert_eq!(med.arm, MEDIAN);
        assert_eq!(med.comparison.wilcoxon_p, None);
        assert_eq!(med.recovered.coverage, Some(0.0));
        assert_eq!(
            ewm.holm_wilcoxon,
            Some(w.p_value),
            "one defined p: Holm is the identity"
        );
        let md = r.markdown();
        assert!(
            md.contains("## 9. Defence: `runs/ft/tuned` against `pusht_keypoints`"),
            "{md}"
        );
        // The undefended policy's recovered-fraction plot carries the defence's series: the
        // table's fraction at q = 1, with a paired jackknife error bar.
        let series_of = |r: &Report| -> Vec<Series> {
            r.plots
                .iter()
                .filter(|p| p.name.starts_with("recovered-pusht_keypoints"))
                .flat_map(|p| p.spec.series.clone())
                .filter(|s| s.label == "tuned (ewm:0.01)")
                .collect()
        };
        let def = series_of(&r);
        assert_eq!(def.len(), 1, "one defence series");
        assert_eq!(def[0].points.len(), 1);
        let p = &def[0].points[0];
        let (cl, b) = (CLEAN_EWM.to_vec(), Q1_EWM.to_vec());
        let (f, se) =
            mte_stats::recovered_fraction_jackknife(&cl, &b, &offsets).expect("jackknife");
        assert_eq!((p.x, p.y, p.err), (1.0, f, Some(se)));
        assert!(
            (f - got).abs() < 1e-12,
            "every seed ran every cell: {f} vs {got}"
        );
        // Without the option the report has no section 9 and no defence series.
        let plain = build(&m, &l, &ReportOptions::default()).expect("report");
        assert!(plain.defence.is_none() && !plain.markdown().contains("## 9. Defence"));
        assert!(series_of(&plain).is_empty());
    }

    /// A corrupted cell that has not run every seed yet (a growing run): the plotted
    /// fractions pair the clean cell's values on the seeds the corrupted cells ran, not its
    /// mean over all seeds, for the median's series and the defence's alike.
    #[test]
    fn recovered_plot_pairs_a_partial_cell_with_the_clean_seeds_it_ran() {
        let (m, mut l) = defended_run(0.1);
        let q1 = |c: &str| c.ends_with("blank-burst-q1-h2");
        l.retain(|line| !matches!(line, Line::Episode(r) if q1(&r.cell) && r.seed < 102));
        let r = build(&m, &l, &tuned_defence()).unwrap_or_else(|e| panic!("{e}"));
        let plot = r
            .plots
            .iter()
            .find(|p| p.name.starts_with("recovered-pusht_keypoints"))
            .expect("the undefended policy's plot");
        let point = |label: &str| {
            let s = plot.spec.series.iter().find(|s| s.label == label);
            s.and_then(|s| s.points.iter().find(|p| p.x == 1.0))
                .cloned()
        };
        let (cl, b) = (CLEAN_EWM[2..].to_vec(), Q1_EWM[2..].to_vec());
        let lifted: Vec<f64> = b.iter().map(|x| x + 0.1).collect();
        let median = Q1_MEDIAN[2..].to_vec();
        for (label, other) in [(MEDIAN, &median), ("tuned (ewm:0.01)", &lifted)] {
            let p = point(label).unwrap_or_else(|| panic!("{label} at q = 1"));
            let (f, se) = mte_stats::recovered_fraction_jackknife(&cl, &b, other).expect("jk");
            assert_eq!((p.y, p.err), (f, Some(se)), "{label}");
        }
        // The tables pair the same way: the defence row and the main row give the plotted
        // values and errors, on the 6 seeds that ran all three cells, and not the fraction
        // against the clean cell's mean over all 8 seeds.
        let def = &r.defence.as_ref().expect("table").rows[0].recovered;
        let main = &row(&r, Q1).recovered;
        for (rec, label) in [(def, "tuned (ewm:0.01)"), (main, MEDIAN)] {
            let p = point(label).expect("point");
            assert_eq!(
                (rec.coverage, rec.coverage_se),
                (Some(p.y), p.err),
                "{label}"
            );
            assert_eq!(rec.seeds, 6, "{label}");
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let all_seeds = recovered_fraction(mean(&CLEAN_EWM), mean(&b), mean(&median)).unwrap();
        assert!(
            (main.coverage.unwrap() - all_seeds).abs() > 1e-4,
            "{all_seeds}"
        );
        // The rendered tables give the fraction with its standard error.
        let md = r.markdown();
        let shown = format!(
            "{:.2} ± {:.2}",
            def.coverage.unwrap(),
            def.coverage_se.unwrap()
        );
        assert!(md.contains(&shown), "{shown}");
    }

    /// A clean cell that has not run every seed of a corrupted cell: the fraction is on the
    /// seeds that ran both, and the report says how many of the paired seeds that is.
    #[test]
    fn recovered_fraction_names_the_seeds_it_leaves_out() {
        let mut l = lines();
        l.retain(|line| !matches!(line, Line::Episode(r) if r.cell == CLEAN && r.seed == 103));
        let r = build(&manifest(), &l, &ReportOptions::default()).unwrap_or_else(|e| panic!("{e}"));
        let rec = &row(&r, Q1).recovered;
        assert_eq!(rec.seeds, 7);
        let keep = |v: &[f64]| -> Vec<f64> {
            v.iter()
                .enumerate()
                .filter(|(i, _)| *i != 3)
                .map(|(_, x)| *x)
                .collect()
        };
        let (f, se) = mte_stats::recovered_fraction_jackknife(
            &keep(&CLEAN_EWM),
            &keep(&Q1_EWM),
            &keep(&Q1_MEDIAN),
        )
        .expect("jackknife");
        assert_eq!((rec.coverage, rec.coverage_se), (Some(f), Some(se)));
        assert!(
            r.markdown()
                .contains("recovered on the 7 of 8 paired seeds that also ran the clean cell"),
            "the partial pairing is named"
        );
    }

    /// A cell of the manifest with no record yet (a sweep stopped before it) is named as not
    /// run, with no comparison and no fraction, and not as a cell without paired episodes.
    #[test]
    fn a_cell_that_has_not_run_is_named_as_such() {
        let mut l = lines();
        l.retain(|line| !matches!(line, Line::Episode(r) if r.cell == Q2));
        let r = build(&manifest(), &l, &ReportOptions::default()).unwrap_or_else(|e| panic!("{e}"));
        let q2 = row(&r, Q2);
        assert!(q2.comparison.is_none());
        assert_eq!(
            q2.recovered.note.as_deref(),
            Some("the cell has not run: no episode recorded")
        );
        assert!(
            row(&r, Q1).comparison.is_some(),
            "the other rows are untouched"
        );
        let md = r.markdown();
        assert!(md.contains(&format!("cell `{Q2}` has not run")), "{md}");
        assert!(!md.contains("no paired episodes"), "{md}");
    }

    #[test]
    fn control_table_reads_an_attack_against_its_control_per_arm() {
        let opts = ReportOptions {
            controls: vec![ControlPair {
                attack: Q2.into(),
                control: Q1.into(),
            }],
            ..Default::default()
        };
        let r = build(&manifest(), &lines(), &opts).unwrap_or_else(|e| panic!("{e}"));
        let t = r.controls.as_ref().expect("control table");
        assert_eq!(t.rows.len(), 2, "one pair x two arms");
        let ewm = &t.rows[0];
        assert_eq!((ewm.arm.as_str(), ewm.attack_cell.as_str()), (EWM, Q2));
        assert_eq!((ewm.control_cell.as_str(), ewm.comparison.n), (Q1, 8));
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let d = ewm.comparison.delta.expect("delta");
        assert!(
            (d.mean - (mean(&Q2_EWM) - mean(&Q1_EWM))).abs() < 1e-12,
            "{d:?}"
        );
        let w = mte_stats::wilcoxon_signed_rank(&Q2_EWM, &Q1_EWM).expect("wilcoxon");
        assert_eq!(ewm.comparison.wilcoxon_p, Some(w.p_value));
        // The median's seed 107 failed under the attack: 7 pairs.
        assert_eq!(t.rows[1].comparison.n, 7);
        let md = r.markdown();
        assert!(md.contains("## 9. Attacks against their controls"), "{md}");
        assert!(md.contains("## 10. Clean cells"), "{md}");
        let e = build(
            &manifest(),
            &lines(),
            &ReportOptions {
                controls: vec![ControlPair {
                    attack: Q2.into(),
                    control: "grey".into(),
                }],
                ..Default::default()
            },
        )
        .expect_err("no such cell")
        .to_string();
        assert!(e.contains("`grey`") && e.contains(Q1), "{e}");
    }

    #[test]
    fn defence_table_names_an_unknown_policy() {
        let (m, l) = defended_run(0.1);
        let e = build(
            &m,
            &l,
            &ReportOptions {
                defence: Some(DefencePair {
                    undefended: "pusht_keypoints".into(),
                    defended: "nope".into(),
                }),
                ..Default::default()
            },
        )
        .unwrap_err();
        assert!(
            matches!(&e, ReportError::UnknownPolicy { role: "defended", policy, .. } if policy == "nope"),
            "{e}"
        );
        assert!(e.to_string().contains("pusht_keypoints, tuned"), "{e}");
    }

    #[test]
    fn defence_table_matches_a_policy_path_however_it_is_spelled() {
        let (m, l) = defended_run(0.1);
        let with = |defended: &str| {
            build(
                &m,
                &l,
                &ReportOptions {
                    defence: Some(DefencePair {
                        undefended: "pusht_keypoints".into(),
                        defended: defended.into(),
                    }),
                    ..Default::default()
                },
            )
        };
        let want = with("runs/ft/tuned")
            .unwrap_or_else(|e| panic!("{e}"))
            .defence;
        assert_eq!(want.as_ref().map(|t| t.rows.len()), Some(2));
        for spelling in [
            "./runs/ft/tuned",
            "sweeps/../runs/ft/tuned",
            "runs/ft/./tuned",
        ] {
            let got = with(spelling).unwrap_or_else(|e| panic!("{spelling}: {e}"));
            let rows = got.defence.map(|t| t.rows);
            assert_eq!(rows, want.as_ref().map(|t| t.rows.clone()), "{spelling}");
        }
        for other in ["ft/tuned", "runs/ft2/tuned/..", "../runs/ft/tuned"] {
            let e = with(other).expect_err(other);
            assert!(
                matches!(
                    e,
                    ReportError::UnknownPolicy {
                        role: "defended",
                        ..
                    }
                ),
                "{other}: {e}"
            );
        }
    }

    #[test]
    fn bad_options_and_records_are_typed_errors() {
        let (m, l) = (manifest(), lines());
        let bad = |opts: ReportOptions| build(&m, &l, &opts).unwrap_err();
        let e = bad(ReportOptions {
            baseline_arm: Some("mean".into()),
            ..Default::default()
        });
        assert!(
            matches!(&e, ReportError::UnknownArm { role: "baseline", arm, .. } if arm == "mean")
        );
        assert!(e.to_string().contains("ewm:0.01, median"), "{e}");
        let e = bad(ReportOptions {
            robust_arm: Some(EWM.into()),
            ..Default::default()
        });
        assert!(matches!(e, ReportError::SameArm { .. }));
        let e = bad(ReportOptions {
            focus_cell: Some("nope".into()),
            ..Default::default()
        });
        assert!(matches!(e, ReportError::UnknownFocusCell { cell } if cell == "nope"));

        let mut l2 = lines();
        if let Some(Line::Episode(e)) = l2.get_mut(3) {
            e.max_coverage = f64::NAN;
        }
        let e = build(&m, &l2, &ReportOptions::default()).unwrap_err();
        assert!(
            matches!(e, ReportError::NonFiniteCoverage { seed: 101, .. }),
            "{e}"
        );
        let mut l3 = lines();
        if let Some(Line::Episode(e)) = l3.get_mut(0) {
            e.cell = "elsewhere".into();
        }
        let e = build(&m, &l3, &ReportOptions::default()).unwrap_err();
        assert!(
            matches!(e, ReportError::RecordOutsideManifest { cell, .. } if cell == "elsewhere")
        );
        let empty = Manifest {
            cells: vec![],
            ..manifest()
        };
        assert!(matches!(
            build(&empty, &[], &ReportOptions::default()),
            Err(ReportError::NoCells { .. })
        ));
        let mut one = manifest();
        for c in &mut one.cells {
            c.arms.truncate(1);
        }
        let only_ewm: Vec<Line> = lines()
            .into_iter()
            .filter(|l| matches!(l, Line::Episode(e) if e.arm == EWM))
            .collect();
        assert!(matches!(
            build(&one, &only_ewm, &ReportOptions::default()),
            Err(ReportError::TooFewArms { .. })
        ));
    }

    #[test]
    fn repeated_records_count_once() {
        let mut l = lines();
        l.extend(lines().into_iter().take(4));
        let r = build(&manifest(), &l, &ReportOptions::default()).unwrap();
        assert_eq!(r.episodes, report().episodes);
        assert!(r.notes.iter().any(|n| n.starts_with("4 repeated")));
        assert_eq!(r.main, report().main);
    }

    #[test]
    fn brackets_distributions_and_overhead_sum_over_episodes() {
        let r = report();
        let med = r.brackets.iter().find(|b| b.arm == MEDIAN).unwrap();
        // 8 + 7 corrupted median episodes, 8 guaranteed steps each.
        assert_eq!(med.episodes, 15);
        assert_eq!(med.rows[0].steps, 15 * 8);
        assert_eq!(med.rows[1].steps, 15 * 2);
        let ewm = r.brackets.iter().find(|b| b.arm == EWM).unwrap();
        assert!((ewm.rows[1].outside_pct - 75.0).abs() < 1e-12);
        // Per cell: the pooled table is the sum of the two corrupted cells' tables.
        assert_eq!(r.cell_brackets.len(), 2);
        assert_eq!(r.cell_brackets[0].cell, Q1);
        let per_cell = |arm: &str, regime: usize| -> (usize, u64) {
            r.cell_brackets.iter().fold((0, 0), |(e, s), c| {
                let a = c.arms.iter().find(|a| a.arm == arm).unwrap();
                (e + a.episodes, s + a.rows[regime].steps)
            })
        };
        assert_eq!(per_cell(MEDIAN, 0), (15, 15 * 8));
        assert_eq!(per_cell(EWM, 1), (ewm.episodes, ewm.rows[1].steps));
        let q2_median = r.cell_brackets[1]
            .arms
            .iter()
            .find(|a| a.arm == MEDIAN)
            .unwrap();
        assert_eq!(
            q2_median.episodes, 7,
            "one median episode of Q2 is an error record"
        );
        let d = r.distributions.iter().find(|d| d.arm == EWM).unwrap();
        assert_eq!(d.m[7], 16 * 120);
        assert_eq!(d.q, vec![8 * 100 + 8 * 60, 8 * 50 + 8 * 50, 8 * 40]);
        let o = r.overhead.iter().find(|o| o.arm == MEDIAN).unwrap();
        assert_eq!((o.episodes, o.steps), (23, 23 * 150));
        let per_step = o.us_per_step().unwrap();
        let runner = 8.0 * 0.1 + 15.0 * 0.08;
        assert!((per_step - 1e6 * runner / (23.0 * 150.0)).abs() < 1e-6);
    }

    /// Section 3's per-cell bracket table is the pooled table with a cell column in front:
    /// the same columns in the same order, every row as wide as its header, and one row per
    /// arm and regime of each corrupted cell.
    #[test]
    fn per_cell_brackets_have_the_pooled_columns() {
        let r = report();
        let md = r.markdown();
        let start = md.find("## 3.").unwrap();
        let end = start + md[start..].find("## 4.").unwrap();
        let cells = |l: &str| -> Vec<String> {
            l.trim_matches('|')
                .split(" | ")
                .map(|c| c.trim().to_string())
                .collect()
        };
        let tables: Vec<Vec<Vec<String>>> = md[start..end]
            .split("\n\n")
            .filter(|t| t.starts_with('|'))
            .map(|t| {
                t.lines()
                    .filter(|l| !l.starts_with("|:") && !l.starts_with("|-"))
                    .map(cells)
                    .collect()
            })
            .collect();
        assert_eq!(tables.len(), 2, "{}", &md[start..end]);
        let (pooled, per_cell) = (&tables[0], &tables[1]);
        assert_eq!(per_cell[0][0], "cell");
        assert_eq!(per_cell[0][1..], pooled[0][..]);
        for t in &tables {
            assert!(t.iter().all(|row| row.len() == t[0].len()));
        }
        let regimes: usize = r
            .cell_brackets
            .iter()
            .flat_map(|c| &c.arms)
            .map(|a| a.rows.len().max(1))
            .sum();
        assert_eq!(per_cell.len() - 1, regimes);
    }

    /// Bursts at another phase are their own curve: the same q at phase 0 and phase 3 gives
    /// two coverage and two success plots against q (each with one point per q) and two
    /// recovered-fraction plots, named and titled by phase.
    #[test]
    fn bursts_at_another_phase_are_another_curve() {
        let mut m = manifest();
        let mut ph3 = blank(2);
        if let Schedule::Burst { phase, .. } = &mut ph3.schedule {
            *phase = 3;
        }
        m.cells[1] = cell("blank-q2-ph3", ph3);
        let lines: Vec<Line> = lines()
            .into_iter()
            .map(|mut l| {
                if let Line::Episode(e) = &mut l
                    && e.cell == Q1
                {
                    e.cell = "blank-q2-ph3".into();
                }
                l
            })
            .filter(|l| !matches!(l, Line::Error(e) if e.cell == Q1))
            .collect();
        let r = build(&m, &lines, &ReportOptions::default()).unwrap();
        let names: Vec<&str> = r.plots.iter().map(|p| p.name.as_str()).collect();
        for name in [
            "coverage-pusht_keypoints-blank-burst-h2",
            "coverage-pusht_keypoints-blank-burst-ph3-h2",
            "success-pusht_keypoints-blank-burst-ph3-h2",
            "recovered-pusht_keypoints-blank-h2",
            "recovered-pusht_keypoints-blank-ph3-h2",
        ] {
            assert!(names.contains(&name), "no plot {name} in {names:?}");
        }
        let ph3 = r
            .plots
            .iter()
            .find(|p| p.name == "coverage-pusht_keypoints-blank-burst-ph3-h2")
            .unwrap();
        assert!(ph3.spec.title.contains("phase 3"), "{}", ph3.spec.title);
        for p in r.plots.iter().filter(|p| !p.name.starts_with("figure")) {
            for series in &p.spec.series {
                let xs: Vec<f64> = series.points.iter().map(|q| q.x).collect();
                let mut unique = xs.clone();
                unique.dedup();
                assert_eq!(xs, unique, "{}: {} repeats an x", p.name, series.label);
            }
        }
        // Phase 3's q = 2 curve: the clean point and its own q = 2 point, the Q1 values.
        let ewm = ph3.spec.series.iter().find(|s| s.label == EWM).unwrap();
        assert_eq!(ewm.points.len(), 2);
        let mean = Q1_EWM.iter().sum::<f64>() / Q1_EWM.len() as f64;
        assert!((ewm.points[1].y - mean).abs() < 1e-12);
    }

    /// A report's recovered-fraction plot and the x values of its first series.
    fn recovered_plot(r: &Report) -> (&Plot, Vec<f64>) {
        let p = r
            .plots
            .iter()
            .find(|p| p.name.starts_with("recovered-"))
            .unwrap();
        (p, p.spec.series[0].points.iter().map(|q| q.x).collect())
    }

    /// The fixture run with its two corrupted cells replaced by occluder cells `(name, side,
    /// q)` (the Q1 and Q2 records renamed to them), errors dropped, and its report.
    fn occluder_report(cells: [(&str, usize, usize); 2]) -> Report {
        let mut m = manifest();
        let occluder = |size, q| CorruptionSpec {
            fault: SensorFault::Occluder { size }.into(),
            schedule: Schedule::Burst {
                q,
                phase: 0,
                period: None,
            },
        };
        for (i, &(name, size, q)) in cells.iter().enumerate() {
            m.cells[i + 1] = cell(name, occluder(size, q));
        }
        let lines: Vec<Line> = lines()
            .into_iter()
            .map(|mut l| {
                if let Line::Episode(e) = &mut l {
                    e.cell = match e.cell.as_str() {
                        Q1 => cells[0].0.into(),
                        Q2 => cells[1].0.into(),
                        c => c.into(),
                    };
                }
                l
            })
            .filter(|l| !matches!(l, Line::Error(_)))
            .collect();
        build(&m, &lines, &ReportOptions::default()).unwrap()
    }

    /// One attack budget at two q: the recovered fraction is plotted against q, not on a
    /// budget axis that holds a single value.
    #[test]
    fn recovered_plot_uses_q_when_the_cells_share_one_budget() {
        let r = occluder_report([("occ-24-q1", 24, 1), ("occ-24-q2", 24, 2)]);
        let (p, xs) = recovered_plot(&r);
        assert_eq!(p.spec.x_label, "q (corrupted queries per period)");
        assert!(p.spec.integer_x && !p.spec.log_x);
        assert_eq!(xs, [1.0, 2.0]);
        let y1 = row(&r, "occ-24-q1").recovered.coverage.unwrap();
        assert_eq!(p.spec.series[0].points[0].y, y1);
        // No budget curve, so no Figure 1 panel for this kind.
        assert!(r.plots.iter().all(|p| !p.name.starts_with("figure")));
    }

    /// A budget-0 cell with a recovered fraction of its own keeps the budget axis (0 and the
    /// attack's budget), so it does not share an x with the attack on a q axis.
    #[test]
    fn recovered_plot_keeps_a_budget_0_cell_with_a_point_on_the_budget_axis() {
        let r = occluder_report([("occ-24", 24, 2), ("occ-0", 0, 2)]);
        assert!(
            row(&r, "occ-0").recovered.coverage.is_some(),
            "the fixture's point"
        );
        let (p, xs) = recovered_plot(&r);
        assert_eq!(p.spec.x_label, "occluder side (px)");
        assert_eq!(xs, [0.0, 24.0]);
    }

    #[test]
    fn recovered_plot_uses_the_attack_budget_when_two_cells_have_one() {
        let r = occluder_report([("occ-24", 24, 2), ("occ-16", 16, 2)]);
        let (p, xs) = recovered_plot(&r);
        assert_eq!(p.spec.x_label, "occluder side (px)");
        assert!(!p.spec.integer_x);
        assert_eq!(xs, [16.0, 24.0]);
        let y24 = row(&r, "occ-24").recovered.coverage.unwrap();
        assert_eq!(p.spec.series[0].points[1].y, y24);
        // Error bars: the jackknife over the seeds of the clean cell and both arms.
        let (_, se) =
            mte_stats::recovered_fraction_jackknife(&CLEAN_EWM, &Q1_EWM, &Q1_MEDIAN).unwrap();
        assert_eq!(p.spec.series[0].points[1].err, Some(se));
        assert!(se > 0.0 && p.spec.series[0].points[0].err.is_some());
        // Beside it, the fraction against the median's own clean value, as the table has it.
        let own = p
            .spec
            .series
            .iter()
            .find(|s| s.label == "median, own clean")
            .expect("own-clean series");
        let rec = &row(&r, "occ-24").recovered;
        assert_eq!(own.points[1].x, 24.0);
        assert_eq!(
            (Some(own.points[1].y), own.points[1].err),
            (rec.coverage_own, rec.coverage_own_se)
        );
        // Two occluder sizes: two coverage-against-q plots (one point each plus clean).
        assert_eq!(
            r.plots
                .iter()
                .filter(|p| p.name.starts_with("coverage-"))
                .count(),
            2
        );
    }

    /// PGD at two balls on one policy: each ball is its own budget curve (iterations are a
    /// budget only at a fixed radius and step), so the eps 0.03 cells do not land on the eps
    /// 0.1 curve's iteration axis; the random-point control joins its radius; Figure 1 draws
    /// both curves.
    #[test]
    fn recovered_plots_split_pgd_cells_by_ball() {
        use mte_policy::PgdConfig;
        let mut m = manifest();
        let pgd = |eps: f64, iterations: usize| CorruptionSpec {
            fault: Fault::Query(crate::corruption::QueryAttack::Pgd(PgdConfig {
                eps,
                step: eps / 16.0,
                iterations,
                random_start: iterations == 0,
                ..PgdConfig::default()
            })),
            schedule: Schedule::Burst {
                q: 2,
                phase: 0,
                period: None,
            },
        };
        m.cells[1] = cell("a-10", pgd(0.1, 10));
        m.cells[2] = cell("a-50", pgd(0.1, 50));
        m.cells.push(cell("b-10", pgd(0.03, 10)));
        m.cells.push(cell("b-50", pgd(0.03, 50)));
        m.cells.push(cell("a-0", pgd(0.1, 0)));
        let out = copied_episodes(&[
            (Q1, &["a-10", "b-10"]),
            (Q2, &["a-50", "b-50"]),
            (CLEAN, &[CLEAN, "a-0"]),
        ]);
        let r = build(&m, &out, &ReportOptions::default()).unwrap();
        let recovered: Vec<&Plot> = r
            .plots
            .iter()
            .filter(|p| p.name.starts_with("recovered-"))
            .collect();
        let names: Vec<&str> = recovered.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "recovered-pusht_keypoints-pgd-eps0.1-step0.00625-h2",
                "recovered-pusht_keypoints-pgd-eps0.03-step0.001875-h2"
            ]
        );
        let xs = |p: &Plot| {
            p.spec.series[0]
                .points
                .iter()
                .map(|q| q.x)
                .collect::<Vec<_>>()
        };
        // Each ball on the iteration axis, one point per budget (the 0.1 ball's control has
        // no point: it holds the clean records).
        for p in &recovered {
            assert_eq!(p.spec.x_label, "PGD iterations");
            assert_eq!(xs(p), [10.0, 50.0], "{}", p.name);
        }
        let y = |id: &str| row(&r, id).recovered.coverage.unwrap();
        assert_eq!(recovered[0].spec.series[0].points[1].y, y("a-50"));
        assert_eq!(recovered[1].spec.series[0].points[1].y, y("b-50"));
        // Figure 1 has both budget curves, each named with its ball.
        let fig = r
            .plots
            .iter()
            .find(|p| p.name.starts_with("figure-1"))
            .expect("figure 1");
        let labels: Vec<&str> = fig.spec.series.iter().map(|s| s.label.as_str()).collect();
        let samples = PgdConfig::default().samples;
        for ball in ["eps 0.1, step 0.00625", "eps 0.03, step 0.001875"] {
            let ball = format!("{ball}, {samples} samples");
            assert!(
                labels.iter().any(|l| l.contains(ball.as_str())),
                "{ball}: {labels:?}"
            );
        }
    }

    /// Two attack kinds with budgets on one policy: Figure 1 puts both curves on one axis of
    /// effort relative to each curve's smallest budget, with the values of their own plots.
    #[test]
    fn figure_one_puts_every_budget_curve_on_one_relative_axis() {
        let mut m = manifest();
        let burst = |fault: Fault| CorruptionSpec {
            fault,
            schedule: Schedule::Burst {
                q: 2,
                phase: 0,
                period: None,
            },
        };
        let occ = |size| burst(SensorFault::Occluder { size }.into());
        let blur = |length| burst(SensorFault::MotionBlur { length }.into());
        m.cells[1] = cell("occ-24", occ(24));
        m.cells[2] = cell("occ-16", occ(16));
        m.cells.push(cell("blur-8", blur(8)));
        m.cells.push(cell("blur-2", blur(2)));
        // A 1 px occluder that does nothing (the clean cell's episodes): no point, so the
        // occluder curve's baseline effort stays 16 px.
        m.cells.push(cell("occ-1", occ(1)));
        let out = copied_episodes(&[
            (Q1, &["occ-24", "blur-8"]),
            (Q2, &["occ-16", "blur-2"]),
            (CLEAN, &[CLEAN, "occ-1"]),
        ]);
        let r = build(&m, &out, &ReportOptions::default()).unwrap();
        let plot = |prefix: &str| {
            r.plots
                .iter()
                .find(|p| p.name.starts_with(prefix))
                .unwrap_or_else(|| panic!("no plot {prefix}*"))
        };
        let fig = plot("figure-1-pusht_keypoints");
        let series = |label: &str| {
            fig.spec
                .series
                .iter()
                .find(|s| s.label == label)
                .unwrap_or_else(|| panic!("no series {label}"))
        };
        let (o, b) = (
            series("median, occluder, h = 2"),
            series("median, motion-blur, h = 2"),
        );
        let xs = |s: &Series| s.points.iter().map(|p| p.x).collect::<Vec<_>>();
        assert_eq!((xs(o), xs(b)), (vec![1.0, 1.5], vec![1.0, 4.0]));
        let own = &plot("recovered-pusht_keypoints-occluder").spec.series[0];
        let ys = |s: &Series| s.points.iter().map(|p| (p.y, p.err)).collect::<Vec<_>>();
        assert_eq!(ys(o), ys(own));
        assert!(!fig.spec.log_x, "a factor of 4 stays linear");
        assert_eq!(
            r.plots
                .iter()
                .filter(|p| p.name.starts_with("figure-1"))
                .count(),
            1
        );
    }

    #[test]
    fn p_values_and_numbers_are_formatted_with_fixed_digits() {
        assert_eq!(fmt_p(1.0), "1.0");
        assert_eq!(fmt_p(0.5), "0.50");
        assert_eq!(fmt_p(0.05), "0.050");
        assert_eq!(fmt_p(0.0078125), "0.0078");
        assert_eq!(fmt_p(0.001), "0.0010");
        assert_eq!(fmt_p(2.2e-4), "2.2e-4");
        assert_eq!(fmt_p(3.2e-6), "3.2e-6");
        assert_eq!(fmt_p(0.0), "< 1e-300");
        assert_eq!(f3(-0.0001), "0.000");
        assert_eq!(s3(0.25), "+0.250");
        assert_eq!(s3(-0.0001), "+0.000");
        assert_eq!(html_inline("a `b<c` d"), "a <code>b&lt;c</code> d");
        assert_eq!(html_inline("odd ` tick"), "odd ` tick");
        assert_eq!(policy_label("a/b/pusht/"), "pusht");
        assert_eq!(slug("a b/c"), "a_b_c");
    }

    #[test]
    fn distinct_keeps_first_occurrences_in_order() {
        assert_eq!(distinct([3, 1, 3, 2, 1]), vec![3, 1, 2]);
        assert_eq!(distinct(["b", "a", "b"]), vec!["b", "a"]);
        assert!(distinct(Vec::<u8>::new()).is_empty());
    }
}
