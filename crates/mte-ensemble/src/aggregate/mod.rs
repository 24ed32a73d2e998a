//! Aggregators: how the candidates for one control time become one action.
//!
//! Every aggregator implements [`Aggregate`]; [`Aggregator`] is the enum of the built-in ones,
//! parsed from a short text form (`median`, `ewm:0.01`, `trimmed-medoid:2`, ...) and
//! (de)serialised as that same string. Candidates arrive **oldest first** (row 0 came from
//! the earliest query), which is what the weight conventions below refer to.

mod geometric;
mod medoid;
mod rank;
mod select;
mod weighted;

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::error::{AggregateError, ParseAggregatorError};
use crate::network::{self, NETWORK_MAX};

/// The exponential-weight coefficient of ACT's temporal ensembling, `m = 0.01`
/// (ACT `imitate_episodes.py`; LeRobot `configuration_act.py`, `temporal_ensemble_coeff`).
pub const DEFAULT_EWM_M: f64 = 0.01;

/// Default iteration bound of the geometric median (Weiszfeld). At `M <= 16` and the
/// relative tolerance 1e-9 it converges in under 30 iterations on our streams; the bound
/// caps the worst case (an estimate stuck on a data point) for real-time use.
pub const DEFAULT_GEOMEDIAN_ITERS: usize = 64;

/// Relative step size below which Weiszfeld iterations stop.
const GEOMEDIAN_TOL: f64 = 1e-9;

/// A read-only view of `len` candidate actions of dimension `dim`, row-major,
/// **oldest first**, every value finite. Rows may be padded to a `stride >= dim` (the
/// ensembler pads to 4 lanes for SIMD); padding lanes are finite and ignored.
#[derive(Debug, Clone, Copy)]
pub struct Candidates<'a> {
    values: &'a [f32],
    dim: usize,
    stride: usize,
}

impl<'a> Candidates<'a> {
    /// Wraps `values` (row-major, `len * dim` values, oldest candidate first).
    ///
    /// Errors when `dim == 0`, the length is not a multiple of `dim`, the set is empty, or a
    /// value is NaN or infinite (exclude such candidates first: see
    /// [`TemporalEnsembler`](crate::TemporalEnsembler), which does).
    pub fn new(values: &'a [f32], dim: usize) -> Result<Self, AggregateError> {
        if dim == 0 || !values.len().is_multiple_of(dim) {
            return Err(AggregateError::Shape {
                len: values.len(),
                dim,
            });
        }
        if values.is_empty() {
            return Err(AggregateError::Empty);
        }
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(AggregateError::NonFinite {
                row: i / dim,
                col: i % dim,
            });
        }
        Ok(Self {
            values,
            dim,
            stride: dim,
        })
    }

    /// Wraps values the caller has already checked (finite, whole rows of `stride >= dim`
    /// values; non-empty, except the empty set of
    /// [`TemporalEnsembler::last_candidates`](crate::TemporalEnsembler::last_candidates)).
    pub(crate) fn from_checked(values: &'a [f32], dim: usize, stride: usize) -> Self {
        debug_assert!(dim > 0 && stride >= dim);
        debug_assert!(values.len().is_multiple_of(stride));
        debug_assert!(values.iter().all(|v| v.is_finite()));
        Self {
            values,
            dim,
            stride,
        }
    }

    /// Number of candidates `M`.
    pub fn len(&self) -> usize {
        self.values.len() / self.stride
    }

    /// False for every set an aggregator is given (at least one candidate); true only for
    /// [`TemporalEnsembler::last_candidates`](crate::TemporalEnsembler::last_candidates)
    /// before a successful step.
    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// Action dimension `d`.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Values per row in [`values`](Self::values), `>= dim`.
    pub fn stride(&self) -> usize {
        self.stride
    }

    /// Candidate `i` (0 = oldest), `dim` values.
    #[inline]
    pub fn row(&self, i: usize) -> &'a [f32] {
        &self.values[i * self.stride..i * self.stride + self.dim]
    }

    /// All values, row-major with [`stride`](Self::stride) values per row.
    pub fn values(&self) -> &'a [f32] {
        self.values
    }
}

