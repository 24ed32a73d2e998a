//! PyTorch's `nn.MultiheadAttention` on candle (packed `in_proj_weight`, the query scaled by
//! `head_dim^-1/2` before the product, additive masks), and training dropout drawn from an
//! injected stream: shared by ACT and the Diffusion Transformer.

use std::cell::RefCell;

use candle_core::{D, Result, Tensor};

use crate::kernels::Products;
use crate::kernels::right_shared;
use candle_nn::{Init, Linear, VarBuilder};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

/// Training-time dropout drawing its masks from an injected stream.
pub struct Dropout<'a> {
    p: f64,
    rng: &'a RefCell<ChaCha8Rng>,
}

impl<'a> Dropout<'a> {
    /// Dropout with probability `p` from `rng`.
    pub fn new(p: f64, rng: &'a RefCell<ChaCha8Rng>) -> Self {
        Self { p, rng }
    }

    /// `x` with each element zeroed with probability `p`, the rest scaled by `1 / (1 - p)`.
    pub fn apply(&self, x: &Tensor) -> Result<Tensor> {
        if self.p <= 0.0 {
            return Ok(x.clone());
        }
        let keep = 1.0 / (1.0 - self.p);
        let mut rng = self.rng.borrow_mut();
        let mask: Vec<f32> = (0..x.elem_count())
            .map(|_| {
                if rng.random::<f64>() < self.p {
                    0.0
                } else {
                    keep as f32
                }
            })
            .collect();
        x * Tensor::from_vec(mask, x.shape(), x.device())?
    }
}

pub fn drop(x: &Tensor, d: Option<&Dropout<'_>>) -> Result<Tensor> {
    match d {
        Some(d) => d.apply(x),
        None => Ok(x.clone()),
    }
}

/// Xavier-uniform for a `(out, in)` matrix, as LeRobot initialises the transformer.
pub fn xavier(out: usize, inp: usize) -> Init {
    let bound = (6.0 / (out + inp) as f64).sqrt();
    Init::Uniform {
        lo: -bound,
        up: bound,
    }
}

pub fn linear_xavier(inp: usize, out: usize, vb: VarBuilder) -> Result<Linear> {
    let w = vb.get_with_hints((out, inp), "weight", xavier(out, inp))?;
    let bound = 1.0 / (inp as f64).sqrt();
    let b = vb.get_with_hints(
        out,
        "bias",
        Init::Uniform {
            lo: -bound,
            up: bound,
        },
    )?;
    Ok(Linear::new(w, Some(b)))
}

/// PyTorch's `nn.MultiheadAttention` (no bias_kv, no zero_attn).
pub struct Attention {
    in_w: Tensor,
    in_b: Tensor,
    out: Linear,
    heads: usize,
}

impl Attention {
    /// Width `d`, `heads` heads, weights under `vb` (`in_proj_weight`, `in_proj_bias`,
    /// `out_proj`), Xavier-uniform matrices and zero input biases when initialised.
    pub fn new(d: usize, heads: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            in_w: vb.get_with_hints((3 * d, d), "in_proj_weight", xavier(3 * d, d))?,
            in_b: vb.get_with_hints(3 * d, "in_proj_bias", Init::Const(0.0))?,
            out: linear_xavier(d, d, vb.pp("out_proj"))?,
            heads,
        })
    }

    /// `x (B, L, D)` through rows `part` of the packed projection, split into heads
    /// `(B, H, L, D / H)`.
    fn project(&self, x: &Tensor, part: usize, products: Products) -> Result<Tensor> {
        let (b, l, d) = x.dims3()?;
        let w = self.in_w.narrow(0, part * d, d)?;
        let bias = self.in_b.narrow(0, part * d, d)?;
        let y = right_shared(&x.contiguous()?, &w.t()?, products)?.broadcast_add(&bias)?;
        y.reshape((b, l, self.heads, d / self.heads))?
            .transpose(1, 2)?
            .contiguous()
    }

    /// Attention of queries `q` over keys `k` and values `v` (all `(B, L, D)`); `pad`, if
    /// given, is an additive `(B, Lk)` mask (0 or a large negative) over the keys.
    pub fn forward(
        &self,
        q: &Tensor,
        k: &Tensor,
        v: &Tensor,
        pad: Option<&Tensor>,
        d: Option<&Dropout<'_>>,
    ) -> Result<Tensor> {
        self.forward_masked(q, k, v, None, pad, d, Products::Fused)
    }

    /// [`Attention::forward`] with an additive `(Lq, Lk)` attention mask as well (PyTorch's
    /// `attn_mask`, e.g. causal), and the projections computed as `products` says
    /// ([`Products::PerSample`]: each sample as a batch of one, batch-invariant).
    #[allow(clippy::too_many_arguments)]
    pub fn forward_masked(
        &self,
        q: &Tensor,
        k: &Tensor,
        v: &Tensor,
        attn_mask: Option<&Tensor>,
        pad: Option<&Tensor>,
        d: Option<&Dropout<'_>>,
        products: Products,
    ) -> Result<Tensor> {
        let (b, lq, dim) = q.dims3()?;
        let scale = 1.0 / ((dim / self.heads) as f64).sqrt();
        let (q, k, v) = (
            (self.project(q, 0, products)? * scale)?,
            self.project(k, 1, products)?,
            self.project(v, 2, products)?,
        );
        let mut scores = q.matmul(&k.transpose(2, 3)?.contiguous()?)?;
        if let Some(mask) = attn_mask {
            scores = scores.broadcast_add(mask)?;
        }
        if let Some(mask) = pad {
            scores = scores.broadcast_add(&mask.unsqueeze(1)?.unsqueeze(1)?)?;
        }
        // The composed softmax: candle's fused `softmax_last_dim` has no backward pass, and
        // through it no gradient would reach the queries and keys (their projections, the
        // position embeddings, PGD's inputs).
        let weights = drop(&candle_nn::ops::softmax(&scores, D::Minus1)?, d)?;
        let y = weights.matmul(&v)?.transpose(1, 2)?.reshape((b, lq, dim))?;
        linear3(&self.out, &y, products)
    }
}

