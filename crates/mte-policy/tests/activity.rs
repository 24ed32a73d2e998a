//! The count of frames that give pixel PGD a gradient (`activity::encoder_activity`), against
//! an oracle that encodes each frame alone; and the fact it rests on: a frame whose every
//! encoder feature is zero after the final ReLU has an exactly zero pixel gradient.

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use mte_policy::activity::{ActivityConfig, encoder_activity};
use mte_policy::config::{DiffusionConfig, ObsKind};
use mte_policy::train::TrainData;
use mte_policy::{DiffusionPolicy, Observation, PolicyError, StatsMap};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

mod common;

const SIDE: usize = 40;

fn stats() -> StatsMap {
    common::stats(&[
        ("observation.state", 0.0, 512.0, 2),
        ("observation.image", 0.0, 1.0, 3),
        ("action", 0.0, 512.0, 2),
    ])
}

fn tiny() -> (DiffusionPolicy, VarMap) {
    let config = DiffusionConfig::cpu(ObsKind::Image)
        .with_overrides(&serde_json::json!({
            "down_dims": [8, 16], "n_groups": 4, "diffusion_step_embed_dim": 8,
            "spatial_softmax_num_keypoints": 4, "num_inference_steps": 2,
            "crop_shape": [32, 32],
            "input_features": {
                "observation.state": {"type": "STATE", "shape": [2]},
                "observation.image": {"type": "VISUAL", "shape": [3, SIDE, SIDE]}
            }
        }))
        .expect("a valid config");
    let vm = VarMap::new();
    let vb = mte_policy::init::seeded_var_builder(&vm, 11, DType::F32, &Device::Cpu);
    (
        DiffusionPolicy::new(config, stats(), vb).expect("policy"),
        vm,
    )
}

/// A frame whose pattern depends on `k`.
fn frame(k: usize) -> Vec<u8> {
    let kf = k as f32;
    (0..SIDE * SIDE * 3)
        .map(|i| {
            let (y, x, c) = ((i / 3 / SIDE) as f32, (i / 3 % SIDE) as f32, (i % 3) as f32);
            (128.0 + 60.0 * (0.3 * x + kf).sin() + 50.0 * (0.2 * y + c - kf).cos()) as u8
        })
        .collect()
}

/// Episodes of 4 and 3 frames.
fn data() -> TrainData {
    let n = 7;
    TrainData {
        state: (0..n).flat_map(|f| [f as f32, 100.0]).collect(),
        env_state: None,
        images: Some((0..n).flat_map(frame).collect()),
        wrist_images: None,
        action: (0..n).flat_map(|f| [f as f32 + 5.0, 120.0]).collect(),
        episode_lengths: vec![4, 3],
        episode_success: vec![true, true],
        stats: stats(),
    }
}

/// The oracle: frame `k` encoded alone, its non-zero feature count.
fn active_alone(p: &DiffusionPolicy, k: usize) -> usize {
    let mut chw = Vec::new();
    mte_policy::vision::push_chw(&frame(k), SIDE, SIDE, &mut chw).expect("frame");
    let x = Tensor::from_vec(chw, (1, 3, SIDE, SIDE), &Device::Cpu).expect("tensor");
    let f: Vec<f32> = p
        .image_features(&x)
        .expect("features")
        .flatten_all()
        .and_then(|t| t.to_vec1())
        .expect("a feature row");
    f.iter().filter(|&&v| v != 0.0).count()
}

fn clean(batch: usize) -> ActivityConfig {
    ActivityConfig { eps: 0.0, batch }
}

