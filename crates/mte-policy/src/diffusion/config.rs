//! Diffusion Policy configuration in LeRobot's `config.json` schema (field names and meanings
//! are LeRobot's `DiffusionConfig`), with the two presets and `validate()`.

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{PolicyError, config_err};
use crate::normalize::NormMode;
use crate::scheduler::{BetaSchedule, PredictionType, SchedulerConfig, SchedulerKind};

/// Feature kinds in LeRobot's `input_features` / `output_features`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum FeatureType {
    /// Camera image (C, H, W).
    Visual,
    /// Robot state (agent position on PushT).
    State,
    /// Environment state (block keypoints on PushT).
    Env,
    /// Action.
    Action,
}

/// One feature: kind and shape.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PolicyFeature {
    /// Kind.
    #[serde(rename = "type")]
    pub kind: FeatureType,
    /// Shape (images: [C, H, W]).
    pub shape: Vec<usize>,
}

/// LeRobot's `DiffusionConfig` fields that determine the network and its use.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct DiffusionConfig {
    /// Always "diffusion" (LeRobot's registry key).
    #[serde(rename = "type")]
    pub kind: String,
    /// Observation steps T_o.
    pub n_obs_steps: usize,
    /// Prediction horizon T_p; divisible by 2^len(down_dims).
    pub horizon: usize,
    /// Actions executed per query in open-loop use.
    pub n_action_steps: usize,
    /// Inputs by name (`observation.state`, `observation.environment_state`, `observation.image`).
    pub input_features: BTreeMap<String, PolicyFeature>,
    /// Outputs by name (`action`).
    pub output_features: BTreeMap<String, PolicyFeature>,
    /// Normalisation per feature kind (keys VISUAL, STATE, ENV, ACTION).
    pub normalization_mapping: BTreeMap<String, NormMode>,
    /// Vision backbone (only "resnet18").
    pub vision_backbone: String,
    /// mte extension: width of the backbone's stem, doubled at each of its four layers
    /// (torchvision's ResNet-18: 64, i.e. 64/128/256/512). Narrower backbones keep the same
    /// topology and key names; multiple of 16 (GroupNorm uses C / 16 groups). Not written to
    /// `config.json` at 64, so the paper preset stays LeRobot's schema.
    #[serde(skip_serializing_if = "is_resnet18_width")]
    pub vision_backbone_width: usize,
    /// Crop (H, W) of images: random in training, centre at evaluation.
    pub crop_shape: Option<[usize; 2]>,
    /// Random crop while training.
    pub crop_is_random: bool,
    /// Pretrained weights (must be null: none can be downloaded here, and GroupNorm replaces them).
    pub pretrained_backbone_weights: Option<String>,
    /// BatchNorm replaced by GroupNorm(C / 16).
    pub use_group_norm: bool,
    /// Spatial-softmax keypoints.
    pub spatial_softmax_num_keypoints: usize,
    /// One encoder per camera (changes the key prefix).
    pub use_separate_rgb_encoder_per_camera: bool,
    /// U-Net channel widths.
    pub down_dims: Vec<usize>,
    /// U-Net convolution kernel size.
    pub kernel_size: usize,
    /// GroupNorm groups in the U-Net.
    pub n_groups: usize,
    /// Timestep embedding width.
    pub diffusion_step_embed_dim: usize,
    /// FiLM with scale and bias (else bias only).
    pub use_film_scale_modulation: bool,
    /// "DDPM" or "DDIM".
    pub noise_scheduler_type: String,
    /// Diffusion steps in training.
    pub num_train_timesteps: usize,
    /// Beta schedule.
    pub beta_schedule: String,
    /// First beta (linear schedules).
    pub beta_start: f64,
    /// Last beta (linear schedules).
    pub beta_end: f64,
    /// "epsilon" or "sample".
    pub prediction_type: String,
    /// Clip the predicted x0.
    pub clip_sample: bool,
    /// Clip range.
    pub clip_sample_range: f64,
    /// Denoising steps at inference (None: num_train_timesteps).
    pub num_inference_steps: Option<usize>,
    /// Mask the loss on padded actions.
    pub do_mask_loss_for_padding: bool,
    /// Learning rate.
    pub optimizer_lr: f64,
    /// mte extension: the noise network is Diffusion Policy's `TransformerForDiffusion` with
    /// these settings instead of the U-Net (absent: the U-Net, LeRobot's only choice; not
    /// written then, so U-Net configs stay LeRobot's schema).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub transformer: Option<TransformerConfig>,
    /// Adam betas.
    pub optimizer_betas: [f64; 2],
    /// Adam epsilon.
    pub optimizer_eps: f64,
    /// AdamW weight decay.
    pub optimizer_weight_decay: f64,
    /// Learning-rate schedule name.
    pub scheduler_name: String,
    /// Warm-up steps.
    pub scheduler_warmup_steps: usize,
}

