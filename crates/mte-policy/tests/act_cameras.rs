//! ACT with two cameras (the scene camera and the wrist camera): the policy feeds the network
//! each camera's frames, normalised with its own statistics, in the config's order (the scene
//! camera's feature-map tokens, then the wrist camera's, as LeRobot's ACT does), against an
//! oracle that calls the network with the two batches made by hand; it trains with frames
//! and with a frozen backbone's cached maps, and PGD attacks an observation of both cameras.

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use mte_policy::act::ActConfig;
use mte_policy::act::model::ActInputs;
use mte_policy::act::policy::ActPolicy;
use mte_policy::act::train::{ActTrainConfig, train};
use mte_policy::config::WRIST_CAMERA;
use mte_policy::normalize::{ImageNorm, Stats};
use mte_policy::train::TrainData;
use mte_policy::{AttackablePolicy, ChunkPolicy, Observation, PgdConfig, PolicyError, StatsMap};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

const SIDE: usize = 32;

fn config() -> ActConfig {
    ActConfig {
        chunk_size: 8,
        n_action_steps: 8,
        dim_model: 32,
        n_heads: 2,
        dim_feedforward: 64,
        n_encoder_layers: 1,
        n_vae_encoder_layers: 1,
        latent_dim: 4,
        vision_backbone_width: 4,
        ..ActConfig::cpu()
    }
    .with_camera("observation.image", [3, SIDE, SIDE])
    .with_wrist_camera()
}

fn stats() -> StatsMap {
    let s = |d: usize, mean: f32, std: f32| Stats {
        min: vec![0.0; d],
        max: vec![512.0; d],
        mean: vec![mean; d],
        std: vec![std; d],
    };
    [
        ("observation.state".to_string(), s(2, 250.0, 120.0)),
        ("action".to_string(), s(2, 250.0, 120.0)),
        ("observation.image".to_string(), s(3, 0.5, 0.25)),
        // The wrist camera's own statistics, unlike the scene camera's.
        (WRIST_CAMERA.to_string(), s(3, 0.3, 0.1)),
    ]
    .into_iter()
    .collect()
}

fn policy() -> ActPolicy {
    let vm = VarMap::new();
    let vb = mte_policy::init::seeded_var_builder(&vm, 5, DType::F32, &Device::Cpu);
    ActPolicy::new(config(), stats(), vb).expect("policy")
}

fn frame(k: usize) -> Vec<u8> {
    (0..SIDE * SIDE * 3)
        .map(|i| ((i * (3 + k) + i / 61 + 17 * k) % 256) as u8)
        .collect()
}

fn obs(k: usize) -> Observation {
    Observation {
        state: vec![100.0 + k as f32, 200.0],
        env_state: None,
        image: Some(frame(k)),
        wrist_image: Some(frame(k + 40)),
    }
}

/// One camera's frames as the network reads them: CHW in [0, 1], normalised with `name`'s
/// statistics.
fn normalised(frames: &[Vec<u8>], name: &str) -> Tensor {
    let mut chw = Vec::new();
    for f in frames {
        mte_policy::vision::push_chw(f, SIDE, SIDE, &mut chw).expect("frame");
    }
    let x = Tensor::from_vec(chw, (frames.len(), 3, SIDE, SIDE), &Device::Cpu).expect("x");
    let n = ImageNorm::mean_std(name, stats().get(name)).expect("stats");
    n.apply(&x).expect("normalised")
}

/// The config's cameras in the order their tokens enter the encoder.
fn camera_names(c: &ActConfig) -> Vec<String> {
    c.image_features()
        .expect("cameras")
        .into_iter()
        .map(|(n, _)| n)
        .collect()
}

#[test]
fn the_config_orders_and_checks_its_cameras() {
    let c = config();
    let names = camera_names(&c);
    assert_eq!(
        names,
        vec!["observation.image".to_string(), WRIST_CAMERA.to_string()]
    );
    c.validate().expect("two cameras");
    // A scene camera named after the wrist camera in name order still comes first.
    let late = config()
        .with_camera("observation.images.zz", [3, SIDE, SIDE])
        .with_wrist_camera();
    let names = camera_names(&late);
    assert_eq!(names[1], WRIST_CAMERA);
    // robomimic's eye-in-hand name is a wrist camera: it comes after the scene camera, even
    // one whose name sorts after it.
    let mut robomimic = config();
    let w = robomimic
        .input_features
        .remove(WRIST_CAMERA)
        .expect("wrist");
    let s = robomimic
        .input_features
        .remove("observation.image")
        .expect("scene");
    robomimic
        .input_features
        .insert("observation.images.robot0_eye_in_hand_image".into(), w);
    robomimic
        .input_features
        .insert("observation.images.zz_agentview".into(), s);
    robomimic.validate().expect("robomimic's camera names");
    let names = camera_names(&robomimic);
    assert_eq!(
        names,
        [
            "observation.images.zz_agentview",
            "observation.images.robot0_eye_in_hand_image"
        ]
    );
    let refused = |c: ActConfig, what: &str| {
        let e = c.validate().expect_err(what).to_string();
        assert!(e.contains("input_features"), "{what}: {e}");
    };
    let mut three = config();
    let f = three.input_features[WRIST_CAMERA].clone();
    three
        .input_features
        .insert("observation.images.top".into(), f.clone());
    refused(three, "three cameras");
    let mut other_shape = config();
    other_shape
        .input_features
        .get_mut(WRIST_CAMERA)
        .expect("wrist")
        .shape = vec![3, 16, 16];
    refused(other_shape, "two shapes");
    let mut wrist_only = config();
    wrist_only.input_features.remove("observation.image");
    refused(wrist_only, "the wrist camera alone");
}

