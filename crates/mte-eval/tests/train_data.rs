//! The dataset-to-policy adapter: the arrays a policy needs, and a typed error naming what
//! a dataset lacks.

use mte_data::{GenerateConfig, ObsSet, generate};
use mte_eval::train_data::{Extra, TrainDataError, load};
use mte_policy::config::{DiffusionConfig, ObsKind};

fn dataset(pixels: bool, keypoints: bool) -> tempfile::TempDir {
    sized(pixels, keypoints, (96, 96))
}

fn sized(pixels: bool, keypoints: bool, image_size: (usize, usize)) -> tempfile::TempDir {
    let dir = tempfile::tempdir().expect("tempdir");
    let config = GenerateConfig {
        episodes: 2,
        seed: 3,
        obs: ObsSet {
            state: true,
            keypoints,
            pixels,
            wrist: false,
        },
        image_size,
        max_steps: 10,
        ..GenerateConfig::default()
    };
    generate(&config, dir.path(), &|_| {}).expect("generate");
    dir
}

#[test]
fn a_keypoint_policy_gets_state_keypoints_and_actions_frame_by_frame() {
    let dir = dataset(false, true);
    let config = DiffusionConfig::cpu(ObsKind::Keypoints);
    let d = load(dir.path(), &config, Extra::default()).expect("arrays");
    let frames: usize = d.episode_lengths.iter().sum();
    assert_eq!(d.episode_lengths.len(), 2);
    assert_eq!(d.state.len(), frames * 2);
    assert_eq!(d.action.len(), frames * 2);
    assert_eq!(d.env_state.as_ref().map(Vec::len), Some(frames * 16));
    assert!(d.images.is_none());
}

#[test]
fn a_missing_feature_or_a_wrong_image_size_is_named() {
    let kp_only = dataset(false, true);
    let image = DiffusionConfig::cpu(ObsKind::Image);
    let e = load(kp_only.path(), &image, Extra::default()).expect_err("no images");
    assert!(
        matches!(e, TrainDataError::MissingFeature { feature, .. } if feature == "observation.image"),
        "{e}"
    );
    let small = sized(true, false, (24, 16));
    let e = load(small.path(), &image, Extra::default()).expect_err("image size");
    assert!(
        matches!(
            e,
            TrainDataError::ImageShape {
                got_h: 16,
                got_w: 24,
                ..
            }
        ),
        "{e}"
    );
    let no_kp = dataset(false, false);
    let kp = DiffusionConfig::cpu(ObsKind::Keypoints);
    let e = load(no_kp.path(), &kp, Extra::default()).expect_err("no keypoints");
    assert!(
        e.to_string().contains("observation.environment_state"),
        "{e}"
    );
    let e = load(
        std::path::Path::new("no/such/dataset"),
        &kp,
        Extra::default(),
    )
    .expect_err("no dataset");
    assert!(matches!(e, TrainDataError::Load { .. }), "{e}");
}
