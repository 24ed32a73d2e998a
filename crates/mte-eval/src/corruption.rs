//! Which queries are corrupted (schedules) and what corruption does (faults).
//!
//! Corruption acts on the *observation of selected queries* (protocol section 4); the policy
//! is unchanged. Observation faults act on the exteroceptive channel only (the camera image,
//! or the block keypoints of a state policy); the agent's own position (proprioception) is
//! never corrupted. Candidate-level corruptions (common-mode bias, oracle bracket attacks)
//! act on the chunks' candidates instead and are applied by the runner.
//!
//! Units: images are HWC `u8`; intensities in fault parameters are in `[0, 1]` (so
//! `sigma = 0.1` is 25.5 grey levels); state coordinates are pixels of the 512 x 512
//! workspace; sizes are pixels of the observation image.
//!
//! Cameras: a policy that also reads the wrist camera has it struck with the scene camera by
//! the faults of the camera itself (blank, stale, frozen, motion blur, noise: the video
//! pipeline fails for every camera); the faults that sit in the scene (occluder, patch) are
//! drawn into the scene camera's frames only.

use std::fmt;

use mte_policy::Observation;
use rand::{Rng, RngCore};
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use crate::label::phase_suffix;

/// Side of the PushT workspace (px), for mapping image sizes onto keypoints.
const WORKSPACE: f64 = 512.0;

/// Which queries are corrupted. Query `i` fires at control time `t_i = i h`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum Schedule {
    /// No query.
    Never,
    /// Sparse bursts: in every period of `period` consecutive queries (default `M_min` of
    /// the chunk geometry) a contiguous run of `q` is corrupted: query `i` is corrupted iff
    /// `(i + phase) mod period < q`.
    Burst {
        /// Corrupted queries per period.
        q: usize,
        /// Offset of the run within the period.
        #[serde(default)]
        phase: usize,
        /// Period in queries; `None` = `M_min`.
        #[serde(default)]
        period: Option<usize>,
    },
    /// Every query whose time lies in `[start, end)` (control steps).
    Dense {
        /// First control step of the window.
        start: u64,
        /// One past the last control step of the window.
        end: u64,
    },
    /// Each query independently with probability `p` (drawn from the episode's corruption
    /// stream, identical across arms).
    Bernoulli {
        /// Probability in `[0, 1]`.
        p: f64,
    },
}

impl Schedule {
    /// Whether query `i` (at control time `t`) is corrupted; `m_min` is the geometry's
    /// smallest covering count. `rng` is drawn only by `Bernoulli`.
    pub fn corrupts(&self, i: u64, t: u64, m_min: usize, rng: &mut dyn RngCore) -> bool {
        match *self {
            Self::Never => false,
            Self::Burst { q, phase, period } => {
                let p = period.unwrap_or(m_min).max(1) as u64;
                (i + phase as u64) % p < q as u64
            }
            Self::Dense { start, end } => (start..end).contains(&t),
            Self::Bernoulli { p } => rng.random_bool(p.clamp(0.0, 1.0)),
        }
    }

    /// Nominal `q` (burst length; 0 for `Never`; for the others the count is measured, and
    /// this reports 1 for "some").
    pub fn q(&self) -> usize {
        match *self {
            Self::Never => 0,
            Self::Burst { q, .. } => q,
            Self::Dense { start, end } => usize::from(end > start),
            Self::Bernoulli { p } => usize::from(p > 0.0),
        }
    }

    /// Checks parameters.
    pub fn validate(&self) -> Result<(), CorruptionError> {
        match *self {
            Self::Bernoulli { p } if !(0.0..=1.0).contains(&p) => Err(CorruptionError::new(
                "schedule.p",
                p,
                "a probability in [0, 1]",
            )),
            Self::Burst {
                period: Some(0), ..
            } => Err(CorruptionError::new(
                "schedule.period",
                0,
                "at least 1 query",
            )),
            Self::Dense { start, end } if end < start => Err(CorruptionError::new(
                "schedule.end",
                end,
                format!("at least start = {start}"),
            )),
            _ => Ok(()),
        }
    }
}

/// Direction an oracle bracket attack pushes in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum OracleMode {
    /// Each step, per coordinate, the bracket end that moves the median farthest.
    Instant,
    /// One direction per coordinate (drawn at the episode start) kept over consecutive
    /// steps.
    Drift,
}

/// What a corrupted query suffers. Each kind is its own type, and where it acts in an
/// episode (`crate::episode` names the stages) follows from the variant: a
/// [`SensorFault`] rewrites the observation window (stage *corrupt*), a [`QueryAttack`]
/// replaces the query by an attacked one (stage *query*), a [`CandidateCorruption`]
/// rewrites the ensembler's candidates (stage *ensemble*).
///
/// On the wire (sweep specs, run manifests) a fault is one flat object tagged by `kind`
/// (`{"kind": "blank"}`, `{"kind": "occluder", "size": 24}`), unknown fields rejected.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(from = "wire::FaultWire", into = "wire::FaultWire")]
pub enum Fault {
    /// Nothing (a clean cell).
    None,
    /// A fault of the camera or of the state estimate.
    Sensor(SensorFault),
    /// An attack on the query itself, through the policy's gradient.
    Query(QueryAttack),
    /// A corruption of the candidates the ensembler combines.
    Candidates(CandidateCorruption),
}

