//! ACT configuration in LeRobot's `config.json` schema (`"type": "act"`; field names and
//! meanings are LeRobot 0.4.4's `ACTConfig`), with the two presets and `validate()`.
//!
//! mte's ACT reads state observations (`observation.state` and, on PushT,
//! `observation.environment_state`) and camera frames (VISUAL features, each `[3, H, W]`,
//! through a ResNet-18 with frozen BatchNorm; cameras in the order of their feature names).

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::config::{
    FeatureType, PolicyFeature, WRIST_CAMERA, action_dim_of, check_cameras, read_json, wrist_last,
};
use crate::error::{PolicyError, config_err};
use crate::normalize::NormMode;

/// LeRobot's `ACTConfig` fields that determine the network and its use.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ActConfig {
    /// Always "act" (LeRobot's registry key).
    #[serde(rename = "type")]
    pub kind: String,
    /// Observation steps. LeRobot's ACT refuses anything but 1. mte extension, for state-only
    /// policies: `k > 1` feeds each state token (and the CVAE encoder's) the state vectors of
    /// the last `k` steps, each normalised, concatenated oldest first; the chunk's row 0 is
    /// then the action at the oldest of those steps, as for Diffusion Policy (`T_o = k`), so
    /// `chunk_size - k + 1` rows are executable. LeRobot cannot load such a checkpoint.
    pub n_obs_steps: usize,
    /// Actions per chunk (T_p).
    pub chunk_size: usize,
    /// Actions executed per query in open-loop use.
    pub n_action_steps: usize,
    /// Inputs by name (`observation.state`, `observation.environment_state`).
    pub input_features: BTreeMap<String, PolicyFeature>,
    /// Outputs by name (`action`).
    pub output_features: BTreeMap<String, PolicyFeature>,
    /// Normalisation per feature kind (keys VISUAL, STATE, ENV, ACTION): LeRobot's default
    /// is MEAN_STD for all.
    pub normalization_mapping: BTreeMap<String, NormMode>,
    /// Vision backbone name (LeRobot: a torchvision ResNet; mte: "resnet18").
    pub vision_backbone: String,
    /// torchvision weights the backbone starts from in LeRobot (e.g.
    /// "ResNet18_Weights.IMAGENET1K_V1"). mte downloads nothing: a loaded checkpoint carries
    /// its backbone, and training starts from torchvision's initialisation or `--init`.
    pub pretrained_backbone_weights: Option<String>,
    /// Dilate layer4 instead of striding it (LeRobot's option; mte: false only).
    pub replace_final_stride_with_dilation: bool,
    /// mte extension: the backbone's stem width (layers `w, 2w, 4w, 8w`); torchvision's
    /// ResNet-18 is 64, which LeRobot always uses. Absent from LeRobot's configs, so 64 on
    /// load; not written at 64, so the paper preset stays LeRobot's schema.
    #[serde(skip_serializing_if = "crate::diffusion::config::is_resnet18_width")]
    pub vision_backbone_width: usize,
    /// Pre-LayerNorm transformer layers (LeRobot and the original: false, post-norm).
    pub pre_norm: bool,
    /// Transformer width.
    pub dim_model: usize,
    /// Attention heads; divides `dim_model`.
    pub n_heads: usize,
    /// Feed-forward width.
    pub dim_feedforward: usize,
    /// Feed-forward activation ("relu", "gelu" or "glu"; mte implements relu and gelu).
    pub feedforward_activation: String,
    /// Transformer encoder layers.
    pub n_encoder_layers: usize,
    /// Transformer decoder layers (LeRobot and the original run 1; see LeRobot's note on the
    /// original's bug).
    pub n_decoder_layers: usize,
    /// Train with the CVAE objective.
    pub use_vae: bool,
    /// Latent size of the CVAE.
    pub latent_dim: usize,
    /// Layers of the CVAE's encoder.
    pub n_vae_encoder_layers: usize,
    /// ACT's temporal ensembling coefficient (null: open loop).
    pub temporal_ensemble_coeff: Option<f64>,
    /// Dropout in training.
    pub dropout: f64,
    /// Weight of the KL term.
    pub kl_weight: f64,
    /// AdamW learning rate.
    pub optimizer_lr: f64,
    /// AdamW learning rate of the backbone's parameters (LeRobot: the same as `optimizer_lr`).
    pub optimizer_lr_backbone: f64,
    /// AdamW weight decay.
    pub optimizer_weight_decay: f64,
}

