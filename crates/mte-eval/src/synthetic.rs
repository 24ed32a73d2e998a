//! The synthetic stress test: what corrupted queries do to each aggregator, without a
//! simulator or a trained policy.
//!
//! Per episode, a smooth reference trajectory `r(t)` in `R^d` (sums of sinusoids around the
//! centre of PushT's 512 x 512 workspace, amplitude 150). Query `i` fires at `t_i = i h` and
//! returns the chunk `A(i)[k] = r(t_i - t_o + 1 + k) + e`, with `e ~ N(0, noise_std^2)` per
//! coordinate: a good policy, slightly noisy. Under the burst schedule (protocol section 4)
//! query `i` is corrupted iff `(i + phase) mod M_min < q`, with a phase drawn per episode;
//! a corrupted chunk is the reference displaced by `corruption` along one random unit
//! direction per episode (the worst case for a mean: every corrupted candidate pulls the
//! same way), plus the same noise. Every aggregator sees the same streams.
//!
//! Measured per aggregator and `q`: tracking error `|a(tau) - r(tau)|` (RMSE over all steps
//! and its 99th percentile), per-episode RMSE for paired tests, and the bracket table.

use mte_ensemble::bracket::nearest_rank;
use mte_ensemble::{
    Aggregator, BracketAccumulator, BracketRow, ChunkGeometry, EnsembleError, EnsemblerOptions,
    MedianTie, QueryMeta, TemporalEnsembler,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::Reporter;

/// Settings of the synthetic stress test. Defaults describe Diffusion Policy on PushT at
/// `h = 2` (the paper's PushT setting), corrupted hard.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SyntheticConfig {
    /// Chunk geometry. Default `t_p = 16, t_o = 2, h = 2` (DP PushT, paper's `h = 2`: `M` 7/8).
    pub geometry: ChunkGeometry,
    /// Action dimension. Default 2 (PushT's target position).
    pub dim: usize,
    /// Control steps per episode. Default 300 (PushT's limit).
    pub steps: u64,
    /// Episodes per `q`. Default 20.
    pub episodes: usize,
    /// Standard deviation of a clean prediction's error, action units. Default 2 px.
    pub noise_std: f64,
    /// Displacement of corrupted chunks, action units. Default 100 px.
    pub corruption: f64,
    /// Corrupted queries per period of `M_min` (the burst length `q`). Default 0..=3.
    pub q_values: Vec<usize>,
    /// Aggregators compared. Default: `ewm` (deployed), `median`, `median:drop-oldest`,
    /// `trimmed-mean:2`, `medoid`.
    pub aggregators: Vec<Aggregator>,
    /// Seed of every random draw.
    pub seed: u64,
}

impl Default for SyntheticConfig {
    fn default() -> Self {
        Self {
            geometry: ChunkGeometry {
                t_p: 16,
                t_o: 2,
                h: 2,
            },
            dim: 2,
            steps: 300,
            episodes: 20,
            noise_std: 2.0,
            corruption: 100.0,
            q_values: vec![0, 1, 2, 3],
            aggregators: vec![
                Aggregator::default(),
                Aggregator::MEDIAN,
                Aggregator::Median {
                    tie: MedianTie::DropOldest,
                },
                Aggregator::TrimmedMean { k: 2 },
                Aggregator::BlockMedoid,
            ],
            seed: 0,
        }
    }
}

