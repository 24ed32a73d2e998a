//! `mte sweep`: run a TOML grid into a run directory.

use std::io::Write as _;
use std::path::Path;

use anyhow::{Context, Result};
use mte_eval::store::RunDir;
use mte_eval::sweep::{
    self, CheckpointSource, CheckpointSourceOn, PolicySource, RunOptions, Shard, SweepSpec,
    SweepSummary,
};
use mte_policy::ComputeDevice;

use crate::args::{Cli, Format, SweepArgs};
use crate::progress::Bar;

/// `git rev-parse HEAD` of the working directory, when git and a repository are there.
pub fn git_commit() -> Option<String> {
    let out = std::process::Command::new("git")
        .args(["rev-parse", "HEAD"])
        .output()
        .ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
        .filter(|s| !s.is_empty())
}

/// Seconds since the Unix epoch.
pub fn now_unix() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// Worker count (the flag, else every core) and lockstep group size.
pub fn options(workers: Option<usize>, batch: usize) -> Result<RunOptions> {
    let workers = match workers {
        Some(0) => anyhow::bail!("--workers must be at least 1"),
        Some(n) => n,
        None => std::thread::available_parallelism().map_or(1, |n| n.get()),
    };
    Ok(RunOptions { workers, batch })
}

/// Where a sweep's policies run: the CPU, or the opened `device`.
pub fn policy_source(device: ComputeDevice) -> Result<Box<dyn PolicySource>> {
    Ok(match device {
        ComputeDevice::Cpu => Box::new(CheckpointSource),
        other => Box::new(CheckpointSourceOn(
            other.open().with_context(|| format!("--device {other}"))?,
        )),
    })
}

/// Creates or resumes `out` and runs `shard` of `spec` in it, the policies on `device`.
pub fn execute(
    cli: &Cli,
    spec: &SweepSpec,
    out: &Path,
    resume: bool,
    shard: Shard,
    options: RunOptions,
    device: ComputeDevice,
) -> Result<SweepSummary> {
    let source = policy_source(device)?;
    let mut manifest = spec.manifest(git_commit(), now_unix());
    for m in &mut manifest.machines {
        *m = m.clone().with_policies_on(device);
    }
    let run = RunDir::create(out, &spec.to_toml()?, &manifest, resume)?;
    let bar = Bar::new(!cli.no_progress && !cli.quiet);
    // Cells and commit come from the stored manifest when resuming (same grid, checked).
    let stored = mte_eval::store::read_manifest(run.root())?;
    let summary = sweep::run(spec, &stored, &run, shard, options, source.as_ref(), &bar)?;
    Ok(summary)
}

/// `mte sweep`
pub fn run(cli: &Cli, a: &SweepArgs) -> Result<()> {
    let text = std::fs::read_to_string(&a.spec)
        .with_context(|| format!("reading {}", a.spec.display()))?;
    let mut spec =
        SweepSpec::from_toml(&text).with_context(|| format!("in {}", a.spec.display()))?;
    if let Some(base) = a.spec.parent() {
        sweep::resolve_policies(&mut spec, base);
    }
    let shard: Shard = a.shard;
    let t0 = std::time::Instant::now();
    let s = execute(
        cli,
        &spec,
        &a.out,
        a.resume,
        shard,
        options(a.workers, a.batch)?,
        a.device,
    )?;
    print_summary(cli, &s, &a.out, t0.elapsed().as_secs_f64())?;
    fail_on_errors(&s, &a.out)
}

/// A sweep that recorded errors fails (exit 2) after its summary, naming the cells.
pub fn fail_on_errors(s: &SweepSummary, out: &Path) -> Result<()> {
    if s.failed_cells.is_empty() {
        return Ok(());
    }
    anyhow::bail!(
        "{} error record(s) in {} cell(s): {} (the reasons are the \"error\" lines of {})",
        s.errors,
        s.failed_cells.len(),
        s.failed_cells.join(", "),
        out.join("cells").display()
    )
}

/// Prints what a sweep did.
pub fn print_summary(cli: &Cli, s: &SweepSummary, out: &Path, secs: f64) -> Result<()> {
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(
            so,
            "{}",
            serde_json::json!({"summary": s, "seconds": secs, "run": out})
        )?,
        Format::Text => {
            if !cli.quiet {
                writeln!(
                    so,
                    "{} cells: {} episodes run, {} already done, {} errors in {secs:.0} s -> {}",
                    s.cells,
                    s.episodes_run,
                    s.episodes_skipped,
                    s.errors,
                    out.display()
                )?;
            }
        }
    }
    Ok(())
}