fn features(image: bool, env_state: bool) -> BTreeMap<String, PolicyFeature> {
    let mut m = BTreeMap::new();
    m.insert(
        "observation.state".into(),
        PolicyFeature {
            kind: FeatureType::State,
            shape: vec![2],
        },
    );
    if image {
        m.insert(
            "observation.image".into(),
            PolicyFeature {
                kind: FeatureType::Visual,
                shape: vec![3, 96, 96],
            },
        );
    }
    if env_state {
        m.insert(
            "observation.environment_state".into(),
            PolicyFeature {
                kind: FeatureType::Env,
                shape: vec![16],
            },
        );
    }
    m
}

impl Default for DiffusionConfig {
    fn default() -> Self {
        Self::paper()
    }
}

/// Which observation a preset conditions on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ObsKind {
    /// 96 x 96 camera frame + agent position (LeRobot's `diffusion_pusht`).
    Image,
    /// 16 block keypoints + agent position.
    Keypoints,
}

/// The wrist camera's feature name (LeRobot's `observation.images.<camera>` form; the
/// name `mte data generate --obs pixels,wrist` writes and mte's trainers use).
pub const WRIST_CAMERA: &str = "observation.images.wrist";

/// Every feature name a loaded checkpoint may give its wrist (eye-in-hand) camera, fed
/// from `Observation::wrist_image`: mte's [`WRIST_CAMERA`]; `wrist_image`, the name
/// LeRobot's LIBERO datasets use; and robomimic's observation key
/// `robot0_eye_in_hand_image` and robosuite's camera name `robot0_eye_in_hand`, the names
/// a policy trained on robomimic data (as Diffusion Policy trains it) carries. Any other
/// camera is a scene camera.
pub const WRIST_CAMERA_NAMES: [&str; 4] = [
    WRIST_CAMERA,
    "observation.images.wrist_image",
    "observation.images.robot0_eye_in_hand_image",
    "observation.images.robot0_eye_in_hand",
];

/// Whether the feature `name` is a wrist camera (one of [`WRIST_CAMERA_NAMES`]).
pub fn is_wrist_camera(name: &str) -> bool {
    WRIST_CAMERA_NAMES.contains(&name)
}

/// torchvision ResNet-18's stem width.
pub const RESNET18_WIDTH: usize = 64;

/// Diffusion Policy's `TransformerForDiffusion` settings (its field names; time and
/// observations as conditioning tokens, as its image and low-dim PushT configs use).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransformerConfig {
    /// Decoder layers.
    pub n_layer: usize,
    /// Attention heads; divides `n_emb`.
    pub n_head: usize,
    /// Token width (feed-forward: 4 x).
    pub n_emb: usize,
    /// Dropout on the token embeddings.
    pub p_drop_emb: f64,
    /// Dropout in attention and feed-forward blocks.
    pub p_drop_attn: f64,
    /// Causal action self-attention, and action token `t` sees condition token `s` only
    /// when `t >= s - 1` (the time token always).
    pub causal_attn: bool,
    /// Transformer-encoder layers over the condition tokens (0: an MLP, Linear 4x, Mish,
    /// Linear).
    pub n_cond_layers: usize,
}

impl TransformerConfig {
    /// Diffusion Policy's hybrid image config (PushT's T_p = 10 experiment): 8 layers, 4
    /// heads, width 256, attention dropout 0.3, causal.
    pub fn paper() -> Self {
        Self {
            n_layer: 8,
            n_head: 4,
            n_emb: 256,
            p_drop_emb: 0.0,
            p_drop_attn: 0.3,
            causal_attn: true,
            n_cond_layers: 0,
        }
    }

    /// The `cpu` preset: 4 layers of width 64, 4 heads.
    pub fn cpu() -> Self {
        Self {
            n_layer: 4,
            n_emb: 64,
            ..Self::paper()
        }
    }

