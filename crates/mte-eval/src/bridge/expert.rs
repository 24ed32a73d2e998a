//! Bridge targets' scripted experts: episodes, and demonstration datasets made from them.
//!
//! The experts live in the worker (they read the simulator's ground truth); this side runs
//! them ([`run_expert`]) and writes what they did as an `mte-demo-v1` dataset with LeRobot's
//! feature names ([`generate`]), episodes in parallel over one worker per thread.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc::{Sender, channel};

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
    /// The wrist camera's frames too (robomimic's `robot0_eye_in_hand_image`), at `image`'s
    /// size; needs `image`.
    pub wrist_image: bool,
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

/// The dataset layout of `target`, its feature sizes those of `first` (an observation and
/// the expert's action).
fn layout(
    target: &Target,
    first: &(Observation, Vec<f32>),
    image: Option<(usize, usize)>,
    wrist_image: bool,
) -> Layout {
    let (o, a) = first;
    let (sd, ed, ad) = match target {
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
        state: (o.state.len(), sd.into()),
        env_state: Some((o.env_state.as_ref().map_or(0, Vec::len), ed.into())),
        pusht_state: false,
        image_hw: image.map(|(w, h)| (h, w)),
        wrist_hw: image.filter(|_| wrist_image).map(|(w, h)| (h, w)),
        action: (a.len(), ad.into()),
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
                wrist_image: o.wrist_image.clone(),
                action: a.clone(),
                reward: f32::from(u8::from(last && ep.success)),
                done: last,
                success: last && ep.success,
            }
        })
        .collect()
}

fn config_err(field: &'static str, value: impl ToString, expected: impl Into<String>) -> DemoError {
    DemoError::Config {
        field,
        value: value.to_string(),
        expected: expected.into(),
    }
}

/// Seeds tried at most: `episodes`, or four times as many when only successes are kept.
fn tries(config: &DemoConfig) -> usize {
    if config.successes_only {
        4 * config.episodes
    } else {
        config.episodes
    }
}

/// What one worker thread does: start a worker, then run the expert on the next untried
/// seed index until the seeds run out or `stop` is set, sending each result (a failed start
/// is sent with index `usize::MAX`).
fn work(
    config: &DemoConfig,
    options: &BridgeOptions,
    next: &AtomicUsize,
    stop: &AtomicBool,
    tx: &Sender<(usize, Result<ExpertEpisode, EnvError>)>,
) {
    let needs = ObsNeeds {
        env_state: true,
        image: config.image,
        wrist_image: config.wrist_image,
    };
    let mut env = match BridgeEnv::spawn(&config.target, needs, options) {
        Ok(e) => e,
        Err(e) => {
            let _ = tx.send((usize::MAX, Err(e)));
            return;
        }
    };
    loop {
        let i = next.fetch_add(1, Ordering::SeqCst);
        if i >= tries(config) || stop.load(Ordering::SeqCst) {
            return;
        }
        let seed = config.first_seed + i as u64;
        let r = run_expert(&mut env, seed, config.max_steps, needs);
        let failed = r.is_err();
        if tx.send((i, r)).is_err() || failed {
            return;
        }
    }
}

/// Writes episodes in seed order as they arrive from the workers, whichever finished first;
/// the dataset is created from the first kept episode's sizes.
struct Recorder<'a> {
    config: &'a DemoConfig,
    out: &'a Path,
    writer: Option<DatasetWriter>,
    pending: BTreeMap<usize, ExpertEpisode>,
    expected: usize,
    kept: usize,
}

impl Recorder<'_> {
    /// Takes episode `i` and writes every episode now in order; true once enough are kept.
    fn accept(
        &mut self,
        i: usize,
        ep: ExpertEpisode,
        on_episode: &(dyn Fn(&EpisodeMeta) + Sync),
    ) -> Result<bool, DemoError> {
        let c = self.config;
        self.pending.insert(i, ep);
        while let Some(ep) = self.pending.remove(&self.expected) {
            self.expected += 1;
            if self.kept == c.episodes || (c.successes_only && !ep.success) {
                continue;
            }
            let w = match self.writer.as_mut() {
                Some(w) => w,
                None => {
                    let first = ep.frames.first().ok_or_else(|| {
                        config_err("max_steps", c.max_steps, "room for at least one step")
                    })?;
                    let layout = layout(&c.target, first, c.image, c.wrist_image);
                    self.writer.insert(DatasetWriter::create_with(
                        self.out,
                        fps(&c.target),
                        layout,
                    )?)
                }
            };
            w.push_episode(ep.seed, ep.max_score, &frames(&ep))?;
            self.kept += 1;
            if let Some(meta) = w.episodes().last() {
                on_episode(meta);
            }
        }
        Ok(self.kept == c.episodes)
    }

    /// Finishes the dataset, or says why there are too few episodes.
    fn finish(self) -> Result<Info, DemoError> {
        let c = self.config;
        let writer = self
            .writer
            .ok_or_else(|| config_err("episodes", c.episodes, "at least one recorded episode"))?;
        if self.kept < c.episodes {
            let tries = tries(c);
            return Err(config_err(
                "episodes",
                c.episodes,
                format!("as many successes within {tries} seeds (got {})", self.kept),
            ));
        }
        let generator = serde_json::json!({
            "target": c.target.to_string(),
            "first_seed": c.first_seed,
            "max_steps": c.max_steps,
            "successes_only": c.successes_only,
            "expert": "the bridge worker's scripted expert (ground-truth poses)",
        });
        Ok(writer.finish(generator)?)
    }
}

/// Records `config.episodes` expert episodes of `config.target` into `out` (a new
/// directory), calling `on_episode` as each is written (in seed order): one worker process
/// per thread, `config.workers` threads.
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
            return Err(config_err(field, 0, ">= 1"));
        }
    }
    if config.wrist_image && config.image.is_none() {
        let expected = "an image size as well (the wrist camera is rendered at the image's size)";
        return Err(config_err("wrist_image", true, expected));
    }
    let (next, stop) = (AtomicUsize::new(0), AtomicBool::new(false));
    let (tx, rx) = channel();
    std::thread::scope(|scope| -> Result<Info, DemoError> {
        for _ in 0..config.workers.min(tries(config)) {
            let tx = tx.clone();
            let (next, stop) = (&next, &stop);
            scope.spawn(move || work(config, options, next, stop, &tx));
        }
        drop(tx);
        let mut recorder = Recorder {
            config,
            out,
            writer: None,
            pending: BTreeMap::new(),
            expected: 0,
            kept: 0,
        };
        for (i, r) in rx {
            // A failure, or enough episodes, stops the workers at their next seed.
            let done = r
                .map_err(DemoError::from)
                .and_then(|ep| recorder.accept(i, ep, on_episode));
            match done {
                Ok(false) => {}
                Ok(true) => stop.store(true, Ordering::SeqCst),
                Err(e) => {
                    stop.store(true, Ordering::SeqCst);
                    return Err(e);
                }
            }
        }
        recorder.finish()
    })
}
