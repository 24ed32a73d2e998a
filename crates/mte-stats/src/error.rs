//! The error type shared by every function of the crate.
//!
//! Every variant carries the values that made the input invalid, so a caller can report
//! *what* was wrong, not only that something was.

use thiserror::Error;

/// Why a statistic could not be computed from its input.
#[derive(Debug, Clone, Copy, PartialEq, Error)]
#[non_exhaustive]
pub enum StatsError {
    /// A sample that needs at least one element was empty.
    #[error("`{argument}` is empty: at least one observation is needed")]
    EmptySample {
        /// Name of the argument that was empty.
        argument: &'static str,
    },
    /// A sample had fewer elements than the statistic needs.
    #[error("`{argument}` has {got} element(s), but at least {needed} are needed")]
    TooFewSamples {
        /// Name of the argument that was too short.
        argument: &'static str,
        /// Minimum number of elements.
        needed: usize,
        /// Number of elements given.
        got: usize,
    },
    /// Two slices that must be paired element by element had different lengths.
    #[error("paired samples differ in length: {left} vs {right}")]
    LengthMismatch {
        /// Length of the first slice.
        left: usize,
        /// Length of the second slice.
        right: usize,
    },
    /// An input value (or a value derived from it, such as a paired difference) was NaN or
    /// infinite.
    #[error("`{argument}`[{index}] = {value} is not finite")]
    NonFinite {
        /// Name of the argument (or derived quantity) holding the value.
        argument: &'static str,
        /// Position of the value in that argument.
        index: usize,
        /// The offending value.
        value: f64,
    },
    /// A count of successes exceeded the number of trials.
    #[error("{successes} successes out of {total} trials: successes must not exceed the total")]
    CountExceedsTotal {
        /// Successes given.
        successes: u64,
        /// Trials given.
        total: u64,
    },
    /// A number of trials was zero where at least one is needed.
    #[error("`{argument}` = 0 trials: at least one trial is needed")]
    ZeroTrials {
        /// Name of the argument that was zero.
        argument: &'static str,
    },
    /// A number of trials exceeded what the crate supports (2^53, so counts are exact `f64`s).
    #[error("{n} trials exceed the supported maximum of {max}")]
    TooManyTrials {
        /// Trials given.
        n: u64,
        /// Largest supported number of trials.
        max: u64,
    },
    /// A probability (or proportion) was NaN or outside `[0, 1]`.
    #[error("probability {value} is not in [0, 1]")]
    InvalidProbability {
        /// The offending value.
        value: f64,
    },
    /// A p-value in a family of p-values was NaN or outside `[0, 1]`.
    #[error("p-value #{index} = {value} is not in [0, 1]")]
    InvalidPValue {
        /// Position in the family.
        index: usize,
        /// The offending value.
        value: f64,
    },
    /// A confidence level was NaN or outside the open interval `(0, 1)`.
    #[error("confidence level {value} is not in (0, 1)")]
    InvalidConfidence {
        /// The offending value.
        value: f64,
    },
    /// The recovered fraction is undefined because the attack did not move the metric.
    #[error(
        "recovered fraction undefined: clean = undefended = {clean} (the attack changed nothing)"
    )]
    UndefinedRecovery {
        /// Metric without attack.
        clean: f64,
        /// Metric under attack without defence (equal to `clean`).
        undefended: f64,
    },
    /// Every paired difference was zero, so a signed-rank test has nothing to rank.
    #[error("all {n} paired differences are zero: the signed-rank test is undefined")]
    AllZeroDifferences {
        /// Number of pairs given (all of them ties).
        n: usize,
    },
}

/// Result alias used throughout the crate.
pub type Result<T> = std::result::Result<T, StatsError>;

/// Checks that every value of `values` is finite; names `argument` in the error.
pub(crate) fn check_finite(argument: &'static str, values: &[f64]) -> Result<()> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(StatsError::NonFinite {
            argument,
            index,
            value: values[index],
        }),
        None => Ok(()),
    }
}

/// Checks that `values` is non-empty and finite.
pub(crate) fn check_sample(argument: &'static str, values: &[f64]) -> Result<()> {
    if values.is_empty() {
        return Err(StatsError::EmptySample { argument });
    }
    check_finite(argument, values)
}

/// Checks that `p` is a probability in `[0, 1]` (NaN rejected).
pub(crate) fn check_probability(p: f64) -> Result<()> {
    if (0.0..=1.0).contains(&p) {
        Ok(())
    } else {
        Err(StatsError::InvalidProbability { value: p })
    }
}
