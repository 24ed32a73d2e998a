//! ACT training end to end on a tiny configuration: it learns (the L1 term falls on a
//! learnable synthetic task), checkpoints in LeRobot's layout, loads through the policy seam,
//! resumes, and is reproducible from its seed.

use mte_policy::act::ActConfig;
use mte_policy::act::train::{ActTrainConfig, train};
use mte_policy::normalize::Stats;
use mte_policy::policy::{Observation, load_policy};
use mte_policy::train::TrainData;

/// Two 40-frame episodes; the action is a fixed linear function of the state, so the chunk
/// is learnable from the observation.
fn data() -> TrainData {
    let (mut state, mut env, mut action) = (Vec::new(), Vec::new(), Vec::new());
    for f in 0..80 {
        let x = (f % 40) as f32 * 10.0;
        state.extend([x, 500.0 - x]);
        env.extend((0..16).map(|k| x + k as f32));
        action.extend([x + 5.0, 490.0 - x]);
    }
    let stat = |d: usize, mean: f32, std: f32| Stats {
        min: vec![0.0; d],
        max: vec![512.0; d],
        mean: vec![mean; d],
        std: vec![std; d],
    };
    TrainData {
        state,
        env_state: Some(env),
        images: None,
        wrist_images: None,
        action,
        episode_lengths: vec![40, 40],
        episode_success: vec![true, true],
        stats: [
            ("observation.state".to_string(), stat(2, 250.0, 120.0)),
            (
                "observation.environment_state".to_string(),
                stat(16, 200.0, 120.0),
            ),
            ("action".to_string(), stat(2, 250.0, 120.0)),
        ]
        .into_iter()
        .collect(),
    }
}

fn seeded_rng(s: u64) -> rand_chacha::ChaCha8Rng {
    <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(s)
}

fn tiny() -> ActConfig {
    ActConfig {
        chunk_size: 8,
        n_action_steps: 8,
        dim_model: 32,
        n_heads: 2,
        dim_feedforward: 64,
        n_encoder_layers: 1,
        n_vae_encoder_layers: 1,
        latent_dim: 4,
        optimizer_lr: 1e-3,
        ..ActConfig::cpu()
    }
}

