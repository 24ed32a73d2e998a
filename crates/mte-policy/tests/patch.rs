//! The physical patch, encoder fine-tuning and the gradient probe on a tiny image policy and
//! a synthetic dataset.

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::VarMap;
use mte_policy::config::{DiffusionConfig, ObsKind};
use mte_policy::patch::{
    Anchor, Ascent, FinetuneConfig, PatchConfig, PlacedPatch, Placement, ProbeConfig,
    finetune_encoder, gradient_probe, paste, train_patch,
};
use mte_policy::train::{TrainData, Windows, sample_batch};
use mte_policy::{DiffusionPolicy, ObsBatch, StatsMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod common;

fn stats() -> StatsMap {
    common::stats(&[
        ("observation.state", 0.0, 512.0, 2),
        ("observation.image", 0.0, 1.0, 3),
        ("action", 0.0, 512.0, 2),
    ])
}

fn config() -> DiffusionConfig {
    DiffusionConfig::cpu(ObsKind::Image)
        .with_overrides(&serde_json::json!({
            "down_dims": [8, 16], "n_groups": 4, "diffusion_step_embed_dim": 8,
            "spatial_softmax_num_keypoints": 4
        }))
        .expect("valid")
}

fn tiny(seed: u64) -> (DiffusionPolicy, VarMap) {
    let vm = VarMap::new();
    let vb = mte_policy::init::seeded_var_builder(&vm, seed, DType::F32, &Device::Cpu);
    (
        DiffusionPolicy::new(config(), stats(), vb).expect("policy"),
        vm,
    )
}

/// Two 24-frame episodes: a bright square moving across a textured frame, actions following it.
fn data() -> TrainData {
    let (n, side) = (48usize, 96usize);
    let mut images = Vec::with_capacity(n * side * side * 3);
    let (mut state, mut action) = (Vec::new(), Vec::new());
    for f in 0..n {
        let c = 10 + (f % 24) * 3;
        for y in 0..side {
            for x in 0..side {
                let on = (c..c + 12).contains(&x) && (c..c + 12).contains(&y);
                let base = ((x * 7 + y * 13) % 64) as u8;
                images.extend_from_slice(&[base + if on { 180 } else { 0 }, base, 255 - base]);
            }
        }
        state.extend_from_slice(&[c as f32 * 5.0, 100.0]);
        action.extend_from_slice(&[c as f32 * 5.0 + 10.0, 120.0]);
    }
    TrainData {
        state,
        env_state: None,
        images: Some(images),
        wrist_images: None,
        action,
        episode_lengths: vec![24, 24],
        episode_success: vec![true, true],
        stats: stats(),
    }
}

/// The image's normalisation is MEAN_STD (from the statistics) or IDENTITY (absent from the
/// mapping, as in LeRobot); MIN_MAX has no meaning for camera frames here and is refused by
/// name, where it used to be read silently as IDENTITY.
#[test]
fn a_min_max_camera_normalisation_is_refused_by_name() {
    let mut c = config();
    c.normalization_mapping
        .insert("VISUAL".into(), mte_policy::normalize::NormMode::MinMax);
    let vm = VarMap::new();
    let vb = mte_policy::init::seeded_var_builder(&vm, 0, DType::F32, &Device::Cpu);
    let Err(e) = DiffusionPolicy::new(c.clone(), stats(), vb) else {
        panic!("MIN_MAX on the camera was accepted");
    };
    match e {
        mte_policy::PolicyError::Config { field, value, .. } => {
            assert_eq!(field, "normalization_mapping.VISUAL");
            assert_eq!(value, "MinMax");
        }
        other => panic!("not a config error: {other}"),
    }
    c.normalization_mapping.remove("VISUAL");
    let vm = VarMap::new();
    let vb = mte_policy::init::seeded_var_builder(&vm, 0, DType::F32, &Device::Cpu);
    assert!(
        DiffusionPolicy::new(c, stats(), vb).is_ok(),
        "absent means IDENTITY"
    );
}

#[test]
fn paste_replaces_exactly_the_square_and_routes_gradients_to_the_patch() {
    let img = Tensor::full(0.25f32, (2, 3, 10, 12), &Device::Cpu).expect("img");
    let patch =
        Var::from_tensor(&Tensor::full(0.75f32, (3, 3, 3), &Device::Cpu).expect("p")).expect("var");
    let out = paste(&img, patch.as_tensor(), 4, 2).expect("paste");
    let v: Vec<f32> = out.flatten_all().expect("flat").to_vec1().expect("vec");
    for (i, &x) in v.iter().enumerate() {
        let (yy, xx) = ((i / 12) % 10, i % 12);
        let inside = (4..7).contains(&xx) && (2..5).contains(&yy);
        assert_eq!(x, if inside { 0.75 } else { 0.25 }, "pixel {i}");
    }
    let g = out.sum_all().expect("sum").backward().expect("backward");
    let gp: Vec<f32> = g
        .get(patch.as_tensor())
        .expect("patch gradient")
        .flatten_all()
        .expect("flat")
        .to_vec1()
        .expect("vec");
    // Each patch pixel appears once in each of the 2 frames.
    assert!(gp.iter().all(|&x| x == 2.0), "{gp:?}");
    assert!(
        paste(&img, patch.as_tensor(), 10, 2).is_err(),
        "outside the frame"
    );
}

fn patch_config(seed: u64) -> PatchConfig {
    PatchConfig {
        side: 32,
        origin: [30, 30],
        placement: Placement::Fixed,
        epochs: 4,
        batches_per_epoch: 4,
        batch_size: 8,
        step: 0.1,
        ascent: Ascent::Sign,
        seed,
    }
}

/// The loss of one fixed batch (seeded windows, noise and timesteps) with `texture` pasted
/// at `origin`, as a graph node (so a patch `Var` gets its gradient).
fn batch_loss(p: &DiffusionPolicy, d: &TrainData, texture: &Tensor, seed: u64) -> Tensor {
    let win = Windows::new(d, p.config(), false);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (obs, x0) = sample_batch(p, d, &win, 8, &mut rng, false).expect("batch");
    let x0 = Tensor::from_vec(x0, (8, 16, 2), &Device::Cpu).expect("x0");
    let eps: Vec<f32> = (0..8 * 16 * 2)
        .map(|_| rand_distr::Distribution::sample(&rand_distr::StandardNormal, &mut rng))
        .collect();
    let eps = Tensor::from_vec(eps, (8, 16, 2), &Device::Cpu).expect("eps");
    let ts: Vec<usize> = (0..8).map(|_| rng.random_range(0..100)).collect();
    let imgs = paste(obs.image.as_ref().expect("img"), texture, 30, 30).expect("paste");
    let obs = ObsBatch {
        image: Some(imgs),
        ..obs
    };
    let cond = p.global_cond(&obs).expect("cond");
    p.loss(&cond, &x0, &eps, &ts, None).expect("loss")
}

/// What patch training rests on, as a property that holds whatever the kernels' rounding:
/// one sign-ascent step of the patch along the gradient that reaches it through the
/// encoder raises the loss of the batch it was computed on. The effect is the realised gain
/// over its first-order prediction `step x |g|_1`; over seeds 1-5 it was 0.47, 1.07, 0.63,
/// 0.56, 0.43 (mean/sd 2.4; below 1 because the step crosses ReLU and max-pool kinks), and
/// one step involves no iteration that could amplify a rounding difference.
///
/// Not asserted, because it is not a clear effect on this fixture: the *held-out* loss of a
/// trained patch against a grey one. On this random-init tiny network, over policy/patch
/// seeds 1-5 (`patch_config`), the trained patch raised the held-out loss by +1.9%, +1.1%,
/// -0.2%, -1.0%, -0.3% (mean +0.3%, sd 1.2%; AMD EPYC with AVX-512, 2026-11-24), so the
/// former single-seed assertion (+1% at seed 3, measured +2.5% on one CPU) was a
/// threshold read off one run, and failed on another CPU.
#[test]
fn a_sign_step_along_the_patch_gradient_raises_the_batch_loss_over_seeds() {
    let d = data();
    let effects: Vec<f64> = (1..=5u64)
        .map(|seed| {
            let (p, _vm) = tiny(seed);
            let grey = Tensor::full(0.5f32, (3, 32, 32), &Device::Cpu).expect("grey");
            let patch = Var::from_tensor(&grey).expect("var");
            const STEP: f64 = 1e-3;
            let l0 = batch_loss(&p, &d, patch.as_tensor(), 40 + seed);
            let g = l0.backward().expect("backward");
            let g = g.get(patch.as_tensor()).expect("the patch gets a gradient");
            let l1_norm = f64::from(
                g.abs()
                    .and_then(|a| a.sum_all())
                    .and_then(|a| a.to_scalar::<f32>())
                    .expect("|g|"),
            );
            let stepped =
                (grey.clone() + (g.sign().expect("sign") * STEP).expect("scale")).expect("step");
            let l1 = batch_loss(&p, &d, &stepped, 40 + seed);
            let (l0, l1) = (
                l0.to_scalar::<f32>().expect("l0"),
                l1.to_scalar::<f32>().expect("l1"),
            );
            // The realised gain over its first-order prediction (1 for a correct gradient
            // and a small step).
            (f64::from(l1) - f64::from(l0)) / (STEP * l1_norm)
        })
        .collect();
    common::assert_clear_effect("sign-step gain / first-order prediction", &effects);
}

#[test]
fn a_trained_patch_stays_in_range_and_is_reproducible() {
    let (p, _vm) = tiny(1);
    let d = data();
    let cfg = patch_config(3);
    let r = train_patch(&p, &d, &cfg, &|_, _| {}).expect("train");
    assert_eq!(r.texture.len(), 3 * 32 * 32);
    assert_eq!(r.epoch_loss.len(), 4);
    assert!(r.texture.iter().all(|v| (0.0..=1.0).contains(v)));
    let again = train_patch(&p, &d, &cfg, &|_, _| {}).expect("train again");
    assert_eq!(again.texture, r.texture, "same seed, same patch");
    let raw = train_patch(
        &p,
        &d,
        &PatchConfig {
            ascent: Ascent::Raw,
            ..cfg.clone()
        },
        &|_, _| {},
    )
    .expect("raw");
    assert_ne!(raw.texture, r.texture, "raw and sign ascent differ");
}

#[test]
fn away_from_goal_placement_keeps_its_rule_and_moves_the_patch() {
    let rule = Placement::AwayFromGoal {
        region: [6, 6, 90, 90],
        goal: [48.0, 48.0],
        min_goal_distance: 28.0,
    };
    let origins = rule.origins(16, [0, 0]);
    assert!(origins.len() > 100, "{} positions", origins.len());
    for [x, y] in &origins {
        assert!(
            *x >= 6 && *y >= 6 && x + 16 <= 90 && y + 16 <= 90,
            "({x}, {y}) leaves the crop"
        );
        let (cx, cy) = (*x as f64 + 8.0, *y as f64 + 8.0);
        assert!(
            (cx - 48.0).hypot(cy - 48.0) >= 28.0,
            "({x}, {y}) too near the goal"
        );
    }
    // A near corner is allowed, the goal's centre is not.
    assert!(origins.contains(&[6, 6]) && !origins.contains(&[40, 40]));
    assert_eq!(Placement::Fixed.origins(16, [3, 4]), vec![[3, 4]]);

    // Trained with the rule, the patch differs from the same patch trained in one place.
    let (p, _vm) = tiny(4);
    let d = data();
    let fixed = PatchConfig {
        side: 16,
        ..patch_config(5)
    };
    let sampled = PatchConfig {
        placement: rule,
        ..fixed.clone()
    };
    let a = train_patch(&p, &d, &fixed, &|_, _| {}).expect("fixed");
    let b = train_patch(&p, &d, &sampled, &|_, _| {}).expect("sampled");
    assert_ne!(a.texture, b.texture);
    let again = train_patch(&p, &d, &sampled, &|_, _| {}).expect("sampled again");
    assert_eq!(b.texture, again.texture, "placements come from the seed");
    let empty = PatchConfig {
        placement: Placement::AwayFromGoal {
            region: [0, 0, 96, 96],
            goal: [48.0, 48.0],
            min_goal_distance: 1e3,
        },
        ..fixed
    };
    let e = train_patch(&p, &d, &empty, &|_, _| {}).expect_err("no position");
    assert!(e.to_string().contains("placement"), "{e}");
}

#[test]
fn patch_errors_are_typed() {
    let (p, _vm) = tiny(1);
    let d = data();
    let bad = PatchConfig {
        origin: [90, 0],
        ..PatchConfig::default()
    };
    let e = train_patch(&p, &d, &bad, &|_, _| {}).expect_err("outside the frame");
    assert!(e.to_string().contains("origin"), "{e}");
    let e = PatchConfig {
        epochs: 0,
        ..PatchConfig::default()
    }
    .validate()
    .expect_err("no epochs");
    assert!(e.to_string().contains("epochs"), "{e}");
}

#[test]
fn finetuning_changes_only_the_encoder_and_the_probe_is_neutral_on_itself() {
    let (p, vm) = tiny(2);
    let d = data();
    let snapshot = |vm: &VarMap| -> Vec<(String, Vec<f32>)> {
        let mut v: Vec<_> = vm
            .data()
            .lock()
            .expect("lock")
            .iter()
            .map(|(k, v)| {
                (
                    k.clone(),
                    v.as_tensor()
                        .flatten_all()
                        .expect("f")
                        .to_vec1()
                        .expect("v"),
                )
            })
            .collect();
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    };
    let before = snapshot(&vm);
    let texture = vec![0.9f32; 3 * 12 * 12];
    let cfg = FinetuneConfig {
        steps: 3,
        lr: 1e-3,
        batch_size: 4,
        regenerate: true,
        ..FinetuneConfig::default()
    };
    let mut seen = Vec::new();
    let r = finetune_encoder(&p, &vm, &d, &texture, 12, &cfg, &mut |s, _| {
        seen.push(s);
        Ok(())
    })
    .expect("finetune");
    assert_eq!(
        seen,
        [1, 2, 3],
        "called after every step with the steps done"
    );
    assert_eq!((r.first_clean_drift, r.last_clean_drift), (None, None));
    assert_eq!(r.steps, 3);
    assert!(r.encoder_tensors > 0);
    assert!(r.first_loss.is_finite() && r.last_consistency >= 0.0);
    assert_ne!(r.texture, texture, "regeneration moved the patch");
    assert!(
        r.first_patch_loss.is_some_and(f64::is_finite)
            && r.last_patch_loss.is_some_and(|l| l > 0.0),
        "{:?}",
        (r.first_patch_loss, r.last_patch_loss)
    );
    let after = snapshot(&vm);
    let mut encoder_changed = false;
    for ((k, a), (_, b)) in before.iter().zip(&after) {
        if k.starts_with("diffusion.rgb_encoder.") {
            encoder_changed |= a != b;
        } else {
            assert_eq!(a, b, "{k} changed: the denoising head must stay frozen");
        }
    }
    assert!(encoder_changed, "no encoder weight moved");
    let probe = gradient_probe(&p, &p, &d, placed(&texture), PROBE).expect("probe");
    for v in [
        probe.cosine,
        probe.grad_norm_ratio,
        probe.patch_cosine,
        probe.patch_grad_norm_ratio,
        probe.clean_cosine,
        probe.clean_grad_norm_ratio,
    ] {
        assert!((v - 1.0).abs() < 1e-6, "{probe:?}");
    }
    assert!(
        (probe.latent_displacement_ratio - 1.0).abs() < 1e-6,
        "{probe:?}"
    );
    let (other, _) = tiny(7);
    let probe = gradient_probe(&p, &other, &d, placed(&texture), PROBE).expect("probe");
    assert!(
        probe.cosine < 0.99,
        "different networks, different gradients: {probe:?}"
    );
    // The gradients are taken at the patched frames: another texture at the same place gives
    // other gradients (at the clean frames they would not depend on it).
    let dark = vec![0.1f32; 3 * 12 * 12];
    let probe2 = gradient_probe(&p, &other, &d, placed(&dark), PROBE).expect("probe");
    assert_ne!(probe.cosine, probe2.cosine, "{probe:?} {probe2:?}");
    assert_ne!(probe.patch_cosine, probe2.patch_cosine);
    assert_eq!(probe.clean_cosine, probe2.clean_cosine);
}

/// Clean image features of 8 fixed windows.
const PROBE: ProbeConfig = ProbeConfig {
    batches: 1,
    batch_size: 4,
    seed: 0,
};

fn placed(texture: &[f32]) -> PlacedPatch<'_> {
    PlacedPatch {
        texture,
        side: 12,
        origin: (30, 30),
    }
}