/// Pre-allocated scratch memory for aggregating up to `capacity` candidates of dimension up
/// to `dim`. Built once; aggregation then never allocates.
#[derive(Debug, Clone)]
pub struct Workspace {
    capacity: usize,
    dim: usize,
    /// Row stride of `rows`: `dim` rounded up to 4 lanes.
    stride: usize,
    rows: Vec<f32>,
    /// Order keys of `rows` for the lane-wise selection (`select`).
    keys: Vec<i32>,
    /// The lower and upper central values of one lane-wise selection, `2 * stride`.
    central: Vec<f32>,
    col: Vec<f32>,
    pairs: Vec<(f32, f64)>,
    dist: Vec<f64>,
    score: Vec<f64>,
    keep: Vec<bool>,
    acc: Vec<f64>,
    acc2: Vec<f64>,
    /// `decay[k] = exp(-decay_m * k)`, cached for the last coefficient used.
    decay: Vec<f64>,
    decay_m: f64,
    /// `decay_totals[o][n]`: the sum of the `n` weights [`exp_weights`](Self::exp_weights)
    /// makes in order `o` (0 oldest-heavy, 1 newest-heavy) for `decay_m`, NaN until first
    /// needed: summing 100 weights is a chain of dependent adds that cost more than the
    /// weighted rows themselves, and `n` alternates between steps at `h > 1`.
    decay_totals: [Vec<f64>; 2],
    /// `median_nets[n]`: the pruned median network for `n` rows.
    median_nets: Vec<Vec<(u16, u16)>>,
}

impl Workspace {
    /// Scratch for up to `capacity` candidates of dimension up to `dim`.
    pub fn new(capacity: usize, dim: usize) -> Self {
        let nets = (0..=capacity.min(NETWORK_MAX))
            .map(network::median_network)
            .collect();
        let stride = dim.div_ceil(4) * 4;
        Self {
            capacity,
            dim,
            stride,
            rows: vec![0.0; capacity * stride],
            keys: vec![0; capacity * stride],
            central: vec![0.0; 2 * stride],
            col: vec![0.0; capacity],
            pairs: vec![(0.0, 0.0); capacity],
            dist: vec![0.0; capacity * capacity],
            score: vec![0.0; capacity],
            keep: vec![false; capacity],
            acc: vec![0.0; stride],
            acc2: vec![0.0; dim],
            decay: vec![1.0; capacity],
            decay_m: 0.0,
            decay_totals: [vec![f64::NAN; capacity + 1], vec![f64::NAN; capacity + 1]],
            median_nets: nets,
        }
    }

    /// Largest candidate count this workspace serves.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Fills `into` with the weights `w_0, w_1, ...` of `r`, the very values (bits) the
    /// built-in means apply to the candidates at those positions.
    pub(crate) fn running_weights_into(&mut self, r: RunningWeights, into: &mut [f64]) {
        match r {
            RunningWeights::Uniform => into.fill(1.0),
            RunningWeights::Decay { m } => {
                self.ensure_decay(m);
                into.copy_from_slice(&self.decay[..into.len()]);
            }
        }
    }

    /// Makes `decay[k] = exp(-|m| k)`, recomputing only when `|m|` changed since last time.
    fn ensure_decay(&mut self, m: f64) {
        let m = m.abs();
        if m != self.decay_m {
            for (k, w) in self.decay.iter_mut().enumerate() {
                *w = (-m * k as f64).exp();
            }
            self.decay_m = m;
            self.decay_totals.iter_mut().for_each(|t| t.fill(f64::NAN));
        }
    }

    /// The oldest-heavy exponential weights `exp(-|m| i)` of `n` candidates, left in
    /// `decay[..n]` (nothing copied), and their sum as [`exp_weights`](Self::exp_weights)
    /// returns it.
    fn decay_weights(&mut self, m: f64, n: usize) -> f64 {
        self.ensure_decay(m);
        let known = &mut self.decay_totals[0][n];
        if known.is_nan() {
            *known = self.decay[..n].iter().fold(0.0, |t, &x| t + x);
        }
        *known
    }

