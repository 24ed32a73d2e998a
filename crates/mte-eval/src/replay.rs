//! Replay a recorded chunk stream through an aggregator.
//!
//! Input: JSON Lines, one query per line, in increasing query time:
//!
//! ```json
//! {"t": 0, "chunk": [[0.1, 0.2], [0.3, 0.4]], "corrupted": false}
//! ```
//!
//! - `t`: control time the query fired (integer steps);
//! - `chunk`: `t_p` rows of `d` actions; row `r` is the action for time `t - (t_o - 1) + r`
//!   (`t_o` is given to [`replay`], since the file cannot know it);
//! - `corrupted` (optional, default `false`): whether the evaluator corrupted the query.
//!
//! Blank lines are skipped. Every line must have the same `t_p` and `d`, and `t` at most
//! [`MAX_QUERY_TIME`]. Output: one [`ReplayStep`] per covered control time from the first
//! query to the last time any chunk covers; a run of control times no chunk covers is one
//! step with `error` and, when it spans more than one time, `through` (never skipped
//! silently). Memory and output are bounded by the number of queries and the chunk window,
//! not by the time span: a stream jumping from `t = 0` to `t = 10^12` writes one gap record.

use std::io::BufRead;

use mte_ensemble::{
    Aggregator, ChunkGeometry, EnsembleError, EnsemblerOptions, QueryMeta, StepReport,
    TemporalEnsembler,
};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// The largest query time a stream may hold: `2^62`, far beyond any episode (a 1 kHz
/// controller reaches it after 146 million years) and far enough from `u64::MAX` that
/// `t + t_p` cannot overflow.
pub const MAX_QUERY_TIME: u64 = 1 << 62;

/// One recorded query.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChunkRecord {
    /// Control time the query fired.
    pub t: u64,
    /// `t_p` rows of `d` actions.
    pub chunk: Vec<Vec<f32>>,
    /// Whether the query was corrupted (evaluation only).
    #[serde(default)]
    pub corrupted: bool,
}

/// A malformed stream or an impossible replay. Line numbers count from 1.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum ReplayError {
    /// The input could not be read.
    #[error("reading the chunk stream: {0}")]
    Io(#[from] std::io::Error),
    /// A line is not a valid record.
    #[error("line {line}: {message}")]
    Parse {
        /// Line number.
        line: usize,
        /// What is wrong (from the JSON parser).
        message: String,
    },
    /// A chunk has no rows or a row has no values.
    #[error("line {line}: empty chunk: expected t_p >= 1 rows of d >= 1 actions")]
    EmptyChunk {
        /// Line number.
        line: usize,
    },
    /// A chunk's shape differs from the first line's, or its rows differ in length.
    #[error("line {line}: chunk is {got}, expected {expected} like line {first_line}")]
    Shape {
        /// Line number.
        line: usize,
        /// Shape found, `rows x cols` (or `row i has n values`).
        got: String,
        /// Shape expected.
        expected: String,
        /// The line that fixed the shape.
        first_line: usize,
    },
    /// Query times do not increase.
    #[error("line {line}: query time t = {t} is not after the previous line's t = {previous}")]
    NotIncreasing {
        /// Line number.
        line: usize,
        /// Its query time.
        t: u64,
        /// The previous line's query time.
        previous: u64,
    },
    /// A query time beyond [`MAX_QUERY_TIME`].
    #[error("line {line}: query time t = {t} is too large: expected t <= {max} (2^62)")]
    TimeOutOfRange {
        /// Line number.
        line: usize,
        /// Its query time.
        t: u64,
        /// [`MAX_QUERY_TIME`].
        max: u64,
    },
    /// The stream holds no record.
    #[error("the chunk stream is empty: expected at least one JSON line")]
    Empty,
    /// `t_o` does not fit the chunks.
    #[error("t_o = {t_o} does not fit chunks of t_p = {t_p} rows: {source}")]
    Geometry {
        /// Observation steps given.
        t_o: usize,
        /// Rows per chunk.
        t_p: usize,
        /// Why.
        source: mte_ensemble::GeometryError,
    },
    /// The ensembler refused a chunk (line given).
    #[error("line {line}: {source}")]
    Insert {
        /// Line number.
        line: usize,
        /// Why.
        source: EnsembleError,
    },
}