/// `layer` on every row of `x (B, L, in)`, the product computed as `products` says.
pub fn linear3(layer: &Linear, x: &Tensor, products: Products) -> Result<Tensor> {
    let y = right_shared(&x.contiguous()?, &layer.weight().t()?, products)?;
    match layer.bias() {
        Some(b) => y.broadcast_add(b),
        None => Ok(y),
    }
}

/// PyTorch's `nn.LayerNorm` (last dimension, eps 1e-5, weight and bias), written with
/// differentiable tensor ops. candle-nn's `LayerNorm` takes a fused kernel for contiguous
/// inputs, and that kernel has no backward pass: gradients stop at it silently, so a
/// transformer built on it trains only the layers after its last norm and passes no
/// gradient to its inputs (PGD). Rows are normalised independently (batch-invariant).
#[derive(Clone, Debug)]
pub struct LayerNorm {
    weight: Tensor,
    bias: Tensor,
    eps: f64,
}

impl LayerNorm {
    /// Width `d`, `weight` (ones) and `bias` (zeros) under `vb`.
    pub fn new(d: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb.get_with_hints(d, "weight", Init::Const(1.0))?,
            bias: vb.get_with_hints(d, "bias", Init::Const(0.0))?,
            eps: 1e-5,
        })
    }

    /// `x (..., d)` normalised over its last dimension.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let d = x.dim(D::Minus1)? as f64;
        let centred = x.broadcast_sub(&(x.sum_keepdim(D::Minus1)? / d)?)?;
        let var = (centred.sqr()?.sum_keepdim(D::Minus1)? / d)?;
        centred
            .broadcast_div(&(var + self.eps)?.sqrt()?)?
            .broadcast_mul(&self.weight)?
            .broadcast_add(&self.bias)
    }
}

/// The position-wise feed-forward block of both transformers:
/// `linear2(dropout(act(linear1(x))))`, `act` ReLU or exact GELU, Xavier-initialised.
pub struct FeedForward {
    linear1: Linear,
    linear2: Linear,
    gelu: bool,
}

impl FeedForward {
    /// Width `d` to `hidden` and back, weights under `vb` (`linear1`, `linear2`).
    pub fn new(d: usize, hidden: usize, gelu: bool, vb: &VarBuilder) -> Result<Self> {
        Ok(Self {
            linear1: linear_xavier(d, hidden, vb.pp("linear1"))?,
            linear2: linear_xavier(hidden, d, vb.pp("linear2"))?,
            gelu,
        })
    }

    /// The block on `x (B, L, d)`, products as `p` says.
    pub fn forward(&self, x: &Tensor, d: Option<&Dropout<'_>>, p: Products) -> Result<Tensor> {
        let h = linear3(&self.linear1, x, p)?;
        let h = if self.gelu { h.gelu_erf()? } else { h.relu()? };
        linear3(&self.linear2, &drop(&h, d)?, p)
    }
}
