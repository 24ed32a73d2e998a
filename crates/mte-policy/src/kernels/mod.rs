//! CPU kernels with backward passes for the image encoder's hot spots.
//!
//! candle 0.9 composes GroupNorm and our strided max pool from many elementwise ops, and runs
//! the convolution's backward through a direct `conv_transpose2d`; on the width-16 encoder
//! at batch 128 a backward pass took 1.9 s (measured with `examples/prof_encoder.rs`), mostly
//! allocating, zeroing and summing full-size temporaries. These fused kernels compute the same
//! values in one pass each (checked against candle's composed versions and against finite
//! differences in their tests). On other devices every function here falls back to candle's
//! own ops, so a CUDA build needs no change.

/// Matches storages of one float type (all f32 or all f64), binds each name to its
/// contiguous slice and wraps `$body`'s vector in a storage of that type; any other dtype, or
/// a mix, is an error naming `$what` and the dtypes. The kernels' dtype dispatch, written
/// once.
macro_rules! float_storages {
    ($what:expr, [$(($name:ident, $s:expr, $l:expr)),+], $body:expr) => {
        match ($($s,)+) {
            ($(candle_core::CpuStorage::F32($name),)+) => {
                $(let $name = $crate::kernels::contiguous($name, $l)?;)+
                candle_core::CpuStorage::F32($body)
            }
            ($(candle_core::CpuStorage::F64($name),)+) => {
                $(let $name = $crate::kernels::contiguous($name, $l)?;)+
                candle_core::CpuStorage::F64($body)
            }
            _ => candle_core::bail!(
                "{}: unsupported dtypes {:?}",
                $what,
                [$(candle_core::backend::BackendStorage::dtype($s)),+]
            ),
        }
    };
}

mod activation;
mod affine;
mod batch;
mod conv;
mod conv1d;
mod exact_norm;
mod film;
mod norm;
mod pool;
mod product;

pub use activation::{mish, relu};
pub use affine::frozen_affine;
pub use batch::{Linear, Products, left_shared, linear, right_shared};
pub use conv::{Conv2d, conv2d};
pub use conv1d::{constant_weights, conv1d_constant, packed_weight};
pub use exact_norm::group_norm_exact;
pub use film::film;
pub use norm::{GroupNorm, group_norm};
pub use pool::max_pool_3x3_s2;

use candle_core::{Layout, Result};

/// The contiguous slice a layout describes (kernels call `.contiguous()` on their inputs).
fn contiguous<'a, T>(data: &'a [T], layout: &Layout) -> Result<&'a [T]> {
    match layout.contiguous_offsets() {
        Some((start, end)) => Ok(&data[start..end]),
        None => candle_core::bail!("mte kernels need contiguous inputs"),
    }
}

/// Whether the fused kernels take `x`: a CPU tensor of f32 or f64.
fn fused_on(x: &candle_core::Tensor) -> bool {
    x.device().is_cpu() && matches!(x.dtype(), candle_core::DType::F32 | candle_core::DType::F64)
}

/// A float element the kernels compute in (f32 and f64; arithmetic in f64).
trait Float: Copy + Default + Send + Sync + std::ops::AddAssign + 'static {
    fn to_f64(self) -> f64;
    fn from_f64(v: f64) -> Self;
}

impl Float for f32 {
    fn to_f64(self) -> f64 {
        self as f64
    }
    fn from_f64(v: f64) -> Self {
        v as f32
    }
}

impl Float for f64 {
    fn to_f64(self) -> f64 {
        self
    }
    fn from_f64(v: f64) -> Self {
        v
    }
}

#[cfg(test)]
pub(crate) mod test_util {
    use candle_core::{Device, Tensor};

    /// A fixed pseudo-random fill in [-1, 1) (no global RNG): an LCG.
    pub fn rand(shape: &[usize], seed: u64) -> Tensor {
        let n: usize = shape.iter().product();
        let mut s = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
        let v: Vec<f64> = (0..n)
            .map(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (s >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
            })
            .collect();
        Tensor::from_vec(v, shape, &Device::Cpu).expect("tensor")
    }

    /// Every value's bits (through f64, exact for f32 values), to compare results bit for
    /// bit.
    pub fn bits(t: &Tensor) -> Vec<u64> {
        t.flatten_all()
            .and_then(|t| t.to_dtype(candle_core::DType::F64))
            .and_then(|t| t.to_vec1::<f64>())
            .expect("values")
            .iter()
            .map(|v| v.to_bits())
            .collect()
    }

    /// The gradient of the probe `sum(y ⊙ r)` with respect to the variable `x`, and the
    /// whole gradient store.
    pub fn probe_gradient(
        y: &Tensor,
        r: &Tensor,
        x: &candle_core::Var,
    ) -> (Tensor, candle_core::backprop::GradStore) {
        let store = (y * r)
            .and_then(|p| p.sum_all())
            .and_then(|p| p.backward())
            .expect("backward");
        let dx = store.get(x.as_tensor()).cloned().expect("input gradient");
        (dx, store)
    }

    /// Max |a - b|.
    pub fn max_diff(a: &Tensor, b: &Tensor) -> f64 {
        (a - b)
            .and_then(|d| d.abs())
            .and_then(|d| d.max_all())
            .and_then(|d| d.to_dtype(candle_core::DType::F64))
            .and_then(|d| d.to_scalar::<f64>())
            .expect("difference")
    }
}