    /// Fills `score[..n]` with exponential weights for `n` oldest-first candidates:
    /// `exp(-|m| i)` when `oldest_heavy`, else `exp(-|m| (n - 1 - i))`, and returns their sum
    /// taken in candidate order from 0 (remembered for the same `m`, `n` and order).
    fn exp_weights(&mut self, m: f64, n: usize, oldest_heavy: bool) -> f64 {
        self.ensure_decay(m);
        let (decay, w) = (&self.decay[..n], &mut self.score[..n]);
        if oldest_heavy {
            w.copy_from_slice(decay);
        } else {
            for (wi, di) in w.iter_mut().zip(decay.iter().rev()) {
                *wi = *di;
            }
        }
        let known = &mut self.decay_totals[usize::from(!oldest_heavy)][n];
        if known.is_nan() {
            *known = w.iter().fold(0.0, |t, &x| t + x);
        }
        *known
    }

    fn check(&self, c: &Candidates<'_>, out: &[f32]) -> Result<(), AggregateError> {
        if out.len() != c.dim() {
            return Err(AggregateError::OutputDimension {
                expected: c.dim(),
                got: out.len(),
            });
        }
        if c.len() > self.capacity || c.dim() > self.dim || c.stride() > self.stride {
            return Err(AggregateError::WorkspaceTooSmall {
                capacity: self.capacity,
                dim: self.dim,
                len: c.len(),
                got_dim: c.dim(),
            });
        }
        Ok(())
    }
}

/// One way of turning the candidate set for a control time into an action.
///
/// Implementations must not allocate: all scratch memory comes from the [`Workspace`].
/// Candidates are finite and oldest first; `out` has `c.dim()` coordinates.
pub trait Aggregate {
    /// Writes the aggregate of `c` into `out`.
    fn aggregate(
        &self,
        c: &Candidates<'_>,
        ws: &mut Workspace,
        out: &mut [f32],
    ) -> Result<(), AggregateError>;

    /// `Some` when this aggregate is a weighted mean whose weight depends only on a
    /// candidate's position among the finite candidates, oldest first, and which
    /// [`aggregate`](Self::aggregate) computes as `Σ_i w_i x_i / Σ_i w_i` in f64, summed in
    /// candidate order from zero (as every built-in mean does). A
    /// [`TemporalEnsembler`](crate::TemporalEnsembler) then keeps these sums per control time
    /// as chunks arrive, and a step reads them instead of gathering its candidates: the same
    /// bits, at ACT's `M = 100` without the gather. The default, `None`, always gathers.
    fn running_weights(&self) -> Option<RunningWeights> {
        None
    }
}

/// `A`'s aggregate without its running weights, so that a
/// [`TemporalEnsembler`](crate::TemporalEnsembler) gathers the candidates at every step: the
/// reference path beside the running sums, for tests and benchmarks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gathered<A>(pub A);

impl<A: Aggregate> Aggregate for Gathered<A> {
    fn aggregate(
        &self,
        c: &Candidates<'_>,
        ws: &mut Workspace,
        out: &mut [f32],
    ) -> Result<(), AggregateError> {
        self.0.aggregate(c, ws, out)
    }
}

/// The weights of a mean that can be summed as candidates arrive (see
/// [`Aggregate::running_weights`]): `w_i` for the `i`-th finite candidate, oldest first.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RunningWeights {
    /// `w_i = 1`: the uniform mean.
    Uniform,
    /// `w_i = exp(-|m| i)`: older candidates weigh more (ACT's and LeRobot's `ewm`).
    Decay {
        /// The decay coefficient `m` (its magnitude is used).
        m: f64,
    },
}

/// Which candidate gets exponential weight index `k = 0`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum WeightOrder {
    /// `k = 0` is the **oldest** candidate: ACT's original code and LeRobot's
    /// `ACTTemporalEnsembler`. With `m > 0` older predictions weigh more. The default,
    /// because it is what deployed systems run.
    #[default]
    OldestFirst,
    /// `k = 0` is the **newest** candidate (`k` = age), as the paper writes it. With `m > 0`
    /// newer predictions weigh more.
    NewestFirst,
}

/// How the coordinate-wise median resolves an even number of candidates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum MedianTie {
    /// Average of the two central order statistics (the paper's definition).
    #[default]
    Average,
    /// The lower central order statistic.
    Lower,
    /// The upper central order statistic.
    Upper,
    /// Drop the oldest candidate, leaving an odd count with a unique median.
    DropOldest,
}

