//! Demonstrations from the scripted PushT expert, generated in parallel and written in order.
//!
//! Episode `i` resets with seed `seed + i` from the chosen reset stream; the expert's optional
//! action noise draws from a ChaCha8 stream seeded with `(seed, i)`. Episodes are simulated in
//! parallel batches and written in index order, so the output is byte-identical whatever the
//! number of threads.

use std::path::Path;
use std::str::FromStr;

use rand::SeedableRng;
use rayon::prelude::*;

use mte_sim::expert::{Expert, ExpertConfig};
use mte_sim::render::Renderer;
use mte_sim::{PushT, ResetStream};

use crate::dataset::{DatasetWriter, EpisodeMeta, Frame, Info};
use crate::error::DataError;

/// Which observations to record (the agent position is always recorded).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ObsSet {
    /// gym-pusht's 5-vector state.
    pub state: bool,
    /// The 16 block keypoints.
    pub keypoints: bool,
    /// Rendered frames.
    pub pixels: bool,
    /// The wrist camera's frames too, at the frames' size (robomimic's
    /// `robot0_eye_in_hand_image`; PushT has no wrist camera).
    #[serde(default)]
    pub wrist: bool,
}

impl FromStr for ObsSet {
    type Err = DataError;
    /// Comma-separated subset of `state`, `keypoints`, `pixels`, `wrist`.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let mut o = ObsSet::default();
        for part in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            match part {
                "state" => o.state = true,
                "keypoints" => o.keypoints = true,
                "pixels" => o.pixels = true,
                "wrist" => o.wrist = true,
                other => {
                    return Err(DataError::Config {
                        field: "obs",
                        value: other.to_string(),
                        expected: "a comma-separated subset of state, keypoints, pixels, wrist",
                    });
                }
            }
        }
        Ok(o)
    }
}

/// What to generate.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GenerateConfig {
    /// Number of episodes.
    pub episodes: usize,
    /// Base seed: episode i resets with `seed + i`.
    pub seed: u64,
    /// Reset stream.
    pub stream: ResetStream,
    /// Observations to record.
    pub obs: ObsSet,
    /// Image (width, height) in px when pixels are recorded; gym-pusht's default is 96 x 96.
    pub image_size: (usize, usize),
    /// Step limit per episode (gym-pusht: 300).
    pub max_steps: usize,
    /// Expert settings.
    pub expert: ExpertConfig,
}

impl Default for GenerateConfig {
    fn default() -> Self {
        GenerateConfig {
            episodes: 100,
            seed: 0,
            stream: ResetStream::Legacy,
            obs: ObsSet {
                state: true,
                keypoints: true,
                pixels: false,
                wrist: false,
            },
            image_size: (96, 96),
            max_steps: mte_sim::geometry::MAX_EPISODE_STEPS,
            expert: ExpertConfig::default(),
        }
    }
}

impl GenerateConfig {
    /// A new dataset in `out` for the observations this configuration records.
    ///
    /// # Errors
    /// `out` already holds a dataset, or cannot be created.
    pub fn writer(&self, out: &Path) -> Result<DatasetWriter, DataError> {
        let image_hw = self
            .obs
            .pixels
            .then_some((self.image_size.1, self.image_size.0));
        DatasetWriter::create(out, 10.0, self.obs.keypoints, self.obs.state, image_hw)
    }

    /// Check every field.
    pub fn validate(&self) -> Result<(), DataError> {
        if self.episodes == 0 {
            return Err(DataError::Config {
                field: "episodes",
                value: "0".into(),
                expected: "at least 1",
            });
        }
        if self.max_steps == 0 {
            return Err(DataError::Config {
                field: "max_steps",
                value: "0".into(),
                expected: "at least 1",
            });
        }
        if self.obs.wrist {
            return Err(DataError::Config {
                field: "obs",
                value: "wrist".into(),
                expected: "PushT's observations (it has no wrist camera; robomimic targets do)",
            });
        }
        let (w, h) = self.image_size;
        if self.obs.pixels && !(1..=2048).contains(&w) || !(1..=2048).contains(&h) {
            return Err(DataError::Config {
                field: "image_size",
                value: format!("{w}x{h}"),
                expected: "sides between 1 and 2048 px",
            });
        }
        if self.seed.checked_add(self.episodes as u64).is_none() {
            return Err(DataError::Config {
                field: "seed",
                value: self.seed.to_string(),
                expected: "seed + episodes to fit in u64",
            });
        }
        self.expert.validate()?;
        Ok(())
    }
}

