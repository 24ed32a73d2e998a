//! `mte attack calibrate`.

use std::io::Write as _;

use anyhow::{Context, Result, ensure};
use mte_eval::calibrate::{CalibrationSpec, calibrate as run_calibration};
use mte_eval::sweep::{CheckpointSource, PolicySource as _};

use crate::args::{CalibrateArgs, Cli, Format};
use crate::progress::Bar;

/// `mte attack calibrate`
pub fn calibrate(cli: &Cli, a: &CalibrateArgs) -> Result<()> {
    ensure!(a.episodes >= 1, "--episodes must be at least 1");
    let arm = a
        .arm
        .parse()
        .with_context(|| format!("--arm {:?}: expected open-loop or an aggregator", a.arm))?;
    let (policy, needs) = CheckpointSource
        .load(&a.policy.to_string_lossy())
        .map_err(anyhow::Error::msg)?;
    let spec = CalibrationSpec {
        arm,
        h: a.stride,
        q: a.q,
        seeds: (0..a.episodes as u64).map(|i| 100_000 + i).collect(),
        iterations: a.iterations.clone(),
        steps: a.steps.clone(),
        eps: a.eps,
        tolerance: a.tolerance,
        max_steps: a.max_steps,
        noise_seed: 0,
    };
    let bar = Bar::new(!cli.no_progress && !cli.quiet);
    let t0 = std::time::Instant::now();
    let rows = run_calibration(policy.as_ref(), needs, &spec, &bar)?;
    let secs = t0.elapsed().as_secs_f64();
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(so, "{}", serde_json::json!({"rows": rows, "seconds": secs}))?,
        Format::Text => {
            writeln!(
                so,
                "PGD calibration against {} (eps {}, q = {}, h = {}, {} episodes), {secs:.0} s",
                a.arm, a.eps, a.q, a.stride, a.episodes
            )?;
            writeln!(so, "| step | iterations | mean max coverage | success | |")?;
            writeln!(so, "|--:|--:|--:|--:|:--|")?;
            for r in &rows {
                writeln!(
                    so,
                    "| {} | {} | {:.3} | {:.0}% | {} |",
                    if r.iterations == 0 {
                        "clean".to_string()
                    } else {
                        r.step.to_string()
                    },
                    r.iterations,
                    r.mean_coverage,
                    100.0 * r.success_rate,
                    if r.stopped {
                        "no further gain: stop"
                    } else {
                        ""
                    }
                )?;
            }
        }
    }
    Ok(())
}