/// An invalid [`SyntheticConfig`] or a failed run.
#[derive(Debug, Clone, PartialEq, Error)]
#[non_exhaustive]
pub enum SyntheticError {
    /// A field is out of range.
    #[error("invalid synthetic config: {field} = {value}: expected {expected}")]
    Invalid {
        /// Field name.
        field: &'static str,
        /// The value given.
        value: String,
        /// What is accepted.
        expected: String,
    },
    /// The geometry is invalid.
    #[error("invalid synthetic config: {0}")]
    Geometry(#[from] mte_ensemble::GeometryError),
    /// The ensembler failed (a bug: the synthetic streams cover every step).
    #[error("ensembler failed at episode {episode}: {source}")]
    Ensemble {
        /// Episode index.
        episode: usize,
        /// The error.
        source: EnsembleError,
    },
}

impl SyntheticConfig {
    /// Checks every field; the error names the field, the value and the accepted range.
    pub fn validate(&self) -> Result<(), SyntheticError> {
        self.geometry.validate()?;
        let bad = |field, value: String, expected: String| {
            Err(SyntheticError::Invalid {
                field,
                value,
                expected,
            })
        };
        if self.dim == 0 {
            return bad("dim", "0".into(), "at least 1".into());
        }
        if self.steps == 0 {
            return bad("steps", "0".into(), "at least 1".into());
        }
        if self.episodes == 0 {
            return bad("episodes", "0".into(), "at least 1".into());
        }
        if !(self.noise_std.is_finite() && self.noise_std >= 0.0) {
            return bad(
                "noise_std",
                self.noise_std.to_string(),
                "a finite value >= 0".into(),
            );
        }
        if !self.corruption.is_finite() {
            return bad(
                "corruption",
                self.corruption.to_string(),
                "a finite value".into(),
            );
        }
        if self.q_values.is_empty() {
            return bad("q_values", "[]".into(), "at least one q".into());
        }
        let m_min = self.geometry.m_min();
        if let Some(&q) = self.q_values.iter().find(|&&q| q > m_min) {
            return bad("q_values", q.to_string(), format!("q <= M_min = {m_min}"));
        }
        if self.aggregators.is_empty() {
            return bad("aggregators", "[]".into(), "at least one aggregator".into());
        }
        for a in &self.aggregators {
            a.validate().map_err(|e| SyntheticError::Invalid {
                field: "aggregators",
                value: a.to_string(),
                expected: e.reason,
            })?;
        }
        Ok(())
    }
}

/// Results for one aggregator at one `q`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SyntheticCell {
    /// Burst length.
    pub q: usize,
    /// The aggregator.
    pub aggregator: Aggregator,
    /// Root-mean-square tracking error over all steps of all episodes (action units).
    pub rmse: f64,
    /// 99th percentile of the per-step tracking error (action units).
    pub p99_error: f64,
    /// Largest per-step tracking error (action units).
    pub max_error: f64,
    /// Per-episode RMSE, in episode order (pairs across aggregators).
    pub episode_rmse: Vec<f64>,
    /// The bracket table (steps with at least one corrupted candidate, by regime).
    pub bracket: Vec<BracketRow>,
}

/// A paired comparison of one aggregator with the baseline (the first configured) at one
/// `q`, over the per-episode RMSE (the same episodes, seeds and corruption for both).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PairedComparison {
    /// Burst length.
    pub q: usize,
    /// The aggregator compared.
    pub aggregator: Aggregator,
    /// The baseline.
    pub baseline: Aggregator,
    /// Mean of `rmse(aggregator) - rmse(baseline)` over episodes (negative: better).
    pub mean_diff: f64,
    /// Its paired standard error (`None` with a single episode).
    pub se: Option<f64>,
    /// Two-sided Wilcoxon signed-rank p-value (`None` when every difference is zero).
    pub wilcoxon_p: Option<f64>,
    /// Holm-adjusted p-value over every comparison of the report.
    pub holm_p: Option<f64>,
}

/// Everything the synthetic stress test measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SyntheticReport {
    /// The configuration that ran.
    pub config: SyntheticConfig,
    /// One cell per `(q, aggregator)`, `q`-major.
    pub cells: Vec<SyntheticCell>,
    /// Each non-baseline aggregator against the baseline, per `q`, Holm-corrected.
    pub comparisons: Vec<PairedComparison>,
    /// Distribution of `M(tau)` over all steps: `(M, count)`.
    pub m_histogram: Vec<(usize, u64)>,
}

/// The reference trajectory of one episode: `d` sums of two sinusoids.
struct Reference {
    coeffs: Vec<[f64; 4]>, // amplitude, frequency (rad/step), phase, second frequency
}

impl Reference {
    fn random(rng: &mut ChaCha8Rng, dim: usize) -> Self {
        let coeffs = (0..dim)
            .map(|_| {
                [
                    rng.random_range(80.0..150.0),
                    rng.random_range(0.01..0.05),
                    rng.random_range(0.0..std::f64::consts::TAU),
                    rng.random_range(0.05..0.12),
                ]
            })
            .collect();
        Self { coeffs }
    }

    fn at(&self, t: f64, out: &mut [f64]) {
        for (o, c) in out.iter_mut().zip(&self.coeffs) {
            *o = 256.0 + c[0] * (c[1] * t + c[2]).sin() + 0.15 * c[0] * (c[3] * t).sin();
        }
    }
}