/// One simulated episode.
struct Episode {
    seed: u64,
    max_coverage: f64,
    frames: Vec<Frame>,
}

fn run_episode(config: &GenerateConfig, i: usize) -> Result<Episode, DataError> {
    let seed = config.seed + i as u64;
    let mut env = PushT::default();
    env.reset(seed, config.stream)?;
    let mut expert = Expert::new(config.expert.clone())?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(config.seed ^ (i as u64).rotate_left(32));
    let (frames, max_coverage) = record_expert(&mut env, &mut expert, &mut rng, config, 0)?;
    Ok(Episode {
        seed,
        max_coverage,
        frames,
    })
}

/// The expert's frames from `env` as it stands, control step `from_step` of its episode,
/// until success or `config.max_steps` (none when `from_step` is already there), with the
/// observations of `config.obs` at `config.image_size`; and the episode's maximum coverage
/// from that state on. `expert` plans from the state it finds (a fresh expert plans at its
/// first call); `rng` feeds its action noise.
///
/// # Errors
/// The simulator or the renderer failed.
pub fn record_expert<R: rand::Rng>(
    env: &mut PushT,
    expert: &mut Expert,
    rng: &mut R,
    config: &GenerateConfig,
    from_step: usize,
) -> Result<(Vec<Frame>, f64), DataError> {
    let mut renderer = config.obs.pixels.then(|| Renderer::new(env.goal()));
    let (w, h) = config.image_size;
    let mut frames = Vec::new();
    let mut max_coverage = env.coverage();
    for t in from_step..config.max_steps {
        let s = env.state_obs();
        let image = match &mut renderer {
            Some(r) => {
                let mut img = vec![0u8; w * h * 3];
                r.observation_with_contacts_into(
                    &env.scene(),
                    env.contact_segments(),
                    w,
                    h,
                    &mut img,
                )?;
                Some(img)
            }
            None => None,
        };
        let kp = env.keypoints();
        let action = expert.act(env, rng)?;
        let info = env.step(action)?;
        max_coverage = max_coverage.max(info.coverage);
        let done = info.is_success || t + 1 == config.max_steps;
        frames.push(Frame {
            state: vec![s[0] as f32, s[1] as f32],
            env_state: config
                .obs
                .keypoints
                .then(|| kp.iter().map(|&v| v as f32).collect()),
            pusht_state: config.obs.state.then(|| s.map(|v| v as f32)),
            image,
            wrist_image: None,
            action: vec![action[0] as f32, action[1] as f32],
            reward: info.reward as f32,
            done,
            success: info.is_success,
        });
        if done {
            break;
        }
    }
    Ok((frames, max_coverage))
}

/// Runs `run(i)` for every `i` in `0..n` in parallel batches (twice the current rayon pool's
/// threads) and hands the results to `sink` in index order, so what `sink` writes does not
/// depend on the thread count; stops at the first error.
///
/// # Errors
/// The first error of `run` or `sink`, in index order.
pub fn in_order<T: Send, E: Send>(
    n: usize,
    run: impl Fn(usize) -> Result<T, E> + Sync,
    mut sink: impl FnMut(T) -> Result<(), E>,
) -> Result<(), E> {
    let batch = (rayon::current_num_threads() * 2).max(1);
    for first in (0..n).step_by(batch) {
        let done: Vec<Result<T, E>> = (first..(first + batch).min(n))
            .into_par_iter()
            .map(&run)
            .collect();
        for result in done {
            sink(result?)?;
        }
    }
    Ok(())
}

/// Generate `config.episodes` expert demonstrations into `out` (a new directory), calling
/// `on_episode` after each episode is written (in index order). Uses the current rayon pool.
pub fn generate(
    config: &GenerateConfig,
    out: &Path,
    on_episode: &(dyn Fn(&EpisodeMeta) + Sync),
) -> Result<Info, DataError> {
    config.validate()?;
    let mut writer = config.writer(out)?;
    in_order(
        config.episodes,
        |i| run_episode(config, i),
        |ep| {
            writer.push_episode(ep.seed, ep.max_coverage, &ep.frames)?;
            writer.episodes().last().into_iter().for_each(on_episode);
            Ok(())
        },
    )?;
    let generator = serde_json::to_value(config).map_err(|e| DataError::Format {
        path: out.to_path_buf(),
        reason: e.to_string(),
    })?;
    writer.finish(serde_json::json!({ "expert_demonstrations": generator }))
}
