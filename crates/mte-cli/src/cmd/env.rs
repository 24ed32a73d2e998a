//! `mte env expert`, `mte env bench`: bridge targets' scripted experts and speed.

use std::io::Write as _;
use std::time::Instant;

use anyhow::{Context, Result};
use mte_eval::Reporter as _;
use mte_eval::bridge::{BridgeEnv, BridgeOptions, run_expert};
use mte_eval::environment::Environment;
use mte_policy::ObsNeeds;

use crate::args::{Cli, EnvBenchArgs, EnvExpertArgs, Format};
use crate::progress::Bar;

const STATE: ObsNeeds = ObsNeeds {
    env_state: false,
    image: None,
    wrist_image: false,
};

/// `mte env expert`
pub fn expert(cli: &Cli, a: &EnvExpertArgs) -> Result<()> {
    let t0 = Instant::now();
    let mut env = BridgeEnv::spawn(&a.env, STATE, &BridgeOptions::default())
        .with_context(|| format!("starting {}", a.env))?;
    let startup = t0.elapsed().as_secs_f64();
    let bar = Bar::new(!cli.no_progress && !cli.quiet);
    bar.start("episodes", a.episodes as u64);
    let mut episodes = Vec::with_capacity(a.episodes);
    for i in 0..a.episodes {
        let seed = a.seed + i as u64;
        let ep = run_expert(&mut env, seed, a.max_steps, STATE)
            .with_context(|| format!("{} seed {seed}", a.env))?;
        episodes.push(ep);
        bar.advance(1);
    }
    bar.finish();
    let secs = t0.elapsed().as_secs_f64();
    let n = episodes.len();
    let ok = episodes.iter().filter(|e| e.success).count();
    let solved: Vec<usize> = episodes
        .iter()
        .filter(|e| e.success)
        .map(|e| e.steps)
        .collect();
    let mean_steps = solved.iter().sum::<usize>() as f64 / solved.len().max(1) as f64;
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(
            so,
            "{}",
            serde_json::json!({"env": a.env.to_string(), "episodes": episodes, "success_rate": ok as f64 / n as f64, "mean_steps_of_successes": mean_steps, "seconds": secs, "startup_seconds": startup, "machine": mte_eval::machine::Machine::detect()})
        )?,
        Format::Text => {
            writeln!(
                so,
                "{}: the scripted expert solved {ok}/{n} ({:.0}%), {mean_steps:.0} steps on average when it did; {secs:.0} s",
                a.env,
                100.0 * ok as f64 / n as f64
            )?;
            let failed: Vec<String> = episodes
                .iter()
                .filter(|e| !e.success)
                .map(|e| e.seed.to_string())
                .collect();
            if !failed.is_empty() {
                writeln!(so, "failed seeds: {}", failed.join(", "))?;
            }
        }
    }
    Ok(())
}

/// `mte env bench`
pub fn bench(cli: &Cli, a: &EnvBenchArgs) -> Result<()> {
    let needs = ObsNeeds {
        env_state: false,
        image: a.image,
        wrist_image: false,
    };
    let mut env = BridgeEnv::spawn(&a.env, needs, &BridgeOptions::default())
        .with_context(|| format!("starting {}", a.env))?;
    env.reset(a.seed)?;
    // Targets with an expert step with its actions (a realistic trajectory); others with zeros.
    let use_expert = env.expert_action().is_ok();
    let zeros = vec![0.0f32; env.action_dim()];
    let t0 = Instant::now();
    for _ in 0..a.steps {
        env.observe(needs)?;
        let action = if use_expert {
            env.expert_action()?
        } else {
            zeros.clone()
        };
        env.step(&action)?;
    }
    let secs = t0.elapsed().as_secs_f64();
    let rate = a.steps as f64 / secs;
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(
            so,
            "{}",
            serde_json::json!({"env": a.env.to_string(), "steps": a.steps, "seconds": secs, "steps_per_second": rate, "image": a.image, "expert_actions": use_expert, "machine": mte_eval::machine::Machine::detect()})
        )?,
        Format::Text => writeln!(
            so,
            "{}: {} steps (observe{} + {} + step) in {secs:.2} s, {rate:.1} steps/s",
            a.env,
            a.steps,
            a.image
                .map(|(w, h)| format!(" with a {w}x{h} frame"))
                .unwrap_or_default(),
            if use_expert { "expert" } else { "zero action" },
        )?,
    }
    Ok(())
}