/// The built-in aggregators.
///
/// | text form | aggregator | bracket guarantee when `2q < M` |
/// |---|---|---|
/// | `ewm[:m]` (= `ewm-oldest[:m]`) | exp-weighted mean, `w_k = exp(-m k)`, `k = 0` oldest (ACT, LeRobot) | no |
/// | `ewm-newest[:m]` | exp-weighted mean, `k` = age, `0` newest (the paper's notation) | no |
/// | `mean` | uniform mean | no |
/// | `latest` | the newest candidate (no ensembling) | no |
/// | `median[:average\|lower\|upper\|drop-oldest]` | coordinate-wise median | **yes** |
/// | `medoid` | block medoid: candidate minimising the sum of Euclidean distances to the others | no (stays a candidate) |
/// | `trimmed-medoid:q` | drop the `q` candidates farthest from the rest, then the medoid | no |
/// | `trimmed-mean:k` | per coordinate, drop the `k` lowest and `k` highest, average the rest | yes if `k >= q` |
/// | `recency-median[:m]` | weighted coordinate-wise median, weights `exp(-m * age)` | if the corrupted weight is below half |
/// | `geomedian[:iters]` | geometric median (Weiszfeld from the coordinate-wise median) | no (breakdown 1/2 in norm) |
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Aggregator {
    /// Exponentially weighted mean, `w_k = exp(-m k)`, normalised over the candidates present.
    ExpWeightedMean {
        /// Decay coefficient `m` per index step (any finite value; 0 = uniform mean).
        m: f64,
        /// Which candidate has index 0.
        order: WeightOrder,
    },
    /// Uniform mean.
    Mean,
    /// The newest candidate.
    Latest,
    /// Coordinate-wise median.
    Median {
        /// Rule for an even candidate count.
        tie: MedianTie,
    },
    /// The candidate with the smallest sum of Euclidean distances to all others; ties go to
    /// the newest.
    BlockMedoid,
    /// Drop the `q` candidates with the largest distance sums (ties: oldest dropped first;
    /// at least one candidate is kept), then the medoid of the rest.
    TrimmedMedoid {
        /// Candidates to drop.
        q: usize,
    },
    /// Per coordinate, drop the `k` smallest and `k` largest values and average the rest;
    /// `k` is capped at `(M - 1) / 2`, so a large `k` becomes the median.
    TrimmedMean {
        /// Values trimmed from each end.
        k: usize,
    },
    /// Weighted coordinate-wise median with recency weights `exp(-m * age)` (age 0 = newest):
    /// the smallest value whose cumulative weight reaches half the total, averaged with the
    /// next when it reaches exactly half. `m = 0` is the median with the average tie rule.
    RecencyMedian {
        /// Decay per age step; `m > 0` favours newer candidates.
        m: f64,
    },
    /// Geometric median by Weiszfeld iterations from the coordinate-wise median.
    GeometricMedian {
        /// Iteration bound.
        max_iter: usize,
    },
}

impl Default for Aggregator {
    /// The deployed default: ACT/LeRobot's exp-weighted mean, `m = 0.01`, oldest first.
    fn default() -> Self {
        Self::ExpWeightedMean {
            m: DEFAULT_EWM_M,
            order: WeightOrder::OldestFirst,
        }
    }
}

impl Aggregator {
    /// The coordinate-wise median with the paper's tie rule.
    pub const MEDIAN: Self = Self::Median {
        tie: MedianTie::Average,
    };

    /// One of each built-in aggregator with its default parameters (`q`/`k` = 1 where a
    /// parameter has no natural default), in the order of the table above.
    pub fn catalogue() -> Vec<Aggregator> {
        vec![
            Self::default(),
            Self::ExpWeightedMean {
                m: DEFAULT_EWM_M,
                order: WeightOrder::NewestFirst,
            },
            Self::Mean,
            Self::Latest,
            Self::MEDIAN,
            Self::Median {
                tie: MedianTie::Lower,
            },
            Self::Median {
                tie: MedianTie::Upper,
            },
            Self::Median {
                tie: MedianTie::DropOldest,
            },
            Self::BlockMedoid,
            Self::TrimmedMedoid { q: 1 },
            Self::TrimmedMean { k: 1 },
            Self::RecencyMedian { m: 0.1 },
            Self::GeometricMedian {
                max_iter: DEFAULT_GEOMEDIAN_ITERS,
            },
        ]
    }

