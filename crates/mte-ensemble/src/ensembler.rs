//! The streaming temporal ensembler: a ring of live chunks keyed by absolute control time.

use std::fmt;

use serde::{Deserialize, Serialize};

use crate::aggregate::{Aggregate, Aggregator, Candidates, Workspace};
use crate::bracket::{self, BracketReport};
use crate::error::EnsembleError;
use crate::geometry::ChunkGeometry;
use crate::running::RunningSums;

/// What the caller knows about one query. The evaluator knows which queries it corrupted; a
/// deployed controller leaves the default (trusted).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
pub struct QueryMeta {
    /// Whether the query's observation was corrupted.
    pub corrupted: bool,
}

impl QueryMeta {
    /// A trusted query.
    pub const CLEAN: Self = Self { corrupted: false };
    /// A query known to be corrupted.
    pub const CORRUPTED: Self = Self { corrupted: true };
}

/// Where a step stands relative to the median's breakdown point, from the `q` corrupted
/// among the `M` aggregated candidates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Regime {
    /// `2q < M`: the coordinate-wise median is guaranteed inside the clean bracket.
    #[serde(rename = "2q<M")]
    Guaranteed,
    /// `2q = M`: a tie, no guarantee.
    #[serde(rename = "2q=M")]
    Tie,
    /// `2q > M`: corrupted candidates are the majority.
    #[serde(rename = "2q>M")]
    Exceeded,
}

impl Regime {
    /// The three regimes in table order.
    pub const ALL: [Regime; 3] = [Regime::Guaranteed, Regime::Tie, Regime::Exceeded];

    /// The regime of `q` corrupted among `m` candidates.
    pub fn of(q: usize, m: usize) -> Self {
        match (2 * q).cmp(&m) {
            std::cmp::Ordering::Less => Self::Guaranteed,
            std::cmp::Ordering::Equal => Self::Tie,
            std::cmp::Ordering::Greater => Self::Exceeded,
        }
    }

    /// Position in [`Regime::ALL`].
    pub fn index(self) -> usize {
        self as usize
    }
}

impl fmt::Display for Regime {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Guaranteed => "2q<M",
            Self::Tie => "2q=M",
            Self::Exceeded => "2q>M",
        })
    }
}

/// What happened at one control time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct StepReport {
    /// Control time of the action.
    pub tau: u64,
    /// `M(tau)`: chunks covering `tau`.
    pub m: usize,
    /// `q(tau)`: covering chunks flagged corrupted.
    pub q: usize,
    /// Candidates excluded for a NaN or infinite coordinate (counted in `m`).
    pub excluded: usize,
    /// Of the excluded, how many were flagged corrupted (counted in `q`).
    pub excluded_corrupted: usize,
    /// Regime of the candidates actually aggregated: `q - excluded_corrupted` corrupted
    /// among `m - excluded`.
    pub regime: Regime,
    /// Query time of the oldest covering chunk.
    pub oldest_query: u64,
    /// Query time of the newest covering chunk.
    pub newest_query: u64,
}

impl StepReport {
    /// Candidates aggregated, `m - excluded`.
    pub fn used(&self) -> usize {
        self.m - self.excluded
    }

    #[cfg(test)]
    pub(crate) fn for_test(m: usize, q: usize) -> Self {
        Self {
            tau: 0,
            m,
            q,
            excluded: 0,
            excluded_corrupted: 0,
            regime: Regime::of(q, m),
            oldest_query: 0,
            newest_query: 0,
        }
    }
}

/// The result of [`TemporalEnsembler::action`]: the action (borrowed from the ensembler),
/// the step report, and the bracket diagnostics when enabled and defined.
#[derive(Debug, Clone, Copy)]
pub struct Step<'a> {
    /// The aggregated action, `d` coordinates.
    pub action: &'a [f32],
    /// Counts and regime.
    pub report: StepReport,
    /// Bracket diagnostics ([`EnsemblerOptions::bracket_diagnostics`], and a clean candidate).
    pub bracket: Option<BracketReport>,
}

/// Construction options of a [`TemporalEnsembler`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct EnsemblerOptions {
    /// How many control steps after the last action served a query may be inserted.
    /// Default (`None`): the stride `h`, enough for a loop that asks for every control time
    /// or only for the query times. The ring holds `span + lookahead` chunks.
    pub lookahead: Option<usize>,
    /// Compute [`BracketReport`]s at every step (`O(M^2 d)` extra; evaluation only).
    pub bracket_diagnostics: bool,
}

/// SIMD width the candidate rows are padded to (4 f32 lanes: one SSE register).
const LANES: usize = 4;

/// One live chunk's bookkeeping.
#[derive(Debug, Clone, Copy, Default)]
struct ChunkSlot {
    t_query: u64,
    /// Chunks flagged corrupted inserted before this one since the last reset: the corrupted
    /// count of a run of live chunks is a difference of two of these.
    corrupted_before: u64,
    corrupted: bool,
    /// Whether every executable value is finite (else see `row_finite`).
    finite: bool,
}

/// Whether every value is finite, without an early exit so that it vectorises.
#[inline]
fn all_finite(values: &[f32]) -> bool {
    const EXP: u32 = 0x7f80_0000; // an all-ones exponent is infinity or NaN
    values
        .iter()
        .fold(0u32, |acc, v| acc | u32::from(v.to_bits() & EXP == EXP))
        == 0
}

/// [`all_finite`] in three lane operations per value (and, add, or), the form the wide
/// levels run fastest: a magnitude's bits (sign cleared) at or above an all-ones exponent
/// (infinity or NaN) carry into the sign bit when the exponent's lowest bit is added.
#[inline(always)]
fn all_finite_carry(values: &[f32]) -> bool {
    const EXP_LSB: u32 = 0x0080_0000;
    let acc = values.iter().fold(0u32, |acc, v| {
        acc | (v.to_bits() & 0x7fff_ffff).wrapping_add(EXP_LSB)
    });
    acc & 0x8000_0000 == 0
}