/// Runs the stress test. Deterministic for a config (including its seed).
pub fn run(
    cfg: &SyntheticConfig,
    reporter: &dyn Reporter,
) -> Result<SyntheticReport, SyntheticError> {
    cfg.validate()?;
    let mut runner = Runner::new(cfg)?;
    let mut cells = Vec::with_capacity(cfg.q_values.len() * cfg.aggregators.len());
    reporter.start(
        "synthetic episodes",
        (cfg.q_values.len() * cfg.episodes) as u64,
    );
    for &q in &cfg.q_values {
        let mut tallies = Tallies::new(cfg.aggregators.len());
        for episode in 0..cfg.episodes {
            runner.episode(q, episode, &mut tallies)?;
            reporter.advance(1);
        }
        cells.extend(tallies.cells(q, &cfg.aggregators));
    }
    reporter.finish();
    let comparisons = compare(&cells, &cfg.aggregators);
    Ok(SyntheticReport {
        config: cfg.clone(),
        cells,
        comparisons,
        m_histogram: runner.m_hist.into_iter().collect(),
    })
}

/// The state the episodes share: one ensembler per aggregator, the clean noise, scratch
/// buffers and the histogram of `M` (over every step of every episode, read off the first
/// aggregator: `M` does not depend on the aggregator).
struct Runner<'a> {
    cfg: &'a SyntheticConfig,
    noise: Normal<f64>,
    ensemblers: Vec<TemporalEnsembler>,
    scratch: Scratch,
    m_hist: std::collections::BTreeMap<usize, u64>,
}

impl<'a> Runner<'a> {
    fn new(cfg: &'a SyntheticConfig) -> Result<Self, SyntheticError> {
        let noise = Normal::new(0.0, cfg.noise_std).map_err(|_| SyntheticError::Invalid {
            field: "noise_std",
            value: cfg.noise_std.to_string(),
            expected: "a finite value >= 0".into(),
        })?;
        let opts = EnsemblerOptions {
            bracket_diagnostics: true,
            ..Default::default()
        };
        let ensemblers = cfg
            .aggregators
            .iter()
            .map(|&a| TemporalEnsembler::with_options(cfg.geometry, cfg.dim, a, opts))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|source| SyntheticError::Ensemble { episode: 0, source })?;
        let scratch = Scratch {
            row: vec![0.0f64; cfg.dim],
            chunk: vec![0.0f32; cfg.geometry.t_p * cfg.dim],
        };
        Ok(Self {
            cfg,
            noise,
            ensemblers,
            scratch,
            m_hist: Default::default(),
        })
    }

    /// Episode `episode` at burst length `q`, every aggregator on the same streams, into
    /// `tallies`.
    fn episode(
        &mut self,
        q: usize,
        episode: usize,
        tallies: &mut Tallies,
    ) -> Result<(), SyntheticError> {
        let (cfg, g) = (self.cfg, self.cfg.geometry);
        let m_min = g.m_min();
        // The same episode seed for every q: the reference and noise pair across q too.
        let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
        rng.set_stream(episode as u64);
        let draws = EpisodeDraws::draw(&mut rng, cfg.dim, m_min);
        for e in &mut self.ensemblers {
            e.reset();
        }
        let ens_err = |source| SyntheticError::Ensemble { episode, source };
        let mut sq = vec![0.0f64; self.ensemblers.len()];
        for tau in 0..cfg.steps {
            if tau % g.h as u64 == 0 {
                let i = tau / g.h as u64;
                let corrupted = ((i as usize + draws.phase) % m_min) < q;
                let scratch = &mut self.scratch;
                draws.chunk(cfg, tau, corrupted, &self.noise, &mut rng, scratch);
                for e in &mut self.ensemblers {
                    e.insert(tau, &scratch.chunk, QueryMeta { corrupted })
                        .map_err(ens_err)?;
                }
            }
            draws.reference.at(tau as f64, &mut self.scratch.row);
            for (a, e) in self.ensemblers.iter_mut().enumerate() {
                let step = e.action(tau).map_err(ens_err)?;
                if a == 0 {
                    *self.m_hist.entry(step.report.m).or_default() += 1;
                }
                let err = step
                    .action
                    .iter()
                    .zip(&self.scratch.row)
                    .map(|(&x, r)| (x as f64 - r).powi(2))
                    .sum::<f64>()
                    .sqrt();
                tallies.errors[a].push(err);
                sq[a] += err * err;
                if let Some(b) = step.bracket {
                    tallies.brackets[a].record(&step.report, &b);
                }
            }
        }
        for (rmse, sq) in tallies.episode_rmse.iter_mut().zip(sq) {
            rmse.push((sq / cfg.steps as f64).sqrt());
        }
        Ok(())
    }
}