impl Default for ActConfig {
    fn default() -> Self {
        Self::paper()
    }
}

fn feature(kind: FeatureType, dim: usize) -> PolicyFeature {
    PolicyFeature {
        kind,
        shape: vec![dim],
    }
}

impl ActConfig {
    /// LeRobot 0.4.4's `ACTConfig` defaults (the original ACT: width 512, 8 heads, 4 encoder
    /// layers, 1 decoder layer, chunk 100, latent 32, KL weight 10), on PushT keypoints.
    pub fn paper() -> Self {
        let inputs = [
            (
                "observation.state".to_string(),
                feature(FeatureType::State, 2),
            ),
            (
                "observation.environment_state".to_string(),
                feature(FeatureType::Env, 16),
            ),
        ];
        let norm = ["VISUAL", "STATE", "ENV", "ACTION"].map(|k| (k.to_string(), NormMode::MeanStd));
        ActConfig {
            kind: "act".into(),
            n_obs_steps: 1,
            chunk_size: 100,
            n_action_steps: 100,
            input_features: inputs.into_iter().collect(),
            output_features: [("action".to_string(), feature(FeatureType::Action, 2))]
                .into_iter()
                .collect(),
            normalization_mapping: norm.into_iter().collect(),
            vision_backbone: "resnet18".into(),
            pretrained_backbone_weights: Some("ResNet18_Weights.IMAGENET1K_V1".into()),
            replace_final_stride_with_dilation: false,
            vision_backbone_width: crate::diffusion::config::RESNET18_WIDTH,
            pre_norm: false,
            dim_model: 512,
            n_heads: 8,
            dim_feedforward: 3200,
            feedforward_activation: "relu".into(),
            n_encoder_layers: 4,
            n_decoder_layers: 1,
            use_vae: true,
            latent_dim: 32,
            n_vae_encoder_layers: 4,
            temporal_ensemble_coeff: None,
            dropout: 0.1,
            kl_weight: 10.0,
            optimizer_lr: 1e-5,
            optimizer_lr_backbone: 1e-5,
            optimizer_weight_decay: 1e-4,
        }
    }

    /// The `cpu` preset: the same architecture at width 128 (4 heads, feed-forward 512, 2
    /// encoder and 2 CVAE-encoder layers, chunk 100), trainable on 2 CPU cores; lr 1e-4 (the
    /// paper preset's 1e-5 is tuned for ImageNet-initialised backbones and long runs); with
    /// images, a ResNet-18 at a quarter of torchvision's width (stem 16, as the image
    /// Diffusion Policy's `cpu` preset) starting from torchvision's initialisation.
    pub fn cpu() -> Self {
        ActConfig {
            pretrained_backbone_weights: None,
            vision_backbone_width: 16,
            optimizer_lr_backbone: 1e-4,
            dim_model: 128,
            n_heads: 4,
            dim_feedforward: 512,
            n_encoder_layers: 2,
            n_vae_encoder_layers: 2,
            latent_dim: 16,
            optimizer_lr: 1e-4,
            ..Self::paper()
        }
    }

    /// `self` reading the robot state and one camera `name` of `[3, H, W]` frames instead of
    /// the environment state (PushT's image observation).
    pub fn with_camera(mut self, name: &str, shape: [usize; 3]) -> Self {
        self.input_features
            .retain(|_, f| f.kind != FeatureType::Env && f.kind != FeatureType::Visual);
        self.input_features.insert(
            name.to_string(),
            PolicyFeature {
                kind: FeatureType::Visual,
                shape: shape.to_vec(),
            },
        );
        self
    }

