//! ResNet-18 backbones and LeRobot's `DiffusionRgbEncoder`.
//!
//! [`ResNet18`] is torchvision's ResNet-18 without its pooling and classifier, at a chosen
//! width, with one of two normalisations ([`BackboneNorm`]): GroupNorm(C / 16) replacing every
//! BatchNorm (Diffusion Policy's `use_group_norm`) or torchvision's `FrozenBatchNorm2d` (ACT).
//! Its tensors are named as the owning model's state dict names them ([`BackboneNames`]).
//!
//! [`RgbEncoder`] is Diffusion Policy's encoder: centre/random crop, the GroupNorm backbone,
//! spatial softmax with a 1x1 keypoint convolution, then Linear + ReLU. Keys mirror LeRobot's
//! under `diffusion.rgb_encoder.` (`backbone.0` conv1, `backbone.1` norm1, `backbone.4..7`
//! layers 1-4, `pool.nets`, `out`). Input: `(B, 3, H, W)` normalised images; output
//! `(B, 2 * num_keypoints)`.
//!
//! The backbone's width is a parameter (`vision_backbone_width`: 64 is torchvision's
//! ResNet-18, the `cpu` presets use 16). Convolutions, GroupNorm and the stem's max pool run
//! on mte's fused CPU kernels ([`crate::kernels`]), which have fast backward passes; so do
//! the ReLUs (the same bits as candle's).

use crate::kernels::{Conv2d, GroupNorm, max_pool_3x3_s2, relu};
use candle_core::{Module, Result, Tensor};
use candle_nn::{Init, VarBuilder};

use crate::kernels::{Linear, Products};

const GN_EPS: f64 = 1e-5;
/// torchvision's `FrozenBatchNorm2d` default.
const FROZEN_BN_EPS: f32 = 1e-5;

fn conv(
    cin: usize,
    cout: usize,
    k: usize,
    stride: usize,
    pad: usize,
    vb: VarBuilder,
) -> Result<Conv2d> {
    Conv2d::new(cin, cout, k, stride, pad, false, vb)
}

/// The normalisation layers of a [`ResNet18`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackboneNorm {
    /// GroupNorm with C / 16 groups, trained (Diffusion Policy's `use_group_norm`; the width
    /// must be a multiple of 16).
    Group,
    /// torchvision's `FrozenBatchNorm2d`: fixed statistics and affine, never trained (ACT).
    FrozenBatch,
}

/// How a state dict names a [`ResNet18`]'s tensors (below the backbone's prefix).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BackboneNames {
    /// `nn.Sequential(*children[:-2])`, as Diffusion Policy keeps it: stem `0` and `1`,
    /// layers `4` to `7`.
    Sequential,
    /// torchvision's attribute names, as ACT's `IntermediateLayerGetter` keeps them: `conv1`,
    /// `bn1`, `layer1` to `layer4`.
    Torchvision,
}

impl BackboneNames {
    fn stem(self) -> (&'static str, &'static str) {
        match self {
            BackboneNames::Sequential => ("0", "1"),
            BackboneNames::Torchvision => ("conv1", "bn1"),
        }
    }

    /// Layer `i` (0-based).
    fn layer(self, i: usize) -> String {
        match self {
            BackboneNames::Sequential => (4 + i).to_string(),
            BackboneNames::Torchvision => format!("layer{}", i + 1),
        }
    }
}

/// torchvision's `FrozenBatchNorm2d` (eps 1e-5): `x * scale + shift` per channel, with
/// `scale = weight / sqrt(running_var + eps)` and `shift = bias - running_mean * scale`,
/// computed in f32 in torchvision's order. Its four tensors are buffers: the products are
/// detached, so no gradient reaches them and no optimiser moves them. Fresh ones start as the
/// identity statistics (weight 1, bias 0, mean 0, variance 1).
#[derive(Clone, Debug)]
pub struct FrozenBatchNorm {
    weight: Tensor,
    bias: Tensor,
    scale: Tensor,
    shift: Tensor,
}