/// A parsed stream: records with their line numbers, and the common shape.
#[derive(Debug, Clone, PartialEq)]
pub struct ChunkStream {
    /// Records in order, with the 1-based line each came from.
    pub records: Vec<(usize, ChunkRecord)>,
    /// Rows per chunk.
    pub t_p: usize,
    /// Actions per row.
    pub dim: usize,
}

/// Reads and checks a whole stream before anything is aggregated.
pub fn read_stream(input: impl BufRead) -> Result<ChunkStream, ReplayError> {
    let mut records: Vec<(usize, ChunkRecord)> = Vec::new();
    let mut shape: Option<(usize, usize, usize)> = None; // t_p, d, first line
    for (i, line) in input.lines().enumerate() {
        let line_no = i + 1;
        let text = line?;
        if text.trim().is_empty() {
            continue;
        }
        let rec: ChunkRecord = serde_json::from_str(&text).map_err(|e| ReplayError::Parse {
            line: line_no,
            message: e.to_string(),
        })?;
        let rows = rec.chunk.len();
        let cols = rec.chunk.first().map_or(0, Vec::len);
        if rows == 0 || cols == 0 {
            return Err(ReplayError::EmptyChunk { line: line_no });
        }
        let (t_p, d, first_line) = *shape.get_or_insert((rows, cols, line_no));
        if let Some((r, row)) = rec.chunk.iter().enumerate().find(|(_, row)| row.len() != d) {
            return Err(ReplayError::Shape {
                line: line_no,
                got: format!("ragged: row {r} has {} values", row.len()),
                expected: format!("{d} values per row"),
                first_line,
            });
        }
        if rows != t_p {
            return Err(ReplayError::Shape {
                line: line_no,
                got: format!("{rows} x {cols}"),
                expected: format!("{t_p} x {d}"),
                first_line,
            });
        }
        if rec.t > MAX_QUERY_TIME {
            return Err(ReplayError::TimeOutOfRange {
                line: line_no,
                t: rec.t,
                max: MAX_QUERY_TIME,
            });
        }
        if let Some((_, prev)) = records.last().filter(|(_, prev)| rec.t <= prev.t) {
            return Err(ReplayError::NotIncreasing {
                line: line_no,
                t: rec.t,
                previous: prev.t,
            });
        }
        records.push((line_no, rec));
    }
    let (t_p, dim, _) = shape.ok_or(ReplayError::Empty)?;
    Ok(ChunkStream { records, t_p, dim })
}

/// The outcome at one control time, or at a run of control times no chunk covers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReplayStep {
    /// Control time (the first of the run, for an uncovered run).
    pub tau: u64,
    /// The last control time of an uncovered run longer than one step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub through: Option<u64>,
    /// The executed action, absent when none could be computed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub action: Option<Vec<f32>>,
    /// Counts and regime, when an action was computed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub report: Option<StepReport>,
    /// Why no action was computed (no chunk covers `tau`, or none is finite).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// Aggregates `stream` with `aggregator`, reading rows as a policy with `t_o` observation
/// steps wrote them, and collects the steps. Queries may come at any stride.
pub fn replay(
    stream: &ChunkStream,
    t_o: usize,
    aggregator: Aggregator,
) -> Result<Vec<ReplayStep>, ReplayError> {
    let mut steps = Vec::new();
    replay_each(stream, t_o, aggregator, |s| {
        steps.push(s);
        Ok::<(), std::convert::Infallible>(())
    })
    .map_err(|e| match e {
        SinkOr::Replay(e) => e,
        SinkOr::Sink(never) => match never {},
    })?;
    Ok(steps)
}

/// A replay error or an error of the step sink.
#[derive(Debug, Error)]
pub enum SinkOr<E> {
    /// The replay failed.
    #[error(transparent)]
    Replay(ReplayError),
    /// The sink failed.
    #[error("{0}")]
    Sink(E),
}

impl<E> From<ReplayError> for SinkOr<E> {
    fn from(e: ReplayError) -> Self {
        Self::Replay(e)
    }
}

