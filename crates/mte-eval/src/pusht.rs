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
//! Observation faults go through [`ObservationCorruptor`]. Common-mode bias `b(tau)` is
//! added to every candidate of `tau` when the newest query covering `tau` is corrupted; all
//! aggregators offered are translation-equivariant, so the runner adds `b(tau)` to the
//! output, which equals shifting every candidate (and keeps the ensembler's candidates
//! clean for the diagnostics). Oracle bracket attacks rewrite corrupted candidates per
//! control time from the clean bracket, so they assemble candidates here and call the
//! aggregator directly. `q(tau)` and `M(tau)` are measured and recorded at every step.

use std::fmt;
use std::str::FromStr;
use std::time::Instant;

use mte_ensemble::bracket::diagnose;
use mte_ensemble::{
    Aggregate, Aggregator, BracketAccumulator, Candidates, ChunkGeometry, EnsembleError,
    EnsemblerOptions, QueryMeta, Regime, StepReport, TemporalEnsembler, Workspace,
};
use mte_policy::{ChunkPolicy, Observation, PolicyError};
use mte_sim::render::Renderer;
use mte_sim::{PushT, ResetStream, SimError};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::corruption::{CorruptionSpec, Fault, ObservationCorruptor, OracleMode};
use crate::record::{EpisodeRecord, StageTimes};

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

/// Which observations the policy reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ObsNeeds {
    /// The 16 keypoints.
    pub env_state: bool,
    /// Rendered frames of this (width, height).
    pub image: Option<(usize, usize)>,
}

impl ObsNeeds {
    /// What a Diffusion Policy with this configuration reads.
    pub fn of(config: &mte_policy::DiffusionConfig) -> Self {
        Self {
            env_state: config
                .vector_dim(mte_policy::config::FeatureType::Env)
                .is_some(),
            image: config.image_shape().map(|[_, h, w]| (w, h)),
        }
    }
}

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

fn observe(
    env: &PushT,
    needs: ObsNeeds,
    renderer: &mut Option<Renderer>,
) -> Result<Observation, RolloutError> {
    let a = env.agent_pos();
    let image = match (needs.image, renderer.as_mut()) {
        (Some((w, h)), Some(r)) => {
            let mut px = vec![0u8; w * h * 3];
            r.observation_with_contacts_into(&env.scene(), env.contact_segments(), w, h, &mut px)?;
            Some(px)
        }
        _ => None,
    };
    Ok(Observation {
        state: vec![a[0] as f32, a[1] as f32],
        env_state: needs
            .env_state
            .then(|| env.keypoints().iter().map(|&v| v as f32).collect()),
        image,
    })
}

/// Candidate assembly for oracle attacks: the live chunks and their flags.
struct OracleState {
    mode: OracleMode,
    /// Per coordinate: +1 pushes towards the bracket's top, -1 towards its bottom (drift).
    direction: Vec<f32>,
    live: Vec<(u64, Vec<f32>, bool)>,
    ws: Workspace,
    values: Vec<f32>,
    flags: Vec<bool>,
    scratch: Vec<f32>,
}