    /// `self` with the wrist camera ([`WRIST_CAMERA`]) beside its scene camera, at the
    /// scene camera's shape; unchanged without a camera. The caller validates.
    pub fn with_wrist_camera(mut self) -> Self {
        let scene = self
            .input_features
            .values()
            .find(|f| f.kind == FeatureType::Visual)
            .cloned();
        if let Some(f) = scene {
            self.input_features.insert(WRIST_CAMERA.to_string(), f);
        }
        self
    }

    /// Override fields of `self` with those present in the JSON object `patch` (LeRobot's
    /// config.json names); an unknown field is an error.
    pub fn with_overrides(&self, patch: &serde_json::Value) -> Result<Self, PolicyError> {
        let c: ActConfig = crate::overrides::apply(self, patch)?;
        c.validate()?;
        Ok(c)
    }

    /// Check every field the network depends on.
    pub fn validate(&self) -> Result<(), PolicyError> {
        if self.kind != "act" {
            return Err(config_err("type", &self.kind, "\"act\""));
        }
        for (name, v) in [
            ("chunk_size", self.chunk_size),
            ("dim_model", self.dim_model),
            ("n_heads", self.n_heads),
            ("dim_feedforward", self.dim_feedforward),
            ("n_encoder_layers", self.n_encoder_layers),
            ("n_decoder_layers", self.n_decoder_layers),
            ("latent_dim", self.latent_dim),
        ] {
            if v == 0 {
                return Err(config_err(name, v, ">= 1"));
            }
        }
        if self.n_obs_steps == 0 || self.n_obs_steps > self.chunk_size {
            return Err(config_err(
                "n_obs_steps",
                self.n_obs_steps,
                format!("1..={} (chunk_size)", self.chunk_size),
            ));
        }
        if self.n_obs_steps > 1 && self.has_images() {
            return Err(config_err(
                "n_obs_steps",
                self.n_obs_steps,
                "1 with a camera (mte's ACT stacks past states, not past frames)",
            ));
        }
        if !self.dim_model.is_multiple_of(self.n_heads) {
            return Err(config_err(
                "n_heads",
                self.n_heads,
                format!("a divisor of dim_model = {}", self.dim_model),
            ));
        }
        if self.n_action_steps == 0 || self.n_action_steps > self.chunk_size {
            return Err(config_err(
                "n_action_steps",
                self.n_action_steps,
                format!("1..={} (chunk_size)", self.chunk_size),
            ));
        }
        if !matches!(self.feedforward_activation.as_str(), "relu" | "gelu") {
            return Err(config_err(
                "feedforward_activation",
                &self.feedforward_activation,
                "\"relu\" or \"gelu\"",
            ));
        }
        if !(0.0..1.0).contains(&self.dropout) {
            return Err(config_err(
                "dropout",
                self.dropout,
                "a probability in [0, 1)",
            ));
        }
        self.validate_images()?;
        if self.env_state_dim().is_none() && self.state_dim().is_none() && !self.has_images() {
            return Err(config_err(
                "input_features",
                self.input_features.keys().collect::<Vec<_>>(),
                "observation.state, observation.environment_state and/or an image",
            ));
        }
        self.action_dim().map(|_| ())
    }

    /// The backbone's fields, and each camera's shape, when there are cameras.
    fn validate_images(&self) -> Result<(), PolicyError> {
        let cameras = self.image_features()?;
        if cameras.is_empty() {
            return Ok(());
        }
        let named: Vec<(&str, &[usize])> = cameras
            .iter()
            .map(|(n, s)| (n.as_str(), s.as_slice()))
            .collect();
        check_cameras(&named)?;
        if self.vision_backbone != "resnet18" {
            return Err(config_err(
                "vision_backbone",
                &self.vision_backbone,
                "\"resnet18\" (the one backbone mte ports)",
            ));
        }
        if self.replace_final_stride_with_dilation {
            return Err(config_err(
                "replace_final_stride_with_dilation",
                true,
                "false (mte's convolutions have no dilation)",
            ));
        }
        if !self.dim_model.is_multiple_of(4) {
            return Err(config_err(
                "dim_model",
                self.dim_model,
                "a multiple of 4 with cameras (the 2-D position embedding pairs sines and cosines of x and y)",
            ));
        }
        if self.vision_backbone_width == 0 {
            return Err(config_err("vision_backbone_width", 0, ">= 1"));
        }
        if !(self.optimizer_lr_backbone.is_finite() && self.optimizer_lr_backbone >= 0.0) {
            return Err(config_err(
                "optimizer_lr_backbone",
                self.optimizer_lr_backbone,
                "a finite rate >= 0",
            ));
        }
        Ok(())
    }

