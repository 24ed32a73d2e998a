//! The dataset-to-policy adapter: the arrays a Diffusion Policy trains on (or is attacked
//! and fine-tuned on) from an `mte data generate` dataset (`mte_data::Dataset`).

use std::path::{Path, PathBuf};

use mte_data::Dataset;
use mte_data::dataset::names;
use mte_policy::config::DiffusionConfig;
use mte_policy::train::{TrainData, stats_from};

/// Why a dataset cannot feed a policy.
#[derive(Debug, thiserror::Error)]
pub enum TrainDataError {
    /// The dataset did not load.
    #[error("loading dataset {dir}: {source}")]
    Load {
        /// The dataset directory.
        dir: PathBuf,
        /// The underlying error.
        source: mte_data::DataError,
    },
    /// The policy needs a feature the dataset lacks.
    #[error("the policy needs `{feature}`, which the dataset lacks: regenerate with {hint}")]
    MissingFeature {
        /// LeRobot feature name.
        feature: &'static str,
        /// The `mte data generate` option that makes it.
        hint: &'static str,
    },
    /// The dataset's images are not the policy's size.
    #[error("dataset images are {got_h}x{got_w}, the policy expects {want:?} (C, H, W)")]
    ImageShape {
        /// Dataset image height.
        got_h: usize,
        /// Dataset image width.
        got_w: usize,
        /// The policy's image shape.
        want: Option<[usize; 3]>,
    },
}

/// What to take from the dataset beyond what the policy observes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Extra {
    /// The block keypoints also for an image policy (the encoder's keypoint regression).
    pub keypoints: bool,
}

/// Loads the dataset at `dir` and takes the arrays a policy of `config` needs.
pub fn load(
    dir: &Path,
    config: &DiffusionConfig,
    extra: Extra,
) -> Result<TrainData, TrainDataError> {
    let ds = Dataset::load(dir).map_err(|source| TrainDataError::Load {
        dir: dir.to_path_buf(),
        source,
    })?;
    from_dataset(&ds, config, extra)
}

/// The arrays a policy of `config` needs, from a loaded dataset.
pub fn from_dataset(
    ds: &Dataset,
    config: &DiffusionConfig,
    extra: Extra,
) -> Result<TrainData, TrainDataError> {
    let need = |feature: &'static str| -> Result<Vec<f32>, TrainDataError> {
        ds.feature(feature)
            .map(<[f32]>::to_vec)
            .map_err(|_| TrainDataError::MissingFeature {
                feature,
                hint: "--obs",
            })
    };
    let image_shape = config.image_shape();
    let env_state = if image_shape.is_none() || extra.keypoints {
        Some(need(names::ENV_STATE)?)
    } else {
        None
    };
    let images = match image_shape {
        None => None,
        Some(want) => {
            let shape = &ds
                .info
                .features
                .get(names::IMAGE)
                .ok_or(TrainDataError::MissingFeature {
                    feature: names::IMAGE,
                    hint: "--obs pixels",
                })?
                .shape;
            let (got_h, got_w) = match shape[..] {
                [h, w, ..] => (h, w),
                _ => (0, 0),
            };
            if want != [3, got_h, got_w] {
                return Err(TrainDataError::ImageShape {
                    got_h,
                    got_w,
                    want: image_shape,
                });
            }
            ds.images.clone()
        }
    };
    let stats = stats_from(ds.stats.iter().map(|(k, s)| {
        let (min, max) = (s.min.clone(), s.max.clone());
        (k.clone(), min, max, s.mean.clone(), s.std.clone())
    }));
    Ok(TrainData {
        state: need(names::STATE)?,
        env_state,
        images,
        action: need(names::ACTION)?,
        episode_lengths: ds.episode_lengths(),
        episode_success: ds.episodes.iter().map(|e| e.success).collect(),
        stats,
    })
}
