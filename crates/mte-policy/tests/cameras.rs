//! A Diffusion Policy with two cameras (the scene camera and the wrist camera), against an
//! oracle that encodes each camera's frame on its own: the conditioning of every observation
//! step is `[state, scene features, wrist features]`, LeRobot's `(b s n) -> b s (n F)`
//! layout, with one shared encoder or one per camera (LeRobot's key names), each camera
//! normalised with its own statistics.

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use mte_policy::config::{DiffusionConfig, FeatureType, ObsKind, PolicyFeature, WRIST_CAMERA};
use mte_policy::normalize::ImageNorm;
use mte_policy::train::{TrainData, Windows, sample_batch};
use mte_policy::vision::RgbEncoder;
use mte_policy::{ChunkPolicy, DiffusionPolicy, Observation, PolicyError, Stats, StatsMap};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

mod common;

const SIDE: usize = 96;

fn stats() -> StatsMap {
    let mut s = common::stats(&[
        ("observation.state", 0.0, 512.0, 2),
        ("observation.image", 0.0, 1.0, 3),
        ("action", 0.0, 512.0, 2),
    ]);
    // The wrist camera's own statistics, unlike the scene camera's.
    s.insert(
        WRIST_CAMERA.into(),
        Stats {
            min: vec![0.0; 3],
            max: vec![1.0; 3],
            mean: vec![0.2, 0.3, 0.4],
            std: vec![0.1, 0.2, 0.3],
        },
    );
    s
}

fn config(separate: bool) -> DiffusionConfig {
    DiffusionConfig::cpu(ObsKind::Image)
        .with_wrist_camera()
        .with_overrides(&serde_json::json!({
            "down_dims": [8, 16], "n_groups": 4, "diffusion_step_embed_dim": 8,
            "spatial_softmax_num_keypoints": 4, "num_inference_steps": 2,
            "use_separate_rgb_encoder_per_camera": separate
        }))
        .expect("a valid two-camera config")
}

fn tiny(separate: bool) -> (DiffusionPolicy, VarMap) {
    let vm = VarMap::new();
    let vb = mte_policy::init::seeded_var_builder(&vm, 7, DType::F32, &Device::Cpu);
    let p = DiffusionPolicy::new(config(separate), stats(), vb).expect("policy");
    (p, vm)
}

/// A smooth frame whose pattern depends on `k` (smooth, so that no activation of the
/// random network saturates and every pixel has a gradient).
fn frame(k: usize) -> Vec<u8> {
    let kf = k as f32;
    (0..SIDE * SIDE * 3)
        .map(|i| {
            let (y, x, c) = ((i / 3 / SIDE) as f32, (i / 3 % SIDE) as f32, (i % 3) as f32);
            let v = 128.0 + 50.0 * (0.13 * x + 0.7 * kf).sin() + 40.0 * (0.07 * y + c + kf).cos();
            v as u8
        })
        .collect()
}

fn obs(k: usize) -> Observation {
    Observation {
        state: vec![100.0 + k as f32, 200.0],
        env_state: None,
        image: Some(frame(k)),
        wrist_image: Some(frame(k + 50)),
    }
}

/// The oracle: camera `name`'s frame normalised with its statistics and encoded alone.
fn encode_alone(enc: &RgbEncoder, name: &str, px: &[u8]) -> Vec<f32> {
    let mut chw = Vec::new();
    mte_policy::vision::push_chw(px, SIDE, SIDE, &mut chw).expect("frame");
    let x = Tensor::from_vec(chw, (1, 3, SIDE, SIDE), &Device::Cpu).expect("tensor");
    let norm = ImageNorm::mean_std(name, stats().get(name)).expect("stats");
    let f = enc
        .forward(&norm.apply(&x).expect("norm"))
        .expect("encoder");
    f.flatten_all().and_then(|t| t.to_vec1()).expect("features")
}

fn encoder(vm: &VarMap, prefix: &str) -> RgbEncoder {
    let vb = mte_policy::init::seeded_var_builder(vm, 7, DType::F32, &Device::Cpu);
    let c = config(false);
    RgbEncoder::with_width(
        c.vision_backbone_width,
        c.crop_shape,
        c.spatial_softmax_num_keypoints,
        vb.pp(prefix),
    )
    .expect("the policy's encoder")
}