fn clean_features(p: &DiffusionPolicy, d: &TrainData) -> Tensor {
    let win = Windows::new(d, p.config(), false);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (obs, _) = sample_batch(p, d, &win, 8, &mut rng, false).expect("batch");
    p.image_features(obs.image.as_ref().expect("img"))
        .expect("features")
}

/// Measured (AMD EPYC with AVX-512, 2026-11-24): ln(current / original drift) over seeds
/// 2-6 at 80 steps 2.05, 1.55, 0.96, 1.14, 0.88 (mean/sd 2.7); at 40 steps one seed gave
/// 0.13 (mean/sd 1.6). After the encoder's products became per-image (batch-invariant
/// kernels, 2026-11-25) seed 4 at 80 steps gave 0.13 too (2.09, 1.55, 0.13, 1.14, 0.89): the
/// effect's size varies from draw to draw, so the test asserts it with a t-test over eight
/// seeds instead of "mean > 2 sd" over five.
#[test]
fn the_original_anchor_holds_clean_features_where_the_frozen_head_expects_them() {
    let d = data();
    let texture = vec![0.9f32; 3 * 12 * 12];
    let cfg = |anchor| FinetuneConfig {
        steps: 80,
        lr: 3e-3,
        consistency: 10.0,
        anchor,
        batch_size: 4,
        ..FinetuneConfig::default()
    };
    let run = |anchor, seed| {
        let (p, vm) = tiny(seed);
        let before = clean_features(&p, &d);
        let mut losses = Vec::new();
        finetune_encoder(&p, &vm, &d, &texture, 12, &cfg(anchor), &mut |_, l| {
            losses.push(l);
            Ok(())
        })
        .expect("finetune");
        let drift = common::max_abs_diff(&before, &clean_features(&p, &d));
        (losses, drift)
    };
    let mut effects = Vec::new();
    for seed in 2..=9 {
        let (orig_losses, orig_drift) = run(Anchor::Original, seed);
        let (cur_losses, cur_drift) = run(Anchor::Current, seed);
        // Same weights at step 0, so the same target; the targets part once the encoder
        // moves.
        assert_eq!(orig_losses[0], cur_losses[0]);
        assert_ne!(orig_losses[1], cur_losses[1]);
        // The current-encoder target can be chased (or collapsed onto); the original one
        // cannot, so clean features move less under it: the log ratio of the drifts.
        effects.push(f64::from(cur_drift / orig_drift).ln());
    }
    common::assert_significant_effect("ln(current-anchor drift / original-anchor drift)", &effects);
}

