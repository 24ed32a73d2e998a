//! Batch invariance: a batch of queries is answered, bit for bit, as each query alone
//! (`ChunkPolicy::predict_chunks`, `AttackablePolicy::predict_chunks_attacked`), for the
//! keypoint and the image policy, so a lockstep runner's results cannot depend on which
//! episodes shared a batch. Tiny seeded networks; different histories and streams per query.

use candle_core::{DType, Device};
use candle_nn::VarMap;
use mte_policy::config::{DiffusionConfig, ObsKind};
use mte_policy::init::seeded_var_builder;
use mte_policy::{
    AttackedQuery, ChunkPolicy, DiffusionPolicy, Observation, PgdConfig, Query, StatsMap,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod common;

type R = Result<(), Box<dyn std::error::Error>>;

/// Observation kinds, each with the U-Net and with the Diffusion Transformer.
const KINDS: [(ObsKind, bool); 4] = [
    (ObsKind::Keypoints, false),
    (ObsKind::Image, false),
    (ObsKind::Keypoints, true),
    (ObsKind::Image, true),
];

/// Chunks asked together, and the same asked alone.
type Both = (Vec<Vec<f32>>, Vec<Vec<f32>>);

/// The tiny U-Net policy, or with `transformer` the tiny Diffusion Transformer.
fn policy(
    kind: ObsKind,
    transformer: bool,
) -> Result<(DiffusionPolicy, VarMap), Box<dyn std::error::Error>> {
    let extra = match kind {
        ObsKind::Image => ("observation.image", 0.0, 1.0, 3),
        _ => ("observation.environment_state", 0.0, 512.0, 16),
    };
    let stats: StatsMap = common::stats(&[
        ("observation.state", 0.0, 512.0, 2),
        ("action", 0.0, 512.0, 2),
        extra,
    ]);
    let mut c = DiffusionConfig::cpu(kind).with_overrides(&serde_json::json!({
        "down_dims": [8, 16], "n_groups": 4, "diffusion_step_embed_dim": 8,
        "num_inference_steps": 4
    }))?;
    if transformer {
        c = c.with_overrides(&serde_json::json!({"transformer": {
            "n_layer": 1, "n_head": 2, "n_emb": 8, "p_drop_emb": 0.0, "p_drop_attn": 0.0,
            "causal_attn": true, "n_cond_layers": 0
        }}))?;
    }
    let vm = VarMap::new();
    let vb = seeded_var_builder(&vm, 3, DType::F32, &Device::Cpu);
    Ok((DiffusionPolicy::new(c, stats, vb)?, vm))
}

fn history(image: bool, seed: u64) -> Vec<Observation> {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    (0..2)
        .map(|_| Observation {
            state: vec![r.random_range(50.0..450.0), r.random_range(50.0..450.0)],
            env_state: (!image).then(|| (0..16).map(|_| r.random_range(50.0..450.0)).collect()),
            image: image.then(|| (0..96 * 96 * 3).map(|_| r.random::<u8>()).collect()),
            wrist_image: None,
        })
        .collect()
}

/// Chunks of `n` queries asked together, then each alone with fresh copies of its stream.
fn sampled(p: &DiffusionPolicy, image: bool, n: u64) -> Result<Both, Box<dyn std::error::Error>> {
    let hs: Vec<_> = (0..n).map(|i| history(image, 10 + i)).collect();
    let mut rngs: Vec<ChaCha8Rng> = (0..n).map(|i| ChaCha8Rng::seed_from_u64(100 + i)).collect();
    let mut qs: Vec<Query<'_>> = hs
        .iter()
        .zip(rngs.iter_mut())
        .map(|(h, rng)| Query { history: h, rng })
        .collect();
    let together = p.predict_chunks(&mut qs)?;
    let alone = (0..n as usize)
        .map(|i| p.predict_chunk(&hs[i], &mut ChaCha8Rng::seed_from_u64(100 + i as u64)))
        .collect::<Result<Vec<_>, _>>()?;
    Ok((together, alone))
}

#[test]
fn batched_sampling_equals_single_queries_bit_for_bit() -> R {
    for (kind, dit) in KINDS {
        let (p, _vm) = policy(kind, dit)?;
        let (together, alone) = sampled(&p, kind == ObsKind::Image, 5)?;
        assert_eq!(together.len(), 5);
        for (i, (a, b)) in together.iter().zip(&alone).enumerate() {
            assert_eq!(a, b, "{kind:?} query {i}: batched differs from alone");
        }
        // The queries differ, so the test could tell a mix-up.
        assert_ne!(together[0], together[1]);
        // A different batch composition (a prefix) gives the same chunks again.
        let (prefix, _) = sampled(&p, kind == ObsKind::Image, 2)?;
        assert_eq!(prefix[..], together[..2]);
    }
    Ok(())
}

#[test]
fn batched_pgd_equals_single_attacks_bit_for_bit() -> R {
    for (kind, dit) in KINDS {
        let (p, _vm) = policy(kind, dit)?;
        let image = kind == ObsKind::Image;
        let cfg = PgdConfig {
            iterations: 3,
            samples: 2,
            step: 0.01,
            random_start: true,
            ..PgdConfig::default()
        };
        let hs: Vec<_> = (0..3).map(|i| history(image, 20 + i)).collect();
        let mut a: Vec<ChaCha8Rng> = (0..3).map(|i| ChaCha8Rng::seed_from_u64(30 + i)).collect();
        let mut s: Vec<ChaCha8Rng> = (0..3).map(|i| ChaCha8Rng::seed_from_u64(40 + i)).collect();
        let mut qs: Vec<AttackedQuery<'_>> = hs
            .iter()
            .zip(a.iter_mut().zip(s.iter_mut()))
            .map(|(history, (attack_rng, sample_rng))| AttackedQuery {
                history,
                attack_rng,
                sample_rng,
            })
            .collect();
        let together = p.pgd_attack_batch(&mut qs, &cfg)?;
        for (i, t) in together.iter().enumerate() {
            let alone = p.pgd_attack(
                &hs[i],
                &cfg,
                &mut ChaCha8Rng::seed_from_u64(30 + i as u64),
                &mut ChaCha8Rng::seed_from_u64(40 + i as u64),
            )?;
            assert_eq!(t.chunk, alone.chunk, "{kind:?} query {i}: chunk");
            assert!(t.max_perturbation > 0.0 && t.max_perturbation <= cfg.eps as f32 + 1e-6);
            assert_eq!(t.max_perturbation, alone.max_perturbation);
        }
        assert_ne!(together[0].chunk, together[1].chunk);
        // The trait's batched path is this one.
        let mut a2: Vec<ChaCha8Rng> = (0..3).map(|i| ChaCha8Rng::seed_from_u64(30 + i)).collect();
        let mut s2: Vec<ChaCha8Rng> = (0..3).map(|i| ChaCha8Rng::seed_from_u64(40 + i)).collect();
        let mut qs: Vec<AttackedQuery<'_>> = hs
            .iter()
            .zip(a2.iter_mut().zip(s2.iter_mut()))
            .map(|(history, (attack_rng, sample_rng))| AttackedQuery {
                history,
                attack_rng,
                sample_rng,
            })
            .collect();
        let via_trait = mte_policy::attackable(&p)?.predict_chunks_attacked(&mut qs, &cfg)?;
        for (v, t) in via_trait.iter().zip(&together) {
            assert_eq!(v, &t.chunk);
        }
    }
    Ok(())
}