/// Rings of rows above this size (bytes) take the large-chunk paths: half a typical 32-48 KiB
/// L1 data cache.
const LARGE_RING_BYTES: usize = 16 * 1024;

/// [`all_finite`] for a whole chunk, compiled for AVX-512, AVX2 and the baseline and chosen
/// at run time: at ACT's `T_p = 100`, `d = 14` the baseline's 4-lane check of every inserted
/// chunk cost more than the copy it guards.
#[cfg_attr(
    not(feature = "cap-avx2"),
    multiversion::multiversion(targets("x86_64+avx512f+avx512vl", "x86_64+avx2", "aarch64+neon"))
)]
#[cfg_attr(
    feature = "cap-avx2",
    multiversion::multiversion(targets("x86_64+avx2", "aarch64+neon"))
)]
fn chunk_finite(values: &[f32]) -> bool {
    all_finite_carry(values)
}

/// Streaming temporal ensembler.
///
/// Insert each query's chunk with the **absolute control time** its query fired
/// ([`insert`](Self::insert)); ask for the action at each control time
/// ([`action`](Self::action)). Strides may vary, queries may be late or missing: the
/// candidate of a chunk from time `t` for control time `tau` is its row
/// `tau - t + t_o - 1`, defined for `0 <= tau - t <= t_p - t_o`.
///
/// Memory is fixed at construction; neither `insert` nor `action` allocates.
///
/// ```
/// use mte_ensemble::{Aggregator, ChunkGeometry, QueryMeta, TemporalEnsembler};
///
/// let g = ChunkGeometry::new(4, 1, 2)?; // 4-step chunks, re-queried every 2 steps
/// let mut ens = TemporalEnsembler::new(g, 1, Aggregator::MEDIAN)?;
/// ens.insert(0, &[0.0, 1.0, 2.0, 3.0], QueryMeta::CLEAN)?;
/// assert_eq!(ens.action(0)?.action, &[0.0]);
/// assert_eq!(ens.action(1)?.action, &[1.0]);
/// ens.insert(2, &[2.5, 3.5, 4.5, 5.5], QueryMeta::CLEAN)?;
/// let step = ens.action(2)?; // candidates 2.0 (query 0) and 2.5 (query 2)
/// assert_eq!(step.action, &[2.25]);
/// assert_eq!(step.report.m, 2);
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
///
/// ## Layout
///
/// A ring of `span + lookahead` chunk slots (`span = t_p - t_o + 1`), in query order, holds
/// the executable rows of each live chunk as one block (one copy per insertion). `action`
/// walks the live chunks oldest first and copies row `tau - t` of each into a candidate
/// matrix whose rows are padded to 4 lanes, so the median's comparator network runs on
/// packed SIMD registers. Rows of 1 to 8, 10 and 14 coordinates are copied by code
/// specialised for that width. A ring too large for L1 (ACT's `T_p = 100`) copies the
/// candidates of 2, 7 or 14 coordinates in at most two contiguous runs of slots, without a
/// per-row finiteness test while every candidate chunk is finite.
///
/// An aggregator that is a weighted mean summed in candidate order
/// ([`Aggregate::running_weights`]: `ewm` and `mean`) is also summed per control time as
/// chunks arrive, into a ring of `span + lookahead` times; a step without a hook or bracket
/// diagnostics then divides two sums instead of gathering, and gives the gathered mean's
/// bits. Its candidates are gathered only if [`last_candidates`](Self::last_candidates)
/// asks for them.
#[derive(Debug, Clone)]
pub struct TemporalEnsembler<A: Aggregate = Aggregator> {
    geometry: ChunkGeometry,
    dim: usize,
    /// Row stride of the candidate matrix: `dim` rounded up to [`LANES`].
    stride: usize,
    span: usize,
    capacity: usize,
    lookahead: usize,
    aggregator: A,
    bracket_diagnostics: bool,
    /// Whether the ring of rows outgrows L1 (ACT's `T_p = 100`, not Diffusion Policy's 16):
    /// then the gather prefetches and the insert's check is the dispatched wide one, which
    /// at small chunks would cost more than they save.
    large: bool,
    /// `capacity * span * dim` values: slot `s`, executable row `r`, coordinate `j`.
    rows: Vec<f32>,
    slots: Vec<ChunkSlot>,
    /// `capacity * span` per-row finiteness, filled only for chunks that are not all finite.
    row_finite: Vec<bool>,
    head: usize,
    len: usize,
    /// Chunks flagged corrupted inserted since the last reset.
    corrupted_inserted: u64,
    last_query: Option<u64>,
    /// Latest control time served; no earlier one may be asked for.
    cursor: Option<u64>,
    // Per-step scratch: the candidate matrix, its flags, the output.
    cand: Vec<f32>,
    cand_corrupted: Vec<bool>,
    /// Candidates aggregated by the last successful step (0 before the first).
    last_used: usize,
    /// Per-time sums when the aggregator is a running mean.
    running: Option<RunningSums>,
    /// A step served from `running` whose candidates are not gathered yet: its time and
    /// candidate count.
    deferred: Option<(u64, usize)>,
    out: Vec<f32>,
    workspace: Workspace,
}

impl<A: Aggregate> TemporalEnsembler<A> {
    /// An ensembler for chunks of `geometry` with `dim` action coordinates.
    pub fn new(geometry: ChunkGeometry, dim: usize, aggregator: A) -> Result<Self, EnsembleError> {
        Self::with_options(geometry, dim, aggregator, EnsemblerOptions::default())
    }

