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

/// Sets the sizes of `config`'s features to the dataset's, so that one preset serves any
/// task: vector features (`observation.state`, `observation.environment_state`, `action`;
/// PushT's 2-D state and action, robomimic's 9-D proprioception and 7-D actions) take the
/// dataset's length, and a camera (`[3, h, w]`, channels first) takes the frame size of the
/// dataset's `[h, w, 3]` frames (PushT's 96 x 96, robomimic's 84 x 84). The crop is left as
/// it is: a crop larger than the frame is then refused by `validate()` by name (robomimic
/// as Diffusion Policy configures it crops 76 x 76). Features the dataset lacks are left as
/// they are (loading the arrays then names what is missing).
pub fn fit_shapes(config: &mut DiffusionConfig, info: &mte_data::Info) {
    let features = config
        .input_features
        .iter_mut()
        .chain(config.output_features.iter_mut());
    for (name, f) in features {
        let Some(d) = info.features.get(name) else {
            continue;
        };
        match (&f.shape[..], &d.shape[..]) {
            ([_], [n]) => f.shape = vec![*n],
            ([c, _, _], [h, w, dc]) if c == dc => f.shape = vec![*c, *h, *w],
            _ => {}
        }
    }
}

/// Loads the dataset at `dir` and takes the arrays a policy of `config` needs.
pub fn load(
    dir: &Path,
    config: &DiffusionConfig,
    extra: Extra,
) -> Result<TrainData, TrainDataError> {
    load_many(&[dir.to_path_buf()], config, extra)
}

/// Loads the datasets at `dirs` as one ([`Dataset::concat`]: episodes in order, statistics
/// pooled) and takes the arrays a policy of `config` needs: demonstrations and corrective
/// episodes (`mte data takeover`) trained on together.
pub fn load_many(
    dirs: &[PathBuf],
    config: &DiffusionConfig,
    extra: Extra,
) -> Result<TrainData, TrainDataError> {
    let load = |dir: &PathBuf| {
        Dataset::load(dir).map_err(|source| TrainDataError::Load {
            dir: dir.clone(),
            source,
        })
    };
    let parts = dirs.iter().map(load).collect::<Result<Vec<_>, _>>()?;
    let ds = Dataset::concat(parts).map_err(|source| TrainDataError::Load {
        dir: dirs.first().cloned().unwrap_or_default(),
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
    let wrist_images = match (images.is_some(), config.has_wrist_camera()) {
        (true, true) => Some(ds.other_images.get(names::WRIST_IMAGE).cloned().ok_or(
            TrainDataError::MissingFeature {
                feature: names::WRIST_IMAGE,
                hint: "--obs pixels,wrist",
            },
        )?),
        _ => None,
    };
    let stats = stats_from(ds.stats.iter().map(|(k, s)| {
        let (min, max) = (s.min.clone(), s.max.clone());
        (k.clone(), min, max, s.mean.clone(), s.std.clone())
    }));
    Ok(TrainData {
        state: need(names::STATE)?,
        env_state,
        images,
        wrist_images,
        action: need(names::ACTION)?,
        episode_lengths: ds.episode_lengths(),
        episode_success: ds.episodes.iter().map(|e| e.success).collect(),
        stats,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use mte_data::Feature;
    use mte_data::npy::DType;
    use mte_policy::config::ObsKind;

    #[test]
    fn features_take_the_datasets_sizes() {
        let mut config = DiffusionConfig::cpu(ObsKind::Keypoints);
        let feature = |n: usize| Feature {
            dtype: DType::F32,
            shape: vec![n],
            file: String::new(),
            description: String::new(),
        };
        let info = mte_data::Info {
            format: mte_data::dataset::FORMAT.into(),
            fps: 20.0,
            episodes: 1,
            frames: 1,
            features: [
                (names::STATE.to_string(), feature(9)),
                (names::ENV_STATE.to_string(), feature(10)),
                (names::ACTION.to_string(), feature(7)),
            ]
            .into_iter()
            .collect(),
            generator: serde_json::Value::Null,
        };
        fit_shapes(&mut config, &info);
        assert_eq!(config.input_features[names::STATE].shape, vec![9]);
        assert_eq!(config.input_features[names::ENV_STATE].shape, vec![10]);
        assert_eq!(config.output_features[names::ACTION].shape, vec![7]);
        config.validate().expect("still valid");
        // Features the dataset lacks keep their shape.
        let mut image = DiffusionConfig::cpu(ObsKind::Image);
        let before = image.input_features.clone();
        fit_shapes(
            &mut image,
            &mte_data::Info {
                features: Default::default(),
                ..info.clone()
            },
        );
        assert_eq!(image.input_features, before);
        // A camera takes the dataset's frame size (channels first); the crop stays.
        let mut frames = mte_data::Info {
            features: Default::default(),
            ..info.clone()
        };
        frames.features.insert(
            names::IMAGE.to_string(),
            Feature {
                shape: vec![84, 84, 3],
                ..feature(1)
            },
        );
        fit_shapes(&mut image, &frames);
        assert_eq!(image.input_features[names::IMAGE].shape, vec![3, 84, 84]);
        assert_eq!(image.crop_shape, Some([84, 84]));
        // Frames of another channel count are not a camera of this policy: left alone.
        frames
            .features
            .get_mut(names::IMAGE)
            .expect("inserted")
            .shape = vec![84, 84, 4];
        let mut other = DiffusionConfig::cpu(ObsKind::Image);
        fit_shapes(&mut other, &frames);
        assert_eq!(other.input_features, before);
    }
}