/// A fault of the sensor, acting on the exteroceptive channel (the camera image, or the
/// block keypoints of a state policy) of a corrupted query's observation window; the
/// agent's own position is never corrupted.
#[derive(Clone, Debug, PartialEq)]
pub enum SensorFault {
    /// Every pixel zero; for a state policy, the keypoints read zero.
    Blank,
    /// The newest frame is replaced by the previous control step's (one missed update).
    Stale,
    /// Every frame is the last one seen before the burst began (camera frozen for the
    /// whole run of consecutive corrupted queries).
    Frozen,
    /// A black `size x size` square at a uniformly random position (one per query); for a
    /// state policy the keypoints inside the square (scaled to the workspace) read zero.
    Occluder {
        /// Side in observation pixels (the paper swept up to 48 of 84).
        size: usize,
    },
    /// Box blur of `length` pixels along a random direction (one per query); for a state
    /// policy, each frame's keypoints are the mean of the last `length` control steps.
    MotionBlur {
        /// Kernel length (pixels, or control steps for state).
        length: usize,
    },
    /// Additive Gaussian noise: `sigma` in intensity units `[0, 1]` for images, pixels of
    /// the workspace for keypoints; images are clamped to `[0, 255]`.
    GaussianNoise {
        /// Standard deviation.
        sigma: f64,
    },
    /// A trained physical patch (`mte attack patch`, a directory with `patch.png` and
    /// `patch.json`) drawn at its world position into every frame of a corrupted query's
    /// window. Image policies only.
    Patch {
        /// The patch directory.
        path: std::path::PathBuf,
        /// The attacker's optimiser step size this patch was trained with (`patch.json`'s
        /// `step`), declared in the spec to place the cell on a step-size axis (the paper's
        /// patch curves): the cell's [`budget`](SensorFault::budget). The runner refuses a
        /// declared step that differs from the file's. `None` (controls, or no curve): no
        /// budget.
        step: Option<f64>,
    },
}

/// An attack that replaces a corrupted query's chunk by the chunk of an attacked input.
#[derive(Clone, Debug, PartialEq)]
pub enum QueryAttack {
    /// PGD on the policy's own training loss at corrupted queries (`mte_policy::attack`):
    /// L-infinity `eps` (pixels in `[0, 1]`, or normalised keypoints), sign steps, a budget
    /// of `iterations`. The attacker is the same whichever arm is deployed.
    Pgd(mte_policy::PgdConfig),
}

/// A corruption of the ensembler's candidate set at the control times a corrupted query
/// covers (applied through `mte_ensemble::CandidateHook` on the real ensembler).
#[derive(Clone, Debug, PartialEq)]
pub enum CandidateCorruption {
    /// Common-mode bias: every candidate covering a control time whose newest query is
    /// corrupted is shifted by the same vector (`magnitude` px at `angle_deg`, turning as
    /// `direction` says).
    CommonMode {
        /// Length of the bias (px).
        magnitude: f64,
        /// Direction, degrees counter-clockwise from +x (at control time 0).
        angle_deg: f64,
        /// Constant, slowly drifting, or random per episode.
        direction: BiasDirection,
    },
    /// Oracle attack confined to the clean bracket: corrupted candidates take the bracket
    /// end that moves the coordinate-wise median farthest.
    Oracle {
        /// Per-step or consistent direction.
        mode: OracleMode,
    },
}

/// How a common-mode bias's direction evolves within an episode. Whatever it is, at one
/// control time every covering candidate gets the same vector.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum BiasDirection {
    /// Fixed at `angle_deg`.
    #[default]
    Constant,
    /// Turning from `angle_deg` by `deg_per_step` degrees per control step (a slowly
    /// drifting bias: 1 degree per step turns a full circle in 360 steps).
    Drift {
        /// Degrees per control step, counter-clockwise.
        deg_per_step: f64,
    },
    /// `angle_deg` plus an angle drawn uniformly from [0, 360) once per episode, from the
    /// episode's seed and the run's noise seed (so both arms of a seed get the same one).
    Random,
}

impl BiasDirection {
    /// Whether this is the default ([`Self::Constant`]).
    pub fn is_constant(&self) -> bool {
        matches!(self, Self::Constant)
    }

    /// The suffix of a cell label: empty, `-drift<deg>`, or `-random`.
    fn label(&self) -> String {
        match self {
            Self::Constant => String::new(),
            Self::Drift { deg_per_step } => format!("-drift{deg_per_step}"),
            Self::Random => "-random".into(),
        }
    }
}

impl From<SensorFault> for Fault {
    fn from(f: SensorFault) -> Self {
        Self::Sensor(f)
    }
}

impl From<QueryAttack> for Fault {
    fn from(a: QueryAttack) -> Self {
        Self::Query(a)
    }
}

impl From<CandidateCorruption> for Fault {
    fn from(c: CandidateCorruption) -> Self {
        Self::Candidates(c)
    }
}

impl Fault {
    /// The sensor fault, if this is one.
    pub fn sensor(&self) -> Option<&SensorFault> {
        match self {
            Self::Sensor(f) => Some(f),
            _ => None,
        }
    }

    /// The PGD attack's settings, if this is one.
    pub fn pgd(&self) -> Option<&mte_policy::PgdConfig> {
        match self {
            Self::Query(QueryAttack::Pgd(c)) => Some(c),
            _ => None,
        }
    }