    /// An ensembler with explicit [`EnsemblerOptions`].
    pub fn with_options(
        geometry: ChunkGeometry,
        dim: usize,
        aggregator: A,
        options: EnsemblerOptions,
    ) -> Result<Self, EnsembleError> {
        geometry.validate().map_err(EnsembleError::Geometry)?;
        if dim == 0 {
            return Err(EnsembleError::ZeroDimension);
        }
        let span = geometry.span();
        let lookahead = options.lookahead.unwrap_or(geometry.h).max(1);
        let capacity = span + lookahead;
        let stride = dim.div_ceil(LANES) * LANES;
        let mut workspace = Workspace::new(span, stride);
        let running = aggregator
            .running_weights()
            .map(|r| RunningSums::new(r, span, capacity, dim, &mut workspace));
        Ok(Self {
            geometry,
            dim,
            stride,
            span,
            capacity,
            lookahead,
            aggregator,
            bracket_diagnostics: options.bracket_diagnostics,
            large: capacity * span * dim * std::mem::size_of::<f32>() > LARGE_RING_BYTES,
            rows: vec![0.0; capacity * span * dim],
            slots: vec![ChunkSlot::default(); capacity],
            row_finite: vec![true; capacity * span],
            head: 0,
            len: 0,
            corrupted_inserted: 0,
            last_query: None,
            cursor: None,
            cand: vec![0.0; span * stride],
            cand_corrupted: vec![false; span],
            last_used: 0,
            running,
            deferred: None,
            out: vec![0.0; dim],
            workspace,
        })
    }

    /// The geometry chunks are interpreted with.
    pub fn geometry(&self) -> ChunkGeometry {
        self.geometry
    }

    /// Action dimension `d`.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// The aggregator.
    pub fn aggregator(&self) -> &A {
        &self.aggregator
    }

    /// Control steps after the last action served that a query may still be inserted.
    pub fn lookahead(&self) -> usize {
        self.lookahead
    }

    /// Chunks currently held.
    pub fn live_chunks(&self) -> usize {
        self.len
    }

    /// The candidates the last step aggregated (after any hook), oldest first, with their
    /// corrupted flags: what a runtime monitor or an observer reads. Empty before the first
    /// step, after a step that failed and after [`reset`](Self::reset). A step served from
    /// running sums (see the type's documentation) gathers its candidates here, once.
    pub fn last_candidates(&mut self) -> (Candidates<'_>, &[bool]) {
        if let Some((tau, used)) = self.deferred.take() {
            // The chunks covering `tau` are all still held (nothing is evicted before the
            // cursor, `tau`); any inserted since the step are newer, so they come after the
            // step's `used` candidates.
            let g = if self.large {
                self.gather_large(tau)
            } else {
                self.gather_any(tau)
            };
            debug_assert!(g.used >= used);
            self.last_used = used;
        }
        let used = self.last_used;
        (
            Candidates::from_checked(&self.cand[..used * self.stride], self.dim, self.stride),
            &self.cand_corrupted[..used],
        )
    }

    /// Forgets every chunk and the time cursor, for a new episode. Does not allocate.
    pub fn reset(&mut self) {
        self.last_used = 0;
        self.deferred = None;
        if let Some(run) = &mut self.running {
            run.clear();
        }
        self.head = 0;
        self.len = 0;
        self.corrupted_inserted = 0;
        self.last_query = None;
        self.cursor = None;
    }

    /// `i mod capacity` for `i < 2 * capacity`, without a division (this is the hot path).
    #[inline]
    fn wrap(&self, i: usize) -> usize {
        if i >= self.capacity {
            i - self.capacity
        } else {
            i
        }
    }

    /// Drops chunks that cannot cover any control time from `tau` on.
    #[inline]
    fn evict_before(&mut self, tau: u64) {
        let reach = (self.span - 1) as u64;
        while self.len > 0 && self.slots[self.head].t_query + reach < tau {
            self.head = self.wrap(self.head + 1);
            self.len -= 1;
        }
    }

    /// Inserts the chunk of the query that fired at control time `t_query`: `t_p x d`
    /// values, row-major, row `r` being the action for time `t_query - (t_o - 1) + r`.
    ///
    /// Query times must strictly increase. A chunk that could only cover control times
    /// already served is refused ([`EnsembleError::StaleChunk`]) rather than dropped
    /// silently, and so is one inserted more than [`lookahead`](Self::lookahead) steps
    /// after the last action served ([`EnsembleError::TooFarAhead`]).
    pub fn insert(
        &mut self,
        t_query: u64,
        chunk: &[f32],
        meta: QueryMeta,
    ) -> Result<(), EnsembleError> {
        let (d, span) = (self.dim, self.span);
        let expected = self.geometry.t_p * d;
        if chunk.len() != expected {
            return Err(EnsembleError::ChunkShape {
                expected,
                got: chunk.len(),
                t_p: self.geometry.t_p,
                dim: d,
            });
        }
        if let Some(last) = self.last_query.filter(|&last| t_query <= last) {
            return Err(EnsembleError::NonMonotonicQuery { t_query, last });
        }
        let last_covered = t_query + (span - 1) as u64;
        if let Some(cursor) = self.cursor {
            if last_covered < cursor {
                return Err(EnsembleError::StaleChunk {
                    t_query,
                    last_covered,
                    cursor,
                });
            }
            if t_query > cursor + self.lookahead as u64 {
                return Err(EnsembleError::TooFarAhead {
                    t_query,
                    floor: cursor,
                    lookahead: self.lookahead,
                });
            }
            self.evict_before(cursor);
        }
        if self.len == self.capacity {
            // Only reachable before the first action: every slot holds a chunk that may
            // still be asked for.
            let floor = self.slots[self.head].t_query;
            return Err(EnsembleError::TooFarAhead {
                t_query,
                floor,
                lookahead: self.lookahead,
            });
        }
        let slot = self.wrap(self.head + self.len);
        let executable = &chunk[self.geometry.first_executable_row() * d..];
        let width = span * d;
        self.rows[slot * width..(slot + 1) * width].copy_from_slice(executable);
        let finite = if self.large {
            chunk_finite(executable)
        } else {
            all_finite(executable)
        };
        if !finite {
            for (flag, row) in self.row_finite[slot * span..(slot + 1) * span]
                .iter_mut()
                .zip(executable.chunks_exact(d))
            {
                *flag = all_finite(row);
            }
        }
        if let Some(run) = &mut self.running {
            let flags = (!finite).then(|| &self.row_finite[slot * span..(slot + 1) * span]);
            run.add_chunk(t_query, executable, meta.corrupted, flags);
        }
        self.slots[slot] = ChunkSlot {
            t_query,
            corrupted_before: self.corrupted_inserted,
            corrupted: meta.corrupted,
            finite,
        };
        self.corrupted_inserted += u64::from(meta.corrupted);
        self.len += 1;
        self.last_query = Some(t_query);
        Ok(())
    }