/// The clean-feature term ties the tuned encoder's clean embedding to the original's, so
/// under the drifting `Current` anchor the clean features move less with it than without:
/// a paired t-test on the log ratio of the drifts over six seeds (no threshold read off a
/// run), and the term's own drift is reported and falls.
#[test]
fn the_clean_feature_term_holds_the_clean_embedding() {
    let d = data();
    let texture = vec![0.9f32; 3 * 12 * 12];
    let cfg = |mu| FinetuneConfig {
        steps: 60,
        lr: 3e-3,
        consistency: 10.0,
        anchor: Anchor::Current,
        clean_features: mu,
        batch_size: 4,
        ..FinetuneConfig::default()
    };
    let run = |mu, seed| {
        let (p, vm) = tiny(seed);
        let before = clean_features(&p, &d);
        let r = finetune_encoder(&p, &vm, &d, &texture, 12, &cfg(mu), &mut |_, _| Ok(()))
            .expect("finetune");
        (r, common::max_abs_diff(&before, &clean_features(&p, &d)))
    };
    let mut effects = Vec::new();
    for seed in 2..=7 {
        let (off, off_drift) = run(0.0, seed);
        let (on, on_drift) = run(10.0, seed);
        assert_eq!(off.first_clean_drift, None);
        assert_eq!((off.first_patch_loss, on.last_patch_loss), (None, None));
        let (first, last) = (
            on.first_clean_drift.expect("on"),
            on.last_clean_drift.expect("on"),
        );
        assert!(first.is_finite() && last.is_finite() && first >= 0.0 && last >= 0.0);
        effects.push(f64::from(off_drift / on_drift).ln());
    }
    common::assert_significant_effect("ln(drift without / with the clean term)", &effects);
}

