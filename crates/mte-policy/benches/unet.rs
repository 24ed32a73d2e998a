//! U-Net forward (one denoising step, batch 1) and one chunk (the full denoising loop) for the
//! `paper` and `cpu` presets, side by side with `shared/reference/peer-bench/bench_diffusion.py`
//! (LeRobot, same configuration, random init). Threads: `RAYON_NUM_THREADS=1` for the
//! peer's 1-thread figures.
//!
//! `RAYON_NUM_THREADS=1 cargo bench -p mte-policy --bench unet`
//!
//! Also: one PGD iteration, and the image encoder's forward + backward at training size.
//! Every evaluation benchmark holds its weights as constants, as a loaded checkpoint does
//! (`frozen_policy`); the training step's are variables.
//!
//! `MTE_BENCH_DEVICE=cuda` (a build with `--features cuda`) runs every benchmark on GPU 0;
//! each iteration then ends with a device synchronisation, so it times the work, not its
//! launch.

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use mte_policy::config::{DiffusionConfig, ObsKind};
use mte_policy::kernels::Products;
use mte_policy::{DiffusionPolicy, Observation, Stats, StatsMap};
use rand::SeedableRng;

fn main() {
    // As the `mte` binary does: freed tensor buffers stay in the heap.
    mte_policy::memory::keep_freed_memory();
    divan::main();
}

/// The device of every benchmark: `MTE_BENCH_DEVICE` (`cpu`, `cuda`, `cuda:N`), else the CPU.
fn dev() -> &'static Device {
    static DEV: std::sync::OnceLock<Device> = std::sync::OnceLock::new();
    DEV.get_or_init(|| {
        let name = std::env::var("MTE_BENCH_DEVICE").unwrap_or_else(|_| "cpu".into());
        let d: mte_policy::ComputeDevice = name.parse().expect("MTE_BENCH_DEVICE");
        d.open().expect("open the benchmark device")
    })
}

/// Waits for the device's queued work (a no-op on the CPU).
fn sync<T>(v: T) -> T {
    dev().synchronize().expect("synchronize");
    v
}

fn stats() -> StatsMap {
    let mm = |n: usize| Stats {
        min: vec![0.0; n],
        max: vec![512.0; n],
        mean: vec![0.5; n],
        std: vec![0.25; n],
    };
    let mut s = StatsMap::new();
    s.insert("observation.state".into(), mm(2));
    s.insert("observation.environment_state".into(), mm(16));
    s.insert("observation.image".into(), mm(3));
    s.insert("action".into(), mm(2));
    s
}

fn policy(preset: &str) -> (DiffusionPolicy, VarMap) {
    let c = match preset {
        "paper" => DiffusionConfig::paper(),
        "cpu-image" => DiffusionConfig::cpu(ObsKind::Image),
        _ => DiffusionConfig::cpu(ObsKind::Keypoints),
    };
    let vm = VarMap::new();
    let vb = VarBuilder::from_varmap(&vm, DType::F32, dev());
    (DiffusionPolicy::new(c, stats(), vb).expect("policy"), vm)
}

/// The policy of `preset` with its weights as constants, as a loaded checkpoint holds them:
/// an attack's backward pass then computes no weight gradients (the PyTorch peer freezes its
/// parameters the same way).
fn frozen_policy(preset: &str) -> DiffusionPolicy {
    let (p, vm) = policy(preset);
    let c = p.config().clone();
    let tensors: std::collections::HashMap<String, Tensor> = vm
        .data()
        .lock()
        .expect("vars")
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().detach()))
        .collect();
    let vb = VarBuilder::from_tensors(tensors, DType::F32, dev());
    DiffusionPolicy::new(c, stats(), vb).expect("frozen policy")
}

#[divan::bench(args = ["paper", "cpu-image", "cpu-keypoints"], sample_count = 10)]
fn unet_forward(bencher: divan::Bencher, preset: &str) {
    forward_batch(bencher, preset, 1, Products::PerSample);
}

/// One U-Net forward on 64 samples, as the lockstep runner batches them (per-sample
/// products, so each sample's bits are those of a batch of one): the peer is
/// `tools/reference/bench_unet_lerobot.py`.
#[divan::bench(args = ["cpu-image", "cpu-keypoints"], sample_count = 10)]
fn unet_forward_batch_64(bencher: divan::Bencher, preset: &str) {
    forward_batch(bencher, preset, 64, Products::PerSample);
}

/// The same with one product for the whole batch (training's path, whose rounding may depend
/// on the batch): what batch invariance costs.
#[divan::bench(args = ["cpu-image", "cpu-keypoints"], sample_count = 10)]
fn unet_forward_batch_64_fused(bencher: divan::Bencher, preset: &str) {
    forward_batch(bencher, preset, 64, Products::Fused);
}

/// One U-Net forward of `preset` on `batch` random noisy chunks at timestep 50.
fn forward_batch(bencher: divan::Bencher, preset: &str, batch: usize, products: Products) {
    let p = frozen_policy(preset);
    let g = if preset == "cpu-keypoints" {
        2 * 18
    } else {
        2 * 66
    };
    let x = Tensor::randn(0f32, 1.0, (batch, 16, 2), dev()).expect("x");
    let cond = Tensor::randn(0f32, 1.0, (batch, g), dev()).expect("cond");
    let t = vec![50; batch];
    bencher.bench_local(|| {
        p.unet()
            .expect("U-Net")
            .forward_with(&x, &t, &cond, products)
            .map(sync)
            .expect("forward")
    });
}

