//! `mte data generate`.

use std::io::Write as _;

use anyhow::{Context, Result};
use mte_data::{GenerateConfig, generate as run_generate};
use mte_sim::expert::ExpertConfig;

use crate::args::{Cli, DataGenerateArgs, Format};
use crate::progress::Bar;

/// `mte data generate`
pub fn generate(cli: &Cli, a: &DataGenerateArgs) -> Result<()> {
    let config = GenerateConfig {
        episodes: a.episodes,
        seed: a.seed,
        stream: a.stream.into(),
        obs: a.obs,
        image_size: (a.image_size, a.image_size),
        max_steps: a.max_steps,
        expert: ExpertConfig {
            action_noise: a.action_noise,
            travel_step: a.travel_step,
            push_step: a.push_step,
            ..ExpertConfig::default()
        },
    };
    config.validate().context("check the generate flags")?;
    let mut pool = rayon::ThreadPoolBuilder::new();
    if let Some(t) = a.threads {
        anyhow::ensure!(t >= 1, "--threads must be at least 1");
        pool = pool.num_threads(t);
    }
    let pool = pool.build()?;
    let bar = Bar::new(!cli.no_progress && !cli.quiet);
    use mte_eval::Reporter as _;
    bar.start("episodes", a.episodes as u64);
    let successes = std::sync::atomic::AtomicUsize::new(0);
    let t0 = std::time::Instant::now();
    let info = pool
        .install(|| {
            run_generate(&config, &a.out, &|m| {
                if m.success {
                    successes.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                }
                bar.advance(1);
            })
        })
        .with_context(|| format!("generating into {}", a.out.display()))?;
    bar.finish();
    let ok = successes.into_inner();
    let secs = t0.elapsed().as_secs_f64();
    let mut out = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(
            out,
            "{}",
            serde_json::json!({ "out": a.out, "episodes": info.episodes, "frames": info.frames, "successes": ok, "seconds": secs })
        )?,
        Format::Text => {
            if !cli.quiet {
                writeln!(
                    out,
                    "{} episodes ({ok} successful), {} frames in {:.1} s -> {}",
                    info.episodes,
                    info.frames,
                    secs,
                    a.out.display()
                )?;
            }
        }
    }
    Ok(())
}
