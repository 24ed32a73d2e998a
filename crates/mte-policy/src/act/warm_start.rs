//! A warm start for ACT's camera backbone from a Diffusion Policy image encoder.
//!
//! No ImageNet weights can be had here, and training ACT's ResNet-18 from scratch costs about
//! a second per step on one core. Diffusion Policy's encoder is the same ResNet-18 (at the
//! same width in the `cpu` presets) with GroupNorm in place of BatchNorm, and mte's image
//! Diffusion Policies have trained encoders. This carries one over: the convolutions as
//! they are, each GroupNorm's affine weight and bias into the frozen BatchNorm at its place,
//! and running statistics *calibrated* so that each frozen norm applies the normalisation the
//! GroupNorm applies on average: per sample and group of 16 channels, the mean and variance
//! over the group's channels and positions, averaged over a batch of training frames and
//! given to every channel of the group ([`crate::vision::ResNet18::calibrate_frozen_norms`],
//! layer by layer on the already calibrated layers' outputs). A GroupNorm normalises each
//! frame by its own statistics; the frozen norm by their average, so the two backbones differ
//! where a frame's statistics differ from the average: [`BackboneWarmStart::relative_error`]
//! measures that on held-out frames. The result is an ordinary ACT backbone with BatchNorm
//! statistics, in LeRobot's layout. An mte extension.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;

use crate::error::PolicyError;
use crate::kernels::Products;
use crate::vision::{BackboneNames, BackboneNorm, ResNet18};

/// Where Diffusion Policy keeps its encoder's backbone in a checkpoint.
pub const DIFFUSION_BACKBONE: &str = "diffusion.rgb_encoder.backbone";
/// Channels per group of Diffusion Policy's GroupNorm (`C / 16` groups).
const GROUP: usize = 16;

/// A converted backbone.
#[derive(Clone, Debug)]
pub struct BackboneWarmStart {
    /// ACT's backbone tensors, named below `backbone.` (torchvision's names), norms with
    /// their calibrated `running_mean` and `running_var`.
    pub tensors: HashMap<String, Tensor>,
    /// `|f_act - f_dp| / |f_dp|` (Frobenius norms) of the two backbones' `layer4` feature
    /// maps on the held-out frames.
    pub relative_error: f64,
}

/// ACT's (torchvision's) name of a tensor that Diffusion Policy's `nn.Sequential` names
/// `key` (below the backbone's prefix): `0` conv1, `1` bn1, `4`..`7` layer1..layer4.
fn act_name(key: &str) -> Option<String> {
    let (head, rest) = key.split_once('.')?;
    match head {
        "0" => Some(format!("conv1.{rest}")),
        "1" => Some(format!("bn1.{rest}")),
        "4" | "5" | "6" | "7" => {
            let layer = head.parse::<usize>().ok()? - 3;
            Some(format!("layer{layer}.{rest}"))
        }
        _ => None,
    }
}

/// Whether an ACT backbone tensor name belongs to a norm (its `weight` or `bias`).
fn is_norm(name: &str) -> bool {
    let Some((module, _)) = name.rsplit_once('.') else {
        return false;
    };
    module.ends_with("downsample.1")
        || module
            .rsplit('.')
            .next()
            .is_some_and(|m| m.starts_with("bn"))
}

/// ACT's frozen-BatchNorm backbone at stem width `width` from its tensors (torchvision's
/// names).
fn frozen_backbone(
    width: usize,
    tensors: HashMap<String, Tensor>,
) -> candle_core::Result<ResNet18> {
    ResNet18::new(
        width,
        BackboneNorm::FrozenBatch,
        BackboneNames::Torchvision,
        VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu),
    )
}