/// As [`replay`], handing each step to `sink` as soon as it is computed (memory bounded by
/// the chunk window). Each uncovered run is handed over once, when the next chunk arrives.
pub fn replay_each<E>(
    stream: &ChunkStream,
    t_o: usize,
    aggregator: Aggregator,
    mut sink: impl FnMut(ReplayStep) -> Result<(), E>,
) -> Result<(), SinkOr<E>> {
    let mut ens = ensembler(stream, t_o, aggregator)?;
    let span = ens.geometry().span() as u64;
    let first = stream.records[0].1.t;
    // read_stream bounds t by MAX_QUERY_TIME, so this cannot overflow.
    let last = stream.records[stream.records.len() - 1].1.t + span - 1;
    let mut next = 0;
    let mut flat = Vec::with_capacity(stream.t_p * stream.dim);
    let mut tau = first;
    while tau <= last {
        while let Some((line, rec)) = stream.records.get(next).filter(|(_, r)| r.t == tau) {
            flat.clear();
            flat.extend(rec.chunk.iter().flatten());
            let meta = QueryMeta {
                corrupted: rec.corrupted,
            };
            ens.insert(rec.t, &flat, meta).map_err(|source| {
                SinkOr::Replay(ReplayError::Insert {
                    line: *line,
                    source,
                })
            })?;
            next += 1;
        }
        match ens.action(tau) {
            Ok(step) => sink(ReplayStep::action(tau, step.action, step.report)),
            Err(e @ EnsembleError::NoCandidates { .. }) => {
                // Nothing covers tau, so nothing covers any time before the next query.
                let until = stream.records.get(next).map_or(last, |(_, r)| r.t - 1);
                sink(ReplayStep::failed(tau, (until > tau).then_some(until), &e))
                    .map_err(SinkOr::Sink)?;
                // Every live chunk ended before tau: start afresh at the next query.
                ens.reset();
                tau = until + 1;
                continue;
            }
            Err(e) => sink(ReplayStep::failed(tau, None, &e)),
        }
        .map_err(SinkOr::Sink)?;
        tau += 1;
    }
    Ok(())
}

/// The ensembler a replay of `stream` runs: the stream's chunk length and action size,
/// `t_o`, stride 1. The stride only bounds how far ahead chunks may be inserted; the replay
/// inserts each chunk at its own time, so h = 1 is exact for any stride.
fn ensembler(
    stream: &ChunkStream,
    t_o: usize,
    aggregator: Aggregator,
) -> Result<TemporalEnsembler, ReplayError> {
    let geometry =
        ChunkGeometry::new(stream.t_p, t_o, 1).map_err(|source| ReplayError::Geometry {
            t_o,
            t_p: stream.t_p,
            source,
        })?;
    TemporalEnsembler::with_options(
        geometry,
        stream.dim,
        aggregator,
        EnsemblerOptions::default(),
    )
    .map_err(|source| ReplayError::Insert {
        line: stream.records[0].0,
        source,
    })
}

impl ReplayStep {
    /// The action computed at `tau`.
    fn action(tau: u64, action: &[f32], report: StepReport) -> Self {
        Self {
            tau,
            through: None,
            action: Some(action.to_vec()),
            report: Some(report),
            error: None,
        }
    }