    /// Whether the output is guaranteed to stay inside the clean candidates' coordinate-wise
    /// range whenever fewer than half of the candidates are corrupted (`2q < M`).
    pub fn has_bracket_guarantee(&self) -> bool {
        matches!(self, Self::Median { .. })
    }

    /// Validates parameters: finite coefficients and a positive iteration bound.
    pub fn validate(&self) -> Result<(), ParseAggregatorError> {
        let bad = |reason: &str| {
            Err(ParseAggregatorError {
                input: self.to_string(),
                reason: reason.to_string(),
            })
        };
        match *self {
            Self::ExpWeightedMean { m, .. } | Self::RecencyMedian { m } if !m.is_finite() => {
                bad("the coefficient m must be a finite number")
            }
            Self::GeometricMedian { max_iter: 0 } => bad("the iteration bound must be at least 1"),
            _ => Ok(()),
        }
    }

    /// Aggregates `c` into a new vector, allocating a workspace: a convenience for offline
    /// use. Real-time code keeps a [`Workspace`] and calls [`Aggregate::aggregate`].
    pub fn aggregate_to_vec(&self, c: &Candidates<'_>) -> Result<Vec<f32>, AggregateError> {
        let mut ws = Workspace::new(c.len(), c.dim());
        let mut out = vec![0.0; c.dim()];
        self.aggregate(c, &mut ws, &mut out)?;
        Ok(out)
    }
}

impl Aggregate for Aggregator {
    fn aggregate(
        &self,
        c: &Candidates<'_>,
        ws: &mut Workspace,
        out: &mut [f32],
    ) -> Result<(), AggregateError> {
        ws.check(c, out)?;
        match *self {
            Self::ExpWeightedMean { m, order } => weighted::exp_weighted_mean(c, m, order, ws, out),
            Self::Mean => weighted::mean(c, ws, out),
            Self::Latest => out.copy_from_slice(c.row(c.len() - 1)),
            Self::Median { tie } => rank::median(c, tie, ws, out),
            Self::BlockMedoid => medoid::block_medoid(c, ws, out),
            Self::TrimmedMedoid { q } => medoid::trimmed_medoid(c, q, ws, out),
            Self::TrimmedMean { k } => rank::trimmed_mean(c, k, ws, out),
            Self::RecencyMedian { m } => rank::recency_median(c, m, ws, out),
            Self::GeometricMedian { max_iter } => geometric::geometric_median(c, max_iter, ws, out),
        }
        Ok(())
    }

    /// The uniform mean, and the exp-weighted mean whose heavier weights go to older
    /// candidates (`ewm:m` with `m >= 0`, the default, and `ewm-newest:m` with `m < 0`):
    /// `weighted::exp_weighted_mean` weighs those with `decay`, in candidate order. The
    /// newer-heavy mean's weights of a candidate change as newer ones arrive, so it gathers.
    fn running_weights(&self) -> Option<RunningWeights> {
        match *self {
            Self::Mean => Some(RunningWeights::Uniform),
            Self::ExpWeightedMean { m, order }
                if (order == WeightOrder::OldestFirst) == (m >= 0.0) =>
            {
                Some(RunningWeights::Decay { m })
            }
            _ => None,
        }
    }
}

impl fmt::Display for Aggregator {
    /// The canonical text form, which [`FromStr`] parses back to the same value.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::ExpWeightedMean {
                m,
                order: WeightOrder::OldestFirst,
            } => write!(f, "ewm:{m}"),
            Self::ExpWeightedMean {
                m,
                order: WeightOrder::NewestFirst,
            } => {
                write!(f, "ewm-newest:{m}")
            }
            Self::Mean => f.write_str("mean"),
            Self::Latest => f.write_str("latest"),
            Self::Median {
                tie: MedianTie::Average,
            } => f.write_str("median"),
            Self::Median {
                tie: MedianTie::Lower,
            } => f.write_str("median:lower"),
            Self::Median {
                tie: MedianTie::Upper,
            } => f.write_str("median:upper"),
            Self::Median {
                tie: MedianTie::DropOldest,
            } => f.write_str("median:drop-oldest"),
            Self::BlockMedoid => f.write_str("medoid"),
            Self::TrimmedMedoid { q } => write!(f, "trimmed-medoid:{q}"),
            Self::TrimmedMean { k } => write!(f, "trimmed-mean:{k}"),
            Self::RecencyMedian { m } => write!(f, "recency-median:{m}"),
            Self::GeometricMedian { max_iter } => write!(f, "geomedian:{max_iter}"),
        }
    }
}