/// Checks the conditioning of two queries against the oracle with `scene` and `wrist`
/// encoders.
fn check_against_oracle(policy: &DiffusionPolicy, scene: &RgbEncoder, wrist: &RgbEncoder) {
    let histories = [vec![obs(0), obs(1)], vec![obs(2), obs(3)]];
    let refs: Vec<&[Observation]> = histories.iter().map(Vec::as_slice).collect();
    let batch = policy.obs_batch(&refs).expect("batch");
    assert_eq!(
        batch
            .image
            .as_ref()
            .expect("images")
            .dims4()
            .expect("4-D")
            .0,
        2 * 2 * 2
    );
    let cond = policy.global_cond(&batch).expect("conditioning");
    let f = 2 * 4;
    let per_step = 2 + 2 * f;
    assert_eq!(cond.dims2().expect("2-D"), (2, 2 * per_step));
    let rows: Vec<Vec<f32>> = cond.to_vec2().expect("rows");
    for (q, h) in histories.iter().enumerate() {
        for (s, o) in h.iter().enumerate() {
            let step = &rows[q][s * per_step..(s + 1) * per_step];
            let want_scene = encode_alone(
                scene,
                "observation.image",
                o.image.as_deref().expect("scene"),
            );
            let want_wrist = encode_alone(
                wrist,
                WRIST_CAMERA,
                o.wrist_image.as_deref().expect("wrist"),
            );
            // The same operations on the same values, batched otherwise: rounding only.
            let d_scene = common::max_abs_diff_slices(&step[2..2 + f], &want_scene);
            let d_wrist = common::max_abs_diff_slices(&step[2 + f..], &want_wrist);
            assert!(
                d_scene < 1e-5 && d_wrist < 1e-5,
                "query {q} step {s}: {d_scene} {d_wrist}"
            );
        }
    }
}

#[test]
fn the_config_names_its_cameras_and_refuses_what_it_cannot_feed() {
    let c = config(false);
    assert_eq!(c.cameras(), vec!["observation.image", WRIST_CAMERA]);
    assert!(c.has_wrist_camera());
    let camera = |shape: Vec<usize>| PolicyFeature {
        kind: FeatureType::Visual,
        shape,
    };
    let refused = |c: DiffusionConfig, what: &str| {
        let e = c.validate().expect_err(what).to_string();
        assert!(e.contains("input_features"), "{what}: {e}");
    };
    let mut other_shape = c.clone();
    other_shape
        .input_features
        .insert(WRIST_CAMERA.into(), camera(vec![3, 84, 84]));
    refused(other_shape, "cameras of two shapes");
    let mut three = c.clone();
    three
        .input_features
        .insert("observation.images.top".into(), camera(vec![3, 96, 96]));
    refused(three, "three cameras");
    let mut wrist_only = c.clone();
    wrist_only.input_features.remove("observation.image");
    refused(wrist_only, "the wrist camera alone");
    // One camera of any name is the scene camera, as before.
    let mut renamed = DiffusionConfig::cpu(ObsKind::Image);
    let f = renamed
        .input_features
        .remove("observation.image")
        .expect("camera");
    renamed
        .input_features
        .insert("observation.images.top".into(), f);
    renamed.validate().expect("one camera of any name");
    assert!(!renamed.has_wrist_camera());
}

#[test]
fn a_shared_encoder_conditions_on_the_scene_then_the_wrist_features() {
    let (policy, vm) = tiny(false);
    assert!(policy.needs().wrist_image);
    assert_eq!(policy.n_cameras(), 2);
    let enc = encoder(&vm, "diffusion.rgb_encoder");
    check_against_oracle(&policy, &enc, &enc);
}

#[test]
fn separate_encoders_have_lerobots_keys_and_each_sees_its_own_camera() {
    let (policy, vm) = tiny(true);
    let keys: Vec<String> = vm.data().lock().expect("map").keys().cloned().collect();
    let under = |p: &str| keys.iter().filter(|k| k.starts_with(p)).count();
    let per_camera = under("diffusion.rgb_encoder.0.");
    assert!(per_camera > 0, "{keys:?}");
    assert_eq!(under("diffusion.rgb_encoder.1."), per_camera);
    assert_eq!(under("diffusion.rgb_encoder."), 2 * per_camera);
    let scene = encoder(&vm, "diffusion.rgb_encoder.0");
    let wrist = encoder(&vm, "diffusion.rgb_encoder.1");
    check_against_oracle(&policy, &scene, &wrist);
}