/// The clean task term enters the objective with its weight, and its gradient reaches the
/// encoder: at the first step (same weights, same batch) the total with weight ν is the
/// total without it plus ν times the reported clean task loss; at the second, the rest of
/// the objective differs too (the first step moved the encoder differently). Its losses are
/// reported when it is on and absent when it is off.
#[test]
fn the_clean_task_term_adds_the_clean_denoising_loss_with_its_weight() {
    let d = data();
    let texture = vec![0.9f32; 3 * 12 * 12];
    let run = |nu: f64, steps| {
        let (p, vm) = tiny(4);
        let cfg = FinetuneConfig {
            steps,
            lr: 3e-3,
            clean_task: nu,
            batch_size: 4,
            ..FinetuneConfig::default()
        };
        let mut losses = Vec::new();
        let r = finetune_encoder(&p, &vm, &d, &texture, 12, &cfg, &mut |_, l| {
            losses.push(l);
            Ok(())
        })
        .expect("finetune");
        (r, losses)
    };
    // Relative rounding of f32 sums of a few terms.
    let close = |a: f64, b: f64| (a - b).abs() <= 1e-5 * a.abs().max(b.abs()).max(1.0);
    let (off, off1) = run(0.0, 1);
    let (on, on1) = run(10.0, 1);
    assert_eq!(
        (off.first_clean_task_loss, off.last_clean_task_loss),
        (None, None)
    );
    let c1 = on.first_clean_task_loss.expect("on");
    assert!(c1.is_finite() && c1 > 0.0, "clean task loss {c1}");
    assert_eq!(on.last_clean_task_loss, Some(c1), "one step: first = last");
    assert!(
        close(on1[0] - off1[0], 10.0 * c1),
        "with the term {} - without {} != 10 x {c1}",
        on1[0],
        off1[0]
    );
    // Two steps: the reported mean gives the second step's clean loss.
    let (_, off2) = run(0.0, 2);
    let (on, on2) = run(10.0, 2);
    let c2 = 2.0 * on.first_clean_task_loss.expect("on") - c1;
    assert!(
        !close(on2[1] - off2[1], 10.0 * c2),
        "the clean term's gradient changed nothing else at step 2"
    );
}

