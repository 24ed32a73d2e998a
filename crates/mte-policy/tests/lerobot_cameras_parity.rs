//! Parity with the real LeRobot 0.4.4 `DiffusionPolicy` on two cameras (the scene camera
//! `agentview_image` and the wrist camera `robot0_eye_in_hand_image`, 84 x 84 with a 76 x 76
//! crop, ResNet-18 with GroupNorm, 9-D state, 7-D actions), with one shared encoder and with
//! one encoder per camera. Fixtures from `tools/reference/lerobot_cameras_reference.py`: the
//! folders are LeRobot's own `pretrained_model/` output (config and processors with their
//! statistics) without the 11 M ResNet weights; both sides fill every parameter from one
//! integer formula (`weight_rule`), and the test writes `model.safetensors` from LeRobot's
//! state-dict listing before loading the folder as any checkpoint is loaded.
//!
//! Tolerances: LeRobot runs float32 on CPU with oneDNN kernels, candle float32 with its own
//! summation order. The conditioning passes 20 convolutions and 17 GroupNorms, so it is
//! held to a bound sized from LeRobot's own float32 rounding (its float32 result against its
//! float64 result, `global_cond_float32_vs_float64_max_abs`): two ports that each round like
//! LeRobot differ by at most about twice that; the bound allows 8 times it, floored at 1e-5.
//! The sample is checked from LeRobot's conditioning, as in `lerobot_parity.rs` (the clip to
//! [-1, 1] in every DDPM step keeps the ten steps' errors from growing).

mod common;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use mte_policy::checkpoint;
use mte_policy::{DiffusionPolicy, Observation};
use serde_json::Value;

use common::max_abs_diff_slices;

const SIDE: usize = 84;
const LAYOUTS: [&str; 2] = ["tiny_cams_shared", "tiny_cams_separate"];

fn fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/lerobot_dp")
}

fn reference() -> Value {
    let text =
        std::fs::read_to_string(fixtures().join("tiny_cams_reference.json")).expect("fixture");
    serde_json::from_str(&text).expect("json")
}

fn floats(v: &Value) -> Vec<f32> {
    match v {
        Value::Array(a) => a.iter().flat_map(floats).collect(),
        Value::Number(n) => vec![n.as_f64().expect("number") as f32],
        other => panic!("not numeric: {other}"),
    }
}

fn dims(v: &Value) -> Vec<usize> {
    v.as_array()
        .expect("shape")
        .iter()
        .map(|d| d.as_u64().expect("dim") as usize)
        .collect()
}

/// The fixture's `weight_rule`: an integer hash of (tensor index, element index) scaled like
/// torch's default initialisation, exact in both languages.
fn rule_values(k: u64, shape: &[usize], groupnorm_weight: bool) -> Vec<f32> {
    let n: usize = shape.iter().product();
    let c = ((k + 1) * 40503 * 65536 + 12345) % (1 << 32);
    let scale = (shape.len() >= 2).then(|| ((n / shape[0]) as f64).sqrt());
    (0..n as u64)
        .map(|j| {
            let h = (j * 2_654_435_761 + c) % (1 << 32);
            let u = h as f64 / 4_294_967_296.0 * 2.0 - 1.0;
            let v = match scale {
                Some(s) => u / s,
                None if groupnorm_weight => 1.0 + u / 10.0,
                None => u / 10.0,
            };
            v as f32
        })
        .collect()
}

/// LeRobot's folder `name` with `model.safetensors` written from the listing, in a temporary
/// directory.
fn checkpoint_dir(r: &Value, name: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().expect("temp dir");
    for entry in std::fs::read_dir(fixtures().join(name)).expect("fixture folder") {
        let path = entry.expect("entry").path();
        std::fs::copy(&path, dir.path().join(path.file_name().expect("name"))).expect("copy");
    }
    let mut tensors = HashMap::new();
    for p in r[name]["parameters"].as_array().expect("parameters") {
        let shape = dims(&p["shape"]);
        let gn = p["groupnorm_weight"].as_bool().expect("flag");
        let v = rule_values(p["index"].as_u64().expect("index"), &shape, gn);
        let first = floats(&p["first"]);
        assert_eq!(
            &v[..first.len()],
            &first[..],
            "{}: the rule differs",
            p["key"]
        );
        let sum: f64 = v.iter().map(|&x| f64::from(x)).sum();
        let expect = p["sum"].as_f64().expect("sum");
        // Both sums in float64 of the same float32 values, in different orders.
        assert!(
            (sum - expect).abs() < 1e-6 * (1.0 + expect.abs()),
            "{}",
            p["key"]
        );
        let t = Tensor::from_vec(v, shape, &Device::Cpu).expect("tensor");
        tensors.insert(p["key"].as_str().expect("key").to_string(), t);
    }
    for b in r[name]["buffers"].as_array().expect("buffers") {
        let t = Tensor::from_vec(floats(&b["values"]), dims(&b["shape"]), &Device::Cpu)
            .expect("buffer");
        tensors.insert(b["key"].as_str().expect("key").to_string(), t);
    }
    candle_core::safetensors::save(&tensors, dir.path().join("model.safetensors"))
        .expect("weights written");
    dir
}

