//! `mte attack calibrate`, `mte attack patch`, `mte defend finetune`, `mte defend probe`.

use std::io::Write as _;

use anyhow::{Context, Result, ensure};
use mte_eval::Reporter as _;
use mte_eval::calibrate::{CalibrationSpec, calibrate as run_calibration};
use mte_eval::sweep::{CheckpointSource, PolicySource as _};

use crate::args::{CalibrateArgs, Cli, Format};
use crate::progress::Bar;

/// `mte attack alignment`
pub fn alignment(cli: &Cli, a: &crate::args::AlignmentArgs) -> Result<()> {
    use crate::args::AlignmentFault;
    use mte_eval::corruption::{CorruptionSpec, Fault, QueryAttack, Schedule, SensorFault};
    use mte_eval::pusht::EpisodeSpec;
    let policy = CheckpointSource
        .load(&a.policy.to_string_lossy())
        .with_context(|| format!("loading {}", a.policy.display()))?;
    let fault = match (a.fault, &a.patch) {
        (AlignmentFault::Pgd, _) => Fault::Query(QueryAttack::Pgd(mte_policy::PgdConfig {
            eps: a.eps,
            iterations: a.iterations,
            ..mte_policy::PgdConfig::default()
        })),
        (AlignmentFault::Blank, _) => Fault::Sensor(SensorFault::Blank),
        (AlignmentFault::Patch, Some(path)) => Fault::Sensor(SensorFault::Patch {
            path: path.clone(),
            step: None,
        }),
        (AlignmentFault::Patch, None) => anyhow::bail!("--fault patch needs --patch DIR"),
    };
    let corruption = CorruptionSpec {
        fault,
        schedule: Schedule::Burst {
            q: a.q,
            period: None,
            phase: 0,
        },
    };
    let execution = a.arm.parse().context("--arm")?;
    let specs: Vec<EpisodeSpec<'_>> = (0..a.episodes as u64)
        .map(|i| EpisodeSpec {
            needs: policy.needs(),
            seed: 100_000 + i,
            stream: Default::default(),
            h: a.stride,
            max_steps: a.max_steps,
            execution,
            corruption: &corruption,
            noise_seed: 0,
            sampling: Default::default(),
            monitors: &[],
            span: None,
        })
        .collect();
    let t0 = std::time::Instant::now();
    let r = mte_eval::alignment::alignment(policy.as_ref(), &specs)?;
    let secs = t0.elapsed().as_secs_f64();
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(
            so,
            "{}",
            serde_json::json!({"alignment": r, "seconds": secs})
        )?,
        Format::Text if !cli.quiet => writeln!(
            so,
            "{} episodes, {} corrupted queries, {} candidate pairs: median cosine {}, quartiles {}, mean displacement {} ({secs:.0} s)",
            r.episodes,
            r.attacked_queries,
            r.pairs,
            r.median.map_or("-".into(), |v| format!("{v:.3}")),
            r.quartiles
                .map_or("-".into(), |(l, h)| format!("[{l:.3}, {h:.3}]")),
            r.mean_norm.map_or("-".into(), |v| format!("{v:.2}")),
        )?,
        Format::Text => {}
    }
    Ok(())
}

/// `mte attack calibrate`
pub fn calibrate(cli: &Cli, a: &CalibrateArgs) -> Result<()> {
    ensure!(a.episodes >= 1, "--episodes must be at least 1");
    let arm = a
        .arm
        .parse()
        .with_context(|| format!("--arm {:?}: expected open-loop or an aggregator", a.arm))?;
    let policy = CheckpointSource
        .load(&a.policy.to_string_lossy())
        .with_context(|| format!("loading {}", a.policy.display()))?;
    let needs = policy.needs();
    let spec = CalibrationSpec {
        arm,
        h: a.stride,
        q: a.q,
        seeds: (0..a.episodes as u64).map(|i| 100_000 + i).collect(),
        iterations: a.iterations.clone(),
        steps: a.steps.clone(),
        eps: a.eps,
        tolerance: a.tolerance,
        max_steps: a.max_steps,
        noise_seed: 0,
    };
    let bar = Bar::new(!cli.no_progress && !cli.quiet);
    let t0 = std::time::Instant::now();
    let rows = run_calibration(policy.as_ref(), needs, &spec, &bar)?;
    let secs = t0.elapsed().as_secs_f64();
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(so, "{}", serde_json::json!({"rows": rows, "seconds": secs}))?,
        Format::Text => {
            writeln!(
                so,
                "PGD calibration against {} (eps {}, q = {}, h = {}, {} episodes), {secs:.0} s",
                a.arm, a.eps, a.q, a.stride, a.episodes
            )?;
            writeln!(so, "| step | iterations | mean max coverage | success | |")?;
            writeln!(so, "|--:|--:|--:|--:|:--|")?;
            for r in &rows {
                writeln!(
                    so,
                    "| {} | {} | {:.3} | {:.0}% | {} |",
                    if r.iterations == 0 {
                        "clean".to_string()
                    } else {
                        r.step.to_string()
                    },
                    r.iterations,
                    r.mean_coverage,
                    100.0 * r.success_rate,
                    if r.stopped {
                        "no further gain: stop"
                    } else {
                        ""
                    }
                )?;
            }
        }
    }
    Ok(())
}

