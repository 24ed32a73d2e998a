//! ACT inference (one chunk, batch 1) and one training step (batch 8, the CVAE path), for the
//! `paper` and `cpu` presets on PushT keypoints, side by side with
//! `tools/reference/bench_act_lerobot.py` (LeRobot 0.4.4's ACT, same configuration, random
//! init, 1 thread).
//!
//! `RAYON_NUM_THREADS=1 cargo bench -p mte-policy --bench act`

use std::cell::RefCell;

use candle_core::{DType, Device, Tensor};
use candle_nn::{Optimizer, VarMap};
use mte_policy::act::model::{ActInputs, Dropout, VaeInput};
use mte_policy::act::{ActConfig, ActPolicy};
use mte_policy::{Observation, Stats, StatsMap};
use rand::SeedableRng;

fn main() {
    // As the `mte` binary does: freed tensor buffers stay in the heap.
    mte_policy::memory::keep_freed_memory();
    divan::main();
}

fn stats() -> StatsMap {
    let s = |n: usize| Stats {
        min: vec![0.0; n],
        max: vec![512.0; n],
        mean: vec![256.0; n],
        std: vec![100.0; n],
    };
    [
        ("observation.state".to_string(), s(2)),
        ("observation.environment_state".to_string(), s(16)),
        ("action".to_string(), s(2)),
    ]
    .into_iter()
    .collect()
}

fn policy(preset: &str) -> (ActPolicy, VarMap) {
    let c = if preset == "paper" {
        ActConfig::paper()
    } else {
        ActConfig::cpu()
    };
    let vm = VarMap::new();
    let vb = mte_policy::init::seeded_var_builder(&vm, 0, DType::F32, &Device::Cpu);
    (ActPolicy::new(c, stats(), vb).expect("policy"), vm)
}

#[divan::bench(args = ["paper", "cpu"])]
fn chunk(bencher: divan::Bencher, preset: &str) {
    let (p, _vm) = policy(preset);
    let obs = Observation {
        state: vec![200.0, 300.0],
        env_state: Some((0..16).map(|k| 200.0 + k as f32).collect()),
        image: None,
        wrist_image: None,
    };
    bencher.bench_local(|| p.predict(&obs).expect("chunk"));
}

#[divan::bench(args = ["paper", "cpu"], sample_count = 10)]
fn train_step(bencher: divan::Bencher, preset: &str) {
    let (p, vm) = policy(preset);
    let c = p.config().clone();
    let b = 8;
    let dev = Device::Cpu;
    let state = Tensor::zeros((b, 2), DType::F32, &dev).expect("state");
    let env = Tensor::zeros((b, 16), DType::F32, &dev).expect("env");
    let actions = Tensor::zeros((b, c.chunk_size, 2), DType::F32, &dev).expect("actions");
    let is_pad = Tensor::zeros((b, c.chunk_size), DType::F32, &dev).expect("pad");
    let eps = Tensor::zeros((b, c.latent_dim), DType::F32, &dev).expect("eps");
    let mut opt = candle_nn::AdamW::new_lr(vm.all_vars(), c.optimizer_lr).expect("adamw");
    let rng = RefCell::new(rand_chacha::ChaCha8Rng::seed_from_u64(0));
    bencher.bench_local(|| {
        let d = Dropout::new(c.dropout, &rng);
        let vae = VaeInput {
            actions: &actions,
            is_pad: &is_pad,
            eps: &eps,
        };
        let out = p
            .net()
            .forward(
                &ActInputs {
                    state: Some(&state),
                    env: Some(&env),
                    images: &[],
                    features: &[],
                },
                Some(&vae),
                Some(&d),
            )
            .expect("forward");
        let (loss, _, _) = p.net().loss(&out, &actions, &is_pad).expect("loss");
        opt.backward_step(&loss).expect("step");
    });
}