    /// The aggregated action for control time `tau`, borrowed until the next call.
    pub fn action(&mut self, tau: u64) -> Result<Step<'_>, EnsembleError> {
        self.action_with(tau, &mut NoHook)
    }

    /// Like [`action`](Self::action), letting `hook` rewrite the candidate set of `tau` in
    /// place after it is gathered and before it is aggregated (and diagnosed): the seam
    /// through which oracle attacks and common-mode bias act on the real candidates. A hook
    /// that leaves a non-finite value is an error ([`EnsembleError::HookNonFinite`]).
    pub fn action_with(
        &mut self,
        tau: u64,
        hook: &mut dyn CandidateHook,
    ) -> Result<Step<'_>, EnsembleError> {
        let (report, bracket) = self.compute(tau, hook)?;
        Ok(Step {
            action: &self.out,
            report,
            bracket,
        })
    }

    /// Like [`action`](Self::action), writing the action into `out` (`d` coordinates).
    pub fn action_into(&mut self, tau: u64, out: &mut [f32]) -> Result<StepReport, EnsembleError> {
        let (report, _) = self.compute(tau, &mut NoHook)?;
        out.copy_from_slice(&self.out);
        Ok(report)
    }

    fn compute(
        &mut self,
        tau: u64,
        hook: &mut dyn CandidateHook,
    ) -> Result<(StepReport, Option<BracketReport>), EnsembleError> {
        if let Some(cursor) = self.cursor.filter(|&c| tau < c) {
            return Err(EnsembleError::TimeWentBackwards { tau, cursor });
        }
        self.cursor = Some(tau);
        self.evict_before(tau);
        self.last_used = 0;
        self.deferred = None;
        if !hook.active()
            && !self.bracket_diagnostics
            && let Some(report) = self.running_step(tau)?
        {
            return Ok((report, None));
        }
        let g = if self.large {
            self.gather_large(tau)
        } else {
            self.gather_any(tau)
        };
        if g.m == 0 {
            let earliest = tau.saturating_sub((self.span - 1) as u64);
            return Err(EnsembleError::NoCandidates { tau, earliest });
        }
        if g.used == 0 {
            return Err(EnsembleError::NoFiniteCandidates { tau, excluded: g.m });
        }
        if hook.active() {
            let (d, stride) = (self.dim, self.stride);
            let mut set = CandidatesMut {
                tau,
                dim: d,
                stride,
                values: &mut self.cand[..g.used * stride],
                corrupted: &self.cand_corrupted[..g.used],
            };
            hook.rewrite(&mut set);
            let bad = (0..g.used).find(|&i| !all_finite(&self.cand[i * stride..i * stride + d]));
            if let Some(index) = bad {
                return Err(EnsembleError::HookNonFinite { tau, index });
            }
        }
        self.last_used = g.used;
        let cands =
            Candidates::from_checked(&self.cand[..g.used * self.stride], self.dim, self.stride);
        self.aggregator
            .aggregate(&cands, &mut self.workspace, &mut self.out)?;
        let report = StepReport {
            tau,
            m: g.m,
            q: g.q,
            excluded: g.m - g.used,
            excluded_corrupted: g.excluded_corrupted,
            regime: Regime::of(g.q - g.excluded_corrupted, g.used),
            oldest_query: g.oldest,
            newest_query: g.newest,
        };
        let bracket = if self.bracket_diagnostics {
            bracket::diagnose(&cands, &self.cand_corrupted[..g.used], &self.out)
        } else {
            None
        };
        Ok((report, bracket))
    }

    /// How many live chunks, from the head, were queried at or before `tau`. Chunks inserted
    /// ahead (query time after `tau`) are at the tail: few, at most the lookahead.
    #[inline]
    fn queried_by(&self, tau: u64) -> usize {
        let mut m = self.len;
        while m > 0 && self.slots[self.wrap(self.head + m - 1)].t_query > tau {
            m -= 1;
        }
        m
    }

    /// The step at `tau` from the running sums: `None` when there are none for `tau` (no
    /// running mean, or a time whose slot was taken), and the caller gathers.
    fn running_step(&mut self, tau: u64) -> Result<Option<StepReport>, EnsembleError> {
        let Some((s, total, sums)) = self.running.as_ref().and_then(|r| r.get(tau)) else {
            return Ok(None);
        };
        // The covering chunks: the live ones from the head (`evict_before(tau)` left none
        // older) to the newest queried at or before `tau`.
        let m = self.queried_by(tau);
        let (used, excluded) = (s.used as usize, s.excluded as usize);
        debug_assert_eq!(m, used + excluded, "running sums out of step at {tau}");
        // A held slot has at least one candidate, so this also excludes `m == 0`.
        if m != used + excluded {
            return Ok(None); // unreachable (see `running`): gather rather than guess
        }
        if used == 0 {
            return Err(EnsembleError::NoFiniteCandidates { tau, excluded: m });
        }
        // `weighted_mean`'s last operation.
        for (o, a) in self.out.iter_mut().zip(sums) {
            *o = (a / total) as f32;
        }
        let (first, last) = (
            self.slots[self.head],
            self.slots[self.wrap(self.head + m - 1)],
        );
        let q =
            (last.corrupted_before + u64::from(last.corrupted) - first.corrupted_before) as usize;
        let excluded_corrupted = s.excluded_corrupted as usize;
        self.deferred = Some((tau, used));
        Ok(Some(StepReport {
            tau,
            m,
            q,
            excluded,
            excluded_corrupted,
            regime: Regime::of(q - excluded_corrupted, used),
            oldest_query: first.t_query,
            newest_query: last.t_query,
        }))
    }

    /// [`gather`](Self::gather) with the action dimension as a constant where a
    /// specialisation exists.
    #[inline(always)]
    fn gather_any(&mut self, tau: u64) -> Gathered {
        match self.dim {
            1 => self.gather::<1>(tau),
            2 => self.gather::<2>(tau),
            3 => self.gather::<3>(tau),
            4 => self.gather::<4>(tau),
            5 => self.gather::<5>(tau),
            6 => self.gather::<6>(tau),
            7 => self.gather::<7>(tau),
            8 => self.gather::<8>(tau),
            10 => self.gather::<10>(tau),
            14 => self.gather::<14>(tau),
            _ => self.gather::<0>(tau),
        }
    }

    /// The gather of a ring too large for L1: [`gather_finite`](Self::gather_finite) where
    /// the dimension has a specialisation and every candidate chunk is finite, else
    /// [`gather`](Self::gather). Out of line, so that the small rings' step keeps its code.
    #[inline(never)]
    fn gather_large(&mut self, tau: u64) -> Gathered {
        let fast = match self.dim {
            2 => self.gather_finite::<2>(tau),
            7 => self.gather_finite::<7>(tau),
            14 => self.gather_finite::<14>(tau),
            _ => None,
        };
        fast.unwrap_or_else(|| self.gather_any(tau))
    }

    /// Copies the finite candidates for `tau` into `cand` (rows padded to `stride`), oldest
    /// first, and counts them. `D` is the action dimension when known at compile time, so
    /// that the row copy is a few moves instead of a `memcpy` call, or 0 for any dimension.
    #[inline]
    fn gather<const D: usize>(&mut self, tau: u64) -> Gathered {
        let (d, stride, span) = (self.dim, self.stride, self.span);
        debug_assert!(D == 0 || D == d);
        let width = span * d;
        let mut g = Gathered::default();
        // The live chunks are slots head.. (wrapping), in query order; those with a query
        // time after `tau` come last and are not candidates yet.
        let mut slot = self.head;
        for k in 0..self.len {
            if k > 0 {
                slot = self.wrap(slot + 1);
            }
            let meta = self.slots[slot];
            if meta.t_query > tau {
                break;
            }
            let offset = (tau - meta.t_query) as usize;
            debug_assert!(offset < span);
            if g.m == 0 {
                g.oldest = meta.t_query;
            }
            g.newest = meta.t_query;
            g.m += 1;
            g.q += usize::from(meta.corrupted);
            if !meta.finite && !self.row_finite[slot * span + offset] {
                g.excluded_corrupted += usize::from(meta.corrupted);
                continue;
            }
            let src = slot * width + offset * d;
            if self.large {
                prefetch_next_row(&self.rows[src..(slot + 1) * width], d);
            }
            let dst = g.used * stride;
            if D > 0 {
                self.cand[dst..dst + D].copy_from_slice(&self.rows[src..src + D]);
            } else {
                self.cand[dst..dst + d].copy_from_slice(&self.rows[src..src + d]);
            }
            self.cand_corrupted[g.used] = meta.corrupted;
            g.used += 1;
        }
        g
    }

    /// [`gather`](Self::gather) for `D` (> 0) the action dimension, when every candidate
    /// chunk is finite (`None`, with `cand` overwritten, when one is not): the candidates are
    /// the live chunks queried at or before `tau`, a prefix of the ring in query order,
    /// copied in at most two contiguous runs of slots (the ring wraps once) with no per-row
    /// test.
    #[inline]
    fn gather_finite<const D: usize>(&mut self, tau: u64) -> Option<Gathered> {
        debug_assert!(D == self.dim);
        let m = self.queried_by(tau);
        if m == 0 {
            return Some(Gathered::default());
        }
        let first = self.head;
        let end = first + m;
        let (run1, run2) = if end > self.capacity {
            (first..self.capacity, 0..end - self.capacity)
        } else {
            (first..end, 0..0)
        };
        let n1 = run1.len();
        let (q1, finite1) = self.copy_run::<D>(tau, run1, 0);
        let (q2, finite2) = self.copy_run::<D>(tau, run2, n1);
        (finite1 && finite2).then(|| Gathered {
            m,
            q: q1 + q2,
            used: m,
            excluded_corrupted: 0,
            oldest: self.slots[self.head].t_query,
            newest: self.slots[self.wrap(self.head + m - 1)].t_query,
        })
    }

    /// Copies the row for `tau` of each chunk in the ring slots `run` (in order) to the
    /// candidate rows from `at` on, with their corrupted flags; returns how many are
    /// corrupted and whether every one of these chunks is finite.
    #[inline(always)]
    fn copy_run<const D: usize>(
        &mut self,
        tau: u64,
        run: std::ops::Range<usize>,
        at: usize,
    ) -> (usize, bool) {
        let (stride, width, n) = (self.stride, self.span * D, run.len());
        let slots = &self.slots[run.clone()];
        let rows = self.rows[run.start * width..run.end * width].chunks_exact(width);
        let cand = self.cand[at * stride..(at + n) * stride].chunks_exact_mut(stride);
        let flags = &mut self.cand_corrupted[at..at + n];
        let (mut q, mut finite) = (0, true);
        for (((meta, chunk), dst), flag) in slots.iter().zip(rows).zip(cand).zip(flags) {
            // `0 <= tau - t_query < span` for a live chunk queried at or before `tau`.
            let rest = &chunk[(tau - meta.t_query) as usize * D..];
            // Only large rings come here: their rows are not in L1 (see `gather`).
            prefetch_next_row(rest, D);
            dst[..D].copy_from_slice(&rest[..D]);
            *flag = meta.corrupted;
            q += usize::from(meta.corrupted);
            finite &= meta.finite;
        }
        (q, finite)
    }
}

