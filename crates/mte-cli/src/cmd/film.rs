//! `mte film` and `mte report --figure2`: the paper's Figure 2, one episode run twice from the
//! same seed under the same corruption with two aggregators, drawn side by side.

use std::io::Write as _;
use std::path::Path;

use anyhow::{Context, Result};
use mte_eval::corruption::{CorruptionSpec, Schedule};
use mte_eval::film::{Film, film, side_by_side, strip};
use mte_eval::pusht::{EpisodeSpec, Execution};
use mte_sim::ResetStream;

use crate::args::{Cli, FilmArgs, Format};
use crate::cmd::media::{Gif, write_png};

/// Steps shown in the still strip.
const STRIP_STEPS: usize = 10;

/// What to film: the episode's reset, schedule and noise, and the two arms.
pub struct Shoot<'a> {
    /// Checkpoint directory.
    pub policy: &'a Path,
    /// Reset seed and stream.
    pub seed: u64,
    /// Reset stream.
    pub stream: ResetStream,
    /// Query stride.
    pub h: usize,
    /// Step limit.
    pub max_steps: usize,
    /// Corruption.
    pub corruption: &'a CorruptionSpec,
    /// Seed of the sampling and corruption streams (the run's).
    pub noise_seed: u64,
    /// Left and right arm.
    pub arms: [Execution; 2],
    /// Panel side (px).
    pub size: usize,
}

/// Films both arms.
pub fn shoot(s: &Shoot<'_>) -> Result<[Film; 2]> {
    let p = mte_policy::load_policy(s.policy)
        .with_context(|| format!("loading {}", s.policy.display()))?;
    let one = |execution| -> Result<Film> {
        let spec = EpisodeSpec {
            needs: p.needs(),
            seed: s.seed,
            stream: s.stream,
            h: s.h,
            max_steps: s.max_steps,
            execution,
            corruption: s.corruption,
            noise_seed: s.noise_seed,
            sampling: Default::default(),
            monitors: &[],
            span: None,
        };
        Ok(film(p.as_ref(), &spec, s.size)?)
    };
    Ok([one(s.arms[0])?, one(s.arms[1])?])
}

/// Writes `figure2.gif` (every step, 10 frames/s like the control rate) and
/// `figure2-strip.png` into `out`; returns `(caption, file name)` of each.
pub fn write_figure(out: &Path, films: &[Film; 2]) -> Result<Vec<(String, String)>> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let pair = [&films[0], &films[1]];
    let (frames, w, h) = side_by_side(&pair);
    let mut gif = Gif::create(&out.join("figure2.gif"), w, h, 10)?;
    for f in &frames {
        gif.push(f)?;
    }
    drop(gif);
    let (rgb, sw, sh) = strip(&pair, STRIP_STEPS);
    write_png(&out.join("figure2-strip.png"), &rgb, sw, sh)?;
    Ok(vec![
        (
            format!(
                "Figure 2: {} (left) and {} (right), every step",
                films[0].record.arm, films[1].record.arm
            ),
            "figure2.gif".into(),
        ),
        (
            format!(
                "Figure 2 as a strip of {STRIP_STEPS} evenly spaced steps: {} (top), {} (bottom)",
                films[0].record.arm, films[1].record.arm
            ),
            "figure2-strip.png".into(),
        ),
    ])
}

/// `mte film`
pub fn run(cli: &Cli, a: &FilmArgs) -> Result<()> {
    let corruption = CorruptionSpec {
        fault: a.fault.clone(),
        schedule: if a.q == 0 {
            Schedule::Never
        } else {
            Schedule::Burst {
                q: a.q,
                phase: 0,
                period: None,
            }
        },
    };
    let arms = [a.arms[0].parse()?, a.arms[1].parse()?];
    let films = shoot(&Shoot {
        policy: &a.policy,
        seed: a.seed,
        stream: a.stream.into(),
        h: a.stride,
        max_steps: a.max_steps,
        corruption: &corruption,
        noise_seed: a.noise_seed,
        arms,
        size: a.size,
    })?;
    let files = write_figure(&a.out, &films)?;
    let mut so = std::io::stdout().lock();
    let summary = |f: &Film| {
        serde_json::json!({"arm": f.record.arm, "success": f.record.success,
            "max_coverage": f.record.max_coverage, "steps": f.record.steps})
    };
    match cli.format {
        Format::Json => writeln!(
            so,
            "{}",
            serde_json::json!({"films": [summary(&films[0]), summary(&films[1])], "files": files})
        )?,
        Format::Text => {
            for f in &films {
                writeln!(
                    so,
                    "{}: max coverage {:.3}, {} after {} steps",
                    f.record.arm,
                    f.record.max_coverage,
                    if f.record.success {
                        "success"
                    } else {
                        "failure"
                    },
                    f.record.steps
                )?;
            }
            for (_, name) in &files {
                writeln!(so, "wrote {}", a.out.join(name).display())?;
            }
        }
    }
    Ok(())
}
