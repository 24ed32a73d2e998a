//! Parity with the real LeRobot 0.4.4 `DiffusionPolicy` (a tiny random-init policy saved by
//! lerobot itself; fixtures from `tools/reference/lerobot_diffusion_reference.py`).
//!
//! Tolerances: LeRobot runs float32 on CPU (oneDNN/MKL kernels); candle runs float32 with its
//! own kernels and summation order, so single ops agree to a few ulp and a 10-step denoising
//! loop to ~1e-5 (the clip to [-1, 1] in every DDPM step keeps errors from growing).

mod common;

use std::path::PathBuf;

use candle_core::{Device, Tensor};
use mte_policy::checkpoint;
use mte_policy::{DiffusionPolicy, Observation};
use serde_json::Value;

use common::max_abs_diff_slices;

fn dir(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/lerobot_dp")
        .join(name)
}

fn reference() -> Value {
    let text = std::fs::read_to_string(dir("tiny_state_reference.json")).expect("fixture");
    serde_json::from_str(&text).expect("json")
}

fn floats(v: &Value) -> Vec<f32> {
    match v {
        Value::Array(a) => a.iter().flat_map(floats).collect(),
        Value::Number(n) => vec![n.as_f64().expect("number") as f32],
        other => panic!("not numeric: {other}"),
    }
}

fn load(name: &str) -> DiffusionPolicy {
    checkpoint::load(&dir(name), &Device::Cpu).expect("checkpoint loads")
}

fn raw_history(r: &Value) -> Vec<Observation> {
    let g = &r["global_conditioning"]["raw"];
    (0..2)
        .map(|k| Observation {
            state: floats(&g["observation.state"][k]),
            env_state: Some(floats(&g["observation.environment_state"][k])),
            image: None,
            wrist_image: None,
        })
        .collect()
}

#[test]
fn both_layouts_load_with_the_same_statistics() {
    let new = load("tiny_state");
    let old = load("tiny_state_old");
    for f in [
        "observation.state",
        "observation.environment_state",
        "action",
    ] {
        assert_eq!(new.stats()[f].min, old.stats()[f].min, "{f}");
        assert_eq!(new.stats()[f].max, old.stats()[f].max, "{f}");
        assert!(!new.stats()[f].min.is_empty());
    }
}

#[test]
fn global_conditioning_matches() {
    let r = reference();
    let p = load("tiny_state");
    let hist = raw_history(&r);
    let obs = p.obs_batch(&[&hist]).expect("batch");
    let cond: Vec<f32> = p
        .global_cond(&obs)
        .expect("cond")
        .flatten_all()
        .expect("flat")
        .to_vec1()
        .expect("vec");
    let expect = floats(&r["global_conditioning"]["global_cond"]);
    // Normalisation is one multiply-add per value: a few ulp.
    assert!(
        max_abs_diff_slices(&cond, &expect) < 1e-6,
        "{cond:?} vs {expect:?}"
    );
}

#[test]
fn unet_outputs_match() {
    let r = reference();
    for name in ["tiny_state", "tiny_state_old"] {
        let p = load(name);
        for case in r["unet_cases"].as_array().expect("cases") {
            let x = Tensor::from_vec(floats(&case["x"]), (1, 16, 2), &Device::Cpu).expect("x");
            let c = floats(&case["global_cond"]);
            let cond = Tensor::from_vec(c.clone(), (1, c.len()), &Device::Cpu).expect("cond");
            let t = case["timestep"].as_u64().expect("t") as usize;
            let emb: Vec<f32> = p
                .unet()
                .expect("U-Net")
                .step_encoder(&[t], &Device::Cpu)
                .expect("emb")
                .flatten_all()
                .expect("f")
                .to_vec1()
                .expect("v");
            assert!(max_abs_diff_slices(&emb, &floats(&case["timestep_embedding"])) < 1e-5);
            let out: Vec<f32> = p
                .unet()
                .expect("U-Net")
                .forward(&x, &[t], &cond)
                .expect("forward")
                .flatten_all()
                .expect("f")
                .to_vec1()
                .expect("v");
            let expect = floats(&case["output"]);
            let d = max_abs_diff_slices(&out, &expect);
            // ~20 layers of float32 convolutions with different summation order: 1e-5.
            assert!(d < 1e-5, "{name} {}: max diff {d}", case["name"]);
        }
        let b = &r["unet_batched_case"];
        let x = Tensor::from_vec(floats(&b["x"]), (2, 16, 2), &Device::Cpu).expect("x");
        let c = floats(&b["global_cond"]);
        let cond = Tensor::from_vec(c.clone(), (2, c.len() / 2), &Device::Cpu).expect("cond");
        let ts: Vec<usize> = b["timesteps"]
            .as_array()
            .expect("ts")
            .iter()
            .map(|v| v.as_u64().expect("t") as usize)
            .collect();
        let out: Vec<f32> = p
            .unet()
            .expect("U-Net")
            .forward(&x, &ts, &cond)
            .expect("forward")
            .flatten_all()
            .expect("f")
            .to_vec1()
            .expect("v");
        assert!(max_abs_diff_slices(&out, &floats(&b["output"])) < 1e-5);
    }
}