impl FrozenBatchNorm {
    /// Load (or create) the `weight`, `bias`, `running_mean` and `running_var` of `c` channels.
    pub fn new(c: usize, vb: VarBuilder) -> Result<Self> {
        let get = |name: &str, v: f64| vb.get_with_hints(c, name, Init::Const(v));
        let (weight, bias) = (get("weight", 1.0)?.detach(), get("bias", 0.0)?.detach());
        let (m, v) = (get("running_mean", 0.0)?, get("running_var", 1.0)?);
        let mut n = Self {
            scale: weight.clone(),
            shift: bias.clone(),
            weight,
            bias,
        };
        n.set_statistics(&m, &v)?;
        Ok(n)
    }

    /// Replace the running statistics (`(C,)` each), keeping the affine weight and bias.
    fn set_statistics(&mut self, mean: &Tensor, var: &Tensor) -> Result<()> {
        let inv_std = (var + f64::from(FROZEN_BN_EPS))?.sqrt()?.recip()?;
        self.scale = (&self.weight * inv_std)?.detach();
        self.shift = (&self.bias - (mean * &self.scale)?)?.detach();
        Ok(())
    }

    /// Sets the running statistics from `x` `(B, C, H, W)`, the layer's input, as a
    /// GroupNorm with groups of `group` channels would see it on average: per sample and
    /// group, the mean and (biased) variance over the group's channels and all positions,
    /// averaged over the batch and given to every channel of the group. Returns `(mean, var)`,
    /// `(C,)` each. Used to carry a GroupNorm backbone's weights over to frozen BatchNorm.
    fn calibrate(&mut self, x: &Tensor, group: usize) -> Result<(Tensor, Tensor)> {
        let (b, c, h, w) = x.dims4()?;
        if group == 0 || !c.is_multiple_of(group) {
            candle_core::bail!("{c} channels do not split into groups of {group}");
        }
        let g = x.detach().reshape((b, c / group, group * h * w))?;
        let mean = g.mean_keepdim(2)?;
        let var = g.broadcast_sub(&mean)?.sqr()?.mean(2)?.mean(0)?;
        let mean = mean.squeeze(2)?.mean(0)?;
        let per_channel = |t: Tensor| {
            t.unsqueeze(1)?
                .broadcast_as((c / group, group))?
                .contiguous()?
                .reshape(c)
        };
        let (mean, var) = (per_channel(mean)?, per_channel(var)?);
        self.set_statistics(&mean, &var)?;
        Ok((mean, var))
    }

    /// `(B, C, H, W)` in, the same shape out: one fused pass whose backward pass computes
    /// only the input's gradient (`kernels::frozen_affine`; candle's bits).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        crate::kernels::frozen_affine(x, &self.scale, &self.shift)
    }
}

/// One normalisation layer of a backbone.
#[derive(Clone, Debug)]
enum Norm {
    Group(GroupNorm),
    Frozen(FrozenBatchNorm),
}