fn image_frame(policy: &mte_policy::DiffusionPolicy) -> Result<(usize, usize)> {
    match policy.config().image_shape() {
        Some([_, h, w]) => Ok((w, h)),
        None => anyhow::bail!("the policy has no camera input: a patch needs an image policy"),
    }
}

/// `mte attack patch`
pub fn patch(cli: &Cli, a: &crate::args::AttackPatchArgs) -> Result<()> {
    use mte_policy::patch::{Ascent, PatchConfig, train_patch};
    let center = a.center;
    let policy = mte_policy::checkpoint::load(&a.policy, &candle_core::Device::Cpu)
        .with_context(|| format!("loading {}", a.policy.display()))?;
    let (w, h) = image_frame(&policy)?;
    ensure!(
        a.side >= 1 && a.side <= w.min(h),
        "--side {}: expected 1..={}",
        a.side,
        w.min(h)
    );
    // The world -> frame placement the simulator draws with, so training and evaluation agree.
    let probe = mte_sim::Patch::new(vec![0; a.side * a.side * 3], a.side, center)?;
    let (x, y) = probe.origin(w, h)?;
    let placement = placement(&policy, a, [w, h])?;
    let cfg = PatchConfig {
        side: a.side,
        origin: [x, y],
        placement,
        epochs: a.epochs,
        batches_per_epoch: a.batches_per_epoch,
        batch_size: a.batch_size,
        step: a.step,
        ascent: match a.ascent {
            crate::args::AscentArg::Sign => Ascent::Sign,
            crate::args::AscentArg::Raw => Ascent::Raw,
        },
        seed: a.seed,
    };
    let data = crate::cmd::train::load_train_data(&a.data, policy.config())?;
    let t0 = std::time::Instant::now();
    let bar = Bar::for_cli(cli, "patch epochs", cfg.epochs);
    let report = train_patch(&policy, &data, &cfg, &|epoch, loss| {
        bar.set(epoch as u64 + 1, Some(format!("policy loss {loss:.4}")));
    })?;
    bar.finish();
    let meta = mte_eval::patch_file::PatchMeta::new(&cfg, &report, center, [w, h], &a.policy);
    mte_eval::patch_file::save(&a.out, &meta, &report.rgb_u8())?;
    let secs = t0.elapsed().as_secs_f64();
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(so, "{}", serde_json::json!({"meta": meta, "seconds": secs}))?,
        Format::Text => writeln!(
            so,
            "patch {s}x{s} at world ({:.0}, {:.0}) = frame ({x}, {y}): loss {:.4} -> {:.4} over {} epochs in {secs:.0} s -> {}",
            center[0],
            center[1],
            report.initial_loss,
            report.epoch_loss.last().copied().unwrap_or(f64::NAN),
            cfg.epochs,
            a.out.display(),
            s = a.side
        )?,
    }
    Ok(())
}

/// The training placement of `mte attack patch` in frame px: the goal's centre and the
/// distance mapped from world px as the simulator draws, the region the policy's centre
/// crop (what it sees at evaluation).
fn placement(
    policy: &mte_policy::DiffusionPolicy,
    a: &crate::args::AttackPatchArgs,
    [w, h]: [usize; 2],
) -> Result<mte_policy::patch::Placement> {
    use mte_policy::patch::Placement;
    Ok(match a.placement {
        crate::args::PlacementArg::Fixed => Placement::Fixed,
        crate::args::PlacementArg::AwayFromGoal => {
            ensure!(
                a.min_goal_distance.is_finite() && a.min_goal_distance >= 0.0,
                "--min-goal-distance {}: expected a finite distance >= 0 (world px)",
                a.min_goal_distance
            );
            let [ch, cw] = policy.config().crop_shape.unwrap_or([h, w]);
            let (x0, y0) = ((w - cw.min(w)) / 2, (h - ch.min(h)) / 2);
            let scale = w as f64 / 512.0;
            let goal = mte_sim::GOAL;
            Placement::AwayFromGoal {
                region: [x0, y0, x0 + cw.min(w), y0 + ch.min(h)],
                goal: [goal.x * scale, goal.y * scale],
                min_goal_distance: a.min_goal_distance * scale,
            }
        }
    })
}

