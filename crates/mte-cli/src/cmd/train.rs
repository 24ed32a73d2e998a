//! `mte train diffusion`.

use std::io::Write as _;

use anyhow::{Context, Result, ensure};
use candle_core::Device;
use mte_eval::Reporter as _;
use mte_eval::train_data;
use mte_policy::config::{DiffusionConfig, ObsKind};
use mte_policy::pretrain::{EncoderPretrainConfig, pretrain_encoder, save_encoder};
use mte_policy::train::{TrainConfig, TrainData, train};

use crate::args::{
    BackboneArg, Cli, Format, LrScheduleArg, PolicyObsArg, PresetArg, TrainActArgs,
    TrainDiffusionArgs, TrainEncoderArgs,
};
use crate::progress::Bar;

/// The JSON object of config fields in `path`.
fn read_overrides(path: &std::path::Path) -> Result<serde_json::Value> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

/// The preset for `obs` (with the Diffusion Transformer's settings for that `backbone`), then
/// the fields of the JSON file `overrides` replaced, so that `--config` can set the
/// transformer's width or depth as it sets any other field.
fn preset_config(
    preset: PresetArg,
    obs: ObsKind,
    backbone: BackboneArg,
    wrist: bool,
    overrides: Option<&std::path::Path>,
) -> Result<DiffusionConfig> {
    let mut config = match preset {
        PresetArg::Cpu => DiffusionConfig::cpu(obs),
        PresetArg::Paper => {
            let mut c = DiffusionConfig::paper();
            if obs == ObsKind::Keypoints {
                c.input_features = DiffusionConfig::cpu(obs).input_features;
            }
            c
        }
    };
    if backbone == BackboneArg::Transformer {
        config = with_transformer(config, preset, obs);
    }
    if wrist {
        wrist_needs_image(obs)?;
        config = config.with_wrist_camera();
    }
    if let Some(path) = overrides {
        config = config.with_overrides(&read_overrides(path)?)?;
    }
    config.validate().context("check the preset and --config")?;
    Ok(config)
}

/// `--wrist` is a second camera: refused without the first (`--obs image`).
fn wrist_needs_image(obs: ObsKind) -> Result<()> {
    ensure!(
        obs == ObsKind::Image,
        "--wrist adds a second camera to an image policy: give --obs image"
    );
    Ok(())
}

/// The Diffusion Transformer's settings on top of `config`: Diffusion Policy's transformer
/// (the `paper` preset's, or the `cpu` one), horizon 10 for images (its T_p = 10 experiment)
/// and 16 for keypoints (its low-dim PushT config), 2 observations, 8 executed. The caller
/// validates the result.
fn with_transformer(
    mut config: DiffusionConfig,
    preset: PresetArg,
    obs: ObsKind,
) -> DiffusionConfig {
    use mte_policy::config::TransformerConfig;
    config.transformer = Some(match preset {
        PresetArg::Paper => TransformerConfig::paper(),
        PresetArg::Cpu => TransformerConfig::cpu(),
    });
    config.horizon = if obs == ObsKind::Image { 10 } else { 16 };
    config.n_action_steps = 8;
    config
}

/// Sizes from the dataset at `dir` (PushT: 2-D state and action, 96 x 96 frames;
/// robomimic: 9-D proprioception, 7-D actions, 84 x 84 frames), then the config checked
/// again (a preset's crop larger than the frames is refused by name: give `--config`).
fn fit_to_data(config: &mut DiffusionConfig, dir: &std::path::Path) -> Result<()> {
    let info = mte_data::Info::read(dir)?;
    mte_eval::train_data::fit_shapes(config, &info);
    config
        .validate()
        .with_context(|| format!("the config fitted to {}", dir.display()))?;
    Ok(())
}

/// `mte train diffusion`
pub fn diffusion(cli: &Cli, a: &TrainDiffusionArgs) -> Result<()> {
    let obs = match a.obs {
        PolicyObsArg::Keypoints => ObsKind::Keypoints,
        PolicyObsArg::Image => ObsKind::Image,
    };
    let mut config = preset_config(a.preset, obs, a.backbone, a.wrist, a.config.as_deref())?;
    let first = a.data.first().context("--data: at least one dataset")?;
    fit_to_data(&mut config, first)?;
    let mut data = train_data::load_many(&a.data, &config, train_data::Extra::default())?;
    if let Some(dir) = &a.normalization_from {
        let stats = mte_policy::checkpoint::read_stats(dir)
            .with_context(|| format!("--normalization-from {}", dir.display()))?;
        let vectors = config.input_features.iter().chain(&config.output_features);
        for (name, _) in vectors.filter(|(_, f)| f.shape.len() == 1) {
            ensure!(
                stats.contains_key(name),
                "--normalization-from {}: no statistics of {name:?}, which the policy normalises",
                dir.display()
            );
        }
        data.stats.extend(stats);
    }
    let tc = TrainConfig {
        steps: a.steps,
        batch_size: a.batch_size,
        seed: a.seed,
        checkpoint_every: a.checkpoint_every,
        init: a.init.clone(),
        init_n_obs_steps: a.init_n_obs_steps,
        freeze_encoder: a.freeze_encoder,
        successful_only: a.successful_only,
        ..TrainConfig::default()
    };
    let bar = Bar::for_cli(cli, "train", a.steps);
    let report = train(
        &config,
        &tc,
        &data,
        &a.out,
        &Device::Cpu,
        &|step, loss, lr| {
            let figure = (step % 10 == 0).then(|| format!("loss {loss:.4} lr {lr:.2e}"));
            bar.set(step as u64, figure);
        },
    )?;
    bar.finish();
    let mut out = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(out, "{}", serde_json::to_string(&report)?)?,
        Format::Text => {
            if !cli.quiet {
                writeln!(
                    out,
                    "trained {} steps (now at {}) in {:.0} s, final loss {} -> {}",
                    report.steps_run,
                    report.step,
                    report.seconds,
                    loss_text(report.final_loss),
                    a.out.display()
                )?;
            }
        }
    }
    Ok(())
}