    /// Whether any input is a camera.
    pub fn has_images(&self) -> bool {
        self.input_features
            .values()
            .any(|f| f.kind == FeatureType::Visual)
    }

    /// The cameras `(name, [3, H, W])` in the order their tokens enter the encoder
    /// (LeRobot's: its config's order): the scene camera, fed from `Observation::image`
    /// whatever its name, then the wrist camera (`Observation::wrist_image`; named one of
    /// [`WRIST_CAMERA_NAMES`](crate::config::WRIST_CAMERA_NAMES)).
    ///
    /// # Errors
    /// A camera whose shape is not three channels of at least 1 x 1 px.
    pub fn image_features(&self) -> Result<Vec<(String, [usize; 3])>, PolicyError> {
        let mut cams = self
            .input_features
            .iter()
            .filter(|(_, f)| f.kind == FeatureType::Visual)
            .map(|(name, f)| match f.shape.as_slice() {
                &[3, h, w] if h > 0 && w > 0 => Ok((name.clone(), [3, h, w])),
                other => Err(config_err(
                    "input_features",
                    format!("{name}: {other:?}"),
                    "an RGB image shape [3, H, W]",
                )),
            })
            .collect::<Result<Vec<_>, _>>()?;
        cams.sort_by_key(|(n, _)| wrist_last(n));
        Ok(cams)
    }

    fn dim_of(&self, kind: FeatureType) -> Option<usize> {
        self.input_features
            .values()
            .find(|f| f.kind == kind)
            .and_then(|f| f.shape.first().copied())
    }

    /// Robot state dimension (`observation.state`), if used.
    pub fn state_dim(&self) -> Option<usize> {
        self.dim_of(FeatureType::State)
    }

    /// Environment state dimension (`observation.environment_state`), if used.
    pub fn env_state_dim(&self) -> Option<usize> {
        self.dim_of(FeatureType::Env)
    }

    /// The width of the robot-state token's input: [`Self::state_dim`] per observed step.
    pub fn state_input_dim(&self) -> Option<usize> {
        self.state_dim().map(|d| d * self.n_obs_steps)
    }

    /// The width of the environment-state token's input: [`Self::env_state_dim`] per
    /// observed step.
    pub fn env_state_input_dim(&self) -> Option<usize> {
        self.env_state_dim().map(|d| d * self.n_obs_steps)
    }

    /// The action dimension.
    pub fn action_dim(&self) -> Result<usize, PolicyError> {
        action_dim_of(&self.output_features)
    }

    /// The normalisation of a feature kind; a kind the mapping lacks is left as it is
    /// (LeRobot's rule: IDENTITY).
    pub fn norm_mode(&self, key: &str) -> NormMode {
        self.normalization_mapping
            .get(key)
            .copied()
            .unwrap_or(NormMode::Identity)
    }

    /// Read a config file (LeRobot's `config.json`; missing fields take the paper preset's
    /// values).
    pub fn from_file(path: &Path) -> Result<Self, PolicyError> {
        let c: ActConfig = read_json(path)?;
        c.validate()?;
        let cameras: Vec<String> = c.image_features()?.into_iter().map(|(n, _)| n).collect();
        crate::config::check_camera_order(path, &cameras)?;
        Ok(c)
    }
}

