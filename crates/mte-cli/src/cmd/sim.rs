//! `mte sim render | rollout | bench`.

use std::io::Write as _;
use std::time::Instant;

use anyhow::{Context, Result, ensure};
use rand::{Rng, SeedableRng};

use mte_sim::expert::{Expert, ExpertConfig};
use mte_sim::render::Renderer;
use mte_sim::{PushT, ResetStream};

use crate::args::{Cli, Format, SimBenchArgs, SimPolicy, SimRenderArgs, SimRolloutArgs};
use crate::cmd::media::{Gif, write_png};
use crate::progress::Bar;

/// `mte sim render`
pub fn render(cli: &Cli, a: &SimRenderArgs) -> Result<()> {
    ensure!(
        (1..=4096).contains(&a.size),
        "--size {} must be between 1 and 4096 px",
        a.size
    );
    let mut env = PushT::default();
    env.reset(a.seed, a.stream.into())
        .context("resetting the simulator")?;
    let mut r = Renderer::new(env.goal());
    let img = if a.vis {
        r.visualization_with_contacts(&env.scene(), env.contact_segments(), None, a.size, a.size)?
    } else {
        {
            let mut img = vec![0u8; a.size * a.size * 3];
            r.observation_with_contacts_into(
                &env.scene(),
                env.contact_segments(),
                a.size,
                a.size,
                &mut img,
            )?;
            img
        }
    };
    write_png(&a.out, &img, a.size, a.size)?;
    if !cli.quiet {
        let s = env.state_obs();
        let line = match cli.format {
            Format::Json => serde_json::json!({ "seed": a.seed, "state": s, "coverage": env.coverage(), "out": a.out }).to_string(),
            Format::Text => format!(
                "seed {}: agent ({:.1}, {:.1}), block ({:.1}, {:.1}, {:.3} rad), coverage {:.3} -> {}",
                a.seed, s[0], s[1], s[2], s[3], s[4], env.coverage(), a.out.display()
            ),
        };
        writeln!(std::io::stdout(), "{line}")?;
    }
    Ok(())
}

/// One episode's outcome.
#[derive(serde::Serialize)]
struct Outcome {
    seed: u64,
    success: bool,
    steps: usize,
    max_coverage: f64,
}

/// `mte sim rollout`
pub fn rollout(cli: &Cli, a: &SimRolloutArgs) -> Result<()> {
    ensure!(a.episodes >= 1, "--episodes must be at least 1");
    ensure!(a.max_steps >= 1, "--max-steps must be at least 1");
    ensure!(
        (16..=2048).contains(&a.gif_size),
        "--gif-size {} must be 16..=2048 px",
        a.gif_size
    );
    let stream: ResetStream = a.stream.into();
    let bar = Bar::new(!cli.no_progress && !cli.quiet);
    use mte_eval::Reporter as _;
    bar.start("episodes", a.episodes as u64);
    let t0 = Instant::now();
    let mut out = Vec::new();
    let mut gif = match &a.gif {
        Some(p) => Some(Gif::create(p, a.gif_size, a.gif_size, 10)?),
        None => None,
    };
    let mut renderer = gif.as_ref().map(|_| Renderer::new(mte_sim::GOAL));
    let mut expert = Expert::new(ExpertConfig::default())?;
    for i in 0..a.episodes {
        let seed = a.seed + i as u64;
        let mut env = PushT::default();
        env.reset(seed, stream)?;
        expert.reset();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let mut max_cov = env.coverage();
        let (mut steps, mut success) = (0, false);
        let record = i == 0;
        if record && let (Some(g), Some(r)) = (gif.as_mut(), renderer.as_mut()) {
            g.push(&r.visualization_with_contacts(
                &env.scene(),
                env.contact_segments(),
                None,
                a.gif_size,
                a.gif_size,
            )?)?;
        }
        while steps < a.max_steps {
            let action = match a.policy {
                SimPolicy::Expert => expert.act(&env, &mut rng)?,
                SimPolicy::Random => [rng.random_range(0.0..512.0), rng.random_range(0.0..512.0)],
            };
            let info = env.step(action)?;
            steps += 1;
            max_cov = max_cov.max(info.coverage);
            if record && let (Some(g), Some(r)) = (gif.as_mut(), renderer.as_mut()) {
                g.push(&r.visualization_with_contacts(
                    &env.scene(),
                    env.contact_segments(),
                    Some(action),
                    a.gif_size,
                    a.gif_size,
                )?)?;
            }
            if info.is_success {
                success = true;
                break;
            }
        }
        out.push(Outcome {
            seed,
            success,
            steps,
            max_coverage: max_cov,
        });
        bar.advance(1);
    }
    bar.finish();
    drop(gif);
    let n = out.len() as f64;
    let successes = out.iter().filter(|o| o.success).count();
    let mean_max = out.iter().map(|o| o.max_coverage).sum::<f64>() / n;
    let secs = t0.elapsed().as_secs_f64();
    let mut stdout = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(
            stdout,
            "{}",
            serde_json::json!({ "episodes": out, "success_rate": successes as f64 / n, "mean_max_coverage": mean_max, "seconds": secs })
        )?,
        Format::Text => {
            if !cli.quiet && (cli.verbose > 0 || out.len() <= 10) {
                for o in &out {
                    writeln!(
                        stdout,
                        "seed {:>6}: {:7} after {:3} steps, max coverage {:.3}",
                        o.seed,
                        if o.success { "success" } else { "failure" },
                        o.steps,
                        o.max_coverage
                    )?;
                }
            }
            writeln!(
                stdout,
                "{successes}/{} successful ({:.0}%), mean max coverage {mean_max:.3}, {secs:.1} s",
                out.len(),
                100.0 * successes as f64 / n
            )?;
            if let Some(p) = &a.gif {
                writeln!(stdout, "wrote {}", p.display())?;
            }
        }
    }
    Ok(())
}

/// `mte sim bench`
pub fn bench(cli: &Cli, a: &SimBenchArgs) -> Result<()> {
    ensure!(a.steps >= 300, "--steps must be at least 300 (one episode)");
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let actions: Vec<[f64; 2]> = (0..a.steps)
        .map(|_| [rng.random_range(0.0..512.0), rng.random_range(0.0..512.0)])
        .collect();
    let mut results = Vec::new();
    for pixels in [false, true] {
        let mut env = PushT::default();
        let mut r = Renderer::new(env.goal());
        let mut img = vec![0u8; 96 * 96 * 3];
        let mut seed = 0;
        let t0 = Instant::now();
        for (i, act) in actions.iter().enumerate() {
            if i % 300 == 0 {
                seed += 1;
                env.reset(seed, ResetStream::Pcg64)?;
            }
            env.step(*act)?;
            if pixels {
                r.observation_with_contacts_into(
                    &env.scene(),
                    env.contact_segments(),
                    96,
                    96,
                    &mut img,
                )?;
            }
        }
        let sps = a.steps as f64 / t0.elapsed().as_secs_f64();
        results.push((if pixels { "pixels 96x96" } else { "state" }, sps));
    }
    let mut stdout = std::io::stdout().lock();
    for (name, sps) in &results {
        match cli.format {
            Format::Json => writeln!(
                stdout,
                "{}",
                serde_json::json!({ "obs": name, "steps_per_s": sps })
            )?,
            Format::Text => writeln!(
                stdout,
                "{name:>12}: {sps:>9.0} steps/s (one thread, uniform random actions; gym-pusht here: 4,585 state / 670 pixels)"
            )?,
        }
    }
    Ok(())
}
