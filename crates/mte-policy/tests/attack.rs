//! PGD on the policy's own loss: it stays in the ball (and in [0, 1] for pixels), it is
//! reproducible from its seeds, and it raises the loss it ascends.

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use mte_policy::config::{DiffusionConfig, ObsKind};
use mte_policy::init::seeded_var_builder;
use mte_policy::{DiffusionPolicy, Observation, PgdConfig, StatsMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod common;

type R = Result<(), Box<dyn std::error::Error>>;

fn stats(image: bool) -> StatsMap {
    let extra = if image {
        ("observation.image", 0.0, 1.0, 3)
    } else {
        ("observation.environment_state", 0.0, 512.0, 16)
    };
    common::stats(&[
        ("observation.state", 0.0, 512.0, 2),
        ("action", 0.0, 512.0, 2),
        extra,
    ])
}

fn policy(
    kind: ObsKind,
    patch: serde_json::Value,
) -> Result<(DiffusionPolicy, VarMap), Box<dyn std::error::Error>> {
    let c = DiffusionConfig::cpu(kind).with_overrides(&patch)?;
    let vm = VarMap::new();
    let vb = seeded_var_builder(&vm, 3, DType::F32, &Device::Cpu);
    Ok((
        DiffusionPolicy::new(c, stats(kind == ObsKind::Image), vb)?,
        vm,
    ))
}

/// `n` seeded normal draws with standard deviation `sd` (candle's `randn` is unseeded).
fn normal(r: &mut ChaCha8Rng, n: usize, sd: f32) -> Vec<f32> {
    (0..n)
        .map(|_| sd * rand_distr::Distribution::<f32>::sample(&rand_distr::StandardNormal, r))
        .collect()
}

fn history(image: bool) -> Vec<Observation> {
    let mut r = ChaCha8Rng::seed_from_u64(11);
    (0..2)
        .map(|_| Observation {
            state: vec![r.random_range(50.0..450.0), r.random_range(50.0..450.0)],
            env_state: (!image).then(|| (0..16).map(|_| r.random_range(50.0..450.0)).collect()),
            image: image.then(|| (0..96 * 96 * 3).map(|_| r.random::<u8>()).collect()),
            wrist_image: None,
        })
        .collect()
}

#[test]
fn keypoint_pgd_is_bounded_seeded_and_raises_the_loss() -> R {
    let (p, _vm) = policy(
        ObsKind::Keypoints,
        serde_json::json!({"down_dims": [8, 16], "n_groups": 4, "diffusion_step_embed_dim": 8}),
    )?;
    let h = history(false);
    let cfg = PgdConfig {
        iterations: 8,
        ..PgdConfig::default()
    };
    let run = |attack_seed: u64| {
        p.pgd_attack(
            &h,
            &cfg,
            &mut ChaCha8Rng::seed_from_u64(attack_seed),
            &mut ChaCha8Rng::seed_from_u64(1),
        )
    };
    let a = run(5)?;
    assert!(
        a.max_perturbation <= cfg.eps as f32 + 1e-6,
        "{}",
        a.max_perturbation
    );
    assert!(a.max_perturbation > 0.0, "the attack moved");
    assert_eq!(run(5)?, a, "same seeds, same attack");
    assert_ne!(run(6)?.chunk, a.chunk);

    // Ascent: on held-out timesteps and noise, the loss at the perturbed observation exceeds
    // the loss at the clean one (generous budget, so the test is about direction), by
    // several times the effect's spread over seeds.
    let big = PgdConfig {
        eps: 0.5,
        step: 0.05,
        iterations: 20,
        samples: 8,
        ..PgdConfig::default()
    };
    let clean = p.obs_batch(&[&h])?;
    let ts: Vec<usize> = (0..32).map(|i| i * 3).collect();
    let mut effects = Vec::new();
    let mut adv = clean.clone();
    for seed in 0..5u64 {
        let mut r = ChaCha8Rng::seed_from_u64(100 + seed);
        let x0 = Tensor::from_vec(normal(&mut r, 32, 0.5), (1, 16, 2), &Device::Cpu)?;
        let eps = Tensor::from_vec(normal(&mut r, 32 * 32, 1.0), (32, 16, 2), &Device::Cpu)?;
        (adv, _, _) = p.pgd_perturb(&h, &x0, &big, &mut ChaCha8Rng::seed_from_u64(9 + seed))?;
        let (l_clean, _) = p.observation_gradient(&clean, &x0, &eps, &ts)?;
        let (l_adv, _) = p.observation_gradient(&adv, &x0, &eps, &ts)?;
        effects.push(f64::from(l_adv / l_clean).ln());
    }
    common::assert_clear_effect("ln(adversarial / clean loss)", &effects);
    // Only the keypoints were touched.
    let ds = (&adv.state - &clean.state)?
        .abs()?
        .flatten_all()?
        .max(0)?
        .to_scalar::<f32>()?;
    assert_eq!(ds, 0.0);
    assert!(
        PgdConfig {
            samples: 0,
            ..PgdConfig::default()
        }
        .validate()
        .is_err()
    );
    Ok(())
}

#[test]
fn image_pgd_stays_in_the_ball_and_in_the_unit_interval() -> R {
    let (p, _vm) = policy(
        ObsKind::Image,
        serde_json::json!({"down_dims": [8, 16], "n_groups": 4, "diffusion_step_embed_dim": 8}),
    )?;
    let h = history(true);
    let x0 = common::randn(4, &[1, 16, 2], 0.5, DType::F32);
    let cfg = PgdConfig {
        iterations: 2,
        samples: 1,
        step: 0.02,
        ..PgdConfig::default()
    };
    let (adv, _, _) = p.pgd_perturb(&h, &x0, &cfg, &mut ChaCha8Rng::seed_from_u64(2))?;
    let clean = p.obs_batch(&[&h])?;
    let (a, c) = (
        adv.image
            .ok_or("adv image")?
            .flatten_all()?
            .to_vec1::<f32>()?,
        clean
            .image
            .ok_or("clean image")?
            .flatten_all()?
            .to_vec1::<f32>()?,
    );
    let mut moved = 0;
    for (x, y) in a.iter().zip(&c) {
        assert!((0.0..=1.0).contains(x), "{x} outside [0, 1]");
        assert!((x - y).abs() <= 0.03 + 1e-6, "{x} vs {y}");
        moved += usize::from(x != y);
    }
    // The pixels the policy sees (the 84 x 84 centre crop: 21,168 of 27,648 values per
    // frame) move; the gradient reaches the image through the whole encoder.
    assert!(moved > a.len() / 3, "pixels moved: {moved} of {}", a.len());
    Ok(())
}
