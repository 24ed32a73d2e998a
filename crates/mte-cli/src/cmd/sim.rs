//! `mte sim render | rollout | bench`.

use std::io::Write as _;
use std::time::Instant;

use anyhow::{Context, Result, ensure};

use mte_sim::PushT;
use mte_sim::expert::{Expert, ExpertConfig};
use mte_sim::render::Renderer;
use mte_sim::rollout::{Driver, RolloutOutcome};

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

/// `mte sim rollout`
pub fn rollout(cli: &Cli, a: &SimRolloutArgs) -> Result<()> {
    ensure!(a.episodes >= 1, "--episodes must be at least 1");
    ensure!(a.max_steps >= 1, "--max-steps must be at least 1");
    ensure!(
        (16..=2048).contains(&a.gif_size),
        "--gif-size {} must be 16..=2048 px",
        a.gif_size
    );
    let bar = Bar::new(!cli.no_progress && !cli.quiet);
    use mte_eval::Reporter as _;
    bar.start("episodes", a.episodes as u64);
    let t0 = Instant::now();
    let out = run_episodes(a, &|| bar.advance(1))?;
    bar.finish();
    print_rollouts(cli, a, &out, t0.elapsed().as_secs_f64())
}

/// The episodes of `mte sim rollout`, the first one drawn into the GIF when one is asked
/// for; `done()` after each.
fn run_episodes(a: &SimRolloutArgs, done: &dyn Fn()) -> Result<Vec<RolloutOutcome>> {
    let mut out = Vec::new();
    let mut gif = match &a.gif {
        Some(p) => Some(Gif::create(p, a.gif_size, a.gif_size, 10)?),
        None => None,
    };
    let mut renderer = Renderer::new(mte_sim::GOAL);
    let mut expert = Expert::new(ExpertConfig::default())?;
    let driver = match a.policy {
        SimPolicy::Expert => Driver::Expert,
        SimPolicy::Random => Driver::Random,
    };
    for i in 0..a.episodes {
        let mut env = PushT::default();
        // Only the first episode is drawn.
        let frame = |env: &PushT, action: Option<[f64; 2]>| -> Result<()> {
            if let (0, Some(g)) = (i, gif.as_mut()) {
                let (scene, contacts) = (env.scene(), env.contact_segments());
                let size = a.gif_size;
                g.push(
                    &renderer.visualization_with_contacts(&scene, contacts, action, size, size)?,
                )?;
            }
            Ok(())
        };
        let seed = a.seed + i as u64;
        out.push(mte_sim::rollout::rollout(
            &mut env,
            &mut expert,
            driver,
            seed,
            a.stream.into(),
            a.max_steps,
            frame,
        )?);
        done();
    }
    Ok(out)
}

/// Prints the outcomes of `mte sim rollout` (each episode in text when there are at most 10
/// or with `-v`), their success rate and mean max coverage.
fn print_rollouts(cli: &Cli, a: &SimRolloutArgs, out: &[RolloutOutcome], secs: f64) -> Result<()> {
    let n = out.len() as f64;
    let successes = out.iter().filter(|o| o.success).count();
    let mean_max = out.iter().map(|o| o.max_coverage).sum::<f64>() / n;
    let mut stdout = std::io::stdout().lock();
    if cli.format == Format::Json {
        let json = serde_json::json!({ "episodes": out, "success_rate": successes as f64 / n, "mean_max_coverage": mean_max, "seconds": secs });
        writeln!(stdout, "{json}")?;
        return Ok(());
    }
    if !cli.quiet && (cli.verbose > 0 || out.len() <= 10) {
        for o in out {
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
    Ok(())
}

/// `mte sim bench`
pub fn bench(cli: &Cli, a: &SimBenchArgs) -> Result<()> {
    ensure!(a.steps >= 300, "--steps must be at least 300 (one episode)");
    let mut results = Vec::new();
    for pixels in [false, true] {
        let sps = mte_sim::rollout::steps_per_second(a.steps, pixels)?;
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