#[test]
fn trains_checkpoints_loads_and_resumes() {
    let dir = tempfile::tempdir().expect("tmp");
    let tc = ActTrainConfig {
        steps: 60,
        batch_size: 16,
        seed: 3,
        checkpoint_every: 30,
        ..Default::default()
    };
    let mut trace = Vec::new();
    let r = train(&data(), tiny(), &tc, dir.path(), &mut |_, l1, _| {
        trace.push(l1)
    })
    .expect("train");
    assert_eq!((r.steps_run, r.step, trace.len()), (60, 60, 60));
    let first: f32 = trace[..10].iter().sum::<f32>() / 10.0;
    let last: f32 = trace[50..].iter().sum::<f32>() / 10.0;
    assert!(last < 0.7 * first, "L1 did not fall: {first} -> {last}");

    let policy = load_policy(dir.path()).expect("load through the seam");
    assert_eq!(
        (policy.horizon(), policy.n_obs_steps(), policy.action_dim()),
        (8, 1, 2)
    );
    assert!(policy.needs().env_state && policy.needs().image.is_none());
    let obs = Observation {
        state: vec![100.0, 400.0],
        env_state: Some((0..16).map(|k| 100.0 + k as f32).collect()),
        image: None,
        wrist_image: None,
    };
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
    let chunk = policy
        .predict_chunk(std::slice::from_ref(&obs), &mut rng)
        .expect("chunk");
    assert_eq!(chunk.len(), 16);
    assert!(chunk.iter().all(|v| v.is_finite()));
    // Deterministic at inference: the latent is zero.
    assert_eq!(
        chunk,
        policy
            .predict_chunk(std::slice::from_ref(&obs), &mut rng)
            .expect("again")
    );

    // Batched queries give each query's chunk alone, bit for bit.
    let other = Observation {
        state: vec![300.0, 120.0],
        env_state: Some((0..16).map(|k| 310.0 - k as f32).collect()),
        image: None,
        wrist_image: None,
    };
    let (h1, h2) = (std::slice::from_ref(&obs), std::slice::from_ref(&other));
    let (mut r1, mut r2) = (seeded_rng(1), seeded_rng(2));
    let mut qs = [
        mte_policy::Query {
            history: h1,
            rng: &mut r1,
        },
        mte_policy::Query {
            history: h2,
            rng: &mut r2,
        },
    ];
    let both = policy.predict_chunks(&mut qs).expect("batch");
    assert_eq!(both[0], chunk);
    assert_eq!(both[1], policy.predict_chunk(h2, &mut rng).expect("alone"));
    assert_ne!(both[0], both[1]);

    // PGD on the keypoints: a zero radius gives the clean chunk bit for bit; a positive one
    // moves it, reproducibly from the attack stream.
    let attack = policy.attackable().expect("ACT is attackable");
    let pgd = |eps: f64| mte_policy::PgdConfig {
        eps,
        step: (eps / 4.0).max(1e-3),
        iterations: 8,
        ..mte_policy::PgdConfig::default()
    };
    let seeded = |s: u64| <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(s);
    let (mut a, mut b) = (seeded(1), seeded(2));
    let zero = attack
        .predict_chunk_attacked(std::slice::from_ref(&obs), &pgd(0.0), &mut a, &mut b)
        .expect("eps 0");
    assert_eq!(zero, chunk);
    let hit = attack
        .predict_chunk_attacked(
            std::slice::from_ref(&obs),
            &pgd(0.5),
            &mut seeded(1),
            &mut b,
        )
        .expect("eps 0.5");
    let again = attack
        .predict_chunk_attacked(
            std::slice::from_ref(&obs),
            &pgd(0.5),
            &mut seeded(1),
            &mut b,
        )
        .expect("again");
    assert_eq!(hit, again);
    assert!(
        hit.iter().zip(&chunk).any(|(x, y)| (x - y).abs() > 1e-3),
        "the attack did not move the chunk"
    );

    // Resume to 70 steps from the directory; the same seed from scratch gives the same run.
    let more = ActTrainConfig {
        steps: 70,
        ..tc.clone()
    };
    let r2 = train(&data(), tiny(), &more, dir.path(), &mut |_, _, _| {}).expect("resume");
    assert_eq!((r2.steps_run, r2.step), (10, 70));
    assert!(
        r2.final_l1.is_some_and(|l| l.is_finite() && l > 0.0),
        "{r2:?}"
    );
    let r3 = train(&data(), tiny(), &more, dir.path(), &mut |_, _, _| {}).expect("done");
    assert_eq!(
        (r3.steps_run, r3.step, r3.final_l1, r3.final_kld),
        (0, 70, None, None),
        "a run at its last step reports no loss"
    );
    let again = tempfile::tempdir().expect("tmp");
    train(&data(), tiny(), &tc, again.path(), &mut |_, _, _| {}).expect("again");
    let w = |d: &std::path::Path| std::fs::read(d.join("model.safetensors")).expect("weights");
    let first_run = tempfile::tempdir().expect("tmp");
    train(&data(), tiny(), &tc, first_run.path(), &mut |_, _, _| {}).expect("third");
    assert_eq!(
        w(again.path()),
        w(first_run.path()),
        "same seed, same weights"
    );

    // The resume is exact: 60 steps, then 10 more from the directory, equal 70 in one go,
    // bit for bit (the moments are restored; fresh ones would make the first steps larger).
    let straight = tempfile::tempdir().expect("tmp");
    train(&data(), tiny(), &more, straight.path(), &mut |_, _, _| {}).expect("straight");
    assert_eq!(
        w(straight.path()),
        w(dir.path()),
        "resumed and uninterrupted runs differ"
    );
    // A stale optimiser state (another step's) is refused, naming both steps.
    std::fs::copy(
        first_run.path().join("optimizer_state.safetensors"),
        dir.path().join("optimizer_state.safetensors"),
    )
    .expect("copy");
    let later = ActTrainConfig {
        steps: 71,
        ..tc.clone()
    };
    let e = train(&data(), tiny(), &later, dir.path(), &mut |_, _, _| {}).expect_err("stale");
    assert!(
        e.to_string().contains("state of step 60") && e.to_string().contains("step 70"),
        "{e}"
    );
}

#[test]
fn bad_settings_are_typed_errors() {
    let dir = tempfile::tempdir().expect("tmp");
    let tc = ActTrainConfig {
        steps: 0,
        batch_size: 4,
        seed: 0,
        checkpoint_every: 0,
        ..Default::default()
    };
    let e = train(&data(), tiny(), &tc, dir.path(), &mut |_, _, _| {}).expect_err("no steps");
    assert!(e.to_string().contains("steps"), "{e}");
    let bad = ActConfig {
        n_heads: 5,
        ..tiny()
    };
    let tc = ActTrainConfig { steps: 1, ..tc };
    let e = train(&data(), bad, &tc, dir.path(), &mut |_, _, _| {}).expect_err("heads");
    assert!(e.to_string().contains("n_heads"), "{e}");
}

/// Every tensor of a `model.safetensors`-layout file, flattened, by name.
fn tensors(path: &std::path::Path) -> std::collections::BTreeMap<String, Vec<f32>> {
    let dev = candle_core::Device::Cpu;
    candle_core::safetensors::load(path, &dev)
        .expect("weights")
        .into_iter()
        .map(|(k, t)| (k, t.flatten_all().and_then(|t| t.to_vec1()).expect("f32")))
        .collect()
}

