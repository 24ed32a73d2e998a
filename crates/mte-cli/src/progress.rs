//! The one progress interface of the binary: an indicatif bar on stderr, hidden for
//! `--no-progress`, `-q`, or when stderr is not a terminal. It implements
//! [`mte_eval::Reporter`] for sweeps and calibration, and carries a running figure (a loss)
//! for training, patch training and fine-tuning.

use std::io::IsTerminal;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use mte_eval::Reporter;

use crate::args::Cli;

/// A progress bar that may be hidden.
pub struct Bar {
    bar: ProgressBar,
}

impl Bar {
    /// A bar, visible only if `show` and stderr is a terminal; its label and length come
    /// with [`Reporter::start`].
    pub fn new(show: bool) -> Self {
        let bar = ProgressBar::with_draw_target(
            Some(0),
            if show && std::io::stderr().is_terminal() {
                ProgressDrawTarget::stderr()
            } else {
                ProgressDrawTarget::hidden()
            },
        );
        let style = ProgressStyle::with_template(
            "{prefix:>20} [{elapsed_precise}] {wide_bar} {pos}/{len} {msg} ({eta} left)",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar());
        bar.set_style(style);
        Self { bar }
    }

    /// A bar of `len` units of `label`, shown unless the command line hides progress.
    pub fn for_cli(cli: &Cli, label: &str, len: usize) -> Self {
        let b = Self::new(!cli.no_progress && !cli.quiet);
        b.start(label, len as u64);
        b
    }

    /// Moves to `pos` units done, showing `figure` (a loss, say) beside the bar.
    pub fn set(&self, pos: u64, figure: Option<String>) {
        self.bar.set_position(pos);
        if let Some(f) = figure {
            self.bar.set_message(f);
        }
    }
}

impl Reporter for Bar {
    fn start(&self, label: &str, total: u64) {
        self.bar.set_prefix(label.to_string());
        self.bar.set_message("");
        self.bar.set_length(total);
        self.bar.set_position(0);
    }

    fn advance(&self, n: u64) {
        self.bar.inc(n);
    }

    fn finish(&self) {
        self.bar.finish_and_clear();
    }
}