    /// What [`budget`](Self::budget) measures, with its unit: a plot's axis label.
    pub fn budget_axis(&self) -> &'static str {
        match self {
            Self::Sensor(SensorFault::Occluder { .. }) => "occluder side (px)",
            Self::Sensor(SensorFault::MotionBlur { .. }) => "blur length (px or steps)",
            Self::Sensor(SensorFault::GaussianNoise { .. }) => "noise sigma",
            Self::Sensor(SensorFault::Patch { .. }) => "patch optimiser step size",
            Self::Query(QueryAttack::Pgd(_)) => "PGD iterations",
            Self::Candidates(CandidateCorruption::CommonMode { .. }) => {
                "common-mode magnitude (action units)"
            }
            _ => "attack budget",
        }
    }

    /// Strength on the fault's natural axis, for plots against attack budget.
    pub fn budget(&self) -> Option<f64> {
        match self {
            Self::None => None,
            Self::Sensor(f) => f.budget(),
            Self::Query(QueryAttack::Pgd(c)) => Some(c.iterations as f64),
            Self::Candidates(CandidateCorruption::CommonMode { magnitude, .. }) => Some(*magnitude),
            Self::Candidates(CandidateCorruption::Oracle { .. }) => None,
        }
    }

    /// Checks parameters.
    pub fn validate(&self) -> Result<(), CorruptionError> {
        match self {
            Self::None | Self::Candidates(CandidateCorruption::Oracle { .. }) => Ok(()),
            Self::Sensor(f) => f.validate(),
            Self::Query(QueryAttack::Pgd(c)) => c
                .validate()
                .map_err(|e| CorruptionError::new("fault (pgd)", c.iterations, e.to_string())),
            Self::Candidates(CandidateCorruption::CommonMode {
                magnitude,
                angle_deg,
                direction,
            }) => {
                let rate_ok = match direction {
                    BiasDirection::Drift { deg_per_step } => deg_per_step.is_finite(),
                    _ => true,
                };
                if magnitude.is_finite() && angle_deg.is_finite() && rate_ok {
                    Ok(())
                } else {
                    Err(CorruptionError::new(
                        "fault.magnitude/angle_deg/direction",
                        format!("{magnitude}/{angle_deg}/{direction:?}"),
                        "finite numbers",
                    ))
                }
            }
        }
    }
}

impl SensorFault {
    /// Strength on the fault's natural axis.
    pub fn budget(&self) -> Option<f64> {
        match *self {
            Self::Occluder { size } => Some(size as f64),
            Self::MotionBlur { length } => Some(length as f64),
            Self::GaussianNoise { sigma } => Some(sigma),
            Self::Patch { step, .. } => step,
            Self::Blank | Self::Stale | Self::Frozen => None,
        }
    }

    /// Checks parameters.
    pub fn validate(&self) -> Result<(), CorruptionError> {
        match *self {
            Self::Occluder { size: 0 } => {
                Err(CorruptionError::new("fault.size", 0, "at least 1 pixel"))
            }
            Self::MotionBlur { length: 0 } => {
                Err(CorruptionError::new("fault.length", 0, "at least 1"))
            }
            Self::GaussianNoise { sigma } if !(sigma.is_finite() && sigma >= 0.0) => Err(
                CorruptionError::new("fault.sigma", sigma, "a finite value >= 0"),
            ),
            Self::Patch {
                step: Some(step), ..
            } if !(step.is_finite() && step > 0.0) => Err(CorruptionError::new(
                "fault.step",
                step,
                "a finite step size > 0 (the patch's patch.json `step`)",
            )),
            _ => Ok(()),
        }
    }
}

impl fmt::Display for Fault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::None => f.write_str("none"),
            Self::Sensor(s) => s.fmt(f),
            Self::Query(QueryAttack::Pgd(c)) => write_pgd(f, c),
            Self::Candidates(CandidateCorruption::CommonMode {
                magnitude,
                angle_deg,
                direction,
            }) => write!(f, "common-{magnitude}@{angle_deg}{}", direction.label()),
            Self::Candidates(CandidateCorruption::Oracle { mode }) => match mode {
                OracleMode::Instant => f.write_str("oracle-inst"),
                OracleMode::Drift => f.write_str("oracle-drift"),
            },
        }
    }
}

/// `pgd-<iterations>`, then every parameter that differs from [`mte_policy::PgdConfig`]'s
/// default (`-eps0.1-step0.00625-s8-rs`), so two attacks in one sweep never share a label.
fn write_pgd(f: &mut fmt::Formatter<'_>, c: &mte_policy::PgdConfig) -> fmt::Result {
    let d = mte_policy::PgdConfig::default();
    write!(f, "pgd-{}", c.iterations)?;
    if c.eps != d.eps {
        write!(f, "-eps{}", c.eps)?;
    }
    if c.step != d.step {
        write!(f, "-step{}", c.step)?;
    }
    if c.samples != d.samples {
        write!(f, "-s{}", c.samples)?;
    }
    if c.random_start != d.random_start {
        f.write_str(if c.random_start { "-rs" } else { "-no-rs" })?;
    }
    Ok(())
}

impl fmt::Display for SensorFault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Blank => f.write_str("blank"),
            Self::Stale => f.write_str("stale"),
            Self::Frozen => f.write_str("frozen"),
            Self::Occluder { size } => write!(f, "occluder-{size}"),
            Self::MotionBlur { length } => write!(f, "blur-{length}"),
            Self::GaussianNoise { sigma } => write!(f, "noise-{sigma}"),
            Self::Patch { path, .. } => write!(
                f,
                "patch-{}",
                path.file_name().map_or_else(
                    || path.display().to_string(),
                    |n| n.to_string_lossy().into()
                )
            ),
        }
    }
}

/// The flat wire form of [`Fault`], unchanged since run files began, so old run
/// directories and sweep specs still load.
mod wire {
    use serde::{Deserialize, Serialize};

    use super::{
        BiasDirection, CandidateCorruption as C, Fault, OracleMode, QueryAttack as Q,
        SensorFault as S,
    };

    #[derive(Clone, Serialize, Deserialize)]
    #[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
    pub(super) enum FaultWire {
        None,
        Blank,
        Stale,
        Frozen,
        Occluder {
            size: usize,
        },
        MotionBlur {
            length: usize,
        },
        GaussianNoise {
            sigma: f64,
        },
        CommonMode {
            magnitude: f64,
            angle_deg: f64,
            #[serde(default, skip_serializing_if = "BiasDirection::is_constant")]
            direction: BiasDirection,
        },
        Pgd(mte_policy::PgdConfig),
        Patch {
            path: std::path::PathBuf,
            #[serde(default, skip_serializing_if = "Option::is_none")]
            step: Option<f64>,
        },
        Oracle {
            mode: OracleMode,
        },
    }