fn load(dir: &Path) -> DiffusionPolicy {
    checkpoint::load(dir, &Device::Cpu).expect("LeRobot's two-camera checkpoint loads")
}

/// The fixture's frame of camera `camera` (0 scene, 1 wrist) at step `k`, HWC.
fn frame(camera: usize, k: usize) -> Vec<u8> {
    let mut v = Vec::with_capacity(SIDE * SIDE * 3);
    for y in 0..SIDE {
        for x in 0..SIDE {
            for c in 0..3 {
                let n = if camera == 0 {
                    7 * x + 13 * y + 101 * c + 17 * k
                } else {
                    x * x + 3 * x * y + 31 * c * (y + 1) + 5 + 29 * k
                };
                v.push((n % 256) as u8);
            }
        }
    }
    v
}

fn observation(k: usize) -> Observation {
    let state = (0..9)
        .map(|i| (0.1 * (i as f64 + 1.0) - 0.2 + 0.05 * k as f64 * (i % 3) as f64) as f32)
        .collect();
    Observation {
        state,
        env_state: None,
        image: Some(frame(0, k)),
        wrist_image: Some(frame(1, k)),
    }
}

fn conditioning(p: &DiffusionPolicy) -> Vec<f32> {
    let hist = [observation(0), observation(1)];
    let obs = p.obs_batch(&[&hist]).expect("batch");
    p.global_cond(&obs)
        .and_then(|c| Ok(c.flatten_all()?.to_vec1()?))
        .expect("conditioning")
}

#[test]
fn lerobots_two_camera_checkpoints_load_with_its_camera_order() {
    let r = reference();
    for name in LAYOUTS {
        let dir = checkpoint_dir(&r, name);
        let p = load(dir.path());
        let order: Vec<&str> = r[name]["image_features_order"]
            .as_array()
            .expect("order")
            .iter()
            .map(|v| v.as_str().expect("name"))
            .collect();
        assert_eq!(p.config().cameras(), order, "{name}");
        assert!(p.config().has_wrist_camera());
    }
}

#[test]
fn two_camera_conditioning_matches_lerobot() {
    let r = reference();
    for name in LAYOUTS {
        let dir = checkpoint_dir(&r, name);
        let cond = conditioning(&load(dir.path()));
        let expect = floats(&r[name]["global_cond"]);
        assert_eq!(cond.len(), expect.len(), "{name}: conditioning width");
        // The state, normalised by one multiply-add: a few ulp.
        let state = floats(&r[name]["normalized_state"]);
        assert!(
            max_abs_diff_slices(&cond[..9], &state[..9]) < 1e-6,
            "{name}"
        );
        assert!(
            max_abs_diff_slices(&cond[137..146], &state[9..]) < 1e-6,
            "{name}"
        );
        let rounding = r[name]["global_cond_float32_vs_float64_max_abs"]
            .as_f64()
            .expect("rounding") as f32;
        let bound = (8.0 * rounding).max(1e-5);
        let d = max_abs_diff_slices(&cond, &expect);
        assert!(
            d < bound,
            "{name}: conditioning differs by {d} (bound {bound})"
        );
        // Not a vacuous match: each camera's frame reaches its own features.
        let (scene, wrist) = (&cond[9..73], &cond[73..137]);
        assert!(max_abs_diff_slices(scene, wrist) > 100.0 * bound, "{name}");
    }
}

#[test]
fn two_camera_sampling_with_recorded_noise_matches_lerobot() {
    let r = reference();
    for name in LAYOUTS {
        let dir = checkpoint_dir(&r, name);
        let p = load(dir.path());
        let s = &r[name]["sampling"];
        let c = floats(&r[name]["global_cond"]);
        let cond = Tensor::from_vec(c.clone(), (1, c.len()), &Device::Cpu).expect("cond");
        let init =
            Tensor::from_vec(floats(&s["initial_noise"]), (1, 16, 7), &Device::Cpu).expect("noise");
        let noises: Vec<(usize, Vec<f32>)> = s["variance_noise"]
            .as_array()
            .expect("noise list")
            .iter()
            .map(|n| (n["t"].as_u64().expect("t") as usize, floats(&n["noise"])))
            .collect();
        let mut k = 0;
        let x = p
            .sample_normalized_with(&cond, init, &mut |t, buf| {
                assert_eq!(t, noises[k].0, "noise drawn at LeRobot's steps");
                buf.copy_from_slice(&noises[k].1);
                k += 1;
            })
            .expect("sample");
        assert_eq!(k, noises.len(), "every recorded noise used");
        let x: Vec<f32> = x.flatten_all().and_then(|t| t.to_vec1()).expect("chunk");
        let d = max_abs_diff_slices(&x, &floats(&s["chunk_normalized"]));
        assert!(d < 2e-5, "{name}: normalised chunk differs by {d}");
        let mut un = x;
        p.action_normalizer().unnormalize(&mut un);
        // Action ranges under 2: 2e-5 normalised is under 2e-5 in action units.
        let d = max_abs_diff_slices(&un, &floats(&s["chunk_unnormalized"]));
        assert!(d < 2e-5, "{name}: chunk differs by {d}");
    }
}