const FORMS: &str = "one of mean, latest, median[:average|lower|upper|drop-oldest], ewm[:m], \
                     ewm-oldest[:m], ewm-newest[:m], medoid, trimmed-medoid:q, trimmed-mean:k, \
                     recency-median[:m], geomedian[:iters]";

impl FromStr for Aggregator {
    type Err = ParseAggregatorError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let err = |reason: String| ParseAggregatorError {
            input: s.to_string(),
            reason,
        };
        let text = s.trim().to_ascii_lowercase();
        let (name, arg) = match text.split_once(':') {
            Some((n, a)) => (n.trim(), Some(a.trim())),
            None => (text.as_str(), None),
        };
        let coef = |default: f64| -> Result<f64, ParseAggregatorError> {
            match arg {
                None => Ok(default),
                Some(a) => a
                    .parse::<f64>()
                    .ok()
                    .filter(|m| m.is_finite())
                    .ok_or_else(|| err(format!("coefficient {a:?} is not a finite number"))),
            }
        };
        let count = |what: &str, min: usize| -> Result<usize, ParseAggregatorError> {
            let a = arg.ok_or_else(|| err(format!("{name} needs {what}, e.g. {name}:1")))?;
            a.parse::<usize>()
                .ok()
                .filter(|v| *v >= min)
                .ok_or_else(|| err(format!("{what} {a:?} is not an integer >= {min}")))
        };
        let no_arg = |agg: Aggregator| match arg {
            None => Ok(agg),
            Some(a) => Err(err(format!("{name} takes no parameter, got {a:?}"))),
        };
        let agg = match name {
            "ewm" | "ewm-oldest" => Self::ExpWeightedMean {
                m: coef(DEFAULT_EWM_M)?,
                order: WeightOrder::OldestFirst,
            },
            "ewm-newest" => Self::ExpWeightedMean {
                m: coef(DEFAULT_EWM_M)?,
                order: WeightOrder::NewestFirst,
            },
            "mean" => no_arg(Self::Mean)?,
            "latest" => no_arg(Self::Latest)?,
            "median" => {
                let tie = match arg {
                    None | Some("average") => MedianTie::Average,
                    Some("lower") => MedianTie::Lower,
                    Some("upper") => MedianTie::Upper,
                    Some("drop-oldest") => MedianTie::DropOldest,
                    Some(a) => {
                        return Err(err(format!(
                            "median tie rule {a:?} is not one of average, lower, upper, drop-oldest"
                        )));
                    }
                };
                Self::Median { tie }
            }
            "medoid" | "block-medoid" => no_arg(Self::BlockMedoid)?,
            "trimmed-medoid" => Self::TrimmedMedoid {
                q: count("a drop count q", 0)?,
            },
            "trimmed-mean" => Self::TrimmedMean {
                k: count("a trim count k", 0)?,
            },
            "recency-median" => Self::RecencyMedian { m: coef(0.1)? },
            "geomedian" | "geometric-median" => Self::GeometricMedian {
                max_iter: if arg.is_some() {
                    count("an iteration bound", 1)?
                } else {
                    DEFAULT_GEOMEDIAN_ITERS
                },
            },
            other => {
                return Err(err(format!(
                    "unknown aggregator {other:?}; expected {FORMS}"
                )));
            }
        };
        Ok(agg)
    }
}

impl Serialize for Aggregator {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for Aggregator {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_forms_round_trip() {
        for agg in Aggregator::catalogue() {
            let text = agg.to_string();
            assert_eq!(text.parse::<Aggregator>().unwrap(), agg, "{text}");
            let json = serde_json::to_string(&agg).unwrap();
            assert_eq!(
                serde_json::from_str::<Aggregator>(&json).unwrap(),
                agg,
                "{json}"
            );
        }
    }