    impl From<FaultWire> for Fault {
        fn from(w: FaultWire) -> Self {
            match w {
                FaultWire::None => Self::None,
                FaultWire::Blank => S::Blank.into(),
                FaultWire::Stale => S::Stale.into(),
                FaultWire::Frozen => S::Frozen.into(),
                FaultWire::Occluder { size } => S::Occluder { size }.into(),
                FaultWire::MotionBlur { length } => S::MotionBlur { length }.into(),
                FaultWire::GaussianNoise { sigma } => S::GaussianNoise { sigma }.into(),
                FaultWire::Patch { path, step } => S::Patch { path, step }.into(),
                FaultWire::Pgd(c) => Q::Pgd(c).into(),
                FaultWire::CommonMode {
                    magnitude,
                    angle_deg,
                    direction,
                } => C::CommonMode {
                    magnitude,
                    angle_deg,
                    direction,
                }
                .into(),
                FaultWire::Oracle { mode } => C::Oracle { mode }.into(),
            }
        }
    }

    impl From<Fault> for FaultWire {
        fn from(f: Fault) -> Self {
            match f {
                Fault::None => Self::None,
                Fault::Sensor(s) => match s {
                    S::Blank => Self::Blank,
                    S::Stale => Self::Stale,
                    S::Frozen => Self::Frozen,
                    S::Occluder { size } => Self::Occluder { size },
                    S::MotionBlur { length } => Self::MotionBlur { length },
                    S::GaussianNoise { sigma } => Self::GaussianNoise { sigma },
                    S::Patch { path, step } => Self::Patch { path, step },
                },
                Fault::Query(Q::Pgd(c)) => Self::Pgd(c),
                Fault::Candidates(C::CommonMode {
                    magnitude,
                    angle_deg,
                    direction,
                }) => Self::CommonMode {
                    magnitude,
                    angle_deg,
                    direction,
                },
                Fault::Candidates(C::Oracle { mode }) => Self::Oracle { mode },
            }
        }
    }
}

/// A fault and the schedule of queries it strikes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CorruptionSpec {
    /// What happens to a corrupted query.
    pub fault: Fault,
    /// Which queries are corrupted.
    pub schedule: Schedule,
}

impl CorruptionSpec {
    /// No corruption.
    pub const CLEAN: Self = Self {
        fault: Fault::None,
        schedule: Schedule::Never,
    };

    /// Whether nothing is ever corrupted.
    pub fn is_clean(&self) -> bool {
        matches!(self.fault, Fault::None) || matches!(self.schedule, Schedule::Never)
    }

    /// Nominal `q` (0 when clean).
    pub fn q(&self) -> usize {
        if self.is_clean() {
            0
        } else {
            self.schedule.q()
        }
    }

    /// Checks both parts.
    pub fn validate(&self) -> Result<(), CorruptionError> {
        self.fault.validate()?;
        self.schedule.validate()
    }

    /// Refuses a burst longer than its period: `q` corrupted queries of every `period`
    /// (default `M_min` of the chunk geometry `t_p`, `t_o`, `h`), so `q <= period`; a longer
    /// burst would silently equal `q = period`. Other schedules pass.
    ///
    /// # Errors
    /// `h` that the geometry refuses, or `q` above the period.
    pub fn check_burst(&self, t_p: usize, t_o: usize, h: usize) -> Result<(), CorruptionError> {
        let Schedule::Burst { q, period, .. } = self.schedule else {
            return Ok(());
        };
        let geometry = mte_ensemble::ChunkGeometry::new(t_p, t_o, h).map_err(|e| {
            CorruptionError::new(
                "h",
                h,
                format!("a stride the policy supports (T_p {t_p}, T_o {t_o}): {e}"),
            )
        })?;
        let p = period.unwrap_or(geometry.m_min());
        if q > p {
            return Err(CorruptionError::new(
                "q",
                q,
                format!("at most the burst period {p} (M_min of T_p {t_p}, T_o {t_o}, h {h})"),
            ));
        }
        Ok(())
    }
}

impl fmt::Display for CorruptionSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.is_clean() {
            return f.write_str("clean");
        }
        match &self.schedule {
            Schedule::Never => f.write_str("clean"),
            Schedule::Burst { q, phase, period } => {
                write!(f, "{}-burst-q{q}{}", self.fault, phase_suffix(*phase))?;
                if let Some(p) = period {
                    write!(f, "-per{p}")?;
                }
                Ok(())
            }
            Schedule::Dense { start, end } => write!(f, "{}-dense-{start}-{end}", self.fault),
            Schedule::Bernoulli { p } => write!(f, "{}-bernoulli-{p}", self.fault),
        }
    }
}

/// A corruption parameter out of range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("`{field}` = {value}: expected {expected}")]
pub struct CorruptionError {
    /// Field.
    pub field: &'static str,
    /// Value given.
    pub value: String,
    /// What was expected.
    pub expected: String,
}

impl CorruptionError {
    fn new(field: &'static str, value: impl fmt::Display, expected: impl Into<String>) -> Self {
        Self {
            field,
            value: value.to_string(),
            expected: expected.into(),
        }
    }
}

/// Applies an observation fault to the input window of corrupted queries, keeping what the
/// fault needs across queries (the frozen frame).
#[derive(Debug, Clone)]
pub struct ObservationCorruptor {
    fault: SensorFault,
    /// The loaded patch of a [`SensorFault::Patch`].
    patch: Option<mte_sim::Patch>,
    /// Exteroceptive frame held while the camera is frozen.
    frozen: Option<Observation>,
}

impl ObservationCorruptor {
    /// A corruptor for `fault`.
    pub fn new(fault: SensorFault) -> Self {
        Self {
            fault,
            patch: None,
            frozen: None,
        }
    }

