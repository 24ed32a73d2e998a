//! The terminal implementation of [`mte_eval::Reporter`]: an indicatif progress bar on
//! stderr, hidden for `--no-progress`, `-q`, or when stderr is not a terminal.

use std::io::IsTerminal;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use mte_eval::Reporter;

/// A progress bar that may be hidden.
pub struct Bar {
    bar: ProgressBar,
}

impl Bar {
    /// A bar, visible only if `show` and stderr is a terminal.
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
            "{msg:>20} [{elapsed_precise}] {wide_bar} {pos}/{len} ({eta} left)",
        )
        .unwrap_or_else(|_| ProgressStyle::default_bar());
        bar.set_style(style);
        Self { bar }
    }
}

impl Reporter for Bar {
    fn start(&self, label: &str, total: u64) {
        self.bar.set_message(label.to_string());
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