#[test]
fn an_observation_without_the_wrist_frame_is_refused_by_name() {
    let (policy, _) = tiny(false);
    let mut o = obs(0);
    o.wrist_image = None;
    let e = policy
        .obs_batch(&[&[obs(1), o]])
        .expect_err("no wrist frame");
    assert!(
        matches!(&e, PolicyError::Input { name, .. } if *name == "observation.images.wrist"),
        "{e}"
    );
}

#[test]
fn the_loss_gradient_reaches_both_cameras_pixels() {
    let (policy, _) = tiny(false);
    // Some of these synthetic frames (obs(1) among them) have every feature at zero after
    // the encoder's final ReLU (LeRobot's) under this random 4-keypoint network, so no pixel
    // gradient at all, with one camera as with two (a finite difference agrees); these two
    // frames have live features.
    let batch = policy.obs_batch(&[&[obs(3), obs(4)]]).expect("batch");
    let x0 = Tensor::zeros((1, 16, 2), DType::F32, &Device::Cpu).expect("x0");
    let eps = Tensor::ones((1, 16, 2), DType::F32, &Device::Cpu).expect("eps");
    let (_, g) = policy
        .observation_gradient(&batch, &x0, &eps, &[5])
        .expect("gradient");
    let g = g.image.expect("an image gradient");
    // Rows: (step 0: scene, wrist), (step 1: scene, wrist).
    let norms: Vec<f32> = (0..4)
        .map(|row| {
            let norm = g.get(row).and_then(|t| t.abs()).and_then(|t| t.sum_all());
            norm.and_then(|t| t.to_scalar()).expect("norm")
        })
        .collect();
    assert!(
        norms.iter().all(|&n| n > 0.0),
        "gradient norms per frame {norms:?}"
    );
}