/// One burst length's tallies, aggregator by aggregator (in the config's order).
struct Tallies {
    /// Tracking error of every step of every episode.
    errors: Vec<Vec<f64>>,
    /// Each episode's RMSE.
    episode_rmse: Vec<Vec<f64>>,
    brackets: Vec<BracketAccumulator>,
}

impl Tallies {
    fn new(aggregators: usize) -> Self {
        Self {
            errors: vec![Vec::new(); aggregators],
            episode_rmse: vec![Vec::new(); aggregators],
            brackets: vec![BracketAccumulator::default(); aggregators],
        }
    }

    /// The cells of burst length `q`, one per aggregator.
    fn cells(self, q: usize, aggregators: &[Aggregator]) -> Vec<SyntheticCell> {
        let rows = self
            .errors
            .into_iter()
            .zip(self.episode_rmse)
            .zip(self.brackets);
        rows.zip(aggregators)
            .map(|(((mut e, episode_rmse), brackets), &aggregator)| {
                let rmse = (e.iter().map(|x| x * x).sum::<f64>() / e.len() as f64).sqrt();
                e.sort_by(f64::total_cmp);
                SyntheticCell {
                    q,
                    aggregator,
                    rmse,
                    p99_error: nearest_rank(&e, 0.99).unwrap_or(0.0),
                    max_error: e.last().copied().unwrap_or(0.0),
                    episode_rmse,
                    bracket: brackets.rows(),
                }
            })
            .collect()
    }
}

/// One synthetic episode's draws, made once per episode in this order: the reference
/// trajectory, the burst phase, the corruption direction.
struct EpisodeDraws {
    reference: Reference,
    phase: usize,
    /// Unit vector the corruption pushes along.
    direction: Vec<f64>,
}

/// Per-step buffers: one reference row, one chunk.
struct Scratch {
    row: Vec<f64>,
    chunk: Vec<f32>,
}

impl EpisodeDraws {
    fn draw(rng: &mut ChaCha8Rng, d: usize, m_min: usize) -> Self {
        let reference = Reference::random(rng, d);
        let phase = rng.random_range(0..m_min);
        let direction: Vec<f64> = if d == 1 {
            vec![if rng.random_bool(0.5) { 1.0 } else { -1.0 }]
        } else {
            // A Gaussian vector, normalised: uniform on the sphere for any d.
            let v: Vec<f64> = (0..d)
                .map(|_| rng.sample(rand_distr::StandardNormal))
                .collect();
            let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-12);
            v.into_iter().map(|x| x / norm).collect()
        };
        Self {
            reference,
            phase,
            direction,
        }
    }

    /// The chunk of the query at `tau` into `scratch.chunk`: the reference plus noise, plus
    /// the corruption along `direction` when `corrupted`.
    fn chunk(
        &self,
        cfg: &SyntheticConfig,
        tau: u64,
        corrupted: bool,
        noise: &Normal<f64>,
        rng: &mut ChaCha8Rng,
        scratch: &mut Scratch,
    ) {
        let (g, d) = (cfg.geometry, cfg.dim);
        for k in 0..g.t_p {
            let t = tau as f64 - (g.t_o as f64 - 1.0) + k as f64;
            self.reference.at(t, &mut scratch.row);
            for j in 0..d {
                let mut v = scratch.row[j] + noise.sample(rng);
                if corrupted {
                    v += cfg.corruption * self.direction[j];
                }
                scratch.chunk[k * d + j] = v as f32;
            }
        }
    }
}