#[test]
fn the_policy_feeds_the_scene_then_the_wrist_camera_each_normalised_alone() {
    let p = policy();
    assert!(p.needs().wrist_image);
    assert_eq!(p.n_cameras(), 2);
    let o = [obs(0), obs(1)];
    let refs: Vec<&Observation> = o.iter().collect();
    let got = p.predict_many(&refs).expect("chunks");
    // The oracle: the network called with the two cameras' batches made by hand.
    let t = p.obs_tensors(&refs).expect("tensors");
    let scene: Vec<Vec<u8>> = o.iter().map(|x| x.image.clone().expect("scene")).collect();
    let wrist: Vec<Vec<u8>> = o
        .iter()
        .map(|x| x.wrist_image.clone().expect("wrist"))
        .collect();
    let images = [
        normalised(&scene, "observation.image"),
        normalised(&wrist, WRIST_CAMERA),
    ];
    let inputs = ActInputs {
        state: t.state.as_ref(),
        env: None,
        images: &images,
        features: &[],
    };
    let out = p.net().forward(&inputs, None, None).expect("forward");
    let rows = out
        .actions
        .flatten_all()
        .and_then(|a| a.to_vec1::<f32>())
        .expect("actions");
    for (q, chunk) in got.iter().enumerate() {
        for (r, row) in chunk.chunks(2).enumerate() {
            let mut want = rows[(q * 8 + r) * 2..(q * 8 + r + 1) * 2].to_vec();
            // The policy unnormalises with the action statistics (mean 250, std 120).
            for v in &mut want {
                *v = *v * (120.0 + 1e-8) + 250.0;
            }
            for (g, w) in row.iter().zip(&want) {
                assert!((g - w).abs() < 1e-3, "query {q} row {r}: {g} against {w}");
            }
        }
    }
    // The wrist camera is read: another wrist frame, another chunk.
    let mut other = obs(0);
    other.wrist_image = Some(frame(7));
    assert_ne!(p.predict(&other).expect("chunk"), got[0]);
    other.wrist_image = None;
    let e = p.predict(&other).expect_err("no wrist frame");
    assert!(
        matches!(&e, PolicyError::Input { name, .. } if *name == WRIST_CAMERA),
        "{e}"
    );
}

fn data() -> TrainData {
    let n = 40;
    TrainData {
        state: (0..n).flat_map(|f| [f as f32 * 10.0, 100.0]).collect(),
        env_state: None,
        images: Some((0..n).flat_map(frame).collect()),
        wrist_images: Some((0..n).flat_map(|f| frame(f + 40)).collect()),
        action: (0..n)
            .flat_map(|f| [f as f32 * 10.0 + 5.0, 120.0])
            .collect(),
        episode_lengths: vec![20, 20],
        episode_success: vec![true, true],
        stats: stats(),
    }
}

/// Training settings of these tests: seed 1, no checkpoint before the end, no init.
fn train_config(steps: usize, batch_size: usize, freeze_backbone: bool) -> ActTrainConfig {
    ActTrainConfig {
        steps,
        batch_size,
        seed: 1,
        checkpoint_every: 100,
        freeze_backbone,
        ..Default::default()
    }
}

#[test]
fn it_trains_on_frames_and_on_a_frozen_backbones_maps_of_both_cameras() {
    for freeze_backbone in [false, true] {
        let dir = tempfile::tempdir().expect("tmp");
        let tc = train_config(3, 4, freeze_backbone);
        let r = train(&data(), config(), &tc, dir.path(), &mut |_, _, _| {}).expect("train");
        assert_eq!(r.step, 3);
        let p = ActPolicy::load(dir.path()).expect("load");
        assert_eq!(p.n_cameras(), 2);
        p.predict(&obs(2)).expect("a chunk from both cameras");
    }
    // Wrist frames of another size, or none, are refused by name.
    let dir = tempfile::tempdir().expect("tmp");
    let tc = train_config(1, 2, false);
    let mut small = data();
    small.wrist_images = Some(vec![0; 40 * 16 * 16 * 3]);
    let e = train(&small, config(), &tc, dir.path(), &mut |_, _, _| {}).expect_err("16 x 16");
    assert!(e.to_string().contains("wrist pixel values"), "{e}");
    let mut none = data();
    none.wrist_images = None;
    let e = train(&none, config(), &tc, dir.path(), &mut |_, _, _| {}).expect_err("no wrist");
    assert!(e.to_string().contains(WRIST_CAMERA), "{e}");
}

#[test]
fn pgd_attacks_an_observation_of_both_cameras() {
    let p = policy();
    let pgd = PgdConfig {
        eps: 0.05,
        step: 0.01,
        iterations: 3,
        ..PgdConfig::default()
    };
    let clean = p.predict(&obs(3)).expect("clean");
    let mut a = ChaCha8Rng::seed_from_u64(1);
    let mut s = ChaCha8Rng::seed_from_u64(2);
    let attacked = p
        .predict_chunk_attacked(&[obs(3)], &pgd, &mut a, &mut s)
        .expect("attacked");
    assert_ne!(attacked, clean);
    // What PGD perturbs is `ObsTensors::image`: both cameras' frames of the observation.
    let t = p.obs_tensors(&[&obs(3)]).expect("tensors");
    assert_eq!(t.image.expect("frames").dims4().expect("4-D").0, 2);
    // With the scene frame held fixed, another wrist frame changes the attacked chunk too.
    let mut other = obs(3);
    other.wrist_image = Some(frame(9));
    let mut a = ChaCha8Rng::seed_from_u64(1);
    let mut s = ChaCha8Rng::seed_from_u64(2);
    let moved = p
        .predict_chunk_attacked(&[other], &pgd, &mut a, &mut s)
        .expect("attacked");
    assert_ne!(moved, attacked);
}