/// `mte defend finetune`
pub fn finetune(cli: &Cli, a: &crate::args::FinetuneArgs) -> Result<()> {
    use mte_policy::patch::{finetune_encoder, rgb_to_texture};
    let cfg = finetune_config(a)?;
    let dev = candle_core::Device::Cpu;
    let (policy, varmap) = mte_policy::checkpoint::load_trainable(&a.policy, &dev)
        .with_context(|| format!("loading {}", a.policy.display()))?;
    image_frame(&policy)?;
    let (meta, patch) = mte_eval::patch_file::load(&a.patch)?;
    let texture = rgb_to_texture(patch.rgb(), meta.side);
    let data = crate::cmd::train::load_train_data(&a.data, policy.config())?;
    let t0 = std::time::Instant::now();
    let bar = Bar::for_cli(cli, "fine-tune", cfg.steps);
    // The current values of every variable, by name, as a checkpoint.
    let save = |dir: &std::path::Path| -> Result<(), mte_policy::PolicyError> {
        let weights: std::collections::HashMap<String, candle_core::Tensor> = varmap
            .data()
            .lock()
            .map_err(|_| candle_core::Error::Msg("variable map poisoned".into()))?
            .iter()
            .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
            .collect();
        mte_policy::checkpoint::save(dir, policy.config(), &weights, policy.stats())
    };
    let report = finetune_encoder(
        &policy,
        &varmap,
        &data,
        &texture,
        meta.side,
        &cfg,
        &mut |s, l| {
            bar.set(s as u64, Some(format!("loss {l:.4}")));
            match a.checkpoint_every {
                Some(n) if s % n == 0 && s < cfg.steps => save(&a.out.join(format!("step-{s}"))),
                _ => Ok(()),
            }
        },
    )?;
    bar.finish();
    save(&a.out)?;
    save_regenerated_patch(a, &cfg, meta, &report)?;
    let secs = t0.elapsed().as_secs_f64();
    let summary = serde_json::json!({
        "policy": a.policy, "patch": a.patch, "config": cfg, "report": {
            "steps": report.steps, "encoder_tensors": report.encoder_tensors,
            "first_loss": report.first_loss, "last_loss": report.last_loss,
            "first_consistency": report.first_consistency,
            "last_consistency": report.last_consistency,
            "first_clean_drift": report.first_clean_drift,
            "last_clean_drift": report.last_clean_drift,
            "first_patch_loss": report.first_patch_loss,
            "last_patch_loss": report.last_patch_loss,
            "first_clean_task_loss": report.first_clean_task_loss,
            "last_clean_task_loss": report.last_clean_task_loss,
        }, "seconds": secs,
    });
    std::fs::write(a.out.join("finetune.json"), format!("{summary:#}\n"))
        .with_context(|| format!("writing {}", a.out.join("finetune.json").display()))?;
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(so, "{summary}")?,
        Format::Text => writeln!(
            so,
            "fine-tuned {} encoder tensors for {} steps in {secs:.0} s: loss {:.4} -> {:.4}, consistency {:.4} -> {:.4} -> {}",
            report.encoder_tensors,
            report.steps,
            report.first_loss,
            report.last_loss,
            report.first_consistency,
            report.last_consistency,
            a.out.display()
        )?,
    }
    Ok(())
}

/// The fine-tuning settings of `mte defend finetune`'s arguments; `--checkpoint-every 0` is
/// refused here, before any work.
fn finetune_config(a: &crate::args::FinetuneArgs) -> Result<mte_policy::patch::FinetuneConfig> {
    use mte_policy::patch::{Anchor, FinetuneConfig};
    if a.checkpoint_every == Some(0) {
        anyhow::bail!("--checkpoint-every 0: expected a step count >= 1");
    }
    Ok(FinetuneConfig {
        steps: a.steps,
        lr: a.lr,
        consistency: a.consistency,
        anchor: match a.anchor {
            crate::args::AnchorArg::Original => Anchor::Original,
            crate::args::AnchorArg::Current => Anchor::Current,
        },
        clean_features: a.clean_features,
        clean_task: a.clean_task,
        batch_size: a.batch_size,
        regenerate: a.regenerate,
        regenerate_step: a.regenerate_step,
        seed: a.seed,
    })
}

/// With `--regenerate`, the patch as the fine-tuning left it, into `out/patch` with its
/// provenance (the regeneration's losses are present exactly when the patch was regenerated).
fn save_regenerated_patch(
    a: &crate::args::FinetuneArgs,
    cfg: &mte_policy::patch::FinetuneConfig,
    meta: mte_eval::patch_file::PatchMeta,
    report: &mte_policy::patch::FinetuneReport,
) -> Result<()> {
    let (Some(first_loss), Some(last_loss)) = (report.first_patch_loss, report.last_patch_loss)
    else {
        return Ok(());
    };
    let r = mte_eval::patch_file::Regeneration {
        from: a.patch.display().to_string(),
        encoder: a.out.display().to_string(),
        steps: report.steps,
        step: cfg.regenerate_step,
        batch_size: cfg.batch_size,
        seed: cfg.seed,
        first_loss,
        last_loss,
    };
    let rgb = mte_policy::patch::texture_to_rgb(&report.texture, meta.side);
    mte_eval::patch_file::save(&a.out.join("patch"), &meta.regenerated(r), &rgb)?;
    Ok(())
}

