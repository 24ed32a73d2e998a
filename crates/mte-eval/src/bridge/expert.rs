//! Bridge targets' scripted experts: episodes, and demonstration datasets made from them.
//!
//! The experts live in the worker (they read the simulator's ground truth); this side runs
//! them ([`run_expert`]) and writes what they did as an `mte-demo-v1` dataset with LeRobot's
//! feature names ([`generate`]), episodes in parallel over one worker per thread.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc::channel;

use mte_data::dataset::{DatasetWriter, EpisodeMeta, Frame, Info, Layout};
use mte_policy::{ObsNeeds, Observation};

use super::{BridgeEnv, BridgeOptions, RobomimicTask, Target};
use crate::environment::{EnvError, Environment};

/// One episode of a bridge target's scripted expert.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ExpertEpisode {
    /// Reset seed.
    pub seed: u64,
    /// Whether the task was solved (the episode ends there).
    pub success: bool,
    /// Control steps run.
    pub steps: usize,
    /// Largest score over the episode.
    pub max_score: f64,
    /// The observations (with `needs`) and the expert's actions, one per step.
    #[serde(skip)]
    pub frames: Vec<(Observation, Vec<f32>)>,
}

/// Runs the scripted expert of `env`'s target from reset seed `seed` for at most
/// `max_steps`, recording what `needs` asks for at every step.
pub fn run_expert(
    env: &mut BridgeEnv,
    seed: u64,
    max_steps: usize,
    needs: ObsNeeds,
) -> Result<ExpertEpisode, EnvError> {
    let mut max_score = env.reset(seed)?;
    let mut frames = Vec::new();
    let mut success = false;
    while frames.len() < max_steps && !success {
        let obs = env.observe(needs)?;
        let action = env.expert_action()?;
        let out = env.step(&action)?;
        frames.push((obs, action));
        max_score = max_score.max(out.score);
        success = out.success;
    }
    Ok(ExpertEpisode {
        seed,
        success,
        steps: frames.len(),
        max_score,
        frames,
    })
}

/// What [`generate`] records.
#[derive(Clone, Debug, PartialEq)]
pub struct DemoConfig {
    /// The target (its worker must have an expert).
    pub target: Target,
    /// Episodes, from reset seeds `first_seed..first_seed + episodes`.
    pub episodes: usize,
    /// First reset seed.
    pub first_seed: u64,
    /// Step limit per episode.
    pub max_steps: usize,
    /// Camera frames of this (width, height), if any.
    pub image: Option<(usize, usize)>,
    /// Only successful episodes are kept (robomimic's "ph" datasets hold successes only);
    /// seeds continue past `first_seed + episodes` until that many are kept, at most
    /// `4 x episodes` tried.
    pub successes_only: bool,
    /// Worker processes (episodes run in parallel).
    pub workers: usize,
}