    /// A corruptor for [`SensorFault::Patch`] with its patch already loaded
    /// ([`crate::patch_file::load`]).
    pub fn with_patch(fault: SensorFault, patch: mte_sim::Patch) -> Self {
        Self {
            patch: Some(patch),
            ..Self::new(fault)
        }
    }

    /// How many control-rate frames before the window the fault may read (stale: 1, blur:
    /// `length - 1`, frozen: the runner passes the last clean frame separately).
    pub fn frames_needed(&self, t_o: usize) -> usize {
        match self.fault {
            SensorFault::Stale => t_o + 1,
            SensorFault::MotionBlur { length } => t_o + length.saturating_sub(1),
            _ => t_o,
        }
    }

    /// The window the policy sees at a query. `frames` holds the clean control-rate
    /// observations, oldest first, the last `t_o` being the query's own window (at least
    /// [`frames_needed`](Self::frames_needed) of them, the first repeated at episode
    /// start). `corrupted` says whether this query is struck; a clean query also ends a
    /// freeze. `image_size` is (width, height) of image observations.
    pub fn window(
        &mut self,
        frames: &[Observation],
        t_o: usize,
        corrupted: bool,
        image_size: Option<(usize, usize)>,
        rng: &mut dyn RngCore,
    ) -> Vec<Observation> {
        let n = frames.len();
        debug_assert!(n >= t_o);
        let mut win: Vec<Observation> = frames[n - t_o..].to_vec();
        if !corrupted {
            self.frozen = None;
            return win;
        }
        match self.fault {
            SensorFault::Blank => win.iter_mut().for_each(blank),
            SensorFault::Stale => {
                let prev = &frames[n.saturating_sub(2)];
                copy_extero(prev, &mut win[t_o - 1]);
            }
            SensorFault::Frozen => {
                // The frame before the burst: the newest frame of the window preceding this
                // query's newest frame, captured at the first corrupted query.
                let held = self
                    .frozen
                    .get_or_insert_with(|| frames[n.saturating_sub(2)].clone())
                    .clone();
                for o in &mut win {
                    copy_extero(&held, o);
                }
            }
            SensorFault::Patch { .. } => {
                if let (Some(p), Some((w, h))) = (&self.patch, image_size) {
                    for o in &mut win {
                        if let Some(img) = o.image.as_mut() {
                            // The runner checked the frame size when it loaded the patch.
                            let _ = p.draw(img, w, h);
                        }
                    }
                }
            }
            SensorFault::Occluder { size } => {
                let (ux, uy) = (rng.random::<f64>(), rng.random::<f64>());
                for o in &mut win {
                    occlude(o, size, ux, uy, image_size);
                }
            }
            SensorFault::MotionBlur { length } => {
                let angle = rng.random::<f64>() * std::f64::consts::TAU;
                for (k, o) in win.iter_mut().enumerate() {
                    if let Some((w, h)) = image_size {
                        for img in o.image.iter_mut().chain(o.wrist_image.iter_mut()) {
                            blur_image(img, w, h, length, angle);
                        }
                    }
                    // The keypoints: the mean of the last `length` frames ending at this one.
                    let end = n - t_o + k + 1;
                    if let Some(kp) = o.env_state.as_mut() {
                        mean_keypoints(&frames[end.saturating_sub(length)..end], kp);
                    }
                }
            }
            SensorFault::GaussianNoise { sigma } => {
                for o in &mut win {
                    add_noise(o, sigma, rng);
                }
            }
        }
        win
    }
}

/// A blank frame: every camera black, every keypoint zero (proprioception untouched).
fn blank(o: &mut Observation) {
    for img in o.image.iter_mut().chain(o.wrist_image.iter_mut()) {
        img.fill(0);
    }
    if let Some(kp) = o.env_state.as_mut() {
        kp.fill(0.0);
    }
}

/// `kp` set to the coordinate-wise mean of the keypoints of `src` (a frame without keypoints
/// counts as zeros).
fn mean_keypoints(src: &[Observation], kp: &mut [f32]) {
    for (j, v) in kp.iter_mut().enumerate() {
        let s: f64 = src
            .iter()
            .map(|f| f64::from(f.env_state.as_ref().map_or(0.0, |e| e[j])))
            .sum();
        *v = (s / src.len() as f64) as f32;
    }
}

