//! `mte eval policy`.

use std::io::Write as _;

use anyhow::{Context, Result, ensure};
use mte_eval::Reporter as _;
use mte_eval::bridge::BridgeOptions;
use mte_eval::corruption::CorruptionSpec;
use mte_eval::dispersion::{CandidateSpread, SpreadSummary};
use mte_eval::pusht::{EpisodeSpec, Execution, run_episode_in, run_episode_observed};
use mte_eval::record::EpisodeRecord;
use mte_policy::ChunkPolicy;

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
    let device = a
        .device
        .open()
        .with_context(|| format!("--device {}", a.device))?;
    let p = mte_eval::sweep::load_named_policy(&a.checkpoint, &device)
        .with_context(|| format!("loading {} on {}", a.checkpoint.display(), a.device))?;
    let corruption = corruption_of(a, p.horizon(), p.n_obs_steps())?;
    let t0 = std::time::Instant::now();
    let runs = run_episodes(cli, a, p.as_ref(), execution, &corruption)?;
    let secs = t0.elapsed().as_secs_f64();
    let out = &runs.records;
    let n = out.len() as f64;
    let succ = out.iter().filter(|o| o.success).count();
    let mean_max = out.iter().map(|o| o.max_coverage).sum::<f64>() / n;
    let spread = runs.spread.summary();
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(
            so,
            "{}",
            serde_json::json!({"episodes": out, "success_rate": succ as f64 / n, "mean_max_coverage": mean_max, "seconds": secs, "horizon": p.horizon(), "execution": a.execution, "stride": a.stride, "sampling": a.sampling, "corruption": corruption, "candidates": spread, "candidates_by_episode": runs.by_episode, "device": a.device.to_string(), "machine": mte_eval::machine::Machine::detect().with_policies_on(a.device)})
        )?,
        Format::Text => {
            writeln!(
                so,
                "{succ}/{} successful, mean max coverage {mean_max:.3} ({}, h = {}, {} sampling), {secs:.0} s on {}",
                out.len(),
                a.execution,
                a.stride,
                format!("{:?}", a.sampling).to_lowercase(),
                a.device,
            )?;
            write_spread(&mut so, &spread)?;
        }
    }
    Ok(())
}

/// The episodes of `mte eval policy`, with the candidates' spread over all of them and per
/// episode.
struct Episodes {
    records: Vec<EpisodeRecord>,
    spread: CandidateSpread,
    by_episode: Vec<SpreadSummary>,
}

/// Runs `--episodes` episodes from `--seed` on, with a progress bar.
fn run_episodes(
    cli: &Cli,
    a: &EvalPolicyArgs,
    p: &dyn ChunkPolicy,
    execution: Execution,
    corruption: &CorruptionSpec,
) -> Result<Episodes> {
    let needs = p.needs();
    // Native PushT runs through `run_episode_observed`; any other target gets one worker.
    let mut bridged = (!a.env.is_pusht())
        .then(|| {
            a.env
                .open(a.stream.into(), needs, &BridgeOptions::default())
        })
        .transpose()
        .with_context(|| format!("starting the environment {}", a.env))?;
    let bar = Bar::new(!cli.no_progress && !cli.quiet);
    bar.start("episodes", a.episodes as u64);
    let mut runs = Episodes {
        records: Vec::new(),
        spread: CandidateSpread::default(),
        by_episode: Vec::new(),
    };
    for i in 0..a.episodes {
        let spec = EpisodeSpec {
            needs,
            seed: a.seed + i as u64,
            stream: a.stream.into(),
            h: a.stride,
            max_steps: a.max_steps,
            execution,
            corruption,
            noise_seed: a.noise_seed,
            sampling: a.sampling.into(),
            monitors: &[],
            span: a.span,
        };
        let mut this = CandidateSpread::default();
        let record = match bridged.as_mut() {
            None => run_episode_observed(p, &spec, &mut this)?,
            // One worker serves every episode: each starts with a seeded reset.
            Some(env) => run_episode_in(env.as_mut(), p, &spec, &mut this)?,
        };
        runs.spread.merge(&this);
        runs.by_episode.push(this.summary());
        runs.records.push(record);
        bar.advance(1);
    }
    bar.finish();
    Ok(runs)
}

/// The candidates' spread in words: the corrupted candidates against the clean ones, then all
/// candidates (in pixels); nothing for lines without steps.
fn write_spread(so: &mut impl std::io::Write, spread: &SpreadSummary) -> Result<()> {
    if spread.corrupted_steps > 0 {
        writeln!(
            so,
            "corrupted candidates at {} steps: {:.4} from the clean candidates' median, whose \
             spread is {:.4} (median ratio {:.2}); outside the clean bracket: {:.1}%",
            spread.corrupted_steps,
            spread.corrupted_to_clean_median,
            spread.clean_spread,
            spread.corrupted_outlyingness,
            100.0 * spread.corrupted_outside_bracket
        )?;
    }
    if spread.steps > 0 {
        let ages: Vec<String> = spread.by_age.iter().map(|v| format!("{v:.1}")).collect();
        writeln!(
            so,
            "candidates over {} steps (px): spread {:.1}, mean-median {:.1}, mean to nearest {:.1}, \
             median to nearest {:.1}, newest to mean {:.1}, newest to median {:.1}, split {:.1}%; \
             distance from the newest by age: {}",
            spread.steps,
            spread.spread,
            spread.mean_to_median,
            spread.mean_to_nearest,
            spread.median_to_nearest,
            spread.newest_to_mean,
            spread.newest_to_median,
            100.0 * spread.split_fraction,
            ages.join(", ")
        )?;
    }
    Ok(())
}

/// `--corruption`, parsed and checked against the policy's chunk geometry (`t_p`, `t_o`)
/// at `--stride`; clean without it.
fn corruption_of(a: &EvalPolicyArgs, t_p: usize, t_o: usize) -> Result<CorruptionSpec> {
    let Some(text) = &a.corruption else {
        return Ok(CorruptionSpec::CLEAN);
    };
    let c: CorruptionSpec = serde_json::from_str(text)
        .with_context(|| format!("--corruption {text:?}: expected a corruption as JSON"))?;
    c.validate()
        .and_then(|()| c.check_burst(t_p, t_o, a.stride))
        .with_context(|| format!("--corruption {text:?}"))?;
    Ok(c)
}