    /// No action at `tau` (through `through`, for an uncovered run), for reason `e`.
    fn failed(tau: u64, through: Option<u64>, e: &EnsembleError) -> Self {
        Self {
            tau,
            through,
            action: None,
            report: None,
            error: Some(e.to_string()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stream(text: &str) -> Result<ChunkStream, ReplayError> {
        read_stream(text.as_bytes())
    }

    #[test]
    fn replays_with_gaps_reported_not_skipped() {
        let s = stream(
            "{\"t\": 0, \"chunk\": [[0.0], [1.0], [2.0]]}\n\n\
             {\"t\": 1, \"chunk\": [[1.5], [2.5], [3.5]], \"corrupted\": true}\n\
             {\"t\": 6, \"chunk\": [[6.0], [7.0], [8.0]]}\n",
        )
        .unwrap();
        assert_eq!((s.t_p, s.dim, s.records.len()), (3, 1, 3));
        let steps = replay(&s, 1, Aggregator::MEDIAN).unwrap();
        assert_eq!(steps.len(), 8); // tau 0..=3, the gap 4..=5 as one record, 6..=8
        assert_eq!(steps[1].action, Some(vec![1.25]));
        assert_eq!(steps[1].report.unwrap().q, 1);
        assert_eq!((steps[4].tau, steps[4].through), (4, Some(5)));
        assert!(steps[4].action.is_none() && steps[4].error.as_ref().unwrap().contains("no chunk"));
        assert_eq!((steps[5].tau, steps[5].through), (6, None));
        assert_eq!(steps[7].action, Some(vec![8.0]));
    }

    /// Against a naive per-time oracle of coverage: every covered time gets an action, and
    /// the gap records tile exactly the uncovered times.
    #[test]
    fn gap_records_tile_the_uncovered_times() {
        let times = [0u64, 2, 3, 9, 30, 31];
        let text: String = times
            .iter()
            .map(|t| format!("{{\"t\": {t}, \"chunk\": [[{t}.0], [{t}.5], [{t}.75]]}}\n"))
            .collect();
        let steps = replay(&stream(&text).unwrap(), 1, Aggregator::Latest).unwrap();
        let mut expected_tau = 0;
        for s in &steps {
            assert_eq!(s.tau, expected_tau, "{s:?}");
            let covering: Vec<u64> = times
                .iter()
                .copied()
                .filter(|&t| t <= s.tau && s.tau < t + 3)
                .collect();
            match s.through {
                Some(end) => {
                    assert!(covering.is_empty() && s.action.is_none(), "{s:?}");
                    assert!(
                        (s.tau..=end).all(|tau| !times.iter().any(|&t| t <= tau && tau < t + 3))
                    );
                    expected_tau = end + 1;
                }
                None => {
                    assert_eq!(s.action.is_some(), !covering.is_empty(), "{s:?}");
                    expected_tau = s.tau + 1;
                }
            }
        }
        assert_eq!(expected_tau, 31 + 3);
    }

    #[test]
    fn a_huge_time_jump_is_one_gap_record_and_overflow_is_refused() {
        let s = stream(
            "{\"t\": 0, \"chunk\": [[0.0], [1.0]]}\n{\"t\": 1000000000000, \"chunk\": [[2.0], [3.0]]}\n",
        )
        .unwrap();
        let steps = replay(&s, 1, Aggregator::MEDIAN).unwrap();
        assert_eq!(steps.len(), 5, "{steps:?}");
        assert_eq!((steps[2].tau, steps[2].through), (2, Some(999_999_999_999)));
        assert_eq!(steps[4].action, Some(vec![3.0]));
        for t in [u64::MAX, MAX_QUERY_TIME + 1] {
            let e = stream(&format!("{{\"t\": {t}, \"chunk\": [[0.0]]}}\n"))
                .unwrap_err()
                .to_string();
            assert!(e.contains(&format!("t = {t} is too large")), "{e}");
        }
        let last = stream(&format!(
            "{{\"t\": {MAX_QUERY_TIME}, \"chunk\": [[0.0], [1.0]]}}\n"
        ))
        .unwrap();
        let steps = replay(&last, 1, Aggregator::MEDIAN).unwrap();
        assert_eq!(steps.len(), 2);
        assert_eq!(steps[1].tau, MAX_QUERY_TIME + 1);
    }

    #[test]
    fn malformed_lines_are_named() {
        let cases = [
            (
                "{\"t\": 0, \"chunk\": [[0.0]]}\n{\"t\": 1, \"chunk\": 5}\n",
                "line 2",
            ),
            (
                "{\"t\": 0, \"chunk\": [[0.0], [1.0, 2.0]]}\n",
                "ragged: row 1 has 2 values",
            ),
            (
                "{\"t\": 0, \"chunk\": [[0.0]]}\n{\"t\": 1, \"chunk\": [[0.0], [1.0]]}\n",
                "2 x 1",
            ),
            (
                "{\"t\": 3, \"chunk\": [[0.0]]}\n{\"t\": 3, \"chunk\": [[0.0]]}\n",
                "t = 3 is not after",
            ),
            ("{\"t\": 0, \"chunk\": []}\n", "line 1: empty chunk"),
            (
                "{\"t\": 0, \"chunk\": [[0.0]], \"extra\": 1}\n",
                "unknown field `extra`",
            ),
            ("\n\n", "empty"),
        ];
        for (text, needle) in cases {
            let e = stream(text).unwrap_err().to_string();
            assert!(e.contains(needle), "{text:?}: {e}");
        }
    }

    #[test]
    fn t_o_must_fit_the_chunks() {
        let s = stream("{\"t\": 0, \"chunk\": [[0.0], [1.0]]}\n").unwrap();
        let e = replay(&s, 3, Aggregator::MEDIAN).unwrap_err().to_string();
        assert!(e.contains("t_o = 3") && e.contains("t_p = 2"), "{e}");
    }
}