#[divan::bench(args = ["paper", "cpu-image", "cpu-keypoints"], sample_count = 3)]
fn chunk(bencher: divan::Bencher, preset: &str) {
    let p = frozen_policy(preset);
    let hist = history(preset);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    bencher.bench_local(|| sync(p.predict(&hist, &mut rng).expect("chunk")));
}

/// 32 chunks at once (`ChunkPolicy::predict_chunks`, as the lockstep runner asks): divide by
/// 32 for the time per chunk, against `chunk` at batch 1.
#[divan::bench(args = ["cpu-image", "cpu-keypoints"], sample_count = 3)]
fn chunks_batch_32(bencher: divan::Bencher, preset: &str) {
    use mte_policy::{ChunkPolicy, Query};
    let p = frozen_policy(preset);
    let hist = history(preset);
    let mut rngs: Vec<rand_chacha::ChaCha8Rng> = (0..32)
        .map(rand_chacha::ChaCha8Rng::seed_from_u64)
        .collect();
    bencher.bench_local(|| {
        let mut qs: Vec<Query<'_>> = rngs
            .iter_mut()
            .map(|rng| Query {
                history: &hist,
                rng,
            })
            .collect();
        sync(p.predict_chunks(&mut qs).expect("chunks"))
    });
}

/// The U-Net's share of one training step at batch 64: the loss's forward and backward with
/// respect to every weight (the `cpu` keypoint preset).
#[divan::bench(sample_count = 5)]
fn unet_train_step(bencher: divan::Bencher) {
    let (p, vm) = policy("cpu-keypoints");
    let cond = Tensor::randn(0f32, 1.0, (64, 2 * (2 + 16)), dev()).expect("cond");
    let x0 = Tensor::randn(0f32, 0.5, (64, 16, 2), dev()).expect("x0");
    let eps = Tensor::randn(0f32, 1.0, (64, 16, 2), dev()).expect("eps");
    let ts: Vec<usize> = (0..64).map(|i| (i * 3) % 100).collect();
    bencher.bench_local(|| {
        let loss = p.loss(&cond, &x0, &eps, &ts, None).expect("loss");
        let grads = loss.backward().expect("backward");
        assert!(sync(grads).get(&vm.all_vars()[0]).is_some());
    });
}

/// One PGD iteration (forward + backward of the loss with respect to the observation, 4
/// diffusion timesteps per iteration, the attack's default) for the `cpu` presets, weights
/// constant as in a loaded checkpoint: the attack's cost is this times its budget, per
/// attacked query.
#[divan::bench(args = ["cpu-image", "cpu-keypoints"], sample_count = 5)]
fn pgd_iteration(bencher: divan::Bencher, preset: &str) {
    let p = frozen_policy(preset);
    let hist = history(preset);
    let x0 = Tensor::randn(0f32, 0.5, (1, 16, 2), dev()).expect("x0");
    let cfg = mte_policy::PgdConfig {
        iterations: 1,
        ..mte_policy::PgdConfig::default()
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    bencher.bench_local(|| sync(p.pgd_perturb(&hist, &x0, &cfg, &mut rng).expect("pgd")));
}

/// One PGD iteration for 16 attacked queries at once (as the lockstep runner attacks them):
/// divide by 16 for the time per attacked query, against `pgd_iteration` at batch 1.
#[divan::bench(args = ["cpu-image", "cpu-keypoints"], sample_count = 3)]
fn pgd_iteration_batch_16(bencher: divan::Bencher, preset: &str) {
    let p = frozen_policy(preset);
    let hist = history(preset);
    let clean = p.obs_batch(&vec![hist.as_slice(); 16]).expect("batch");
    let x0 = Tensor::randn(0f32, 0.5, (16, 16, 2), dev()).expect("x0");
    let cfg = mte_policy::PgdConfig {
        iterations: 1,
        ..mte_policy::PgdConfig::default()
    };
    let mut rngs: Vec<rand_chacha::ChaCha8Rng> = (0..16)
        .map(rand_chacha::ChaCha8Rng::seed_from_u64)
        .collect();
    bencher.bench_local(|| {
        let mut r: Vec<&mut dyn rand::RngCore> = rngs
            .iter_mut()
            .map(|r| r as &mut dyn rand::RngCore)
            .collect();
        sync(p.pgd_perturb_batch(&clean, &x0, &cfg, &mut r).expect("pgd"))
    });
}

/// The image encoder's share of one training step: forward and backward of its features for
/// a batch of 64 windows x 2 observation steps = 128 crops of 84 x 84 (the `cpu` preset's
/// quarter-width ResNet-18 runs on mte's fused CPU kernels, `mte_policy::kernels`).
#[divan::bench(sample_count = 5)]
fn encoder_train_step(bencher: divan::Bencher) {
    let vm = VarMap::new();
    let vb = VarBuilder::from_varmap(&vm, DType::F32, dev());
    let enc = mte_policy::vision::RgbEncoder::with_width(16, Some([84, 84]), 32, vb).expect("enc");
    let x = Tensor::rand(0f32, 1.0, (128, 3, 84, 84), dev()).expect("x");
    bencher.bench_local(|| {
        let f = enc.forward_cropped(&x).expect("forward");
        f.sqr()
            .and_then(|v| v.sum_all())
            .and_then(|l| l.backward())
            .map(sync)
            .expect("backward")
    });
}

/// Two identical observations of the kind `preset` reads.
fn history(preset: &str) -> Vec<Observation> {
    let obs = Observation {
        state: vec![200.0, 300.0],
        env_state: (preset == "cpu-keypoints").then(|| vec![250.0; 16]),
        image: (preset != "cpu-keypoints").then(|| vec![128u8; 96 * 96 * 3]),
        wrist_image: None,
    };
    vec![obs.clone(), obs]
}
