//! # mte-ensemble: robust temporal ensembling of action chunks
//!
//! A chunked policy (Diffusion Policy, ACT) predicts `t_p` future actions per query and is
//! re-queried every `h` control steps, so each control time `tau` is covered by `M(tau)`
//! overlapping predictions, its *candidates*. This crate turns those candidates into the one
//! action to execute, every control step, without allocating.
//!
//! ## The pieces
//!
//! - [`ChunkGeometry`] (`t_p`, `t_o`, `h`): which query covers which control time, the
//!   covering set `C(tau)`, `M_min` and `M_max` ([`geometry`] documents the time axis).
//! - [`TemporalEnsembler`]: a ring of live chunks keyed by the **absolute control time**
//!   each query fired. [`insert`](TemporalEnsembler::insert) a chunk when its query
//!   returns, ask [`action`](TemporalEnsembler::action) at each control time. Returns the
//!   action and a [`StepReport`] (`M`, corrupted `q`, [`Regime`], excluded candidates).
//! - [`Aggregator`]: the built-in statistics behind one trait, [`Aggregate`], parsed from
//!   short text (`median`, `ewm:0.01`, `trimmed-medoid:2`, ...).
//! - [`bracket`]: diagnostics of the output against the range of the clean candidates,
//!   and the [`BracketAccumulator`] that builds the paper's breakdown table.
//!
//! ## Example
//!
//! ```
//! use mte_ensemble::{Aggregator, ChunkGeometry, QueryMeta, TemporalEnsembler};
//!
//! // Diffusion Policy on PushT: 16-step chunks, 2 observation steps, re-queried every 2.
//! let g = ChunkGeometry::new(16, 2, 2)?;
//! let mut ens = TemporalEnsembler::new(g, 2, "median".parse::<Aggregator>()?)?;
//! let chunk = vec![0.5f32; 16 * 2]; // t_p x d, row-major, from the policy
//! for tau in 0..10u64 {
//!     if tau % 2 == 0 {
//!         ens.insert(tau, &chunk, QueryMeta::CLEAN)?;
//!     }
//!     let step = ens.action(tau)?;
//!     assert_eq!(step.action, &[0.5, 0.5]);
//! }
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
//!
//! ## Median or exp-weighted mean?
//!
//! ACT's temporal ensembling (and LeRobot's `ACTTemporalEnsembler`) executes the
//! exponentially weighted mean of the candidates. A mean has breakdown point zero: one
//! corrupted prediction, from a blank camera frame or an adversarial observation, drags the
//! action as far as its own error, scaled by its weight. The coordinate-wise median cannot be
//! dragged outside the range of the clean candidates while fewer than half of them are
//! corrupted (`2q < M`), whatever values the corrupted ones take. Use:
//!
//! - `ewm` (the default) to reproduce a deployed ACT or LeRobot system exactly;
//! - `median` when observations can be corrupted; `median:drop-oldest` avoids the tie
//!   `2q = M` at even `M`, where the guarantee is lost;
//! - `trimmed-mean:k` for a smoother estimate that still tolerates `k` outliers per
//!   coordinate; `medoid` / `trimmed-medoid:q` to always execute a proposed action;
//!   `geomedian` for a rotation-equivariant robust centre.
//!
//! ## Conventions
//!
//! - Time is in integer **control steps**; a chunk is `t_p x d`, row-major; row `r` of the
//!   chunk from the query at `t` is the action for `t - (t_o - 1) + r`.
//! - Candidates are ordered **oldest first**. Exponential weights `exp(-m k)` index `k` from
//!   the oldest candidate by default ([`WeightOrder::OldestFirst`], ACT and LeRobot: `m > 0`
//!   favours older predictions); [`WeightOrder::NewestFirst`] is the paper's `k = age`.
//! - Actions are `f32` (what policies emit); sums are accumulated in `f64`.
//! - Candidates with a NaN or infinite coordinate are excluded and counted; if none is left,
//!   [`EnsembleError::NoFiniteCandidates`] — never a NaN action.
//!
//! ## What this crate does not do
//!
//! It does not run policies, schedule queries, or corrupt anything: the caller decides when
//! to query and marks corrupted queries in [`QueryMeta`] when it knows (evaluation only).
//!
//! ## Design: why a ring keyed by time
//!
//! LeRobot's ensembler keeps a running weighted average per pending slot, which ties it to
//! one aggregator (a mean can be updated online, a median cannot) and to a fixed stride of
//! one. Keeping the raw chunks in a ring of at most `t_p - t_o + 2` slots costs
//! `O(t_p^2 d)` floats, supports every aggregator and any stride (varying, late, missing
//! queries), and gathering the `M` candidates per step is a handful of copies. The means
//! (`ewm`, `mean`) also keep LeRobot's kind of running sums, per control time beside the
//! ring, summed in candidate order so that they give the gathered mean's bits: at ACT's
//! `M = 100` they spare the step its 100-row gather ([`Aggregate::running_weights`]).
#![deny(missing_docs)]

pub mod aggregate;
pub mod bracket;
mod ensembler;
mod error;
pub mod geometry;
pub mod monitor;
mod network;
mod running;

pub use aggregate::{
    Aggregate, Aggregator, Candidates, DEFAULT_EWM_M, Gathered, MedianTie, RunningWeights,
    WeightOrder, Workspace,
};
pub use bracket::{BracketAccumulator, BracketReport, BracketRow};
pub use ensembler::{
    CandidateHook, CandidatesMut, EnsemblerOptions, NoHook, QueryMeta, Regime, Step, StepReport,
    TemporalEnsembler,
};
pub use error::{AggregateError, EnsembleError, GeometryError, ParseAggregatorError};
pub use geometry::ChunkGeometry;
pub use monitor::{Acc, Monitor, MonitorError, MonitorKind, Threshold, Tide};