#[test]
fn counts_match_frames_encoded_alone() {
    let (p, _vm) = tiny();
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let r = encoder_activity(&p, &data(), clean(3), &mut rng).expect("report");
    let alone: Vec<usize> = (0..7).map(|k| active_alone(&p, k)).collect();
    assert_eq!(r.frames, 7);
    assert_eq!(r.features, 8);
    assert_eq!(r.dead_frames, alone.iter().filter(|&&a| a == 0).count());
    assert_eq!(r.active_min, *alone.iter().min().unwrap());
    let mean = alone.iter().sum::<usize>() as f64 / 7.0;
    assert!(
        (r.active_mean - mean).abs() < 1e-12,
        "{} vs {mean}",
        r.active_mean
    );
    // Windows of n_obs_steps = 2 within the episodes: 3 + 2.
    assert_eq!(r.windows, 5);
    // The random encoder passes something on these frames (else the test above is vacuous).
    assert!(r.active_mean > 0.0);
    // The batch size does not change the counts.
    let one = encoder_activity(&p, &data(), clean(1), &mut rng).expect("report");
    assert_eq!(one, r);
}

#[test]
fn all_dead_features_mean_no_pixel_gradient() {
    let (p, vm) = tiny();
    // Every pre-activation of the final ReLU far below zero.
    let bias = vm
        .data()
        .lock()
        .unwrap()
        .get("diffusion.rgb_encoder.out.bias")
        .expect("the encoder's output bias")
        .clone();
    bias.set(&Tensor::full(-1e3f32, 8, &Device::Cpu).unwrap())
        .unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let r = encoder_activity(&p, &data(), ActivityConfig { eps: 0.1, batch: 4 }, &mut rng)
        .expect("report");
    assert_eq!((r.dead_frames, r.dead_windows, r.windows), (7, 5, 5));
    assert_eq!((r.never_active, r.active_min, r.active_median), (8, 0, 0));
    // Such a frame's pixel gradient is exactly zero.
    let history: Vec<Observation> = (0..2)
        .map(|k| Observation {
            state: vec![k as f32, 100.0],
            env_state: None,
            image: Some(frame(k)),
            wrist_image: None,
        })
        .collect();
    let obs = p.obs_batch(&[&history]).expect("batch");
    let tp = p.config().horizon;
    let x0 = common::randn(2, &[1, tp, 2], 1.0, DType::F32);
    let eps = common::randn(3, &[1, tp, 2], 1.0, DType::F32);
    let (_, g) = p
        .observation_gradient(&obs, &x0, &eps, &[5])
        .expect("gradient");
    let g: Vec<f32> = g
        .image
        .expect("image gradient")
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap();
    assert!(
        g.iter().all(|&v| v == 0.0),
        "a dead frame passed a gradient"
    );
}

#[test]
fn noise_is_seeded_and_bad_input_is_refused() {
    let (p, _vm) = tiny();
    let noisy = ActivityConfig { eps: 0.2, batch: 2 };
    let run = |seed| encoder_activity(&p, &data(), noisy, &mut ChaCha8Rng::seed_from_u64(seed));
    assert_eq!(run(5).unwrap(), run(5).unwrap());
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    for bad in [
        ActivityConfig {
            eps: -0.1,
            batch: 1,
        },
        ActivityConfig {
            eps: f32::NAN,
            batch: 1,
        },
        ActivityConfig { eps: 0.0, batch: 0 },
    ] {
        assert!(matches!(
            encoder_activity(&p, &data(), bad, &mut rng),
            Err(PolicyError::Config { .. })
        ));
    }
    let mut no_frames = data();
    no_frames.images = None;
    let e = encoder_activity(&p, &no_frames, clean(1), &mut rng).expect_err("no frames");
    assert!(e.to_string().contains("data.images"), "{e}");
    let mut torn = data();
    torn.images.as_mut().unwrap().pop();
    assert!(encoder_activity(&p, &torn, clean(1), &mut rng).is_err());
    let mut lengths = data();
    lengths.episode_lengths = vec![4, 4];
    let e = encoder_activity(&p, &lengths, clean(1), &mut rng).expect_err("lengths");
    assert!(e.to_string().contains("episode_lengths"), "{e}");
}
