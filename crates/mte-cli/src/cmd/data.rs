//! `mte data generate`, `mte data takeover`.

use std::io::Write as _;

use anyhow::{Context, Result};
use mte_data::{GenerateConfig, generate as run_generate};
use mte_sim::expert::ExpertConfig;

use crate::args::{Cli, DataGenerateArgs, DataTakeoverArgs, Format};
use crate::progress::Bar;

/// `mte data generate`
pub fn generate(cli: &Cli, a: &DataGenerateArgs) -> Result<()> {
    if let mte_eval::environment::EnvTarget::Bridge(target) = &a.env {
        return generate_bridged(cli, a, target);
    }
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
    let pool = thread_pool(a.threads)?;
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

/// `mte data generate --env <bridge target>`: the worker's scripted expert, recorded.
fn generate_bridged(
    cli: &Cli,
    a: &DataGenerateArgs,
    target: &mte_eval::bridge::Target,
) -> Result<()> {
    use mte_eval::Reporter as _;
    use mte_eval::bridge::expert::{DemoConfig, generate as record};
    let config = DemoConfig {
        target: target.clone(),
        episodes: a.episodes,
        first_seed: a.seed,
        max_steps: a.max_steps,
        image: a.obs.pixels.then_some((a.image_size, a.image_size)),
        wrist_image: a.obs.wrist,
        successes_only: !a.keep_failures,
        workers: a
            .threads
            .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, usize::from)),
    };
    let bar = Bar::new(!cli.no_progress && !cli.quiet);
    bar.start("episodes", a.episodes as u64);
    let t0 = std::time::Instant::now();
    let info = record(
        &config,
        &a.out,
        &mte_eval::bridge::BridgeOptions::default(),
        &|_| bar.advance(1),
    )
    .with_context(|| format!("recording {target}'s expert into {}", a.out.display()))?;
    bar.finish();
    let secs = t0.elapsed().as_secs_f64();
    let mut out = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(
            out,
            "{}",
            serde_json::json!({ "out": a.out, "env": target.to_string(), "episodes": info.episodes, "frames": info.frames, "seconds": secs })
        )?,
        Format::Text => {
            if !cli.quiet {
                writeln!(
                    out,
                    "{} episodes of {target}'s expert ({} frames) in {secs:.0} s -> {}",
                    info.episodes,
                    info.frames,
                    a.out.display()
                )?;
            }
        }
    }
    Ok(())
}

/// `mte data takeover`
pub fn takeover(cli: &Cli, a: &DataTakeoverArgs) -> Result<()> {
    use mte_eval::Reporter as _;
    use mte_eval::takeover::generate_takeover;
    let config = takeover_config(a)?;
    config.validate().context("check the takeover flags")?;
    let policy = mte_eval::sweep::load_named_policy(&a.checkpoint, &candle_core::Device::Cpu)
        .with_context(|| format!("loading {}", a.checkpoint.display()))?;
    let pool = thread_pool(a.threads)?;
    let bar = Bar::new(!cli.no_progress && !cli.quiet);
    bar.start("episodes", a.episodes as u64);
    let tally = std::sync::Mutex::new((0usize, 0usize, 0.0f64));
    let t0 = std::time::Instant::now();
    let name = a.checkpoint.display().to_string();
    let info = pool
        .install(|| {
            generate_takeover(policy.as_ref(), &name, &config, &a.out, &|e| {
                let mut t = tally
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner);
                t.0 += usize::from(e.policy_success);
                t.1 += usize::from(e.expert_success);
                t.2 += e.coverage_at_switch;
                bar.advance(1);
            })
        })
        .with_context(|| format!("recording takeovers into {}", a.out.display()))?;
    bar.finish();
    let (policy_done, expert_ok, coverage) = tally
        .into_inner()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let secs = t0.elapsed().as_secs_f64();
    let mean_switch_coverage = coverage / a.episodes as f64;
    let mut out = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(
            out,
            "{}",
            serde_json::json!({ "out": a.out, "episodes": a.episodes, "recorded": info.episodes, "frames": info.frames,
                "policy_finished_first": policy_done, "expert_successes": expert_ok,
                "mean_coverage_at_switch": mean_switch_coverage, "seconds": secs })
        )?,
        Format::Text => {
            if !cli.quiet {
                writeln!(
                    out,
                    "{} of {} episodes recorded ({policy_done} finished by the policy before the switch), \
                     {} frames, expert successful in {expert_ok}, mean coverage at the switch {mean_switch_coverage:.3}, \
                     {secs:.1} s -> {}",
                    info.episodes,
                    a.episodes,
                    info.frames,
                    a.out.display()
                )?;
            }
        }
    }
    Ok(())
}

/// The rayon pool of `--threads` (all cores when absent).
fn thread_pool(threads: Option<usize>) -> Result<rayon::ThreadPool> {
    let mut pool = rayon::ThreadPoolBuilder::new();
    if let Some(t) = threads {
        anyhow::ensure!(t >= 1, "--threads must be at least 1");
        pool = pool.num_threads(t);
    }
    Ok(pool.build()?)
}

/// `mte data takeover`'s flags as the takeover's configuration (not yet validated).
fn takeover_config(a: &DataTakeoverArgs) -> Result<mte_eval::takeover::TakeoverConfig> {
    use mte_eval::takeover::TakeoverConfig;
    Ok(TakeoverConfig {
        record: GenerateConfig {
            episodes: a.episodes,
            seed: a.seed,
            stream: a.stream.into(),
            obs: a.obs,
            image_size: (a.image_size, a.image_size),
            max_steps: a.max_steps,
            expert: ExpertConfig {
                travel_step: a.travel_step,
                push_step: a.push_step,
                resume_pushes: a.resume_pushes,
                ..ExpertConfig::default()
            },
        },
        execution: a.execution.parse().with_context(|| {
            format!(
                "--execution {:?}: expected open-loop or an aggregator",
                a.execution
            )
        })?,
        h: a.stride,
        switch: a.switch,
        noise_seed: a.noise_seed,
    })
}
