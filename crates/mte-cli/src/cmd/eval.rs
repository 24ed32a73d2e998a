//! `mte eval policy`.

use std::io::Write as _;

use anyhow::{Context, Result, ensure};
use mte_eval::Reporter as _;
use mte_eval::corruption::CorruptionSpec;
use mte_eval::pusht::{EpisodeSpec, Execution, run_episode};

use crate::args::{Cli, EvalPolicyArgs, Format};
use crate::progress::Bar;

/// `mte eval policy`
pub fn policy(cli: &Cli, a: &EvalPolicyArgs) -> Result<()> {
    ensure!(a.episodes >= 1, "--episodes must be at least 1");
    let execution: Execution = a.execution.parse().with_context(|| {
        format!(
            "--execution {:?}: expected open-loop or an aggregator",
            a.execution
        )
    })?;
    let p = mte_policy::load_policy(&a.checkpoint)
        .with_context(|| format!("loading {}", a.checkpoint.display()))?;
    let needs = p.needs();
    let bar = Bar::new(!cli.no_progress && !cli.quiet);
    bar.start("episodes", a.episodes as u64);
    let t0 = std::time::Instant::now();
    let mut out = Vec::new();
    for i in 0..a.episodes {
        let seed = a.seed + i as u64;
        let spec = EpisodeSpec {
            needs,
            seed,
            stream: a.stream.into(),
            h: a.stride,
            max_steps: a.max_steps,
            execution,
            corruption: &CorruptionSpec::CLEAN,
            noise_seed: a.noise_seed,
        };
        out.push(run_episode(p.as_ref(), &spec)?);
        bar.advance(1);
    }
    bar.finish();
    let n = out.len() as f64;
    let succ = out.iter().filter(|o| o.success).count();
    let mean_max = out.iter().map(|o| o.max_coverage).sum::<f64>() / n;
    let secs = t0.elapsed().as_secs_f64();
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(
            so,
            "{}",
            serde_json::json!({"episodes": out, "success_rate": succ as f64 / n, "mean_max_coverage": mean_max, "seconds": secs, "horizon": p.horizon(), "machine": mte_eval::machine::Machine::detect()})
        )?,
        Format::Text => writeln!(
            so,
            "{succ}/{} successful, mean max coverage {mean_max:.3} ({} , h = {}), {secs:.0} s",
            out.len(),
            a.execution,
            a.stride
        )?,
    }
    Ok(())
}