/// Errors of [`generate`].
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DemoError {
    /// A worker failed.
    #[error(transparent)]
    Env(#[from] EnvError),
    /// The dataset could not be written.
    #[error(transparent)]
    Data(#[from] mte_data::DataError),
    /// A setting is out of range.
    #[error("`{field}` = {value}: expected {expected}")]
    Config {
        /// Field.
        field: &'static str,
        /// Value.
        value: String,
        /// Expectation.
        expected: String,
    },
}

/// The dataset layout of `target`'s observations.
fn layout(
    target: &Target,
    state: usize,
    env_state: usize,
    image: Option<(usize, usize)>,
) -> Layout {
    let (s, e, a) = match target {
        Target::Robomimic(_) => (
            "robot0_eef_pos (3, m), robot0_eef_quat (4, x y z w), robot0_gripper_qpos (2, m)",
            "the task's object-state (robosuite; object poses and their offsets to the gripper)",
            "OSC_POSE delta in [-1, 1]: position (3, x 0.05 m), axis-angle (3, x 0.5 rad), gripper (-1 open, +1 close)",
        ),
        _ => (
            "the environment's state observation",
            "the environment state",
            "action",
        ),
    };
    Layout {
        state: (state, s.into()),
        env_state: Some((env_state, e.into())),
        pusht_state: false,
        image_hw: image.map(|(w, h)| (h, w)),
        action: (0, a.into()),
        reward: "1 once the task is solved after the action, else 0".into(),
        success: "the task is solved after the action (robosuite: _check_success())".into(),
    }
}

/// Control rate of `target` (Hz): robomimic's 20, else PushT's 10.
fn fps(target: &Target) -> f64 {
    match target {
        Target::Robomimic(RobomimicTask::Lift | RobomimicTask::Can | RobomimicTask::Square) => 20.0,
        _ => 10.0,
    }
}

fn frames(ep: &ExpertEpisode) -> Vec<Frame> {
    let n = ep.frames.len();
    ep.frames
        .iter()
        .enumerate()
        .map(|(t, (o, a))| {
            let last = t + 1 == n;
            Frame {
                state: o.state.clone(),
                env_state: o.env_state.clone(),
                pusht_state: None,
                image: o.image.clone(),
                action: a.clone(),
                reward: f32::from(u8::from(last && ep.success)),
                done: last,
                success: last && ep.success,
            }
        })
        .collect()
}

/// Records `config.episodes` expert episodes of `config.target` into `out` (a new
/// directory), calling `on_episode` as each is written (in seed order).
pub fn generate(
    config: &DemoConfig,
    out: &Path,
    options: &BridgeOptions,
    on_episode: &(dyn Fn(&EpisodeMeta) + Sync),
) -> Result<Info, DemoError> {
    for (field, v) in [
        ("episodes", config.episodes),
        ("max_steps", config.max_steps),
        ("workers", config.workers),
    ] {
        if v == 0 {
            return Err(DemoError::Config {
                field,
                value: "0".into(),
                expected: ">= 1".into(),
            });
        }
    }
    let needs = ObsNeeds {
        env_state: true,
        image: config.image,
    };
    let tries = if config.successes_only {
        4 * config.episodes
    } else {
        config.episodes
    };
    let next = AtomicUsize::new(0);
    let stop = AtomicUsize::new(0);
    let (tx, rx) = channel::<(usize, Result<ExpertEpisode, EnvError>)>();
    std::thread::scope(|scope| -> Result<Info, DemoError> {
        for _ in 0..config.workers.min(tries) {
            let tx = tx.clone();
            let (next, stop) = (&next, &stop);
            scope.spawn(move || {
                let mut env = match BridgeEnv::spawn(&config.target, needs, options) {
                    Ok(e) => e,
                    Err(e) => {
                        let _ = tx.send((usize::MAX, Err(e)));
                        return;
                    }
                };
                loop {
                    let i = next.fetch_add(1, Ordering::SeqCst);
                    if i >= tries || stop.load(Ordering::SeqCst) > 0 {
                        return;
                    }
                    let r = run_expert(
                        &mut env,
                        config.first_seed + i as u64,
                        config.max_steps,
                        needs,
                    );
                    let failed = r.is_err();
                    if tx.send((i, r)).is_err() || failed {
                        return;
                    }
                }
            });
        }
        drop(tx);
        let mut writer: Option<DatasetWriter> = None;
        let mut pending: BTreeMap<usize, ExpertEpisode> = BTreeMap::new();
        let (mut expected, mut kept) = (0usize, 0usize);
        for (i, r) in rx {
            let ep = match r {
                Ok(ep) => ep,
                Err(e) => {
                    stop.store(1, Ordering::SeqCst);
                    return Err(e.into());
                }
            };
            pending.insert(i, ep);
            // Write in seed order, so the dataset does not depend on which worker was faster.
            while let Some(ep) = pending.remove(&expected) {
                expected += 1;
                if kept == config.episodes || (config.successes_only && !ep.success) {
                    continue;
                }
                let w = match writer.as_mut() {
                    Some(w) => w,
                    None => {
                        let (o, a): &(Observation, Vec<f32>) =
                            ep.frames.first().ok_or_else(|| DemoError::Config {
                                field: "max_steps",
                                value: config.max_steps.to_string(),
                                expected: "room for at least one step".into(),
                            })?;
                        let mut l = layout(
                            &config.target,
                            o.state.len(),
                            o.env_state.as_ref().map_or(0, Vec::len),
                            config.image,
                        );
                        l.action.0 = a.len();
                        writer.insert(DatasetWriter::create_with(out, fps(&config.target), l)?)
                    }
                };
                w.push_episode(ep.seed, ep.max_score, &frames(&ep))?;
                kept += 1;
                if let Some(meta) = w.episodes().last() {
                    on_episode(meta);
                }
                if kept == config.episodes {
                    stop.store(1, Ordering::SeqCst);
                }
            }
        }
        let writer = writer.ok_or_else(|| DemoError::Config {
            field: "episodes",
            value: config.episodes.to_string(),
            expected: "at least one recorded episode".into(),
        })?;
        if kept < config.episodes {
            return Err(DemoError::Config {
                field: "episodes",
                value: config.episodes.to_string(),
                expected: format!("as many successes within {tries} seeds (got {kept})"),
            });
        }
        let generator = serde_json::json!({
            "target": config.target.to_string(),
            "first_seed": config.first_seed,
            "max_steps": config.max_steps,
            "successes_only": config.successes_only,
            "expert": "the bridge worker's scripted expert (ground-truth poses)",
        });
        Ok(writer.finish(generator)?)
    })
}
