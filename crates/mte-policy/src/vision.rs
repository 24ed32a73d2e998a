//! LeRobot's `DiffusionRgbEncoder`: centre/random crop, torchvision ResNet-18 without its
//! last two children, every BatchNorm replaced by GroupNorm(C / 16), spatial softmax with a
//! 1x1 keypoint convolution, then Linear + ReLU. Keys mirror LeRobot's under
//! `diffusion.rgb_encoder.` (`backbone.0` conv1, `backbone.1` norm1, `backbone.4..7` layers
//! 1-4, `pool.nets`, `out`).
//!
//! Input: `(B, 3, H, W)` normalised images; output `(B, 2 * num_keypoints)`.
//!
//! The backbone's width is a parameter (`vision_backbone_width`: 64 is torchvision's
//! ResNet-18, the `cpu` preset uses 16). Convolutions, GroupNorm and the stem's max pool run
//! on mte's fused CPU kernels ([`crate::kernels`]), which have fast backward passes; so do
//! the ReLUs (the same bits as candle's).

use crate::kernels::{Conv2d, GroupNorm, max_pool_3x3_s2, relu};
use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

use crate::kernels::{Linear, Products};

const GN_EPS: f64 = 1e-5;

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

fn gn(c: usize, vb: VarBuilder) -> Result<GroupNorm> {
    GroupNorm::new(c / 16, c, GN_EPS, vb)
}

/// torchvision's `BasicBlock` with GroupNorm.
#[derive(Clone, Debug)]
pub struct BasicBlock {
    conv1: Conv2d,
    bn1: GroupNorm,
    conv2: Conv2d,
    bn2: GroupNorm,
    downsample: Option<(Conv2d, GroupNorm)>,
}

impl BasicBlock {
    fn new(cin: usize, cout: usize, stride: usize, vb: VarBuilder) -> Result<Self> {
        let downsample = if stride != 1 || cin != cout {
            Some((
                conv(cin, cout, 1, stride, 0, vb.pp("downsample.0"))?,
                gn(cout, vb.pp("downsample.1"))?,
            ))
        } else {
            None
        };
        Ok(BasicBlock {
            conv1: conv(cin, cout, 3, stride, 1, vb.pp("conv1"))?,
            bn1: gn(cout, vb.pp("bn1"))?,
            conv2: conv(cout, cout, 3, 1, 1, vb.pp("conv2"))?,
            bn2: gn(cout, vb.pp("bn2"))?,
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
}

/// The RGB encoder.
#[derive(Clone, Debug)]
pub struct RgbEncoder {
    conv1: Conv2d,
    bn1: GroupNorm,
    layers: Vec<Vec<BasicBlock>>,
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
        let b = vb.pp("backbone");
        let mut layers = Vec::new();
        let widths = [w0, 2 * w0, 4 * w0, 8 * w0];
        let mut cin = w0;
        for (i, &w) in widths.iter().enumerate() {
            let stride = if i == 0 { 1 } else { 2 };
            let lb = b.pp(4 + i);
            layers.push(vec![
                BasicBlock::new(cin, w, stride, lb.pp("0"))?,
                BasicBlock::new(w, w, 1, lb.pp("1"))?,
            ]);
            cin = w;
        }
        let keypoints = Conv2d::new(8 * w0, num_kp, 1, 1, 0, true, vb.pp("pool.nets"))?;
        Ok(RgbEncoder {
            conv1: conv(3, w0, 7, 2, 3, b.pp("0"))?,
            bn1: gn(w0, b.pp("1"))?,
            layers,
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

    /// The intermediate activations of the encoder on a cropped batch: the backbone's
    /// feature map `(B, 512, h, w)`, the spatial-softmax keypoints `(B, K, 2)` and the
    /// output feature `(B, 2K)` (for monitors, probes and attacks).
    pub fn forward_parts(&self, x: &Tensor, products: Products) -> Result<EncoderParts> {
        let h = self
            .backbone_stages(x, products)?
            .pop()
            .ok_or_else(|| candle_core::Error::Msg("backbone produced no stage".into()))?;
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