    #[test]
    fn short_forms_parse_to_the_documented_defaults() {
        assert_eq!("ewm".parse::<Aggregator>().unwrap(), Aggregator::default());
        assert_eq!(
            "ewm-newest:0.5".parse::<Aggregator>().unwrap(),
            Aggregator::ExpWeightedMean {
                m: 0.5,
                order: WeightOrder::NewestFirst
            }
        );
        assert_eq!("MEDIAN".parse::<Aggregator>().unwrap(), Aggregator::MEDIAN);
        assert_eq!(
            "trimmed-medoid:2".parse::<Aggregator>().unwrap(),
            Aggregator::TrimmedMedoid { q: 2 }
        );
        assert_eq!(
            "geomedian".parse::<Aggregator>().unwrap(),
            Aggregator::GeometricMedian {
                max_iter: DEFAULT_GEOMEDIAN_ITERS
            }
        );
    }

    #[test]
    fn bad_text_forms_name_the_value() {
        for (text, needle) in [
            ("medain", "unknown aggregator \"medain\""),
            ("ewm:abc", "\"abc\" is not a finite number"),
            ("ewm:nan", "not a finite number"),
            ("trimmed-medoid", "needs a drop count"),
            ("trimmed-mean:-1", "\"-1\" is not an integer"),
            ("median:middle", "\"middle\""),
            ("mean:3", "takes no parameter"),
            ("geomedian:0", "iteration bound \"0\""),
        ] {
            let e = text.parse::<Aggregator>().unwrap_err().to_string();
            assert!(e.contains(needle), "{text}: {e}");
        }
    }

    #[test]
    fn candidates_reject_bad_shapes_and_non_finite_values() {
        assert_eq!(
            Candidates::new(&[1.0, 2.0, 3.0], 2).unwrap_err(),
            AggregateError::Shape { len: 3, dim: 2 }
        );
        assert_eq!(Candidates::new(&[], 2).unwrap_err(), AggregateError::Empty);
        assert_eq!(
            Candidates::new(&[1.0, 2.0, f32::NAN, 0.0], 2).unwrap_err(),
            AggregateError::NonFinite { row: 1, col: 0 }
        );
    }

    #[test]
    fn workspace_rejects_oversized_sets() {
        let vals = [0.0f32; 6];
        let c = Candidates::new(&vals, 2).unwrap();
        let mut ws = Workspace::new(2, 2);
        let mut out = [0.0; 2];
        assert!(matches!(
            Aggregator::MEDIAN.aggregate(&c, &mut ws, &mut out),
            Err(AggregateError::WorkspaceTooSmall { .. })
        ));
        let mut short = [0.0; 1];
        let mut ws = Workspace::new(3, 2);
        assert_eq!(
            Aggregator::MEDIAN.aggregate(&c, &mut ws, &mut short),
            Err(AggregateError::OutputDimension {
                expected: 2,
                got: 1
            })
        );
    }

    /// The exp-weighted mean remembers its weights' sum per count, order and coefficient; a
    /// workspace reused across counts (as at h > 1), orders and coefficients must give the
    /// bits of a fresh workspace, whose sum is computed at the call.
    #[test]
    fn remembered_weight_sums_give_a_fresh_workspace_bits() {
        let dim = 3;
        let vals: Vec<f32> = (0..40 * dim)
            .map(|i| ((i * 37 % 101) as f32 * 0.731).sin() * 50.0)
            .collect();
        let mut reused = Workspace::new(40, dim);
        let steps = [
            (7, 0.01),
            (8, 0.01),
            (7, 0.01),
            (40, -0.3),
            (8, 0.5),
            (40, 0.01),
        ];
        for order in [WeightOrder::OldestFirst, WeightOrder::NewestFirst] {
            for &(n, m) in &steps {
                let c = Candidates::new(&vals[..n * dim], dim).unwrap();
                let agg = Aggregator::ExpWeightedMean { m, order };
                let (mut a, mut b) = ([0f32; 3], [0f32; 3]);
                agg.aggregate(&c, &mut reused, &mut a).unwrap();
                agg.aggregate(&c, &mut Workspace::new(40, dim), &mut b)
                    .unwrap();
                assert_eq!(
                    a.map(f32::to_bits),
                    b.map(f32::to_bits),
                    "{n} {m} {order:?}"
                );
            }
        }
    }
}
