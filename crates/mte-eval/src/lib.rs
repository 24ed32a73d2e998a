//! # mte-eval: measuring what an aggregator buys you
//!
//! Turns the pieces of mte into experiments whose outcomes pair episode by episode.
//!
//! - [`environment`]: the environment seam ([`environment::Environment`], native
//!   [`environment::PushTEnv`]); [`episode`]: an episode's named stages and the observer
//!   seam; [`pusht`]: chunked execution of a policy under corruption ([`corruption`]),
//!   paired across arms; [`sweep`], [`store`], [`record`]: grids run into resumable run
//!   directories; [`report`]: paired tests, tables and plots; [`machine`]: the CPU a run ran
//!   on; [`calibrate`]: PGD budget calibration; [`patch_file`]: trained patches on disk;
//!   [`train_data`]: the arrays a policy trains, is attacked or fine-tuned on, from a
//!   dataset; [`dispersion`]: how spread the candidates an aggregator combines are (the
//!   instrument of the clean-data confound); [`film`]: episodes drawn side by side (the
//!   paper's Figure 2); [`takeover`]: corrective demonstrations, the expert taking over
//!   from states a policy reached (DAgger's data).
//! - [`synthetic`]: a stress test without a simulator. A smooth reference trajectory, a
//!   chunked "policy" that predicts it with small noise, and a burst schedule that replaces
//!   `q` of every `M_min` queries with arbitrary values. Every aggregator sees the same
//!   streams, so tracking errors pair by episode.
//! - [`replay`]: aggregate a recorded chunk stream (JSON Lines) offline.
//! - [`Reporter`]: the progress seam. Libraries never print; the `mte` binary implements
//!   this trait with progress bars.
//!
//! Conventions: time in integer control steps, actions in the policy's units (PushT:
//! pixels of the 512 x 512 workspace), randomness always from an explicit seed.
#![deny(missing_docs)]

pub mod alignment;
pub mod bridge;
pub mod calibrate;
pub mod corruption;
pub mod dispersion;
pub mod environment;
pub mod episode;
pub mod expert_policy;
pub mod film;
mod label;
pub mod lockstep;
pub mod machine;
pub mod monitoring;
pub mod patch_file;
pub mod pusht;
pub mod record;
pub mod replay;
pub mod report;
pub mod store;
pub mod sweep;
pub mod synthetic;
pub mod takeover;
pub mod train_data;

/// Progress callbacks for long-running work. All methods default to doing nothing.
///
/// Implementations must be cheap: they are called once per episode.
pub trait Reporter: Sync {
    /// A phase with `total` units of work starts.
    fn start(&self, _label: &str, _total: u64) {}
    /// `n` more units are done.
    fn advance(&self, _n: u64) {}
    /// The phase is over.
    fn finish(&self) {}
}

/// A [`Reporter`] that reports nothing.
#[derive(Debug, Clone, Copy, Default)]
pub struct Silent;

impl Reporter for Silent {}