#[test]
fn a_checkpoint_round_trips_and_a_foreign_camera_order_is_refused() {
    let (policy, vm) = tiny(true);
    let dir = tempfile::tempdir().expect("tempdir");
    let weights: HashMap<String, Tensor> = vm
        .data()
        .lock()
        .expect("map")
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect();
    mte_policy::checkpoint::save(dir.path(), policy.config(), &weights, policy.stats())
        .expect("save");
    let back = mte_policy::checkpoint::load(dir.path(), &Device::Cpu).expect("load");
    assert_eq!(back.config(), policy.config());
    let h = [obs(0), obs(1)];
    let a = policy
        .global_cond(&policy.obs_batch(&[&h]).expect("batch"))
        .expect("cond");
    let b = back
        .global_cond(&back.obs_batch(&[&h]).expect("batch"))
        .expect("cond");
    assert_eq!(common::max_abs_diff(&a, &b), 0.0);
    // A config.json listing the wrist camera first: LeRobot would concatenate in that order.
    let path = dir.path().join("config.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).expect("read")).expect("json");
    let feats = v["input_features"].as_object().expect("object").clone();
    // serde_json's map sorts its keys: the object is written by hand in this order.
    let mut reordered = vec![(WRIST_CAMERA.to_string(), feats[WRIST_CAMERA].clone())];
    for (k, f) in feats.iter().filter(|(k, _)| *k != WRIST_CAMERA) {
        reordered.push((k.clone(), f.clone()));
    }
    let body: Vec<String> = reordered
        .iter()
        .map(|(k, f)| format!("{}: {f}", serde_json::Value::from(k.as_str())))
        .collect();
    v["input_features"] = serde_json::Value::String("@@".into());
    let text = v
        .to_string()
        .replace("\"@@\"", &format!("{{{}}}", body.join(", ")));
    std::fs::write(&path, text).expect("write");
    let e = match mte_policy::checkpoint::load(dir.path(), &Device::Cpu) {
        Ok(_) => panic!("a foreign camera order loaded"),
        Err(e) => e.to_string(),
    };
    assert!(
        e.contains("input_features") && e.contains(WRIST_CAMERA),
        "{e}"
    );
}

fn data(with_wrist: bool) -> TrainData {
    let n = 12;
    TrainData {
        state: (0..n).flat_map(|f| [f as f32 * 10.0, 100.0]).collect(),
        env_state: None,
        images: Some((0..n).flat_map(frame).collect()),
        wrist_images: with_wrist.then(|| (0..n).flat_map(|f| frame(f + 50)).collect()),
        action: (0..n)
            .flat_map(|f| [f as f32 * 10.0 + 5.0, 120.0])
            .collect(),
        episode_lengths: vec![n],
        episode_success: vec![true],
        stats: stats(),
    }
}

#[test]
fn training_batches_carry_both_cameras_and_a_dataset_without_the_wrist_is_refused() {
    let (policy, _) = tiny(false);
    let d = data(true);
    let win = Windows::new(&d, policy.config(), false);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let (batch, _) = sample_batch(&policy, &d, &win, 3, &mut rng, true).expect("batch");
    let crop = policy.config().crop_shape.expect("the preset crops");
    let dims = batch.image.expect("images").dims4().expect("4-D");
    assert_eq!(dims, (3 * 2 * 2, 3, crop[0], crop[1]));
    let d = data(false);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let e = sample_batch(&policy, &d, &win, 3, &mut rng, true).expect_err("no wrist frames");
    assert!(e.to_string().contains("observation.images.wrist"), "{e}");
}

/// `c` with its cameras renamed: the scene camera to `scene`, the wrist camera to `wrist`.
fn renamed(c: &DiffusionConfig, scene: &str, wrist: &str) -> DiffusionConfig {
    let mut c = c.clone();
    let s = c.input_features.remove("observation.image").expect("scene");
    let w = c.input_features.remove(WRIST_CAMERA).expect("wrist");
    c.input_features.insert(scene.into(), s);
    c.input_features.insert(wrist.into(), w);
    c
}

#[test]
fn a_policy_naming_its_cameras_as_robomimic_does_is_fed_like_mtes_own() {
    let (scene, wrist) = (
        "observation.images.agentview_image",
        "observation.images.robot0_eye_in_hand_image",
    );
    for separate in [false, true] {
        let (policy, _) = tiny(separate);
        let c = renamed(policy.config(), scene, wrist);
        c.validate().expect("robomimic's camera names");
        assert_eq!(c.cameras(), vec![scene, wrist]);
        assert!(c.has_wrist_camera());
        let mut s = stats();
        let img = s.remove("observation.image").expect("scene stats");
        let wst = s.remove(WRIST_CAMERA).expect("wrist stats");
        s.insert(scene.into(), img);
        s.insert(wrist.into(), wst);
        let vm = VarMap::new();
        let vb = mte_policy::init::seeded_var_builder(&vm, 7, DType::F32, &Device::Cpu);
        let other = DiffusionPolicy::new(c, s, vb).expect("policy");
        assert_eq!(other.n_cameras(), 2);
        let h = [obs(0), obs(1)];
        let a = policy
            .global_cond(&policy.obs_batch(&[&h]).expect("batch"))
            .expect("cond");
        let b = other
            .global_cond(&other.obs_batch(&[&h]).expect("batch"))
            .expect("cond");
        // The same weights, statistics and frames under other names: the same values.
        assert_eq!(common::max_abs_diff(&a, &b), 0.0, "separate {separate}");
    }
    // Each wrist alias is recognised; two wrist cameras, or a wrist camera alone, are not
    // a pair mte can feed.
    let base = config(false);
    for alias in mte_policy::config::WRIST_CAMERA_NAMES {
        let c = renamed(&base, "observation.images.top", alias);
        c.validate().expect(alias);
        assert_eq!(c.cameras()[1], alias);
    }
    let two_wrists = renamed(&base, "observation.images.wrist_image", WRIST_CAMERA);
    let e = two_wrists.validate().expect_err("two wrist cameras");
    assert!(e.to_string().contains("wrist camera"), "{e}");
    let mut alone = renamed(&base, "observation.images.top", wrist);
    alone.input_features.remove("observation.images.top");
    let e = alone.validate().expect_err("a wrist camera alone");
    assert!(e.to_string().contains("scene camera"), "{e}");
}