/// Converts the GroupNorm backbone of the Diffusion Policy weights at `path` (stem width
/// `width`) into ACT's frozen-BatchNorm backbone, calibrated on the normalised frames
/// `calibration` `(B, 3, H, W)` and checked on `held_out` (normalised as ACT's camera
/// normalisation reads them; mte normalises images with the same dataset statistics for both
/// policies).
///
/// # Errors
/// A missing or misshapen tensor (naming it), a width that is not a multiple of 16, or a
/// compute failure.
pub fn backbone_from_diffusion(
    path: &Path,
    width: usize,
    calibration: &Tensor,
    held_out: &Tensor,
) -> Result<BackboneWarmStart, PolicyError> {
    let dev = Device::Cpu;
    let ck = |why: String| crate::checkpoint::ck(path, why);
    let all = candle_core::safetensors::load(path, &dev)?;
    let prefix = format!("{DIFFUSION_BACKBONE}.");
    let mut act = HashMap::new();
    for (key, t) in &all {
        let Some(rest) = key.strip_prefix(&prefix) else {
            continue;
        };
        let name = act_name(rest).ok_or_else(|| ck(format!("unexpected backbone tensor {key}")))?;
        if is_norm(&name) && name.ends_with(".weight") {
            let module = &name[..name.len() - ".weight".len()];
            let c = t.dim(0)?;
            act.insert(
                format!("{module}.running_mean"),
                Tensor::zeros(c, DType::F32, &dev)?,
            );
            act.insert(
                format!("{module}.running_var"),
                Tensor::ones(c, DType::F32, &dev)?,
            );
        }
        act.insert(name, t.to_dtype(DType::F32)?);
    }
    if act.is_empty() {
        return Err(ck(format!("no tensors under {DIFFUSION_BACKBONE}")));
    }
    let dp = ResNet18::new(
        width,
        BackboneNorm::Group,
        BackboneNames::Sequential,
        VarBuilder::from_tensors(all, DType::F32, &dev).pp(DIFFUSION_BACKBONE),
    )
    .map_err(|e| ck(format!("not a width-{width} ResNet-18 encoder: {e}")))?;
    let mut frozen = frozen_backbone(width, act.clone())?;
    let stats = frozen.calibrate_frozen_norms(calibration, GROUP, BackboneNames::Torchvision)?;
    for (module, s) in stats {
        act.insert(format!("{module}.running_mean"), s.mean);
        act.insert(format!("{module}.running_var"), s.var);
    }
    let reference = dp.forward(held_out, Products::PerSample)?;
    let diff = (frozen.forward(held_out, Products::PerSample)? - &reference)?;
    let norm = |t: &Tensor| -> Result<f64, PolicyError> {
        Ok(f64::from(t.sqr()?.sum_all()?.to_scalar::<f32>()?).sqrt())
    };
    let relative_error = norm(&diff)? / norm(&reference)?.max(f64::MIN_POSITIVE);
    Ok(BackboneWarmStart {
        tensors: act,
        relative_error,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_nn::VarMap;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::StandardNormal;

    #[test]
    fn sequential_names_map_to_torchvision_names() {
        assert_eq!(act_name("0.weight").as_deref(), Some("conv1.weight"));
        assert_eq!(act_name("1.bias").as_deref(), Some("bn1.bias"));
        assert_eq!(
            act_name("5.0.downsample.1.weight").as_deref(),
            Some("layer2.0.downsample.1.weight")
        );
        assert_eq!(
            act_name("7.1.conv2.weight").as_deref(),
            Some("layer4.1.conv2.weight")
        );
        assert_eq!(act_name("8.weight"), None);
        assert!(is_norm("layer1.0.bn2.weight") && is_norm("layer3.0.downsample.1.bias"));
        assert!(is_norm("bn1.weight"));
        assert!(!is_norm("layer3.0.downsample.0.weight") && !is_norm("conv1.weight"));
    }

    /// A random GroupNorm ResNet-18 at width 16, saved as Diffusion Policy names it.
    fn diffusion_backbone(dir: &Path) -> std::path::PathBuf {
        let vm = VarMap::new();
        let vb = crate::init::seeded_var_builder(&vm, 7, DType::F32, &Device::Cpu);
        ResNet18::new(
            16,
            BackboneNorm::Group,
            BackboneNames::Sequential,
            vb.pp(DIFFUSION_BACKBONE),
        )
        .expect("backbone");
        let path = dir.join("model.safetensors");
        vm.save(&path).expect("save");
        path
    }

    /// `n` copies of one random frame, each plus noise of standard deviation `noise`.
    fn frames(seed: u64, n: usize, noise: f32) -> Tensor {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut draw = |len: usize, sd: f32| -> Vec<f32> {
            (0..len)
                .map(|_| sd * rng.sample::<f32, _>(StandardNormal))
                .collect()
        };
        let base = draw(3 * 32 * 32, 1.0);
        let v: Vec<f32> = draw(n * 3 * 32 * 32, noise)
            .iter()
            .enumerate()
            .map(|(i, e)| base[i % base.len()] + e)
            .collect();
        Tensor::from_vec(v, (n, 3, 32, 32), &Device::Cpu).expect("frames")
    }

    /// On frames whose statistics are all alike (here one frame repeated) the average of
    /// the per-frame statistics is each frame's own, so the converted backbone computes what
    /// the GroupNorm one does, up to float rounding; every norm got statistics, equal within
    /// a group of 16 channels and positive. On frames that differ the error grows.
    #[test]
    fn a_groupnorm_backbone_becomes_a_calibrated_frozen_one() {
        let dir = tempfile::tempdir().expect("tmp");
        let path = diffusion_backbone(dir.path());
        let same =
            backbone_from_diffusion(&path, 16, &frames(1, 4, 0.0), &frames(1, 2, 0.0)).expect("ws");
        // f32 through 20 norms and 17 convolutions: ~1e-6 per operation.
        assert!(
            same.relative_error < 1e-4,
            "relative error {}",
            same.relative_error
        );
        let vars = same.tensors["layer3.0.downsample.1.running_var"]
            .to_vec1::<f32>()
            .expect("var");
        assert_eq!(vars.len(), 64);
        assert!(vars.iter().all(|&v| v > 0.0 && v.is_finite()));
        assert!(vars[..16].iter().all(|&v| v == vars[0]));
        assert!(vars[16..32].iter().all(|&v| v == vars[16]));
        let norms = same
            .tensors
            .keys()
            .filter(|k| k.ends_with("running_mean"))
            .count();
        // stem + 8 blocks x 2 + 3 shortcuts
        assert_eq!(norms, 1 + 16 + 3);
        let varied =
            backbone_from_diffusion(&path, 16, &frames(2, 8, 0.3), &frames(3, 4, 0.3)).expect("ws");
        assert!(varied.relative_error > same.relative_error);
    }

    #[test]
    fn identity_statistics_would_not_match() {
        let dir = tempfile::tempdir().expect("tmp");
        let path = diffusion_backbone(dir.path());
        let ws = backbone_from_diffusion(&path, 16, &frames(1, 16, 0.1), &frames(2, 8, 0.1))
            .expect("ws");
        let mut identity = ws.tensors.clone();
        for (k, t) in identity.iter_mut() {
            if k.ends_with("running_mean") {
                *t = t.zeros_like().expect("zeros");
            } else if k.ends_with("running_var") {
                *t = t.ones_like().expect("ones");
            }
        }
        let net = |m: HashMap<String, Tensor>| frozen_backbone(16, m).expect("net");
        let x = frames(3, 4, 0.1);
        let a = net(ws.tensors).forward(&x, Products::PerSample).expect("a");
        let b = net(identity).forward(&x, Products::PerSample).expect("b");
        let d = (a - b)
            .expect("d")
            .abs()
            .expect("abs")
            .max_all()
            .expect("max");
        assert!(d.to_scalar::<f32>().expect("scalar") > 1e-3);
    }

    #[test]
    fn another_width_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().expect("tmp");
        let path = diffusion_backbone(dir.path());
        let err = backbone_from_diffusion(&path, 32, &frames(1, 2, 0.1), &frames(2, 2, 0.1))
            .expect_err("width 32");
        assert!(err.to_string().contains("model.safetensors"), "{err}");
    }
}