/// With an average of the weights: the optimised weights move exactly as without it (the
/// average only reads them), the policy file is the average and the optimised weights lie
/// beside it, and a resumed run goes on from the saved average: after one more step the
/// average is `d · saved + (1 − d) · weights` with `d` the decay of that step.
#[test]
fn an_averaged_run_keeps_its_raw_weights_and_resumes_its_average() {
    let base = ActTrainConfig {
        steps: 20,
        batch_size: 16,
        seed: 5,
        checkpoint_every: 0,
        ..Default::default()
    };
    let averaged = ActTrainConfig {
        ema_max_decay: Some(0.9),
        ..base.clone()
    };
    let (plain, ema) = (
        tempfile::tempdir().expect("tmp"),
        tempfile::tempdir().expect("tmp"),
    );
    train(&data(), tiny(), &base, plain.path(), &mut |_, _, _| {}).expect("plain");
    train(&data(), tiny(), &averaged, ema.path(), &mut |_, _, _| {}).expect("averaged");
    let raw20 = tensors(&ema.path().join("raw_model.safetensors"));
    assert_eq!(raw20, tensors(&plain.path().join("model.safetensors")));
    assert!(!plain.path().join("raw_model.safetensors").exists());
    let avg20 = tensors(&ema.path().join("model.safetensors"));
    assert_eq!(
        avg20.keys().collect::<Vec<_>>(),
        raw20.keys().collect::<Vec<_>>()
    );
    assert_ne!(avg20, raw20, "the average lags the weights");
    load_policy(ema.path()).expect("the average loads as a policy");

    let one_more = ActTrainConfig {
        steps: 21,
        ..averaged
    };
    train(&data(), tiny(), &one_more, ema.path(), &mut |_, _, _| {}).expect("resume");
    let (raw21, avg21) = (
        tensors(&ema.path().join("raw_model.safetensors")),
        tensors(&ema.path().join("model.safetensors")),
    );
    let d = 0.9f32.min(21.0 / 30.0); // the ramp (1 + 20) / (10 + 20) at step 20
    let mut worst = 0f32;
    for (k, a) in &avg21 {
        for ((&a, &s), &w) in a.iter().zip(&avg20[k]).zip(&raw21[k]) {
            worst = worst.max((a - (d * s + (1.0 - d) * w)).abs());
        }
    }
    assert!(worst < 1e-5, "the resumed average is off by {worst}");
    assert_ne!(raw21, raw20, "the resumed run took a step");

    // Resumed without the average, the run goes on from its raw weights and leaves no stale
    // copy of them behind.
    let plain_more = ActTrainConfig { steps: 22, ..base };
    train(&data(), tiny(), &plain_more, ema.path(), &mut |_, _, _| {}).expect("no average");
    assert!(!ema.path().join("raw_model.safetensors").exists());
    let raw22 = tensors(&ema.path().join("model.safetensors"));
    assert_ne!(raw22, raw21, "one more step from the raw weights");
    // The average only read the weights and the resumes are exact, so the weights are those
    // of 22 plain steps in one go (a start from the average, which lags, would differ).
    let straight = tempfile::tempdir().expect("tmp");
    train(
        &data(),
        tiny(),
        &plain_more,
        straight.path(),
        &mut |_, _, _| {},
    )
    .expect("straight");
    assert_eq!(raw22, tensors(&straight.path().join("model.safetensors")));
    assert_ne!(avg21, raw21, "the average lags the weights");
}

/// The cosine schedule changes the run (the learning rate is applied, not just recorded);
/// a warm-up as long as the run and an average's decay of 1 are typed errors.
#[test]
fn the_cosine_schedule_is_applied_and_bad_recipes_are_refused() {
    use mte_policy::act::train::LrSchedule;
    let base = ActTrainConfig {
        steps: 10,
        batch_size: 8,
        seed: 2,
        checkpoint_every: 0,
        ..Default::default()
    };
    let cosine = ActTrainConfig {
        lr_schedule: LrSchedule::Cosine { warmup_steps: 3 },
        ..base.clone()
    };
    let (a, b) = (
        tempfile::tempdir().expect("tmp"),
        tempfile::tempdir().expect("tmp"),
    );
    train(&data(), tiny(), &base, a.path(), &mut |_, _, _| {}).expect("constant");
    train(&data(), tiny(), &cosine, b.path(), &mut |_, _, _| {}).expect("cosine");
    let w = |d: &std::path::Path| tensors(&d.join("model.safetensors"));
    assert_ne!(w(a.path()), w(b.path()));
    assert_eq!(LrSchedule::Constant.factor(7, 10), 1.0);
    assert!(LrSchedule::Cosine { warmup_steps: 3 }.factor(9, 10) < 0.1);

    let long_warmup = ActTrainConfig {
        lr_schedule: LrSchedule::Cosine { warmup_steps: 10 },
        ..base.clone()
    };
    let e = train(&data(), tiny(), &long_warmup, a.path(), &mut |_, _, _| {}).expect_err("warm-up");
    assert!(e.to_string().contains("warmup_steps"), "{e}");
    let no_decay = ActTrainConfig {
        ema_max_decay: Some(1.0),
        ..base
    };
    let e = train(&data(), tiny(), &no_decay, a.path(), &mut |_, _, _| {}).expect_err("decay 1");
    assert!(e.to_string().contains("ema_max_decay"), "{e}");
}
