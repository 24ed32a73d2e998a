//! Fixtures shared by the integration tests.
#![allow(dead_code)] // each test file uses a subset

use candle_core::Tensor;
use mte_policy::{Stats, StatsMap};

/// Normalisation statistics: per feature (name, min, max, dim), mean 0.5 and std 0.25 on
/// every coordinate.
pub fn stats(features: &[(&str, f32, f32, usize)]) -> StatsMap {
    features
        .iter()
        .map(|&(name, lo, hi, n)| {
            (
                name.to_string(),
                Stats {
                    min: vec![lo; n],
                    max: vec![hi; n],
                    mean: vec![0.5; n],
                    std: vec![0.25; n],
                },
            )
        })
        .collect()
}

/// The largest absolute elementwise difference of two same-shape tensors.
pub fn max_abs_diff(a: &Tensor, b: &Tensor) -> f32 {
    (a - b)
        .and_then(|x| x.abs())
        .and_then(|x| x.max_all())
        .and_then(|x| x.to_scalar::<f32>())
        .expect("same-shape f32 tensors")
}