/// `mte train act`
pub fn act(cli: &Cli, a: &TrainActArgs) -> Result<()> {
    use mte_policy::act::ActConfig;
    use mte_policy::act::train::{ActTrainConfig, LrSchedule, train as train_act};
    let mut config = match a.preset {
        PresetArg::Cpu => ActConfig::cpu(),
        PresetArg::Paper => ActConfig::paper(),
    };
    let obs = match a.obs {
        PolicyObsArg::Keypoints => ObsKind::Keypoints,
        PolicyObsArg::Image => ObsKind::Image,
    };
    // The arrays and their statistics, as a Diffusion Policy of the same observation reads
    // them (the image's per-channel mean and std included).
    let mut dp = DiffusionConfig::cpu(obs);
    if a.wrist {
        wrist_needs_image(obs)?;
        dp = dp.with_wrist_camera();
    }
    if let Some(shape) = dp.image_shape() {
        config = config.with_camera("observation.image", shape);
        if a.wrist {
            config = config.with_wrist_camera();
        }
    }
    if let Some(path) = &a.config {
        config = config.with_overrides(&read_overrides(path)?)?;
    }
    let data = load_train_data(&a.data, &dp)?;
    let tc = ActTrainConfig {
        steps: a.steps,
        batch_size: a.batch_size,
        seed: a.seed,
        checkpoint_every: a.checkpoint_every,
        init: a.init.clone(),
        backbone_from: a.backbone_from.clone(),
        freeze_backbone: a.freeze_backbone,
        lr_schedule: match a.lr_schedule {
            LrScheduleArg::Constant => LrSchedule::Constant,
            LrScheduleArg::Cosine => LrSchedule::Cosine {
                warmup_steps: a.lr_warmup,
            },
        },
        ema_max_decay: a.ema,
    };
    let bar = Bar::for_cli(cli, "train act", a.steps);
    let report = train_act(&data, config, &tc, &a.out, &mut |step, l1, kld| {
        let figure = (step % 10 == 0).then(|| format!("l1 {l1:.4} kld {kld:.4}"));
        bar.set(step as u64, figure);
    })?;
    bar.finish();
    let mut out = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(out, "{}", serde_json::to_string(&report)?)?,
        Format::Text if !cli.quiet => writeln!(
            out,
            "trained {} steps (now at {}) in {:.0} s, final l1 {} kld {} -> {}",
            report.steps_run,
            report.step,
            report.seconds,
            loss_text(report.final_l1),
            loss_text(report.final_kld),
            a.out.display()
        )?,
        Format::Text => {}
    }
    let converted = report
        .backbone_relative_error
        .zip(a.backbone_from.as_deref());
    if let (Some((e, dp)), Format::Text, false) = (converted, cli.format, cli.quiet) {
        let dp = dp.display();
        writeln!(
            out,
            "backbone from {dp}: relative error {e:.4} on 64 training frames"
        )?;
    }
    Ok(())
}

/// `mte train encoder`
pub fn encoder(cli: &Cli, a: &TrainEncoderArgs) -> Result<()> {
    let mut config = preset_config(
        a.preset,
        ObsKind::Image,
        BackboneArg::Unet,
        false,
        a.config.as_deref(),
    )?;
    let first = a.data.first().context("--data: at least one dataset")?;
    fit_to_data(&mut config, first)?;
    let data = train_data::load_many(&a.data, &config, train_data::Extra { keypoints: true })?;
    let pc = EncoderPretrainConfig {
        steps: a.steps,
        batch_size: a.batch_size,
        lr: a.lr,
        seed: a.seed,
        ..EncoderPretrainConfig::default()
    };
    let bar = Bar::for_cli(cli, "train", a.steps);
    let (weights, report) =
        pretrain_encoder(&config, &pc, &data, &Device::Cpu, &|step, loss, lr| {
            let figure = (step % 10 == 0).then(|| format!("loss {loss:.4} lr {lr:.2e}"));
            bar.set(step as u64, figure);
        })?;
    bar.finish();
    let path = save_encoder(&a.out, &weights, &pc, &report)?;
    let mut out = std::io::stdout().lock();
    match cli.format {
        Format::Json => writeln!(out, "{}", serde_json::to_string(&report)?)?,
        Format::Text => {
            if !cli.quiet {
                let mm = |v: Option<f32>| v.map_or("-".to_string(), |v| format!("{v:.1}"));
                writeln!(
                    out,
                    "pre-trained {} steps in {:.0} s: loss {:.4} -> {:.4}; held-out keypoint \
                     error {} (predicting the mean: {}) -> {}",
                    report.steps,
                    report.seconds,
                    report.first_loss,
                    report.final_loss,
                    mm(report.heldout_mae),
                    mm(report.heldout_mae_of_mean),
                    path.display()
                )?;
            }
        }
    }
    Ok(())
}

/// The arrays a policy of `config` trains (or is attacked / fine-tuned) on, from an
/// `mte data generate` dataset.
pub fn load_train_data(dir: &std::path::Path, config: &DiffusionConfig) -> Result<TrainData> {
    Ok(train_data::load(dir, config, train_data::Extra::default())?)
}

/// A loss for the terminal, four decimals; `-` when the call ran no step.
fn loss_text(loss: Option<f32>) -> String {
    loss.map_or_else(|| "-".to_owned(), |l| format!("{l:.4}"))
}
