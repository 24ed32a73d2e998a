//! How many camera frames give pixel PGD a gradient at all.
//!
//! The image encoder ends in `ReLU(Linear(spatial-softmax keypoints))`, and the observation
//! gradient of the denoising loss reaches the pixels only through those features. A frame
//! whose every feature is zero after that ReLU (each pre-activation ≤ 0) therefore has an
//! exactly zero pixel gradient: sign-gradient PGD leaves it where its random start put it.
//! A query conditions on `n_obs_steps` consecutive frames, so its gradient is zero when all
//! of them are. [`encoder_activity`] counts both on a dataset's frames, clean or with the
//! uniform noise of PGD's random start.

use candle_core::Tensor;
use rand::{Rng, RngCore};
use serde::{Deserialize, Serialize};

use super::model::DiffusionPolicy;
use super::train::TrainData;
use crate::error::{PolicyError, config_err};

/// Which frames to encode and how to perturb them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ActivityConfig {
    /// Half-width of the uniform noise added to every pixel (pixels in `[0, 1]`, the result
    /// clipped to it), as PGD's random start draws it; 0 for the clean frames.
    pub eps: f32,
    /// Frames encoded per forward pass.
    pub batch: usize,
}

impl ActivityConfig {
    /// # Errors
    /// A negative or non-finite `eps`, or a zero batch.
    pub fn validate(&self) -> Result<(), PolicyError> {
        if !(self.eps.is_finite() && self.eps >= 0.0) {
            return Err(config_err("eps", self.eps, "a finite value >= 0"));
        }
        if self.batch == 0 {
            return Err(config_err("batch", self.batch, ">= 1"));
        }
        Ok(())
    }
}

/// The encoder's activity over a dataset's frames (the scene camera).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ActivityReport {
    /// Frames encoded (every frame of the dataset).
    pub frames: usize,
    /// Features per frame (`2 K`).
    pub features: usize,
    /// The noise half-width the frames carried.
    pub eps: f32,
    /// Frames whose every feature is zero: no pixel gradient.
    pub dead_frames: usize,
    /// Windows of `n_obs_steps` consecutive frames of one episode (a query's observation
    /// history) whose every frame is dead: queries PGD cannot move.
    pub windows: usize,
    /// Of [`ActivityReport::windows`], those with every frame dead.
    pub dead_windows: usize,
    /// Mean number of non-zero features per frame.
    pub active_mean: f64,
    /// Fewest non-zero features of any frame.
    pub active_min: usize,
    /// Median number of non-zero features (the lower middle value for an even count).
    pub active_median: usize,
    /// Features that are zero on every frame (units that never pass a gradient).
    pub never_active: usize,
}

/// Encode every scene-camera frame of `data` with `policy`'s encoder (centre crop, as at
/// inference), each frame perturbed by `cfg.eps` uniform noise drawn from `rng`, and count
/// the features that are non-zero.
///
/// # Errors
/// A policy without a camera or with two (the wrist camera is not counted), a dataset
/// without frames or with frames of another size, or a bad `cfg`.
pub fn encoder_activity(
    policy: &DiffusionPolicy,
    data: &TrainData,
    cfg: ActivityConfig,
    rng: &mut dyn RngCore,
) -> Result<ActivityReport, PolicyError> {
    cfg.validate()?;
    let [_, h, w] = scene_shape(policy)?;
    let images = data
        .images
        .as_deref()
        .ok_or_else(|| config_err("data.images", "none", "a dataset with camera frames"))?;
    let frame_len = 3 * h * w;
    if images.is_empty() || !images.len().is_multiple_of(frame_len) {
        return Err(config_err(
            "data.images",
            images.len(),
            format!("a whole number (>= 1) of {h} x {w} x 3 frames"),
        ));
    }
    let mut active = Vec::with_capacity(images.len() / frame_len);
    let mut ever = Vec::new();
    for chunk in images.chunks(cfg.batch * frame_len) {
        let n = chunk.len() / frame_len;
        let mut x = Vec::with_capacity(chunk.len());
        for px in chunk.chunks_exact(frame_len) {
            crate::vision::push_chw(px, h, w, &mut x)
                .map_err(|why| config_err("data.images", why, "frames of the policy's size"))?;
        }
        if cfg.eps > 0.0 {
            for v in &mut x {
                *v = (*v + rng.random_range(-cfg.eps..=cfg.eps)).clamp(0.0, 1.0);
            }
        }
        let x = Tensor::from_vec(x, (n, 3, h, w), policy.device())?;
        let f: Vec<Vec<f32>> = policy.image_features(&x)?.to_vec2()?;
        for row in f {
            ever.resize(row.len(), false);
            for (e, &v) in ever.iter_mut().zip(&row) {
                *e |= v != 0.0;
            }
            active.push(row.iter().filter(|&&v| v != 0.0).count());
        }
    }
    let (windows, dead_windows) =
        dead_windows(&active, &data.episode_lengths, policy.config().n_obs_steps)?;
    let mut sorted = active.clone();
    sorted.sort_unstable();
    Ok(ActivityReport {
        frames: active.len(),
        features: ever.len(),
        eps: cfg.eps,
        dead_frames: active.iter().filter(|&&a| a == 0).count(),
        windows,
        dead_windows,
        active_mean: active.iter().sum::<usize>() as f64 / active.len() as f64,
        active_min: sorted[0],
        active_median: sorted[(sorted.len() - 1) / 2],
        never_active: ever.iter().filter(|&&e| !e).count(),
    })
}

/// The one camera's `[3, h, w]`.
fn scene_shape(policy: &DiffusionPolicy) -> Result<[usize; 3], PolicyError> {
    if policy.n_cameras() != 1 {
        return Err(config_err(
            "input_features",
            policy.config().cameras(),
            "exactly one camera (the scene camera's frames are counted)",
        ));
    }
    policy
        .config()
        .image_shape()
        .ok_or_else(|| config_err("input_features", "no image shape", "a [3, h, w] camera"))
}

/// Windows of `n_obs` consecutive frames within each episode, and those whose every frame
/// has no active feature. An episode shorter than `n_obs` has no window.
fn dead_windows(
    active: &[usize],
    episode_lengths: &[usize],
    n_obs: usize,
) -> Result<(usize, usize), PolicyError> {
    if episode_lengths.iter().sum::<usize>() != active.len() {
        return Err(config_err(
            "data.episode_lengths",
            episode_lengths.iter().sum::<usize>(),
            format!("the number of frames, {}", active.len()),
        ));
    }
    let (mut windows, mut dead, mut start) = (0, 0, 0);
    for &len in episode_lengths {
        let ep = &active[start..start + len];
        for win in ep.windows(n_obs.max(1)) {
            windows += 1;
            dead += usize::from(win.iter().all(|&a| a == 0));
        }
        start += len;
    }
    Ok((windows, dead))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn windows_count_within_episodes_only() {
        // Episodes of 3 and 2 frames; frames 2 (end of the first) and 3 (start of the
        // second) are dead, but no window spans the episode boundary.
        let active = [4, 1, 0, 0, 5];
        assert_eq!(dead_windows(&active, &[3, 2], 2).unwrap(), (3, 0));
        assert_eq!(dead_windows(&[0, 0, 3], &[3], 2).unwrap(), (2, 1));
        assert_eq!(dead_windows(&[0, 0, 0], &[3], 1).unwrap(), (3, 3));
        // A short episode has no window.
        assert_eq!(dead_windows(&[0], &[1], 2).unwrap(), (0, 0));
        assert!(dead_windows(&[0, 1], &[3], 2).is_err());
    }
}