impl Norm {
    fn new(kind: BackboneNorm, c: usize, vb: VarBuilder) -> Result<Self> {
        Ok(match kind {
            BackboneNorm::Group => Norm::Group(GroupNorm::new(c / 16, c, GN_EPS, vb)?),
            BackboneNorm::FrozenBatch => Norm::Frozen(FrozenBatchNorm::new(c, vb)?),
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        match self {
            Norm::Group(n) => n.forward(x),
            Norm::Frozen(n) => n.forward(x),
        }
    }

    /// Calibrates a frozen norm on its input `x` (recording its statistics in `stats`), then
    /// applies it; a GroupNorm is only applied.
    fn calibrate(
        &mut self,
        x: &Tensor,
        group: usize,
        stats: &mut Vec<NormStats>,
    ) -> Result<Tensor> {
        if let Norm::Frozen(n) = self {
            let (mean, var) = n.calibrate(x, group)?;
            stats.push(NormStats { mean, var });
        }
        self.forward(x)
    }
}

/// The running statistics a calibration gave one frozen norm, `(C,)` each.
#[derive(Clone, Debug)]
pub struct NormStats {
    /// `running_mean`.
    pub mean: Tensor,
    /// `running_var`.
    pub var: Tensor,
}

/// torchvision's `BasicBlock`.
#[derive(Clone, Debug)]
struct BasicBlock {
    conv1: Conv2d,
    bn1: Norm,
    conv2: Conv2d,
    bn2: Norm,
    downsample: Option<(Conv2d, Norm)>,
}

impl BasicBlock {
    fn new(
        cin: usize,
        cout: usize,
        stride: usize,
        norm: BackboneNorm,
        vb: VarBuilder,
    ) -> Result<Self> {
        let downsample = if stride != 1 || cin != cout {
            Some((
                conv(cin, cout, 1, stride, 0, vb.pp("downsample.0"))?,
                Norm::new(norm, cout, vb.pp("downsample.1"))?,
            ))
        } else {
            None
        };
        Ok(BasicBlock {
            conv1: conv(cin, cout, 3, stride, 1, vb.pp("conv1"))?,
            bn1: Norm::new(norm, cout, vb.pp("bn1"))?,
            conv2: conv(cout, cout, 3, 1, 1, vb.pp("conv2"))?,
            bn2: Norm::new(norm, cout, vb.pp("bn2"))?,
            downsample,
        })
    }

    fn forward(&self, x: &Tensor, products: Products) -> Result<Tensor> {
        let out = relu(&self.bn1.forward(&self.conv1.forward(x, products)?)?)?;
        let out = self.bn2.forward(&self.conv2.forward(&out, products)?)?;
        let id = match &self.downsample {
            Some((c, n)) => n.forward(&c.forward(x, products)?)?,
            None => x.clone(),
        };
        relu(&(out + id)?)
    }

    /// [`Self::forward`], calibrating each frozen norm on its input in the order of
    /// [`BasicBlock::NORMS`].
    fn calibrate(
        &mut self,
        x: &Tensor,
        group: usize,
        stats: &mut Vec<NormStats>,
    ) -> Result<Tensor> {
        let p = Products::Fused;
        let out = relu(
            &self
                .bn1
                .calibrate(&self.conv1.forward(x, p)?, group, stats)?,
        )?;
        let out = self
            .bn2
            .calibrate(&self.conv2.forward(&out, p)?, group, stats)?;
        let id = match &mut self.downsample {
            Some((c, n)) => n.calibrate(&c.forward(x, p)?, group, stats)?,
            None => x.clone(),
        };
        relu(&(out + id)?)
    }

    /// The names of a block's norms, in calibration order.
    const NORMS: [&'static str; 3] = ["bn1", "bn2", "downsample.1"];
}

/// A camera frame as stored (RGB u8, `h x w x 3`, row-major) appended to `out` as a
/// network reads it: `(3, h, w)` channel-major f32 in [0, 1] (`v / 255`).
///
/// # Errors
/// A frame of another length, naming both.
pub fn push_chw(
    px: &[u8],
    h: usize,
    w: usize,
    out: &mut Vec<f32>,
) -> std::result::Result<(), String> {
    if px.len() != 3 * h * w {
        return Err(format!("{} bytes, expected {h}x{w}x3 RGB", px.len()));
    }
    let start = out.len();
    out.resize(start + 3 * h * w, 0.0);
    let chw = &mut out[start..];
    for (i, rgb) in px.chunks_exact(3).enumerate() {
        for (c, &v) in rgb.iter().enumerate() {
            chw[c * h * w + i] = f32::from(v) / 255.0;
        }
    }
    Ok(())
}

/// The camera frames of observation `o` that a policy reads, appended to `out` as
/// [`push_chw`] does, in mte's camera order: the scene camera's (`image`), then, when
/// `wrist`, the wrist camera's, each `h x w`.
///
/// # Errors
/// A missing or misshapen frame, named by its camera.
pub fn push_camera_frames(
    o: &crate::policy::Observation,
    wrist: bool,
    h: usize,
    w: usize,
    out: &mut Vec<f32>,
) -> std::result::Result<(), crate::error::PolicyError> {
    let scene = ("observation.image", &o.image);
    let wrist = wrist.then_some((crate::config::WRIST_CAMERA, &o.wrist_image));
    for (name, px) in std::iter::once(scene).chain(wrist) {
        push_chw(px.as_deref().unwrap_or_default(), h, w, out)
            .map_err(|reason| crate::error::PolicyError::Input { name, reason })?;
    }
    Ok(())
}

/// Rows `(R, …)` whose first dimension cycles through `n` cameras (`(b n)`, as
/// [`push_camera_frames`] lays them out) as one `(R / n, …)` tensor per camera; one camera:
/// the rows themselves.
///
/// # Errors
/// `R` not a multiple of `n`.
pub fn split_cameras(
    rows: &Tensor,
    n: usize,
) -> std::result::Result<Vec<Tensor>, crate::error::PolicyError> {
    if n <= 1 {
        return Ok(vec![rows.clone()]);
    }
    let dims = rows.dims();
    if dims.first().is_none_or(|r| !r.is_multiple_of(n)) {
        return Err(crate::error::config_err(
            "image",
            dims,
            format!("rows in multiples of the {n} cameras"),
        ));
    }
    let mut shape = vec![dims[0] / n, n];
    shape.extend_from_slice(&dims[1..]);
    let by_camera = rows.reshape(shape)?;
    (0..n)
        .map(|i| Ok(by_camera.narrow(1, i, 1)?.squeeze(1)?))
        .collect()
}

/// torchvision's ResNet-18 up to `layer4` (no pooling, no classifier): a `(B, 3, H, W)`
/// image in, the `(B, 8 w0, H / 32, W / 32)` feature map out (sides rounded up at each
/// stride-2 stage).
#[derive(Clone, Debug)]
pub struct ResNet18 {
    conv1: Conv2d,
    bn1: Norm,
    layers: Vec<Vec<BasicBlock>>,
    out_channels: usize,
}

impl ResNet18 {
    /// Build/load at stem width `w0` (layers `w0, 2 w0, 4 w0, 8 w0`; torchvision's is 64)
    /// with `norm`, its tensors named by `names` under `vb`.
    pub fn new(
        w0: usize,
        norm: BackboneNorm,
        names: BackboneNames,
        vb: VarBuilder,
    ) -> Result<Self> {
        let mut layers = Vec::new();
        let mut cin = w0;
        for (i, w) in [w0, 2 * w0, 4 * w0, 8 * w0].into_iter().enumerate() {
            let stride = if i == 0 { 1 } else { 2 };
            let lb = vb.pp(names.layer(i));
            layers.push(vec![
                BasicBlock::new(cin, w, stride, norm, lb.pp("0"))?,
                BasicBlock::new(w, w, 1, norm, lb.pp("1"))?,
            ]);
            cin = w;
        }
        let (c1, n1) = names.stem();
        Ok(Self {
            conv1: conv(3, w0, 7, 2, 3, vb.pp(c1))?,
            bn1: Norm::new(norm, w0, vb.pp(n1))?,
            layers,
            out_channels: 8 * w0,
        })
    }

    /// Channels of the feature map (8 x the stem width; ResNet-18: 512).
    pub fn out_channels(&self) -> usize {
        self.out_channels
    }

    /// The activation after the stem (conv, norm, ReLU, max pool) and after each of the four
    /// layers.
    pub fn stages(&self, x: &Tensor, products: Products) -> Result<Vec<Tensor>> {
        let h = relu(&self.bn1.forward(&self.conv1.forward(x, products)?)?)?;
        // Max pool 3x3, stride 2, padding 1: after ReLU every value is >= 0, so zero padding
        // is equivalent to torch's -inf padding.
        let mut h = max_pool_3x3_s2(&h)?;
        let mut out = vec![h.clone()];
        for layer in &self.layers {
            for block in layer {
                h = block.forward(&h, products)?;
            }
            out.push(h.clone());
        }
        Ok(out)
    }

    /// Sets every frozen norm's running statistics from the batch `x` `(B, 3, H, W)`, layer
    /// by layer in forward order, each from its input as the already calibrated layers before
    /// it produce it (see `FrozenBatchNorm::calibrate`, groups of `group` channels). Returns
    /// each norm's key below the backbone's prefix (named by `names`) with its statistics.
    /// A GroupNorm backbone is left as it is and returns nothing.
    pub fn calibrate_frozen_norms(
        &mut self,
        x: &Tensor,
        group: usize,
        names: BackboneNames,
    ) -> Result<Vec<(String, NormStats)>> {
        let mut stats = Vec::new();
        let h = self
            .bn1
            .calibrate(&self.conv1.forward(x, Products::Fused)?, group, &mut stats)?;
        let mut h = max_pool_3x3_s2(&relu(&h)?)?;
        let mut keys = vec![names.stem().1.to_string()];
        for (i, layer) in self.layers.iter_mut().enumerate() {
            for (j, block) in layer.iter_mut().enumerate() {
                h = block.calibrate(&h, group, &mut stats)?;
                let norms = if block.downsample.is_some() { 3 } else { 2 };
                for n in &BasicBlock::NORMS[..norms] {
                    keys.push(format!("{}.{j}.{n}", names.layer(i)));
                }
            }
        }
        Ok(keys.into_iter().zip(stats).collect())
    }

    /// The feature map after `layer4`.
    pub fn forward(&self, x: &Tensor, products: Products) -> Result<Tensor> {
        self.stages(x, products)?
            .pop()
            .ok_or_else(|| candle_core::Error::Msg("backbone produced no stage".into()))
    }
}

/// The RGB encoder.
#[derive(Clone, Debug)]
pub struct RgbEncoder {
    backbone: ResNet18,
    keypoints: Conv2d,
    out: Linear,
    crop: Option<[usize; 2]>,
    num_kp: usize,
}

impl RgbEncoder {
    /// Build/load for images cropped to `crop` (None: full image) with `num_kp` keypoints.
    pub fn new(crop: Option<[usize; 2]>, num_kp: usize, vb: VarBuilder) -> Result<Self> {
        Self::with_width(64, crop, num_kp, vb)
    }

    /// As [`RgbEncoder::new`] with stem width `w0` (layers `w0, 2 w0, 4 w0, 8 w0`; ResNet-18
    /// is 64). `w0` must be a multiple of 16 for GroupNorm(C / 16).
    pub fn with_width(
        w0: usize,
        crop: Option<[usize; 2]>,
        num_kp: usize,
        vb: VarBuilder,
    ) -> Result<Self> {
        let backbone = ResNet18::new(
            w0,
            BackboneNorm::Group,
            BackboneNames::Sequential,
            vb.pp("backbone"),
        )?;
        let keypoints = Conv2d::new(8 * w0, num_kp, 1, 1, 0, true, vb.pp("pool.nets"))?;
        Ok(RgbEncoder {
            backbone,
            keypoints,
            out: crate::kernels::linear(2 * num_kp, 2 * num_kp, vb.pp("out"))?,
            crop,
            num_kp,
        })
    }

    /// Output width (2 x keypoints).
    pub fn feature_dim(&self) -> usize {
        2 * self.num_kp
    }

    /// The crop offset torchvision's `CenterCrop` takes: round((size - crop) / 2).
    pub fn center_offset(size: usize, crop: usize) -> usize {
        ((size - crop) as f64 / 2.0).round() as usize
    }

    /// Crop `(B, C, H, W)` at (top, left) to the configured crop (no-op without one).
    pub fn crop_at(&self, x: &Tensor, top: usize, left: usize) -> Result<Tensor> {
        match self.crop {
            Some([ch, cw]) => x.narrow(2, top, ch)?.narrow(3, left, cw),
            None => Ok(x.clone()),
        }
    }

    /// Evaluation forward: centre crop, backbone, spatial softmax, Linear, ReLU; each image
    /// computed exactly as alone (batch-invariant products, [`Products::PerSample`]).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (_, _, h, w) = x.dims4()?;
        let x = match self.crop {
            Some([ch, cw]) => {
                self.crop_at(x, Self::center_offset(h, ch), Self::center_offset(w, cw))?
            }
            None => x.clone(),
        };
        Ok(self.forward_parts(&x, Products::PerSample)?.feature)
    }

    /// Forward on an already cropped batch (training applies its own random crops), with
    /// the whole batch's products fused ([`Products::Fused`]: training needs no batch
    /// invariance).
    pub fn forward_cropped(&self, x: &Tensor) -> Result<Tensor> {
        Ok(self.forward_parts(x, Products::Fused)?.feature)
    }

    /// The backbone's activation after the stem (conv, norm, ReLU, max pool) and after each
    /// of the four layers, for a cropped batch.
    pub fn backbone_stages(&self, x: &Tensor, products: Products) -> Result<Vec<Tensor>> {
        self.backbone.stages(x, products)
    }

    /// The intermediate activations of the encoder on a cropped batch: the backbone's
    /// feature map `(B, 512, h, w)`, the spatial-softmax keypoints `(B, K, 2)` and the
    /// output feature `(B, 2K)` (for monitors, probes and attacks).
    pub fn forward_parts(&self, x: &Tensor, products: Products) -> Result<EncoderParts> {
        let h = self.backbone.forward(x, products)?;
        let f = self.keypoints.forward(&h, products)?;
        let (b, k, fh, fw) = f.dims4()?;
        // The composed softmax, not candle's fused `softmax_last_dim`: the fused kernel has
        // no backward pass, which would cut the observation gradient (PGD) at this point.
        let att = candle_nn::ops::softmax(&f.reshape((b, k, fh * fw))?, candle_core::D::Minus1)?;
        let grid = pos_grid(fh, fw, x.device())?.to_dtype(f.dtype())?;
        let keypoints = crate::kernels::right_shared(&att, &grid, products)?;
        let feature = relu(
            &self
                .out
                .forward(&keypoints.reshape((b, k * 2))?, products)?,
        )?;
        Ok(EncoderParts {
            feature_map: h,
            keypoints,
            feature,
        })
    }
}

/// Intermediate activations of the encoder.
#[derive(Clone, Debug)]
pub struct EncoderParts {
    /// Backbone output `(B, 512, h, w)`.
    pub feature_map: Tensor,
    /// Spatial-softmax keypoints `(B, K, 2)`, (x, y) in [-1, 1].
    pub keypoints: Tensor,
    /// Final feature `(B, 2K)` after Linear + ReLU.
    pub feature: Tensor,
}

/// LeRobot's `pos_grid` buffer: `(H W, 2)` rows (x, y) from meshgrid(linspace(-1, 1, W),
/// linspace(-1, 1, H)), row-major over (y, x).
pub fn pos_grid(h: usize, w: usize, device: &candle_core::Device) -> Result<Tensor> {
    let lin = |n: usize, i: usize| {
        if n == 1 {
            -1.0
        } else {
            -1.0 + 2.0 * i as f64 / (n - 1) as f64
        }
    };
    let mut v = Vec::with_capacity(h * w * 2);
    for y in 0..h {
        for x in 0..w {
            v.push(lin(w, x) as f32);
            v.push(lin(h, y) as f32);
        }
    }
    Tensor::from_vec(v, (h * w, 2), device)
}