/// Zero-mean Gaussian noise on the exteroceptive channels: `sigma` of the full range on
/// pixels (`sigma * 255` grey levels, rounded and clamped to `0..=255`), `sigma` in the
/// keypoints' own units. The scene camera's pixels draw first, then the wrist camera's, then
/// the keypoints.
fn add_noise(o: &mut Observation, sigma: f64, rng: &mut dyn RngCore) {
    if let Ok(nd) = Normal::new(0.0, sigma * 255.0) {
        for img in o.image.iter_mut().chain(o.wrist_image.iter_mut()) {
            for p in img.iter_mut() {
                let v = f64::from(*p) + nd.sample(rng);
                *p = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    if let (Some(kp), Ok(nd)) = (o.env_state.as_mut(), Normal::new(0.0, sigma)) {
        for v in kp.iter_mut() {
            *v = (f64::from(*v) + nd.sample(rng)) as f32;
        }
    }
}

/// Copies the exteroceptive channels (cameras, keypoints) of `src` into `dst`.
fn copy_extero(src: &Observation, dst: &mut Observation) {
    dst.image.clone_from(&src.image);
    dst.wrist_image.clone_from(&src.wrist_image);
    dst.env_state.clone_from(&src.env_state);
}

/// Blacks out a `size` square whose top-left corner sits at fraction (`ux`, `uy`) of the
/// free range; keypoints inside the same square of the workspace read zero.
fn occlude(o: &mut Observation, size: usize, ux: f64, uy: f64, image_size: Option<(usize, usize)>) {
    if let (Some(img), Some((w, h))) = (o.image.as_mut(), image_size) {
        let s = size.min(w).min(h);
        let x0 = (ux * (w - s) as f64).floor() as usize;
        let y0 = (uy * (h - s) as f64).floor() as usize;
        for y in y0..y0 + s {
            img[(y * w + x0) * 3..(y * w + x0 + s) * 3].fill(0);
        }
    }
    if let Some(kp) = o.env_state.as_mut() {
        // The square in workspace pixels, taking a 96-pixel camera when no image is
        // rendered (the dataset's default).
        let side = image_size.map_or(96.0, |(w, _)| w as f64);
        let s = (size as f64 * WORKSPACE / side).min(WORKSPACE);
        let (x0, y0) = (ux * (WORKSPACE - s), uy * (WORKSPACE - s));
        for p in kp.chunks_exact_mut(2) {
            let (x, y) = (f64::from(p[0]), f64::from(p[1]));
            if (x0..x0 + s).contains(&x) && (y0..y0 + s).contains(&y) {
                p[0] = 0.0;
                p[1] = 0.0;
            }
        }
    }
}

/// Box blur of `length` taps along `angle`, sampling nearest pixels, clamped at the edges.
fn blur_image(img: &mut [u8], w: usize, h: usize, length: usize, angle: f64) {
    if length <= 1 {
        return;
    }
    let src = img.to_vec();
    let (dx, dy) = (angle.cos(), angle.sin());
    let half = (length as f64 - 1.0) / 2.0;
    let offsets: Vec<(isize, isize)> = (0..length)
        .map(|k| {
            let s = k as f64 - half;
            ((s * dx).round() as isize, (s * dy).round() as isize)
        })
        .collect();
    for y in 0..h {
        for x in 0..w {
            let mut acc = [0u32; 3];
            for &(ox, oy) in &offsets {
                let sx = (x as isize + ox).clamp(0, w as isize - 1) as usize;
                let sy = (y as isize + oy).clamp(0, h as isize - 1) as usize;
                let i = (sy * w + sx) * 3;
                for c in 0..3 {
                    acc[c] += u32::from(src[i + c]);
                }
            }
            let i = (y * w + x) * 3;
            for c in 0..3 {
                img[i + c] = ((acc[c] + length as u32 / 2) / length as u32) as u8;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn frame(v: u8, kp: f32) -> Observation {
        Observation {
            state: vec![1.0, 2.0],
            env_state: Some(vec![kp; 16]),
            image: Some(vec![v; 8 * 8 * 3]),
            wrist_image: None,
        }
    }

    #[test]
    fn burst_schedule_follows_the_formula() {
        let s = Schedule::Burst {
            q: 2,
            phase: 1,
            period: None,
        };
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let hits: Vec<bool> = (0..14).map(|i| s.corrupts(i, i * 2, 7, &mut rng)).collect();
        for (i, &hit) in hits.iter().enumerate() {
            assert_eq!(hit, (i + 1) % 7 < 2, "query {i}");
        }
        assert_eq!(hits.iter().filter(|&&x| x).count(), 4);
    }

    #[test]
    fn dense_and_bernoulli_schedules() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let d = Schedule::Dense { start: 10, end: 20 };
        assert!(!d.corrupts(4, 8, 7, &mut rng));
        assert!(d.corrupts(5, 10, 7, &mut rng));
        assert!(!d.corrupts(10, 20, 7, &mut rng));
        let b = Schedule::Bernoulli { p: 0.3 };
        let n = (0..10_000)
            .filter(|&i| b.corrupts(i, i, 7, &mut rng))
            .count();
        assert!((2700..3300).contains(&n), "{n}");
        assert!(Schedule::Bernoulli { p: 1.5 }.validate().is_err());
        assert!(Schedule::Dense { start: 5, end: 1 }.validate().is_err());
    }

    #[test]
    fn faults_touch_only_the_exteroceptive_channel_of_corrupted_queries() {
        let frames = vec![frame(10, 1.0), frame(20, 2.0), frame(30, 3.0)];
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mut blank = ObservationCorruptor::new(SensorFault::Blank);
        let clean = blank.window(&frames, 2, false, Some((8, 8)), &mut rng);
        assert_eq!(clean, frames[1..].to_vec());
        let w = blank.window(&frames, 2, true, Some((8, 8)), &mut rng);
        for o in &w {
            assert!(o.image.as_ref().is_some_and(|i| i.iter().all(|&p| p == 0)));
            assert!(
                o.env_state
                    .as_ref()
                    .is_some_and(|k| k.iter().all(|&v| v == 0.0))
            );
            assert_eq!(o.state, vec![1.0, 2.0]);
        }
        let mut stale = ObservationCorruptor::new(SensorFault::Stale);
        let w = stale.window(&frames, 2, true, Some((8, 8)), &mut rng);
        assert_eq!(w[1].image, frames[1].image);
        assert_eq!(w[0].image, frames[1].image);
    }

    #[test]
    fn frozen_camera_holds_the_frame_before_the_burst_until_a_clean_query() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut c = ObservationCorruptor::new(SensorFault::Frozen);
        let f1 = vec![frame(1, 1.0), frame(2, 2.0), frame(3, 3.0)];
        let w = c.window(&f1, 2, true, Some((8, 8)), &mut rng);
        assert!(w.iter().all(|o| o.image == frame(2, 0.0).image));
        let f2 = vec![frame(3, 3.0), frame(4, 4.0), frame(5, 5.0)];
        let w = c.window(&f2, 2, true, Some((8, 8)), &mut rng);
        assert!(
            w.iter().all(|o| o.image == frame(2, 0.0).image),
            "still frozen"
        );
        let w = c.window(&f2, 2, false, Some((8, 8)), &mut rng);
        assert_eq!(w, f2[1..].to_vec());
        let w = c.window(&f2, 2, true, Some((8, 8)), &mut rng);
        assert!(
            w.iter().all(|o| o.image == frame(4, 0.0).image),
            "a new freeze"
        );
    }

    #[test]
    fn camera_faults_strike_the_wrist_camera_and_scene_faults_do_not() {
        let with_wrist = |v: u8, w: u8| Observation {
            wrist_image: Some(vec![w; 8 * 8 * 3]),
            ..frame(v, 1.0)
        };
        let frames = vec![with_wrist(10, 20), with_wrist(30, 40), with_wrist(50, 60)];
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let zeros = |img: &Option<Vec<u8>>| {
            img.as_ref()
                .map_or(0, |i| i.iter().filter(|&&p| p == 0).count())
        };
        let mut blank = ObservationCorruptor::new(SensorFault::Blank);
        for o in blank.window(&frames, 2, true, Some((8, 8)), &mut rng) {
            assert_eq!(zeros(&o.image), 8 * 8 * 3);
            assert_eq!(zeros(&o.wrist_image), 8 * 8 * 3);
        }
        // Stale: the newest frame is the previous one, for both cameras alike.
        let mut stale = ObservationCorruptor::new(SensorFault::Stale);
        let w = stale.window(&frames, 2, true, Some((8, 8)), &mut rng);
        assert_eq!(w[1].image, frames[1].image);
        assert_eq!(w[1].wrist_image, frames[1].wrist_image);
        let mut occ = ObservationCorruptor::new(SensorFault::Occluder { size: 3 });
        for (o, f) in occ
            .window(&frames, 2, true, Some((8, 8)), &mut rng)
            .iter()
            .zip(&frames[1..])
        {
            assert_eq!(zeros(&o.image), 3 * 3 * 3);
            assert_eq!(
                o.wrist_image, f.wrist_image,
                "the occluder sits in the scene"
            );
        }
        let mut noise = ObservationCorruptor::new(SensorFault::GaussianNoise { sigma: 0.2 });
        for (o, f) in noise
            .window(&frames, 2, true, Some((8, 8)), &mut rng)
            .iter()
            .zip(&frames[1..])
        {
            assert_ne!(o.wrist_image, f.wrist_image);
        }
    }

    #[test]
    fn occluder_blacks_out_exactly_a_square() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let mut c = ObservationCorruptor::new(SensorFault::Occluder { size: 3 });
        let frames = vec![frame(200, 100.0), frame(200, 100.0)];
        let w = c.window(&frames, 2, true, Some((8, 8)), &mut rng);
        for o in &w {
            let zeros = o
                .image
                .as_ref()
                .map_or(0, |i| i.iter().filter(|&&p| p == 0).count());
            assert_eq!(zeros, 3 * 3 * 3);
        }
        assert_eq!(w[0].image, w[1].image, "one position per query");
        assert!(SensorFault::Occluder { size: 0 }.validate().is_err());
    }

    #[test]
    fn a_patch_is_drawn_into_every_frame_of_corrupted_queries_only() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        // 2 x 2 patch at world (256, 256): frame (3, 3) of an 8 x 8 frame.
        let patch = mte_sim::Patch::new(vec![7; 12], 2, [256.0, 256.0]).expect("patch");
        let fault = SensorFault::Patch {
            path: "p/my-patch".into(),
            step: None,
        };
        assert_eq!(Fault::from(fault.clone()).to_string(), "patch-my-patch");
        let mut c = ObservationCorruptor::with_patch(fault, patch);
        let frames = vec![frame(200, 100.0), frame(200, 100.0)];
        for o in c.window(&frames, 2, true, Some((8, 8)), &mut rng) {
            let img = o.image.expect("image");
            for (i, &v) in img.iter().enumerate() {
                let (x, y) = ((i / 3) % 8, i / 24);
                let inside = (3..5).contains(&x) && (3..5).contains(&y);
                assert_eq!(v, if inside { 7 } else { 200 }, "pixel ({x}, {y})");
            }
        }
        let clean = c.window(&frames, 2, false, Some((8, 8)), &mut rng);
        assert!(clean.iter().all(|o| {
            o.image
                .as_ref()
                .is_some_and(|i| i.iter().all(|&p| p == 200))
        }));
    }

    #[test]
    fn motion_blur_preserves_a_flat_image_and_averages_keypoints() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut c = ObservationCorruptor::new(SensorFault::MotionBlur { length: 3 });
        let frames = vec![
            frame(90, 0.0),
            frame(90, 3.0),
            frame(90, 6.0),
            frame(90, 9.0),
        ];
        let w = c.window(&frames, 2, true, Some((8, 8)), &mut rng);
        assert!(
            w.iter()
                .all(|o| o.image.as_ref().is_some_and(|i| i.iter().all(|&p| p == 90)))
        );
        assert_eq!(w[0].env_state.as_ref().map(|k| k[0]), Some(3.0));
        assert_eq!(w[1].env_state.as_ref().map(|k| k[0]), Some(6.0));
        let mut img = vec![0u8; 8 * 8 * 3];
        img[(4 * 8 + 4) * 3] = 255;
        blur_image(&mut img, 8, 8, 3, 0.0);
        assert_eq!(img[(4 * 8 + 3) * 3], 85);
        assert_eq!(img[(4 * 8 + 5) * 3], 85);
        assert_eq!(img[(4 * 8 + 4) * 3], 85);
    }

    #[test]
    fn gaussian_noise_is_seeded_and_clamped() {
        let frames = vec![frame(250, 0.0), frame(5, 0.0)];
        let run = |seed| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            ObservationCorruptor::new(SensorFault::GaussianNoise { sigma: 0.2 }).window(
                &frames,
                2,
                true,
                Some((8, 8)),
                &mut rng,
            )
        };
        assert_eq!(run(7), run(7));
        assert_ne!(run(7), run(8));
        assert!(
            SensorFault::GaussianNoise { sigma: f64::NAN }
                .validate()
                .is_err()
        );
    }

    #[test]
    fn a_patch_s_declared_step_is_its_budget_and_leaves_its_id_alone() {
        let parse = |j: &str| serde_json::from_str::<Fault>(j).map_err(|e| e.to_string());
        let bare = parse(r#"{"kind":"patch","path":"p/sign"}"#).expect("bare");
        let stepped = parse(r#"{"kind":"patch","path":"p/sign","step":1.5e-3}"#).expect("step");
        assert_eq!((bare.budget(), stepped.budget()), (None, Some(1.5e-3)));
        assert_eq!(
            bare.to_string(),
            stepped.to_string(),
            "the cell id is the path's"
        );
        // Written back without a `step` where there is none, so old specs round-trip.
        let j = serde_json::to_string(&bare).expect("json");
        assert!(!j.contains("step"), "{j}");
        let j = serde_json::to_string(&stepped).expect("json");
        assert_eq!(parse(&j), Ok(stepped));
        for bad in [0.0, -1e-3, f64::NAN, f64::INFINITY] {
            let f = SensorFault::Patch {
                path: "p".into(),
                step: Some(bad),
            };
            let e = f.validate().expect_err("a bad step");
            assert!(e.to_string().contains("fault.step"), "{e}");
        }
    }

    #[test]
    fn the_flat_wire_form_maps_onto_the_typed_kinds() {
        let parse = |j: &str| serde_json::from_str::<Fault>(j).map_err(|e| e.to_string());
        let cases: Vec<(&str, Fault)> = vec![
            (r#"{"kind":"none"}"#, Fault::None),
            (r#"{"kind":"blank"}"#, SensorFault::Blank.into()),
            (r#"{"kind":"frozen"}"#, SensorFault::Frozen.into()),
            (
                r#"{"kind":"motion-blur","length":5}"#,
                SensorFault::MotionBlur { length: 5 }.into(),
            ),
            (
                r#"{"kind":"oracle","mode":"drift"}"#,
                CandidateCorruption::Oracle {
                    mode: OracleMode::Drift,
                }
                .into(),
            ),
            (
                r#"{"kind":"common-mode","magnitude":8.0,"angle_deg":90.0}"#,
                CandidateCorruption::CommonMode {
                    magnitude: 8.0,
                    angle_deg: 90.0,
                    direction: BiasDirection::Constant,
                }
                .into(),
            ),
            (
                r#"{"kind":"common-mode","magnitude":8.0,"angle_deg":0.0,
                    "direction":{"kind":"drift","deg_per_step":0.5}}"#,
                CandidateCorruption::CommonMode {
                    magnitude: 8.0,
                    angle_deg: 0.0,
                    direction: BiasDirection::Drift { deg_per_step: 0.5 },
                }
                .into(),
            ),
            (
                r#"{"kind":"common-mode","magnitude":8.0,"angle_deg":0.0,
                    "direction":{"kind":"random"}}"#,
                CandidateCorruption::CommonMode {
                    magnitude: 8.0,
                    angle_deg: 0.0,
                    direction: BiasDirection::Random,
                }
                .into(),
            ),
        ];
        for (json, want) in cases {
            assert_eq!(parse(json).as_ref(), Ok(&want), "{json}");
            let back = serde_json::to_string(&want).unwrap_or_default();
            assert_eq!(parse(&back).as_ref(), Ok(&want), "{back}");
        }
        let pgd = parse(r#"{"kind":"pgd","eps":0.05,"iterations":3}"#);
        assert!(
            matches!(pgd, Ok(Fault::Query(QueryAttack::Pgd(ref c))) if c.iterations == 3),
            "{pgd:?}"
        );
        let e = parse(r#"{"kind":"occluder","size":4,"colour":1}"#).expect_err("unknown field");
        assert!(e.contains("colour"), "{e}");
    }

    #[test]
    fn specs_round_trip_and_name_themselves() {
        let s = CorruptionSpec {
            fault: SensorFault::Occluder { size: 24 }.into(),
            schedule: Schedule::Burst {
                q: 2,
                phase: 0,
                period: None,
            },
        };
        let j = serde_json::to_string(&s).unwrap_or_default();
        let back: CorruptionSpec = serde_json::from_str(&j).unwrap_or(CorruptionSpec::CLEAN);
        assert_eq!(back, s);
        assert_eq!(s.to_string(), "occluder-24-burst-q2");
        assert_eq!(s.q(), 2);
        // A nonzero phase and a period are part of the name (cell ids, resumed runs).
        let later = CorruptionSpec {
            schedule: Schedule::Burst {
                q: 2,
                phase: 3,
                period: Some(9),
            },
            ..s.clone()
        };
        assert_eq!(later.to_string(), "occluder-24-burst-q2-ph3-per9");
        assert_eq!(CorruptionSpec::CLEAN.to_string(), "clean");
        assert_eq!(CorruptionSpec::CLEAN.q(), 0);
    }

    #[test]
    fn pgd_labels_name_every_non_default_parameter() {
        let pgd = |c: mte_policy::PgdConfig| Fault::Query(QueryAttack::Pgd(c)).to_string();
        let d = mte_policy::PgdConfig::default();
        assert_eq!(pgd(d.clone()), format!("pgd-{}", d.iterations));
        let wide = mte_policy::PgdConfig {
            eps: 0.1,
            step: 0.00625,
            iterations: 20,
            ..d.clone()
        };
        assert_eq!(pgd(wide.clone()), "pgd-20-eps0.1-step0.00625");
        let narrow = mte_policy::PgdConfig {
            iterations: 20,
            ..d.clone()
        };
        assert_ne!(pgd(wide), pgd(narrow));
        let other = mte_policy::PgdConfig {
            samples: 8,
            random_start: !d.random_start,
            ..d
        };
        assert!(pgd(other).ends_with("-s8-rs"));
    }
}
