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
    only: &[String],
    out: &Path,
    opts: &ReportOptions,
    figure2: bool,
) -> Result<()> {
    let (mut manifest, mut lines) = mte_eval::store::load_runs(runs)?;
    mte_eval::store::keep_cells(&mut manifest, &mut lines, only)?;
    let mut r = report::build(&manifest, &lines, opts).context("building the report")?;
    if figure2 && let Some(f) = r.figure2.as_mut() {
        let stream = run_stream(&runs[0])?;
        let arms = [r.baseline.parse()?, r.robust.parse()?];
        let films = crate::cmd::film::shoot(&crate::cmd::film::Shoot {
            policy: Path::new(&f.policy),
            seed: f.seed,
            stream,
            h: f.h,
            max_steps: f.max_steps,
            corruption: &f.corruption,
            noise_seed: manifest.noise_seed,
            arms,
            size: 128,
        })
        .context("filming Figure 2")?;
        for (film, (success, coverage)) in films.iter().zip([f.baseline, f.robust]) {
            let same = film.record.success == success && film.record.max_coverage == coverage;
            if !same {
                r.notes.push(format!(
                    "Figure 2: the filmed `{}` episode (max coverage {:.3}) differs from the recorded \
                     one ({coverage:.3}): the run was made on another CPU or mte version",
                    film.record.arm, film.record.max_coverage
                ));
            }
        }
        f.files = crate::cmd::film::write_figure(out, &films)?;
    }
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

/// The reset stream of a run directory's sweep spec (legacy where it has none).
fn run_stream(run: &Path) -> Result<mte_sim::ResetStream> {
    let path = run.join("spec.toml");
    if !path.exists() {
        return Ok(mte_sim::ResetStream::Legacy);
    }
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let spec = mte_eval::sweep::SweepSpec::from_toml(&text)
        .with_context(|| format!("parsing {}", path.display()))?;
    Ok(spec.stream)
}

/// `mte report`
pub fn run(cli: &Cli, a: &ReportArgs) -> Result<()> {
    let out = a.out.clone().unwrap_or_else(|| a.runs[0].clone());
    let opts = ReportOptions {
        baseline_arm: a.baseline.clone(),
        robust_arm: a.robust.clone(),
        focus_cell: a.cell.clone(),
        defence: a.defence.clone(),
        controls: a.control.clone(),
        mcnemar: a.mcnemar,
    };
    write_and_print(cli, &a.runs, &a.only, &out, &opts, a.figure2)
}