impl OracleState {
    /// Candidates for `tau` with corrupted ones rewritten; returns (m, q).
    fn candidates(&mut self, g: ChunkGeometry, d: usize, tau: u64) -> (usize, usize) {
        let span = g.span() as u64;
        self.live.retain(|(t, _, _)| t + span > tau);
        self.values.clear();
        self.flags.clear();
        for (t, chunk, corrupted) in &self.live {
            if let Some(r) = g.candidate_row(*t, tau) {
                self.values.extend_from_slice(&chunk[r * d..(r + 1) * d]);
                self.flags.push(*corrupted);
            }
        }
        let m = self.flags.len();
        let q = self.flags.iter().filter(|&&c| c).count();
        if q == 0 || q == m {
            return (m, q);
        }
        for j in 0..d {
            let clean: Vec<f32> = (0..m)
                .filter(|&i| !self.flags[i])
                .map(|i| self.values[i * d + j])
                .collect();
            let lo = clean.iter().copied().fold(f32::INFINITY, f32::min);
            let hi = clean.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            let target = match self.mode {
                OracleMode::Drift => {
                    if self.direction[j] >= 0.0 {
                        hi
                    } else {
                        lo
                    }
                }
                OracleMode::Instant => {
                    // The end that moves the coordinate-wise median farthest from the
                    // clean candidates' median.
                    let base = median(&clean, &mut self.scratch);
                    let with = |v: f32, s: &mut Vec<f32>| {
                        let mut all = clean.clone();
                        all.extend(std::iter::repeat_n(v, q));
                        median(&all, s)
                    };
                    let (up, down) = (with(hi, &mut self.scratch), with(lo, &mut self.scratch));
                    if (up - base).abs() >= (down - base).abs() {
                        hi
                    } else {
                        lo
                    }
                }
            };
            for i in 0..m {
                if self.flags[i] {
                    self.values[i * d + j] = target;
                }
            }
        }
        (m, q)
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

/// Run one episode of one arm. The returned record's `cell` is empty (the caller names it).
pub fn run_episode(
    policy: &dyn ChunkPolicy,
    spec: &EpisodeSpec<'_>,
) -> Result<EpisodeRecord, RolloutError> {
    let t_start = Instant::now();
    let (t_p, t_o, d) = (policy.horizon(), policy.n_obs_steps(), policy.action_dim());
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
    let fault = &spec.corruption.fault;
    let schedule = &spec.corruption.schedule;
    let clean = spec.corruption.is_clean();
    let mut times = StageTimes::default();

    let t = Instant::now();
    let mut env = PushT::default();
    env.reset(spec.seed, spec.stream)?;
    times.sim_s += t.elapsed().as_secs_f64();
    let mut renderer = spec.needs.image.map(|_| Renderer::new(env.goal()));
    let mut oracle = match (fault, spec.execution) {
        (Fault::Oracle { mode }, Execution::Ensemble(_)) if !clean => {
            let mut r = query_rng(spec.noise_seed, spec.seed, 0, 2);
            Some(OracleState {
                mode: *mode,
                direction: (0..d)
                    .map(|_| if r.random_bool(0.5) { 1.0 } else { -1.0 })
                    .collect(),
                live: Vec::new(),
                ws: Workspace::new(geometry.span() + h, d),
                values: Vec::new(),
                flags: Vec::new(),
                scratch: Vec::new(),
            })
        }
        (Fault::Oracle { .. }, Execution::OpenLoop) if !clean => {
            return Err(RolloutError::Config {
                field: "arm",
                value: "open-loop".into(),
                expected: "an aggregator: oracle attacks rewrite an ensembler's candidates".into(),
            });
        }
        _ => None,
    };
    // Oracle attacks assemble their own candidates; every other ensemble arm uses the
    // streaming ensembler.
    let mut ens = match (spec.execution, &oracle) {
        (Execution::Ensemble(a), None) => Some(TemporalEnsembler::with_options(
            geometry,
            d,
            a,
            EnsemblerOptions {
                lookahead: None,
                bracket_diagnostics: !clean,
            },
        )?),
        _ => None,
    };
    let bias: Option<[f32; 2]> = match *fault {
        Fault::CommonMode {
            magnitude,
            angle_deg,
        } => {
            let a = angle_deg.to_radians();
            Some([(magnitude * a.cos()) as f32, (magnitude * a.sin()) as f32])
        }
        _ => None,
    };
    let mut corruptor = match fault {
        Fault::Patch { path } => {
            let Some((w, h)) = spec.needs.image else {
                return Err(RolloutError::Config {
                    field: "fault",
                    value: fault.to_string(),
                    expected: "an image policy (a patch is drawn into camera frames)".into(),
                });
            };
            let (_, patch) = crate::patch_file::load(path).map_err(|e| RolloutError::Config {
                field: "fault.path",
                value: path.display().to_string(),
                expected: format!("a patch directory ({e})"),
            })?;
            // Fails here, not per frame, if the texture does not fit the frame.
            patch.origin(w, h).map_err(|e| RolloutError::Config {
                field: "fault.path",
                value: path.display().to_string(),
                expected: e.to_string(),
            })?;
            ObservationCorruptor::with_patch(fault.clone(), patch)
        }
        _ => ObservationCorruptor::new(fault.clone()),
    };
    let keep = corruptor.frames_needed(t_o).max(t_o + 1);
    let mut frames: Vec<Observation> = Vec::with_capacity(keep + 1);
    let mut chunk = Vec::new();
    let mut out = vec![0f32; d];
    let mut max_coverage = env.coverage();
    let (mut queries, mut corrupted_queries) = (0usize, 0usize);
    // Whether the newest query was corrupted, and whether its candidates count as corrupted
    // (not under common-mode bias, which shifts every candidate alike: no clean bracket).
    let (mut newest_corrupted, mut newest_flagged) = (false, false);
    let (mut m_counts, mut q_counts) = (Vec::new(), Vec::new());
    let mut bracket = BracketAccumulator::default();
    let m_min = geometry.m_min();
    let mut success = false;
    let mut steps = 0;
    while steps < spec.max_steps {
        let t = Instant::now();
        let o = observe(&env, spec.needs, &mut renderer)?;
        times.render_s += t.elapsed().as_secs_f64();
        if frames.is_empty() {
            frames = vec![o; keep];
        } else {
            frames.remove(0);
            frames.push(o);
        }
        let k = steps % h;
        if k == 0 {
            let i = (steps / h) as u64;
            let t = Instant::now();
            let mut crng = query_rng(spec.noise_seed, spec.seed, i, 1);
            let corrupted = !clean && schedule.corrupts(i, steps as u64, m_min, &mut crng);
            let window = corruptor.window(&frames, t_o, corrupted, spec.needs.image, &mut crng);
            times.corruption_s += t.elapsed().as_secs_f64();
            let t = Instant::now();
            let mut srng = query_rng(spec.noise_seed, spec.seed, i, 0);
            chunk = match fault {
                Fault::Pgd(cfg) if corrupted => {
                    let c = policy.predict_chunk_attacked(&window, cfg, &mut crng, &mut srng)?;
                    times.corruption_s += t.elapsed().as_secs_f64();
                    c
                }
                _ => {
                    let c = policy.predict_chunk(&window, &mut srng)?;
                    times.policy_s += t.elapsed().as_secs_f64();
                    c
                }
            };
            queries += 1;
            corrupted_queries += usize::from(corrupted);
            newest_corrupted = corrupted;
            newest_flagged = corrupted && bias.is_none();
            let t = Instant::now();
            if let Some(o) = oracle.as_mut() {
                o.live.push((steps as u64, chunk.clone(), newest_flagged));
            } else if let Some(e) = ens.as_mut() {
                e.insert(
                    steps as u64,
                    &chunk,
                    QueryMeta {
                        corrupted: newest_flagged,
                    },
                )?;
            }
            times.ensemble_s += t.elapsed().as_secs_f64();
        }
        let tau = steps as u64;
        let t_ens = Instant::now();
        let (m, q) = match (oracle.as_mut(), ens.as_mut(), spec.execution) {
            (Some(o), _, Execution::Ensemble(agg)) => {
                let t = Instant::now();
                let (m, q) = o.candidates(geometry, d, tau);
                times.corruption_s += t.elapsed().as_secs_f64();
                let c = Candidates::new(&o.values, d)?;
                agg.aggregate(&c, &mut o.ws, &mut out)?;
                if let Some(b) = diagnose(&c, &o.flags, &out) {
                    let report = StepReport {
                        tau,
                        m,
                        q,
                        excluded: 0,
                        excluded_corrupted: 0,
                        regime: Regime::of(q, m),
                        oldest_query: 0,
                        newest_query: tau,
                    };
                    bracket.record(&report, &b);
                }
                (m, q)
            }
            (_, Some(e), _) => {
                let s = e.action(tau)?;
                out.copy_from_slice(s.action);
                if let Some(b) = s.bracket {
                    bracket.record(&s.report, &b);
                }
                (s.report.m, s.report.q)
            }
            _ => {
                let r = t_o - 1 + k;
                out.copy_from_slice(&chunk[r * d..(r + 1) * d]);
                (1, usize::from(newest_flagged))
            }
        };
        times.ensemble_s += t_ens.elapsed().as_secs_f64();
        bump(&mut m_counts, m);
        bump(&mut q_counts, q);
        if let (Some(b), true) = (bias, newest_corrupted) {
            for (x, bj) in out.iter_mut().zip(b) {
                *x += bj;
            }
        }
        let action = [f64::from(out[0]), f64::from(out[1])];
        let t = Instant::now();
        let info = env.step(action)?;
        times.sim_s += t.elapsed().as_secs_f64();
        steps += 1;
        max_coverage = max_coverage.max(info.coverage);
        if info.is_success {
            success = true;
            break;
        }
    }
    times.total_s = t_start.elapsed().as_secs_f64();
    Ok(EpisodeRecord {
        cell: String::new(),
        arm: spec.execution.to_string(),
        seed: spec.seed,
        success,
        max_coverage,
        steps,
        queries,
        corrupted_queries,
        m_counts,
        q_counts,
        bracket: (!clean && matches!(spec.execution, Execution::Ensemble(_))).then_some(bracket),
        times,
    })
}