/// Asks for the line that the row after `row[..d]` ends in (the row this chunk serves at the
/// next control time), so that the next step's gather finds it in L1: each live chunk's
/// rows are read one after another, one per step, from rings too large for L1 at ACT's
/// M = 100. A hint only: it changes no value and cannot fault.
#[inline(always)]
#[allow(unsafe_code)]
fn prefetch_next_row(row: &[f32], d: usize) {
    #[cfg(target_arch = "x86_64")]
    if let Some(last) = row.get(2 * d - 1) {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // SAFETY: SSE is part of every x86_64 target, and a prefetch of a valid address
        // (here an element of `row`) reads nothing the program can observe.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(std::ptr::from_ref(last).cast()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (row, d);
}

/// A rewrite of one control time's candidate set before aggregation (see
/// [`TemporalEnsembler::action_with`]). Implemented for closures over [`CandidatesMut`].
pub trait CandidateHook {
    /// Whether the hook acts at all (a hook that returns `false` costs nothing).
    fn active(&self) -> bool {
        true
    }
    /// Rewrites the candidates in place.
    fn rewrite(&mut self, set: &mut CandidatesMut<'_>);
}

impl<F: FnMut(&mut CandidatesMut<'_>)> CandidateHook for F {
    fn rewrite(&mut self, set: &mut CandidatesMut<'_>) {
        self(set);
    }
}

/// The hook that does nothing ([`TemporalEnsembler::action`] uses it; the ensembler skips
/// an inactive hook entirely).
#[derive(Debug, Clone, Copy, Default)]
pub struct NoHook;

impl CandidateHook for NoHook {
    fn active(&self) -> bool {
        false
    }
    fn rewrite(&mut self, _: &mut CandidatesMut<'_>) {}
}

/// The finite candidates of one control time, oldest first, as a hook sees them: `d`
/// values per candidate, writable; whether each came from a corrupted query.
#[derive(Debug)]
pub struct CandidatesMut<'a> {
    tau: u64,
    dim: usize,
    stride: usize,
    values: &'a mut [f32],
    corrupted: &'a [bool],
}

impl CandidatesMut<'_> {
    /// The control time.
    pub fn tau(&self) -> u64 {
        self.tau
    }
    /// Number of candidates.
    pub fn len(&self) -> usize {
        self.corrupted.len()
    }
    /// Whether there is no candidate (never, inside a hook).
    pub fn is_empty(&self) -> bool {
        self.corrupted.is_empty()
    }
    /// Action dimension `d`.
    pub fn dim(&self) -> usize {
        self.dim
    }
    /// Candidate `i` (oldest first), `d` values.
    pub fn row(&self, i: usize) -> &[f32] {
        &self.values[i * self.stride..i * self.stride + self.dim]
    }
    /// Candidate `i`, writable.
    pub fn row_mut(&mut self, i: usize) -> &mut [f32] {
        &mut self.values[i * self.stride..i * self.stride + self.dim]
    }
    /// Whether candidate `i` came from a query flagged corrupted.
    pub fn corrupted(&self, i: usize) -> bool {
        self.corrupted[i]
    }
    /// Coordinate `j` of candidate `i`.
    pub fn get(&self, i: usize, j: usize) -> f32 {
        self.values[i * self.stride + j]
    }
}

/// Counts from one gather.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
struct Gathered {
    m: usize,
    q: usize,
    used: usize,
    excluded_corrupted: usize,
    oldest: u64,
    newest: u64,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::GeometryError;

    fn ramp(t: u64, t_p: usize, t_o: usize) -> Vec<f32> {
        // Row r is the action for time t - (t_o - 1) + r; value = that time + query offset.
        (0..t_p)
            .map(|r| (t as f32 - (t_o as f32 - 1.0) + r as f32) + t as f32 * 0.001)
            .collect()
    }

    #[test]
    fn candidates_come_from_the_right_rows() {
        let g = ChunkGeometry::new(16, 2, 2).unwrap();
        let mut e = TemporalEnsembler::new(g, 1, Aggregator::Latest).unwrap();
        for i in 0..60u64 {
            let t = 2 * i;
            e.insert(t, &ramp(t, 16, 2), QueryMeta::CLEAN).unwrap();
            for tau in [t, t + 1] {
                let step = e.action(tau).unwrap();
                // Latest = the query at t, whose row for tau encodes tau.
                assert!((step.action[0] - (tau as f32 + t as f32 * 0.001)).abs() < 1e-3);
                if tau >= 16 {
                    assert_eq!(step.report.m, g.m_at(tau), "tau {tau}");
                }
            }
        }
        assert_eq!(
            e.action(101).map(|s| s.report.m),
            Err(EnsembleError::TimeWentBackwards {
                tau: 101,
                cursor: 119
            })
        );
    }

    #[test]
    fn worked_example_counts_at_100_and_101() {
        let g = ChunkGeometry::new(16, 2, 2).unwrap();
        let mut e = TemporalEnsembler::new(g, 1, Aggregator::MEDIAN).unwrap();
        for t in (0..=100).step_by(2) {
            e.insert(t, &ramp(t, 16, 2), QueryMeta::CLEAN).unwrap();
            if t < 100 {
                e.action(t).unwrap();
            }
        }
        let s = e.action(100).unwrap().report;
        assert_eq!((s.m, s.oldest_query, s.newest_query), (8, 86, 100));
        let s = e.action(101).unwrap().report;
        assert_eq!((s.m, s.oldest_query, s.newest_query), (7, 88, 100));
    }

    #[test]
    fn late_and_missing_queries_are_handled_by_time() {
        let g = ChunkGeometry::new(6, 1, 2).unwrap();
        let mut e = TemporalEnsembler::new(g, 1, Aggregator::Mean).unwrap();
        e.insert(0, &[0.0; 6], QueryMeta::CLEAN).unwrap();
        e.action(0).unwrap();
        e.action(1).unwrap();
        e.action(2).unwrap(); // query at 2 is late
        e.insert(3, &[1.0; 6], QueryMeta::CLEAN).unwrap();
        let s = e.action(3).unwrap();
        assert_eq!((s.report.m, s.action[0]), (2, 0.5));
        // Query at 5 missing; 9 uncovered by the chunk from 3 (covers 3..=8).
        assert_eq!(e.action(8).unwrap().report.m, 1);
        assert_eq!(
            e.action(9).map(|s| s.report.m),
            Err(EnsembleError::NoCandidates {
                tau: 9,
                earliest: 4
            })
        );
    }

    #[test]
    fn bad_calls_are_typed_errors() {
        let g = ChunkGeometry::new(4, 1, 1).unwrap();
        assert_eq!(
            TemporalEnsembler::new(g, 0, Aggregator::MEDIAN).unwrap_err(),
            EnsembleError::ZeroDimension
        );
        let bad = ChunkGeometry {
            t_p: 4,
            t_o: 0,
            h: 1,
        };
        assert_eq!(
            TemporalEnsembler::new(bad, 1, Aggregator::MEDIAN).unwrap_err(),
            EnsembleError::Geometry(GeometryError::ZeroObservationSteps)
        );
        let mut e = TemporalEnsembler::new(g, 2, Aggregator::MEDIAN).unwrap();
        assert_eq!(
            e.insert(0, &[0.0; 7], QueryMeta::CLEAN),
            Err(EnsembleError::ChunkShape {
                expected: 8,
                got: 7,
                t_p: 4,
                dim: 2
            })
        );
        e.insert(5, &[0.0; 8], QueryMeta::CLEAN).unwrap();
        assert_eq!(
            e.insert(5, &[0.0; 8], QueryMeta::CLEAN),
            Err(EnsembleError::NonMonotonicQuery {
                t_query: 5,
                last: 5
            })
        );
        e.action(20).unwrap_err();
        assert_eq!(
            e.insert(10, &[0.0; 8], QueryMeta::CLEAN),
            Err(EnsembleError::StaleChunk {
                t_query: 10,
                last_covered: 13,
                cursor: 20
            })
        );
    }

    #[test]
    fn lookahead_bounds_chunks_inserted_ahead() {
        let g = ChunkGeometry::new(3, 1, 1).unwrap();
        let mut e = TemporalEnsembler::new(g, 1, Aggregator::Mean).unwrap();
        // span 3 + lookahead 1 (= h) = 4 slots.
        assert_eq!(e.lookahead(), 1);
        for t in 0..4 {
            e.insert(t, &[t as f32; 3], QueryMeta::CLEAN).unwrap();
        }
        assert_eq!(
            e.insert(4, &[0.0; 3], QueryMeta::CLEAN),
            Err(EnsembleError::TooFarAhead {
                t_query: 4,
                floor: 0,
                lookahead: 1
            })
        );
        assert_eq!(e.action(2).unwrap().report.m, 3);
        assert_eq!(
            e.insert(4, &[0.0; 3], QueryMeta::CLEAN),
            Err(EnsembleError::TooFarAhead {
                t_query: 4,
                floor: 2,
                lookahead: 1
            })
        );
        e.action(3).unwrap();
        e.insert(4, &[4.0; 3], QueryMeta::CLEAN).unwrap();
        let s = e.action(4).unwrap();
        assert_eq!((s.report.m, s.action[0]), (3, 3.0));
        let opts = EnsemblerOptions {
            lookahead: Some(5),
            ..Default::default()
        };
        let mut e = TemporalEnsembler::with_options(g, 1, Aggregator::Mean, opts).unwrap();
        assert_eq!(e.lookahead(), 5);
        for t in 0..6 {
            e.insert(t, &[t as f32; 3], QueryMeta::CLEAN).unwrap();
        }
        assert_eq!(e.action(2).unwrap().action, &[1.0]);
        assert_eq!(e.action(5).unwrap().action, &[4.0]);
    }

    #[test]
    fn non_finite_candidates_are_excluded_and_counted() {
        let g = ChunkGeometry::new(3, 1, 1).unwrap();
        let opts = EnsemblerOptions {
            lookahead: Some(2),
            ..Default::default()
        };
        let mut e = TemporalEnsembler::with_options(g, 1, Aggregator::MEDIAN, opts).unwrap();
        e.insert(0, &[1.0, 1.0, 1.0], QueryMeta::CLEAN).unwrap();
        e.insert(1, &[f32::NAN, f32::NAN, 9.0], QueryMeta::CORRUPTED)
            .unwrap();
        e.insert(2, &[3.0, f32::INFINITY, 3.0], QueryMeta::CLEAN)
            .unwrap();
        let s = e.action(2).unwrap();
        assert_eq!(s.action, &[2.0]);
        assert_eq!((s.report.m, s.report.q, s.report.excluded), (3, 1, 1));
        assert_eq!(s.report.excluded_corrupted, 1);
        assert_eq!(s.report.regime, Regime::Guaranteed);
        assert!(s.action.iter().all(|v| v.is_finite()));
        let g = ChunkGeometry::new(2, 1, 1).unwrap();
        let mut e = TemporalEnsembler::new(g, 1, Aggregator::MEDIAN).unwrap();
        e.insert(0, &[f32::NAN, 0.0], QueryMeta::CLEAN).unwrap();
        assert_eq!(
            e.action(0).map(|s| s.report),
            Err(EnsembleError::NoFiniteCandidates {
                tau: 0,
                excluded: 1
            })
        );
    }

    #[test]
    fn reset_starts_a_new_episode() {
        let g = ChunkGeometry::new(3, 1, 1).unwrap();
        let mut e = TemporalEnsembler::new(g, 1, Aggregator::Mean).unwrap();
        e.insert(10, &[1.0; 3], QueryMeta::CLEAN).unwrap();
        e.action(10).unwrap();
        e.reset();
        assert_eq!(e.live_chunks(), 0);
        e.insert(0, &[2.0; 3], QueryMeta::CLEAN).unwrap();
        assert_eq!(e.action(0).unwrap().action, &[2.0]);
    }

    /// Chunks inserted far apart before the first action can take a time's running-sum slot
    /// (the ring holds `span + lookahead` times); that time is then gathered, and its action
    /// and counts are still right.
    #[test]
    fn a_time_whose_running_slot_was_taken_is_gathered() {
        let g = ChunkGeometry::new(4, 1, 1).unwrap(); // span 4, lookahead 1: 5 slots
        let mut e = TemporalEnsembler::new(g, 1, Aggregator::Mean).unwrap();
        assert!(e.running.is_some());
        e.insert(0, &[1.0, 2.0, 3.0, 4.0], QueryMeta::CLEAN)
            .unwrap();
        // Times 7..10 take the slots of times 2, 3 and 0 (7, 8 and 10 mod 5); time 1 keeps its.
        e.insert(7, &[9.0; 4], QueryMeta::CORRUPTED).unwrap();
        let step = e.action(0).unwrap();
        assert_eq!(step.action, &[1.0]);
        assert_eq!((step.report.m, step.report.q), (1, 0));
        assert_eq!(e.deferred, None, "time 0 was gathered, not read from sums");
        let step = e.action(1).unwrap();
        assert_eq!((step.action, step.report.m), (&[2.0][..], 1));
        assert!(e.deferred.is_some(), "time 1 kept its sums");
        assert_eq!(e.last_candidates().0.values(), &[2.0, 0.0, 0.0, 0.0]);
        let step = e.action(3).unwrap();
        assert_eq!((step.action, step.report.m), (&[4.0][..], 1));
        assert_eq!(e.deferred, None, "time 3 was gathered");
        let step = e.action(7).unwrap();
        assert_eq!((step.action, step.report.q), (&[9.0][..], 1));
        assert!(e.deferred.is_some(), "time 7 is summed");
    }

    /// The large rings' gather (two contiguous runs, no per-row test while every chunk is
    /// finite) gives the general gather's candidates, flags and counts exactly, at ACT-sized
    /// rings with every specialised dimension, with the ring wrapping, chunks inserted ahead,
    /// corrupted chunks and the odd non-finite chunk (where it must defer to the general path).
    #[test]
    fn large_ring_gather_matches_the_general_gather() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0x1234_5678_9abc_def1);
        let mut next = move || rng.random::<u64>();
        let mut deferred = 0;
        for (t_p, h, d) in [(100, 1, 14), (100, 3, 7), (60, 1, 2), (100, 2, 14)] {
            let g = ChunkGeometry::new(t_p, 1, h).unwrap();
            let opts = EnsemblerOptions {
                lookahead: Some(h + 1),
                ..Default::default()
            };
            let mut e = TemporalEnsembler::with_options(g, d, Aggregator::MEDIAN, opts).unwrap();
            assert!(e.large, "t_p {t_p} d {d} is a large ring");
            for tau in 0..(3 * t_p as u64) {
                if tau % h as u64 == 0 {
                    let mut chunk: Vec<f32> = (0..t_p * d)
                        .map(|_| (next() >> 40) as f32 / 1e5 - 80.0)
                        .collect();
                    if next() % 40 == 0 {
                        let at = (next() as usize) % chunk.len();
                        chunk[at] = f32::NAN;
                    }
                    let meta = QueryMeta {
                        corrupted: next() % 3 == 0,
                    };
                    // Every other query arrives one step ahead of its action.
                    let t = if tau > 0 && next() % 2 == 0 {
                        tau + 1
                    } else {
                        tau
                    };
                    if e.last_query.is_none_or(|l| t > l) {
                        e.insert(t, &chunk, meta).unwrap();
                    }
                }
                e.cursor = Some(tau);
                e.evict_before(tau);
                let fast = match d {
                    2 => e.gather_finite::<2>(tau),
                    7 => e.gather_finite::<7>(tau),
                    _ => e.gather_finite::<14>(tau),
                };
                let fast_rows = e.cand[..fast.map_or(0, |g| g.used) * e.stride].to_vec();
                let fast_flags = e.cand_corrupted[..fast.map_or(0, |g| g.used)].to_vec();
                let slow = e.gather_any(tau);
                match fast {
                    Some(f) => {
                        assert_eq!(f, slow, "t_p {t_p} d {d} tau {tau}");
                        let rows = &e.cand[..slow.used * e.stride];
                        for (a, b) in fast_rows.chunks(e.stride).zip(rows.chunks(e.stride)) {
                            assert_eq!(a[..d], b[..d], "t_p {t_p} d {d} tau {tau}");
                        }
                        assert_eq!(fast_flags, e.cand_corrupted[..slow.used]);
                    }
                    None => deferred += 1,
                }
                assert_eq!(e.gather_large(tau), slow);
            }
        }
        assert!(
            deferred > 0,
            "a non-finite chunk sent some steps to the general gather"
        );
    }

    #[test]
    fn finiteness_checks_see_every_infinity_and_nan() {
        let finite = [
            0.0,
            -0.0,
            1e-45,
            -1e-45,
            f32::MAX,
            f32::MIN,
            f32::MIN_POSITIVE,
        ];
        assert!(all_finite(&finite) && chunk_finite(&finite));
        for bad in [
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
            f32::from_bits(0x7f80_0001),
            f32::from_bits(0xffff_ffff),
        ] {
            for at in [0, 3, 39] {
                let mut v = vec![1.5f32; 40];
                v[at] = bad;
                assert!(!all_finite(&v), "{bad} at {at}");
                assert!(!chunk_finite(&v), "{bad} at {at}");
            }
        }
    }

    #[test]
    fn regime_boundaries() {
        assert_eq!(Regime::of(3, 7), Regime::Guaranteed);
        assert_eq!(Regime::of(4, 8), Regime::Tie);
        assert_eq!(Regime::of(4, 7), Regime::Exceeded);
        assert_eq!(Regime::of(0, 1), Regime::Guaranteed);
        assert_eq!(Regime::Tie.to_string(), "2q=M");
    }
}