/// `mte defend probe`
pub fn probe(cli: &Cli, a: &crate::args::ProbeArgs) -> Result<()> {
    use mte_policy::patch::{gradient_probe, rgb_to_texture};
    let dev = candle_core::Device::Cpu;
    let load = |p: &std::path::Path| {
        mte_policy::checkpoint::load(p, &dev).with_context(|| format!("loading {}", p.display()))
    };
    let (original, tuned) = (load(&a.original)?, load(&a.tuned)?);
    let (w, h) = image_frame(&original)?;
    let (meta, patch) = mte_eval::patch_file::load(&a.patch)?;
    let origin = patch.origin(w, h)?;
    let data = crate::cmd::train::load_train_data(&a.data, original.config())?;
    let texture = rgb_to_texture(patch.rgb(), meta.side);
    let r = gradient_probe(
        &original,
        &tuned,
        &data,
        mte_policy::patch::PlacedPatch {
            texture: &texture,
            side: meta.side,
            origin,
        },
        mte_policy::patch::ProbeConfig {
            batches: a.batches,
            batch_size: a.batch_size,
            seed: a.seed,
        },
    )?;
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(so, "{}", serde_json::json!(r))?,
        Format::Text => writeln!(
            so,
            "gradient probe over {} batches at the patched frames: cosine {:.3}, gradient norm ratio (tuned/original) {:.3}; on the patch's pixels {:.3}, {:.3}; at the clean frames {:.3}, {:.3}; latent displacement ratio {:.3}",
            r.batches,
            r.cosine,
            r.grad_norm_ratio,
            r.patch_cosine,
            r.patch_grad_norm_ratio,
            r.clean_cosine,
            r.clean_grad_norm_ratio,
            r.latent_displacement_ratio
        )?,
    }
    Ok(())
}

/// `mte attack activity`
pub fn activity(cli: &Cli, a: &crate::args::ActivityArgs) -> Result<()> {
    use mte_policy::activity::{ActivityConfig, encoder_activity};
    use rand::SeedableRng as _;
    let dev = candle_core::Device::Cpu;
    let policy = mte_policy::checkpoint::load(&a.policy, &dev)
        .with_context(|| format!("loading {}", a.policy.display()))?;
    let data = crate::cmd::train::load_train_data(&a.data, policy.config())?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(a.seed);
    let mut reports = Vec::with_capacity(a.eps.len());
    for &eps in &a.eps {
        let cfg = ActivityConfig {
            eps,
            batch: a.batch,
        };
        reports.push(encoder_activity(&policy, &data, cfg, &mut rng)?);
    }
    let mut so = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(so, "{}", serde_json::json!(reports))?,
        Format::Text => {
            writeln!(
                so,
                "{:>6} {:>7} {:>11} {:>16} {:>12} {:>10} {:>12}",
                "eps",
                "frames",
                "dead frames",
                "dead windows",
                "active mean",
                "min/median",
                "never active"
            )?;
            for r in &reports {
                writeln!(
                    so,
                    "{:>6} {:>7} {:>11} {:>16} {:>12.2} {:>10} {:>12}",
                    r.eps,
                    r.frames,
                    r.dead_frames,
                    format!("{} of {}", r.dead_windows, r.windows),
                    r.active_mean,
                    format!("{}/{}", r.active_min, r.active_median),
                    format!("{} of {}", r.never_active, r.features)
                )?;
            }
        }
    }
    Ok(())
}

/// `mte attack control`
pub fn control(cli: &Cli, a: &crate::args::AttackControlArgs) -> Result<()> {
    use mte_eval::patch_file::ControlKind;
    let kind = match a.kind {
        crate::args::ControlArg::MeanColour => ControlKind::MeanColour,
        crate::args::ControlArg::Grey => ControlKind::Grey,
        crate::args::ControlArg::Noise => ControlKind::Noise { seed: a.seed },
    };
    let meta = mte_eval::patch_file::control(&a.patch, &a.out, kind)?;
    if !cli.quiet {
        writeln!(
            std::io::stdout(),
            "wrote the {kind} control of {} ({} px at world ({:.0}, {:.0})) to {}",
            a.patch.display(),
            meta.side,
            meta.center[0],
            meta.center[1],
            a.out.display()
        )?;
    }
    Ok(())
}
