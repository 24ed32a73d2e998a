//! `mte report`: tables, paired tests and plots from run directories.

use std::io::Write as _;
use std::path::Path;

use anyhow::{Context, Result};
use mte_eval::report::{self, ReportOptions};

use crate::args::{Cli, Format, ReportArgs};

/// Builds the report of `runs`, writes it to `out` and prints it.
pub fn write_and_print(
    cli: &Cli,
    runs: &[std::path::PathBuf],
    out: &Path,
    opts: &ReportOptions,
) -> Result<()> {
    let (manifest, lines) = mte_eval::store::load_runs(runs)?;
    let r = report::build(&manifest, &lines, opts).context("building the report")?;
    let files = r
        .write(out)
        .with_context(|| format!("writing the report into {}", out.display()))?;
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(
            so,
            "{}",
            serde_json::json!({"files": files, "markdown": r.markdown()})
        )?,
        Format::Text => {
            if !cli.quiet {
                writeln!(so, "{}", r.markdown())?;
                writeln!(so, "report: {}", out.join("report.html").display())?;
            }
        }
    }
    Ok(())
}

/// `mte report`
pub fn run(cli: &Cli, a: &ReportArgs) -> Result<()> {
    let out = a.out.clone().unwrap_or_else(|| a.runs[0].clone());
    let opts = ReportOptions {
        baseline_arm: a.baseline.clone(),
        robust_arm: a.robust.clone(),
        focus_cell: a.cell.clone(),
        defence: a.defence.clone(),
    };
    write_and_print(cli, &a.runs, &out, &opts)
}
