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

/// The largest absolute elementwise difference of two same-length slices.
pub fn max_abs_diff_slices(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Mean and sample standard deviation (n - 1) of `xs` (at least two values).
pub fn mean_sd(xs: &[f64]) -> (f64, f64) {
    assert!(xs.len() >= 2, "a spread needs at least two seeds");
    let n = xs.len() as f64;
    let mean = xs.iter().sum::<f64>() / n;
    let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (mean, var.sqrt())
}

/// How many times its spread over seeds an optimised effect must be to be asserted.
///
/// Why this form: an optimised outcome (a trained patch, a PGD perturbation, a fine-tuned
/// encoder) depends on every rounding of the matrix kernels, and those differ between CPUs
/// (`gemm` sizes its blocks from the caches). Another CPU perturbs a run by rounding errors,
/// which optimisation may amplify at most into a different draw of the same experiment;
/// changing the seed is such a draw (other data, other noise, another initial network). An
/// effect with every seed positive and a mean `K` sample standard deviations above zero is a
/// property of the method: a new draw from a roughly normal spread falls below zero with
/// probability about 2% at `K = 2`, and a rounding perturbation of the same seed moves it far
/// less than a new draw does. A broken method (no effect) fails it.
pub const K_SPREAD: f64 = 2.0;

/// Asserts that `effects` (one per seed, positive = the expected direction) are all
/// positive and their mean is at least [`K_SPREAD`] standard deviations above zero.
pub fn assert_clear_effect(label: &str, effects: &[f64]) {
    let (mean, sd) = mean_sd(effects);
    // Shown with `--nocapture`: the figures behind the margin, for the test's docs.
    #[allow(clippy::print_stderr)]
    {
        eprintln!(
            "{label}: {effects:?}, mean {mean:.4}, sd {sd:.4}, mean/sd {:.1}",
            mean / sd
        );
    }
    assert!(
        effects.iter().all(|&e| e > 0.0) && mean > K_SPREAD * sd,
        "{label}: effects over seeds {effects:?} (mean {mean:.4}, sd {sd:.4}) are not all \
         positive with mean > {K_SPREAD} sd"
    );
}

/// A seeded normal tensor (`candle`'s `randn` draws from a global, unseeded generator, so
/// tests never use it): standard deviation `sd`, float32 or float64.
pub fn randn(seed: u64, shape: &[usize], sd: f64, dtype: candle_core::DType) -> Tensor {
    use rand::SeedableRng;
    let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let n: usize = shape.iter().product();
    let v: Vec<f64> = (0..n)
        .map(|_| sd * rand_distr::Distribution::<f64>::sample(&rand_distr::StandardNormal, &mut r))
        .collect();
    Tensor::from_vec(v, shape, &candle_core::Device::Cpu)
        .and_then(|t| t.to_dtype(dtype))
        .expect("a tensor of the given shape")
}

/// One-sided 95% quantiles of Student's t, degrees of freedom 1 to 12 (scipy
/// `t.ppf(0.95, df)`, rounded up in the third decimal).
const T95: [f64; 12] = [
    6.314, 2.920, 2.354, 2.132, 2.016, 1.944, 1.895, 1.860, 1.834, 1.813, 1.797, 1.783,
];

/// Asserts that the mean of `effects` (one per seed, positive = the expected direction) is
/// significantly above zero: a one-sided one-sample t-test at the 5% level.
///
/// For effects whose size varies a lot from seed to seed (one draw near zero among large
/// ones), where [`assert_clear_effect`]'s "every seed positive, mean > 2 sd" judges the
/// spread of one small sample rather than the effect; the test's seed count is chosen so
/// that the effect measured here would pass with a wide margin.
#[allow(dead_code)]
pub fn assert_significant_effect(label: &str, effects: &[f64]) {
    let (mean, sd) = mean_sd(effects);
    let n = effects.len();
    assert!((2..=T95.len() + 1).contains(&n), "{label}: {n} seeds");
    let t = mean / (sd / (n as f64).sqrt());
    #[allow(clippy::print_stderr)]
    {
        eprintln!(
            "{label}: {effects:?}, mean {mean:.4}, sd {sd:.4}, t {t:.2} (df {})",
            n - 1
        );
    }
    assert!(
        t > T95[n - 2],
        "{label}: effects over seeds {effects:?} (mean {mean:.4}, sd {sd:.4}, t {t:.2}) are not \
         significantly above zero (one-sided t-test, 5%, needs t > {})",
        T95[n - 2]
    );
}