    fn validate(&self) -> Result<(), PolicyError> {
        for (name, v) in [
            ("transformer.n_layer", self.n_layer),
            ("transformer.n_head", self.n_head),
        ] {
            if v == 0 {
                return Err(config_err(name, v, ">= 1"));
            }
        }
        if self.n_emb == 0 || !self.n_emb.is_multiple_of(2 * self.n_head) {
            return Err(config_err(
                "transformer.n_emb",
                self.n_emb,
                format!("a positive multiple of 2 n_head = {}", 2 * self.n_head),
            ));
        }
        for (name, p) in [
            ("transformer.p_drop_emb", self.p_drop_emb),
            ("transformer.p_drop_attn", self.p_drop_attn),
        ] {
            if !(0.0..1.0).contains(&p) {
                return Err(config_err(name, p, "a probability in [0, 1)"));
            }
        }
        Ok(())
    }
}

/// The dimension of the `action` output feature (shape `[d]`), shared by every policy
/// config.
pub(crate) fn action_dim_of(
    outputs: &BTreeMap<String, PolicyFeature>,
) -> Result<usize, PolicyError> {
    match outputs.get("action") {
        Some(f) if f.shape.len() == 1 && f.shape[0] > 0 => Ok(f.shape[0]),
        other => Err(config_err(
            "output_features",
            other,
            "an `action` feature of shape [d]",
        )),
    }
}

/// mte's camera rule, for every policy class: one scene camera of any name (fed from
/// `Observation::image`), or a scene camera and a wrist camera (one of
/// [`WRIST_CAMERA_NAMES`]); every camera of one shape (the bridge renders the wrist camera
/// at the scene camera's size; LeRobot's Diffusion Policy requires it too). `cameras` are
/// `(name, shape)` in mte's order.
pub(crate) fn check_cameras(cameras: &[(&str, &[usize])]) -> Result<(), PolicyError> {
    let names: Vec<&str> = cameras.iter().map(|(n, _)| *n).collect();
    if names.len() == 1 && is_wrist_camera(names[0]) {
        return Err(config_err(
            "input_features",
            &names,
            "a scene camera beside the wrist camera",
        ));
    }
    let wrist_pair = names.len() == 2 && !is_wrist_camera(names[0]) && is_wrist_camera(names[1]);
    if names.len() > 1 && !wrist_pair {
        return Err(config_err(
            "input_features",
            &names,
            format!(
                "one camera, or a scene camera and one wrist camera (named one of {WRIST_CAMERA_NAMES:?})"
            ),
        ));
    }
    if let Some(&(first, shape)) = cameras.first()
        && let Some((name, other)) = cameras.iter().find(|(_, s)| *s != shape)
    {
        return Err(config_err(
            "input_features",
            format!("{name}: {other:?}"),
            format!("every camera of one shape ({shape:?}, as {first})"),
        ));
    }
    Ok(())
}

/// The sort key of mte's camera order: the wrist camera last, the others (a stable sort)
/// in name order.
pub(crate) fn wrist_last(name: &str) -> bool {
    is_wrist_camera(name)
}

/// Refuses a `config.json` at `path` whose `input_features` list the `cameras` in another
/// order than mte feeds them (LeRobot concatenates camera features, or tokens, in the
/// file's order; serde's maps forget it). A file without `input_features` passes.
pub(crate) fn check_camera_order<S: AsRef<str>>(
    path: &Path,
    cameras: &[S],
) -> Result<(), PolicyError> {
    let listed: FeatureOrder = read_json(path)?;
    let ours: Vec<&str> = cameras.iter().map(AsRef::as_ref).collect();
    let visual: Vec<&str> = listed
        .input_features
        .0
        .iter()
        .map(String::as_str)
        .filter(|n| ours.contains(n))
        .collect();
    if !listed.input_features.0.is_empty() && visual != ours {
        return Err(config_err(
            "input_features",
            visual,
            format!("the cameras listed in mte's order {ours:?}"),
        ));
    }
    Ok(())
}

/// The order in which a `config.json` lists its `input_features` (serde's maps forget it;
/// LeRobot's camera features follow it).
#[derive(Deserialize)]
#[serde(default)]
#[derive(Default)]
struct FeatureOrder {
    input_features: KeyOrder,
}

/// A JSON object's keys in file order.
#[derive(Default)]
struct KeyOrder(Vec<String>);