#[cfg(test)]
impl ActConfig {
    /// A tiny keypoint ACT for unit tests: width 16, 2 heads, one encoder and one CVAE
    /// encoder layer, chunk 4, latent 4, no dropout.
    pub(crate) fn tiny() -> Self {
        ActConfig {
            chunk_size: 4,
            n_action_steps: 4,
            dim_model: 16,
            n_heads: 2,
            dim_feedforward: 32,
            n_encoder_layers: 1,
            n_vae_encoder_layers: 1,
            latent_dim: 4,
            dropout: 0.0,
            ..ActConfig::cpu()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Past states stack for a state-only ACT; zero steps, more than a chunk, or history with
    /// a camera are refused by name.
    #[test]
    fn several_observed_steps_are_a_state_only_extension() {
        let two = ActConfig {
            n_obs_steps: 2,
            ..ActConfig::cpu()
        };
        two.validate().expect("two steps of state");
        assert_eq!(two.state_input_dim(), Some(4));
        assert_eq!(two.env_state_input_dim(), Some(32));
        assert_eq!(ActConfig::cpu().env_state_input_dim(), Some(16));
        for bad in [
            ActConfig {
                n_obs_steps: 0,
                ..ActConfig::cpu()
            },
            ActConfig {
                n_obs_steps: ActConfig::cpu().chunk_size + 1,
                ..ActConfig::cpu()
            },
            two.clone().with_camera("observation.image", [3, 32, 32]),
        ] {
            let e = bad.validate().expect_err("refused").to_string();
            assert!(e.contains("n_obs_steps"), "{e}");
        }
    }

    #[test]
    fn presets_validate_and_bad_fields_are_named() {
        ActConfig::paper().validate().expect("paper");
        ActConfig::cpu().validate().expect("cpu");
        let bad = ActConfig {
            n_heads: 3,
            ..ActConfig::cpu()
        };
        assert!(
            bad.validate()
                .expect_err("3 heads")
                .to_string()
                .contains("n_heads")
        );
        let mut img = ActConfig::cpu();
        img.input_features.insert(
            "observation.image".into(),
            PolicyFeature {
                kind: FeatureType::Visual,
                shape: vec![3, 96, 96],
            },
        );
        img.validate().expect("a camera is an input");
        assert_eq!(
            img.image_features().expect("shape"),
            vec![("observation.image".to_string(), [3, 96, 96])]
        );
        for (bad, field) in [
            (
                ActConfig {
                    vision_backbone: "resnet34".into(),
                    ..img.clone()
                },
                "vision_backbone",
            ),
            (
                ActConfig {
                    replace_final_stride_with_dilation: true,
                    ..img.clone()
                },
                "replace_final_stride_with_dilation",
            ),
            (
                ActConfig {
                    vision_backbone_width: 0,
                    ..img.clone()
                },
                "vision_backbone_width",
            ),
        ] {
            let e = bad.validate().expect_err(field).to_string();
            assert!(e.contains(field), "{e}");
        }
        let mut grey = img.clone();
        grey.input_features
            .get_mut("observation.image")
            .expect("camera")
            .shape = vec![1, 96, 96];
        let e = grey.validate().expect_err("one channel").to_string();
        assert!(e.contains("[1, 96, 96]"), "{e}");
        assert_eq!(ActConfig::paper().state_dim(), Some(2));
        assert_eq!(ActConfig::paper().env_state_dim(), Some(16));
    }

    #[test]
    fn overrides_replace_fields_and_reject_unknown_ones() {
        let c = ActConfig::cpu()
            .with_overrides(&serde_json::json!({"chunk_size": 20, "n_action_steps": 20}))
            .expect("valid override");
        assert_eq!((c.chunk_size, c.n_action_steps, c.dim_model), (20, 20, 128));
        let e = ActConfig::cpu()
            .with_overrides(&serde_json::json!({"chunk_sise": 20}))
            .expect_err("a typo is not a field")
            .to_string();
        assert!(e.contains("chunk_sise"), "{e}");
        let e = ActConfig::cpu()
            .with_overrides(&serde_json::json!({"chunk_size": 20}))
            .expect_err("n_action_steps 100 > chunk 20")
            .to_string();
        assert!(e.contains("n_action_steps"), "{e}");
    }
}