#[test]
fn a_failing_step_callback_stops_fine_tuning_and_bad_weights_are_refused() {
    let d = data();
    let (p, vm) = tiny(3);
    let texture = vec![0.5f32; 3 * 12 * 12];
    let cfg = FinetuneConfig {
        steps: 5,
        batch_size: 2,
        ..FinetuneConfig::default()
    };
    let mut calls = 0;
    let e = finetune_encoder(&p, &vm, &d, &texture, 12, &cfg, &mut |s, _| {
        calls += 1;
        if s == 2 {
            Err(mte_policy::PolicyError::Candle(candle_core::Error::Msg(
                "disk full".into(),
            )))
        } else {
            Ok(())
        }
    })
    .expect_err("the callback's error");
    assert!(e.to_string().contains("disk full"), "{e}");
    assert_eq!(calls, 2, "no step after the failing one");
    for bad in [-1.0, f64::NAN] {
        let cfg = FinetuneConfig {
            clean_features: bad,
            ..cfg.clone()
        };
        let e = finetune_encoder(&p, &vm, &d, &texture, 12, &cfg, &mut |_, _| Ok(()))
            .expect_err("refused");
        assert!(e.to_string().contains("clean_features"), "{e}");
        let task = FinetuneConfig {
            clean_task: bad,
            ..FinetuneConfig::default()
        };
        let e = finetune_encoder(&p, &vm, &d, &texture, 12, &task, &mut |_, _| Ok(()))
            .expect_err("refused");
        assert!(e.to_string().contains("clean_task"), "{e}");
    }
}

#[test]
fn keypoint_policies_cannot_carry_a_patch() {
    let c = DiffusionConfig::cpu(ObsKind::Keypoints)
        .with_overrides(&serde_json::json!({"down_dims": [8, 16], "n_groups": 4, "diffusion_step_embed_dim": 8}))
        .expect("valid");
    let mut s = stats();
    s.extend(common::stats(&[(
        "observation.environment_state",
        0.0,
        512.0,
        16,
    )]));
    let vm = VarMap::new();
    let vb = mte_policy::init::seeded_var_builder(&vm, 8, DType::F32, &Device::Cpu);
    let p = DiffusionPolicy::new(c, s, vb).expect("policy");
    let mut d = data();
    d.env_state = Some(vec![1.0; 48 * 16]);
    let e = train_patch(&p, &d, &PatchConfig::default(), &|_, _| {}).expect_err("no camera");
    assert!(e.to_string().contains("image"), "{e}");
}