#[test]
fn full_sampling_with_recorded_noise_matches() {
    let r = reference();
    let s = &r["sampling_direct"];
    let p = load("tiny_state");
    let c = floats(&s["global_cond"]);
    let cond = Tensor::from_vec(c.clone(), (1, c.len()), &Device::Cpu).expect("cond");
    let init =
        Tensor::from_vec(floats(&s["initial_noise"]), (1, 16, 2), &Device::Cpu).expect("noise");
    let noises: Vec<(usize, Vec<f32>)> = s["variance_noise"]
        .as_array()
        .expect("noise list")
        .iter()
        .map(|n| (n["t"].as_u64().expect("t") as usize, floats(&n["noise"])))
        .collect();
    let mut k = 0;
    let x = p
        .sample_normalized_with(&cond, init, &mut |t, buf| {
            assert_eq!(t, noises[k].0, "noise drawn at the same steps as LeRobot");
            buf.copy_from_slice(&noises[k].1);
            k += 1;
        })
        .expect("sample");
    assert_eq!(k, noises.len());
    let x: Vec<f32> = x.flatten_all().expect("f").to_vec1().expect("v");
    let expect = floats(&s["chunk_normalized"]);
    let d = max_abs_diff_slices(&x, &expect);
    assert!(d < 2e-5, "normalised chunk max diff {d}");
    let mut un = x.clone();
    p.action_normalizer().unnormalize(&mut un);
    // Action range ~500 px: 2e-5 normalised is 5e-3 px.
    assert!(max_abs_diff_slices(&un, &floats(&s["chunk_unnormalized"])) < 1e-2);
}

#[test]
fn training_loss_matches() {
    let r = reference();
    let l = &r["training_loss"];
    let p = load("tiny_state");
    let cond_v = floats(&l["global_cond"]);
    let cond = Tensor::from_vec(cond_v.clone(), (2, cond_v.len() / 2), &Device::Cpu).expect("cond");
    let x0 = Tensor::from_vec(
        floats(&l["normalized_batch"]["action"]),
        (2, 16, 2),
        &Device::Cpu,
    )
    .expect("x0");
    let eps = Tensor::from_vec(floats(&l["eps"]), (2, 16, 2), &Device::Cpu).expect("eps");
    let ts: Vec<usize> = l["timesteps"]
        .as_array()
        .expect("ts")
        .iter()
        .map(|v| v.as_u64().expect("t") as usize)
        .collect();
    let loss = p
        .loss(&cond, &x0, &eps, &ts, None)
        .expect("loss")
        .to_scalar::<f32>()
        .expect("scalar");
    let expect = l["loss"].as_f64().expect("loss") as f32;
    assert!(
        (loss - expect).abs() < 1e-5 * expect.abs().max(1.0),
        "{loss} vs {expect}"
    );
}

#[test]
fn a_misshapen_or_missing_key_is_an_error_naming_it() {
    let tmp = tempfile::tempdir().expect("tmp");
    for f in std::fs::read_dir(dir("tiny_state")).expect("dir") {
        let f = f.expect("entry").path();
        std::fs::copy(&f, tmp.path().join(f.file_name().expect("name"))).expect("copy");
    }
    let w = tmp.path().join("model.safetensors");
    let mut tensors = candle_core::safetensors::load(&w, &Device::Cpu).expect("load");
    tensors.remove("diffusion.unet.mid_modules.1.conv2.block.0.weight");
    candle_core::safetensors::save(&tensors, &w).expect("save");
    let e = checkpoint::load(tmp.path(), &Device::Cpu)
        .err()
        .expect("missing key")
        .to_string();
    assert!(e.contains("mid_modules.1.conv2.block.0.weight"), "{e}");

    tensors.insert(
        "diffusion.unet.mid_modules.1.conv2.block.0.weight".into(),
        Tensor::zeros((3, 3, 3), candle_core::DType::F32, &Device::Cpu).expect("zeros"),
    );
    candle_core::safetensors::save(&tensors, &w).expect("save");
    let e = checkpoint::load(tmp.path(), &Device::Cpu)
        .err()
        .expect("bad shape")
        .to_string();
    assert!(
        e.contains("mid_modules.1.conv2.block.0.weight") && e.contains("shape"),
        "{e}"
    );

    let bytes = std::fs::read(&w).expect("read");
    std::fs::write(&w, &bytes[..bytes.len() / 2]).expect("truncate");
    let e = checkpoint::load(tmp.path(), &Device::Cpu)
        .err()
        .expect("truncated")
        .to_string();
    assert!(e.contains("model.safetensors"), "{e}");
}
