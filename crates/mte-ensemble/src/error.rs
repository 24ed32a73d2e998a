//! Error types of the ensembling crate. Every variant carries the values involved.

use thiserror::Error;

/// An invalid [`ChunkGeometry`](crate::ChunkGeometry).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
#[non_exhaustive]
pub enum GeometryError {
    /// `t_p` (prediction horizon) was zero.
    #[error("prediction horizon t_p = 0: a chunk needs at least one row")]
    ZeroHorizon,
    /// `t_o` (observation steps) was zero.
    #[error("observation steps t_o = 0: a query sees at least its current observation (t_o >= 1)")]
    ZeroObservationSteps,
    /// `t_o` exceeded `t_p`, so no row of the chunk lies in the future.
    #[error(
        "observation steps t_o = {t_o} exceed the prediction horizon t_p = {t_p}: \
         expected 1 <= t_o <= t_p"
    )]
    ObservationStepsExceedHorizon {
        /// Observation steps given.
        t_o: usize,
        /// Prediction horizon given.
        t_p: usize,
    },
    /// The stride `h` was zero.
    #[error("stride h = 0: queries must fire every h >= 1 control steps")]
    ZeroStride,
    /// The stride leaves control times that no chunk covers.
    #[error(
        "stride h = {h} leaves timesteps uncovered: a chunk covers t_p - t_o + 1 = {max} control \
         steps, so h must be at most {max}"
    )]
    StrideLeavesGaps {
        /// Stride given.
        h: usize,
        /// Largest stride without gaps, `t_p - t_o + 1`.
        max: usize,
    },
}

/// A failure of [`TemporalEnsembler`](crate::TemporalEnsembler) operations.
///
/// All variants are `Copy` so that returning one never allocates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
#[non_exhaustive]
pub enum EnsembleError {
    /// The geometry is invalid.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
    /// The action dimension was zero at construction.
    #[error("action dimension d = 0: expected d >= 1")]
    ZeroDimension,
    /// An inserted chunk had the wrong number of values.
    #[error(
        "chunk has {got} values, expected t_p x d = {t_p} x {dim} = {expected} (row-major, \
         row 0 = the action for time t_query - t_o + 1)"
    )]
    ChunkShape {
        /// Values expected, `t_p * d`.
        expected: usize,
        /// Values given.
        got: usize,
        /// Prediction horizon.
        t_p: usize,
        /// Action dimension.
        dim: usize,
    },
    /// Queries must be inserted in strictly increasing control time.
    #[error(
        "query time {t_query} is not after the previous query at {last}: queries must be \
         inserted in strictly increasing control time"
    )]
    NonMonotonicQuery {
        /// Query time given.
        t_query: u64,
        /// Previous query time.
        last: u64,
    },
    /// The chunk arrived too late to cover any control time that can still be asked for.
    #[error(
        "chunk from the query at {t_query} covers control times up to {last_covered}, but \
         actions up to {cursor} have already been served: it arrived too late to be used"
    )]
    StaleChunk {
        /// Query time given.
        t_query: u64,
        /// Last control time the chunk covers.
        last_covered: u64,
        /// Earliest control time that may still be asked for.
        cursor: u64,
    },
    /// The chunk was inserted further ahead of the last action served than the lookahead
    /// the ensembler was built with.
    #[error(
        "query at {t_query} is more than {lookahead} control steps after {floor}, the earliest \
         time that may still be asked for: ask for actions first, or build the ensembler \
         with a larger lookahead"
    )]
    TooFarAhead {
        /// Query time given.
        t_query: u64,
        /// Earliest control time that may still be asked for.
        floor: u64,
        /// Lookahead of the ensembler.
        lookahead: usize,
    },
    /// An action was requested for a control time before one already served.
    #[error(
        "control time {tau} is before {cursor}, which was already served: time only moves forward"
    )]
    TimeWentBackwards {
        /// Control time asked for.
        tau: u64,
        /// Latest control time served.
        cursor: u64,
    },
    /// No inserted chunk covers the requested control time.
    #[error("no chunk covers control time {tau}: no query fired in [{earliest}, {tau}]")]
    NoCandidates {
        /// Control time asked for.
        tau: u64,
        /// Earliest query time that would cover `tau`.
        earliest: u64,
    },
    /// Candidates cover the control time but all of them have a non-finite coordinate.
    #[error("all {excluded} candidates for control time {tau} have NaN or infinite coordinates")]
    NoFiniteCandidates {
        /// Control time asked for.
        tau: u64,
        /// Candidates excluded as non-finite.
        excluded: usize,
    },
    /// A candidate hook left a NaN or infinite coordinate in the candidate set.
    #[error(
        "the candidate hook left a non-finite value in candidate {index} of control time {tau}: \
         hooks must keep candidates finite"
    )]
    HookNonFinite {
        /// Control time.
        tau: u64,
        /// Candidate index (oldest first).
        index: usize,
    },
    /// An aggregation failed.
    #[error(transparent)]
    Aggregate(#[from] AggregateError),
    /// A monitored chunk had a NaN or infinite value (monitors score finite chunks only).
    #[error(
        "chunk value at row {row}, coordinate {col} is NaN or infinite: monitors need finite chunks"
    )]
    NonFiniteChunk {
        /// Row of the chunk.
        row: usize,
        /// Coordinate.
        col: usize,
    },
}

/// A failure of one aggregation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
#[non_exhaustive]
pub enum AggregateError {
    /// The candidate set was empty.
    #[error("no candidates to aggregate")]
    Empty,
    /// The values do not form whole rows of a positive dimension.
    #[error("{len} values do not form rows of dimension {dim} (expected dim >= 1 dividing len)")]
    Shape {
        /// Number of values given.
        len: usize,
        /// Dimension given.
        dim: usize,
    },
    /// A candidate coordinate was NaN or infinite.
    #[error("candidate {row} has a non-finite value at coordinate {col}")]
    NonFinite {
        /// Candidate index (0 = oldest).
        row: usize,
        /// Coordinate index.
        col: usize,
    },
    /// The output buffer length differs from the candidates' dimension.
    #[error("output buffer has {got} coordinates, candidates have {expected}")]
    OutputDimension {
        /// Dimension of the candidates.
        expected: usize,
        /// Length of the output buffer.
        got: usize,
    },
    /// More candidates, or a larger dimension, than the workspace was built for.
    #[error(
        "{len} candidates of dimension {got_dim} exceed the workspace ({capacity} candidates of \
         dimension {dim})"
    )]
    WorkspaceTooSmall {
        /// Candidate capacity of the workspace.
        capacity: usize,
        /// Dimension of the workspace.
        dim: usize,
        /// Candidates given.
        len: usize,
        /// Dimension given.
        got_dim: usize,
    },
}

/// A text form of an aggregator that could not be parsed.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error("invalid aggregator {input:?}: {reason}")]
pub struct ParseAggregatorError {
    /// The text given.
    pub input: String,
    /// What was expected.
    pub reason: String,
}