/// Paired tests of every aggregator against the first, per `q`, Holm over the family.
fn compare(cells: &[SyntheticCell], aggregators: &[Aggregator]) -> Vec<PairedComparison> {
    let baseline = aggregators[0];
    let mut out: Vec<PairedComparison> = Vec::new();
    for base in cells.iter().filter(|c| c.aggregator == baseline) {
        for cell in cells
            .iter()
            .filter(|c| c.q == base.q && c.aggregator != baseline)
        {
            let (x, y) = (&cell.episode_rmse, &base.episode_rmse);
            let n = x.len() as f64;
            let mean_diff = x.iter().zip(y).map(|(a, b)| a - b).sum::<f64>() / n;
            out.push(PairedComparison {
                q: base.q,
                aggregator: cell.aggregator,
                baseline,
                mean_diff,
                se: mte_stats::mean_and_paired_se(x, y).ok().map(|s| s.se),
                wilcoxon_p: mte_stats::wilcoxon_signed_rank(x, y)
                    .ok()
                    .map(|w| w.p_value),
                holm_p: None,
            });
        }
    }
    let tested: Vec<usize> = (0..out.len())
        .filter(|&i| out[i].wilcoxon_p.is_some())
        .collect();
    let raw: Vec<f64> = tested.iter().filter_map(|&i| out[i].wilcoxon_p).collect();
    if let Ok(adjusted) = mte_stats::holm(&raw) {
        for (&i, p) in tested.iter().zip(adjusted) {
            out[i].holm_p = Some(p);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Silent;
    use mte_ensemble::Regime;

    fn small() -> SyntheticConfig {
        SyntheticConfig {
            episodes: 3,
            steps: 120,
            ..SyntheticConfig::default()
        }
    }

    #[test]
    fn median_beats_the_mean_under_bursts_and_ties_it_clean() {
        let r = run(&small(), &Silent).unwrap();
        let cell = |q, a: Aggregator| {
            r.cells
                .iter()
                .find(|c| c.q == q && c.aggregator == a)
                .unwrap()
                .clone()
        };
        let (ewm0, med0) = (cell(0, Aggregator::default()), cell(0, Aggregator::MEDIAN));
        // Clean: both track within a few noise standard deviations.
        assert!(
            ewm0.rmse < 6.0 && med0.rmse < 6.0,
            "{} {}",
            ewm0.rmse,
            med0.rmse
        );
        for q in 1..=3 {
            let (ewm, med) = (cell(q, Aggregator::default()), cell(q, Aggregator::MEDIAN));
            assert!(
                med.rmse < ewm.rmse,
                "q={q}: median {} vs ewm {}",
                med.rmse,
                ewm.rmse
            );
            // The guaranteed regime: the median never leaves the clean bracket.
            if let Some(row) = med.bracket.iter().find(|r| r.regime == Regime::Guaranteed) {
                assert_eq!(row.outside_pct, 0.0, "q={q}");
                assert!(row.steps > 0);
            }
            let ewm_row = ewm
                .bracket
                .iter()
                .find(|r| r.regime == Regime::Guaranteed)
                .unwrap();
            assert!(ewm_row.outside_pct > 50.0, "q={q}: {}", ewm_row.outside_pct);
        }
        // M alternates between 7 and 8 once 7 queries have fired (tau >= 12), and never
        // exceeds 8 (T_p = 16, T_o = 2, h = 2).
        let runs = (small().episodes * small().q_values.len()) as u64;
        let steady: u64 = r
            .m_histogram
            .iter()
            .filter(|(m, _)| *m >= 7)
            .map(|(_, n)| n)
            .sum();
        assert_eq!(steady, runs * (120 - 12));
        assert_eq!(r.m_histogram.last().unwrap().0, 8);
    }

    #[test]
    fn paired_tests_favour_the_median_under_attack() {
        let r = run(
            &SyntheticConfig {
                episodes: 8,
                ..small()
            },
            &Silent,
        )
        .unwrap();
        let c = r
            .comparisons
            .iter()
            .find(|c| c.q == 2 && c.aggregator == Aggregator::MEDIAN)
            .unwrap();
        assert!(c.mean_diff < 0.0, "{c:?}");
        // 8 episodes all favouring the median: the exact two-sided p is 2 / 2^8.
        assert!((c.wilcoxon_p.unwrap() - 2.0 / 256.0).abs() < 1e-12, "{c:?}");
        assert!(c.holm_p.unwrap() >= c.wilcoxon_p.unwrap());
        // (aggregators - 1) comparisons per q.
        assert_eq!(r.comparisons.len(), 4 * 4);
    }

    #[test]
    fn runs_are_deterministic_and_paired() {
        let a = run(&small(), &Silent).unwrap();
        let b = run(&small(), &Silent).unwrap();
        assert_eq!(a, b);
        let other = run(&SyntheticConfig { seed: 1, ..small() }, &Silent).unwrap();
        assert_ne!(a.cells[0].episode_rmse, other.cells[0].episode_rmse);
    }

    #[test]
    fn invalid_configs_name_the_field() {
        let e = SyntheticConfig {
            q_values: vec![9],
            ..small()
        }
        .validate()
        .unwrap_err();
        assert!(e.to_string().contains("q_values = 9") && e.to_string().contains("M_min = 7"));
        let e = SyntheticConfig {
            noise_std: f64::NAN,
            ..small()
        }
        .validate()
        .unwrap_err();
        assert!(e.to_string().contains("noise_std = NaN"), "{e}");
        let e = SyntheticConfig { dim: 0, ..small() }
            .validate()
            .unwrap_err();
        assert!(e.to_string().contains("dim = 0"));
    }
}