impl<'de> Deserialize<'de> for KeyOrder {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Keys;
        impl<'de> serde::de::Visitor<'de> for Keys {
            type Value = KeyOrder;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("an object")
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(
                self,
                mut m: A,
            ) -> Result<KeyOrder, A::Error> {
                let mut keys = Vec::new();
                while let Some((k, _)) = m.next_entry::<String, serde::de::IgnoredAny>()? {
                    keys.push(k);
                }
                Ok(KeyOrder(keys))
            }
        }
        d.deserialize_map(Keys)
    }
}

/// A JSON file parsed as `T`, with the path in every error.
pub(crate) fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, PolicyError> {
    let text = std::fs::read_to_string(path).map_err(|source| PolicyError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    serde_json::from_str(&text).map_err(|source| PolicyError::Json {
        path: path.to_path_buf(),
        source,
    })
}

pub(crate) fn is_resnet18_width(w: &usize) -> bool {
    *w == RESNET18_WIDTH
}

impl DiffusionConfig {
    /// The published PushT configuration (LeRobot `diffusion_pusht`, peer-facts 3.1):
    /// image + state, down_dims [512, 1024, 2048], horizon 16, 2 observation steps, 8 executed,
    /// 100 DDPM steps.
    pub fn paper() -> Self {
        let mut norm = BTreeMap::new();
        norm.insert("VISUAL".into(), NormMode::MeanStd);
        norm.insert("STATE".into(), NormMode::MinMax);
        norm.insert("ENV".into(), NormMode::MinMax);
        norm.insert("ACTION".into(), NormMode::MinMax);
        let mut out = BTreeMap::new();
        out.insert(
            "action".into(),
            PolicyFeature {
                kind: FeatureType::Action,
                shape: vec![2],
            },
        );
        DiffusionConfig {
            kind: "diffusion".into(),
            n_obs_steps: 2,
            horizon: 16,
            n_action_steps: 8,
            input_features: features(true, false),
            output_features: out,
            normalization_mapping: norm,
            vision_backbone: "resnet18".into(),
            vision_backbone_width: RESNET18_WIDTH,
            crop_shape: Some([84, 84]),
            crop_is_random: true,
            pretrained_backbone_weights: None,
            use_group_norm: true,
            spatial_softmax_num_keypoints: 32,
            use_separate_rgb_encoder_per_camera: false,
            down_dims: vec![512, 1024, 2048],
            kernel_size: 5,
            n_groups: 8,
            diffusion_step_embed_dim: 128,
            use_film_scale_modulation: true,
            noise_scheduler_type: "DDPM".into(),
            num_train_timesteps: 100,
            beta_schedule: "squaredcos_cap_v2".into(),
            beta_start: 1e-4,
            beta_end: 0.02,
            prediction_type: "epsilon".into(),
            clip_sample: true,
            clip_sample_range: 1.0,
            num_inference_steps: None,
            do_mask_loss_for_padding: false,
            optimizer_lr: 1e-4,
            transformer: None,
            optimizer_betas: [0.95, 0.999],
            optimizer_eps: 1e-8,
            optimizer_weight_decay: 1e-6,
            scheduler_name: "cosine".into(),
            scheduler_warmup_steps: 500,
        }
    }

    /// The small CPU preset: same topology, narrow U-Net (down_dims [32, 64, 128], embedding
    /// 32), quarter-width ResNet-18 for images, 16 DDIM inference steps: ~0.23 s per batch-64 training step on 2 cores (measured),
    /// so ~15k steps an hour. `obs` picks the conditioning.
    pub fn cpu(obs: ObsKind) -> Self {
        DiffusionConfig {
            input_features: features(obs == ObsKind::Image, obs == ObsKind::Keypoints),
            // ResNet-18's topology at a quarter of its width (16/32/64/128): ~1/16 of its
            // FLOPs, so the image encoder trains on 2 cores.
            vision_backbone_width: 16,
            down_dims: vec![32, 64, 128],
            diffusion_step_embed_dim: 32,
            noise_scheduler_type: "DDIM".into(),
            num_inference_steps: Some(16),
            optimizer_lr: 3e-4,
            scheduler_warmup_steps: 200,
            ..Self::paper()
        }
    }

    /// Read a config file (LeRobot's `config.json` or any subset of its fields: missing fields
    /// take the paper preset's values).
    pub fn from_file(path: &Path) -> Result<Self, PolicyError> {
        let c: DiffusionConfig = read_json(path)?;
        c.validate()?;
        check_camera_order(path, &c.cameras())?;
        Ok(c)
    }

    /// Override fields of `self` with those present in the JSON object `patch`.
    pub fn with_overrides(&self, patch: &serde_json::Value) -> Result<Self, PolicyError> {
        let c: DiffusionConfig = crate::overrides::apply(self, patch)?;
        c.validate()?;
        Ok(c)
    }

    /// The action dimension.
    pub fn action_dim(&self) -> Result<usize, PolicyError> {
        action_dim_of(&self.output_features)
    }

    /// Dimension of a vector input by kind (None if absent).
    pub fn vector_dim(&self, kind: FeatureType) -> Option<usize> {
        self.input_features
            .values()
            .find(|f| f.kind == kind)
            .and_then(|f| f.shape.first().copied())
    }

    /// The image feature, if any: (C, H, W) (every camera has it: `validate()` checks).
    pub fn image_shape(&self) -> Option<[usize; 3]> {
        self.input_features
            .values()
            .find(|f| f.kind == FeatureType::Visual)
            .and_then(|f| (f.shape.len() == 3).then(|| [f.shape[0], f.shape[1], f.shape[2]]))
    }

    /// The cameras (VISUAL features) in the order their features are concatenated in the
    /// conditioning (LeRobot's `image_features` order): the scene camera, fed from
    /// `Observation::image` whatever its name, then the wrist camera (fed from
    /// `Observation::wrist_image`; named one of [`WRIST_CAMERA_NAMES`]) when the policy
    /// has it.
    pub fn cameras(&self) -> Vec<&str> {
        let mut names: Vec<&str> = self
            .input_features
            .iter()
            .filter(|(_, f)| f.kind == FeatureType::Visual)
            .map(|(n, _)| n.as_str())
            .collect();
        names.sort_by_key(|n| wrist_last(n));
        names
    }

    /// Whether the policy reads a wrist camera (a VISUAL feature named one of
    /// [`WRIST_CAMERA_NAMES`]).
    pub fn has_wrist_camera(&self) -> bool {
        self.input_features
            .iter()
            .any(|(n, f)| f.kind == FeatureType::Visual && is_wrist_camera(n))
    }

    /// This config with the wrist camera added beside the scene camera (same shape), or
    /// unchanged if it has no camera. The caller validates.
    pub fn with_wrist_camera(mut self) -> Self {
        if let Some(shape) = self.image_shape() {
            self.input_features.insert(
                WRIST_CAMERA.into(),
                PolicyFeature {
                    kind: FeatureType::Visual,
                    shape: shape.to_vec(),
                },
            );
        }
        self
    }

    /// Inference steps in use.
    pub fn inference_steps(&self) -> usize {
        self.num_inference_steps.unwrap_or(self.num_train_timesteps)
    }

    /// The noise scheduler this config describes.
    pub fn scheduler_config(&self) -> Result<SchedulerConfig, PolicyError> {
        let kind = match self.noise_scheduler_type.as_str() {
            "DDPM" => SchedulerKind::Ddpm,
            "DDIM" => SchedulerKind::Ddim,
            other => {
                return Err(config_err(
                    "noise_scheduler_type",
                    other,
                    "\"DDPM\" or \"DDIM\"",
                ));
            }
        };
        let beta_schedule = match self.beta_schedule.as_str() {
            "squaredcos_cap_v2" => BetaSchedule::SquaredcosCapV2,
            "linear" => BetaSchedule::Linear,
            "scaled_linear" => BetaSchedule::ScaledLinear,
            other => {
                return Err(config_err(
                    "beta_schedule",
                    other,
                    "squaredcos_cap_v2, linear or scaled_linear",
                ));
            }
        };
        let prediction_type = match self.prediction_type.as_str() {
            "epsilon" => PredictionType::Epsilon,
            "sample" => PredictionType::Sample,
            other => {
                return Err(config_err(
                    "prediction_type",
                    other,
                    "\"epsilon\" or \"sample\"",
                ));
            }
        };
        let base = SchedulerConfig::lerobot_pusht();
        Ok(SchedulerConfig {
            kind,
            num_train_timesteps: self.num_train_timesteps,
            beta_start: self.beta_start,
            beta_end: self.beta_end,
            beta_schedule,
            prediction_type,
            clip_sample: self.clip_sample,
            clip_sample_range: self.clip_sample_range,
            ..base
        })
    }

    /// Upper bounds on every size, checked before anything is allocated, so that a hostile
    /// or mistyped `config.json` (`"horizon": 1000000000`) is a typed error, not an abort
    /// out of memory. Each bound leaves 10x or more room over the largest published
    /// configuration (Diffusion Policy: horizon 16, down_dims up to 2048, 100 train steps;
    /// ACT: chunk 100).
    fn validate_sizes(&self) -> Result<(), PolicyError> {
        let at_most = |field: &'static str, value: usize, max: usize| {
            if value > max {
                Err(config_err(field, value, format!("at most {max}")))
            } else {
                Ok(())
            }
        };
        at_most("horizon", self.horizon, 1024)?;
        at_most("n_obs_steps", self.n_obs_steps, 64)?;
        at_most("n_action_steps", self.n_action_steps, 1024)?;
        at_most("down_dims (length)", self.down_dims.len(), 6)?;
        for &d in &self.down_dims {
            at_most("down_dims", d, 16_384)?;
        }
        at_most("kernel_size", self.kernel_size, 63)?;
        at_most(
            "diffusion_step_embed_dim",
            self.diffusion_step_embed_dim,
            16_384,
        )?;
        at_most(
            "spatial_softmax_num_keypoints",
            self.spatial_softmax_num_keypoints,
            4096,
        )?;
        at_most("vision_backbone_width", self.vision_backbone_width, 1024)?;
        at_most("num_train_timesteps", self.num_train_timesteps, 100_000)?;
        for f in self
            .input_features
            .values()
            .chain(self.output_features.values())
        {
            at_most("feature shape (rank)", f.shape.len(), 3)?;
            for &s in &f.shape {
                at_most("feature shape", s, 4096)?;
            }
        }
        Ok(())
    }

    /// The horizon against the noise network and `n_action_steps` against the horizon.
    fn validate_horizon(&self) -> Result<(), PolicyError> {
        // The U-Net: LeRobot's rule (stricter than the network needs, which is
        // 2^(len - 1)); kept so that every config we write loads in LeRobot.
        let (factor, why) = if let Some(t) = &self.transformer {
            t.validate()?;
            (1, "the transformer takes any horizon")
        } else {
            (1usize << self.down_dims.len(), "2^len(down_dims)")
        };
        if self.horizon == 0 || !self.horizon.is_multiple_of(factor) {
            return Err(config_err(
                "horizon",
                self.horizon,
                format!("a positive multiple of {factor} ({why})"),
            ));
        }
        if self.n_action_steps == 0 || self.n_action_steps + self.n_obs_steps - 1 > self.horizon {
            return Err(config_err(
                "n_action_steps",
                self.n_action_steps,
                format!(
                    "1..={} (horizon - n_obs_steps + 1)",
                    self.horizon + 1 - self.n_obs_steps.min(self.horizon + 1)
                ),
            ));
        }
        Ok(())
    }

    /// The image feature and its encoder settings, when the policy reads images.
    fn validate_image(&self) -> Result<(), PolicyError> {
        let Some([c, h, w]) = self.image_shape() else {
            return Ok(());
        };
        let cameras: Vec<(&str, &[usize])> = self
            .cameras()
            .into_iter()
            .map(|n| (n, self.input_features[n].shape.as_slice()))
            .collect();
        check_cameras(&cameras)?;
        if c != 3 {
            return Err(config_err("input_features", [c, h, w], "3-channel images"));
        }
        if self.vision_backbone != "resnet18" {
            return Err(config_err(
                "vision_backbone",
                &self.vision_backbone,
                "\"resnet18\"",
            ));
        }
        if self.vision_backbone_width < 16 || !self.vision_backbone_width.is_multiple_of(16) {
            return Err(config_err(
                "vision_backbone_width",
                self.vision_backbone_width,
                "a multiple of 16 (GroupNorm uses C / 16 groups), >= 16",
            ));
        }
        if self.pretrained_backbone_weights.is_some() {
            return Err(config_err(
                "pretrained_backbone_weights",
                &self.pretrained_backbone_weights,
                "null (no weights can be downloaded; GroupNorm would ruin them anyway)",
            ));
        }
        if let Some([ch, cw]) = self.crop_shape
            && (ch > h || cw > w || ch < 32 || cw < 32)
        {
            return Err(config_err(
                "crop_shape",
                [ch, cw],
                format!("within the {h}x{w} image, at least 32x32"),
            ));
        }
        Ok(())
    }

    /// Check every field; errors name the field and what was expected.
    pub fn validate(&self) -> Result<(), PolicyError> {
        if self.kind != "diffusion" {
            return Err(config_err("type", &self.kind, "\"diffusion\""));
        }
        self.validate_sizes()?;
        if self.n_obs_steps == 0 {
            return Err(config_err("n_obs_steps", self.n_obs_steps, ">= 1"));
        }
        if self.down_dims.is_empty() || self.down_dims.contains(&0) {
            return Err(config_err(
                "down_dims",
                &self.down_dims,
                "non-empty, all > 0",
            ));
        }
        self.validate_horizon()?;
        if self.kernel_size.is_multiple_of(2) {
            return Err(config_err("kernel_size", self.kernel_size, "an odd number"));
        }
        if self.n_groups == 0 || self.down_dims.iter().any(|d| d % self.n_groups != 0) {
            return Err(config_err(
                "n_groups",
                self.n_groups,
                "a divisor of every down_dims entry",
            ));
        }
        if !self.down_dims[0].is_multiple_of(8) {
            // The final block's GroupNorm has 8 groups whatever n_groups says (as in LeRobot).
            return Err(config_err(
                "down_dims",
                &self.down_dims,
                "a first width divisible by 8",
            ));
        }
        if self.diffusion_step_embed_dim < 4 || !self.diffusion_step_embed_dim.is_multiple_of(2) {
            return Err(config_err(
                "diffusion_step_embed_dim",
                self.diffusion_step_embed_dim,
                "an even number >= 4",
            ));
        }
        if self.vector_dim(FeatureType::State).is_none() {
            return Err(config_err(
                "input_features",
                self.input_features.keys().collect::<Vec<_>>(),
                "an observation.state feature",
            ));
        }
        if self.image_shape().is_none() && self.vector_dim(FeatureType::Env).is_none() {
            return Err(config_err(
                "input_features",
                self.input_features.keys().collect::<Vec<_>>(),
                "an image or an environment_state feature",
            ));
        }
        self.validate_image()?;
        self.action_dim()?;
        self.scheduler_config()?.validate()?;
        if self.inference_steps() == 0 || self.inference_steps() > self.num_train_timesteps {
            return Err(config_err(
                "num_inference_steps",
                self.num_inference_steps,
                format!("1..={}", self.num_train_timesteps),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_validate() {
        DiffusionConfig::paper().validate().expect("paper");
        DiffusionConfig::cpu(ObsKind::Keypoints)
            .validate()
            .expect("cpu keypoints");
        DiffusionConfig::cpu(ObsKind::Image)
            .validate()
            .expect("cpu image");
    }

    #[test]
    fn errors_name_the_field() {
        let bad = DiffusionConfig {
            horizon: 12,
            ..DiffusionConfig::paper()
        };
        let e = bad
            .validate()
            .expect_err("12 is not a multiple of 8")
            .to_string();
        assert!(e.contains("horizon") && e.contains("multiple of 8"), "{e}");
        let e = DiffusionConfig::paper()
            .with_overrides(&serde_json::json!({"n_groups": 7}))
            .expect_err("7 does not divide 512")
            .to_string();
        assert!(e.contains("n_groups"), "{e}");
        let ok = DiffusionConfig::paper()
            .with_overrides(&serde_json::json!({"down_dims": [32, 64]}))
            .expect("valid override");
        assert_eq!(ok.down_dims, vec![32, 64]);
    }

    #[test]
    fn an_unknown_override_is_an_error_naming_it() {
        let e = DiffusionConfig::paper()
            .with_overrides(&serde_json::json!({"horizn": 8}))
            .expect_err("a typo is not a field")
            .to_string();
        assert!(e.contains("horizn"), "{e}");
        let e = DiffusionConfig::paper()
            .with_overrides(&serde_json::json!([1, 2]))
            .expect_err("not an object")
            .to_string();
        assert!(e.contains("JSON object"), "{e}");
    }

    #[test]
    fn json_round_trip_keeps_lerobot_names() {
        let c = DiffusionConfig::paper();
        let v = serde_json::to_value(&c).expect("serialise");
        assert_eq!(v["type"], "diffusion");
        assert_eq!(v["input_features"]["observation.image"]["type"], "VISUAL");
        assert_eq!(v["normalization_mapping"]["ACTION"], "MIN_MAX");
        let back: DiffusionConfig = serde_json::from_value(v).expect("parse");
        assert_eq!(back, c);
    }
}
