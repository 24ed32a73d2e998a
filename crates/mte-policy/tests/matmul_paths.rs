//! The one CPU-dependent kernel under the policies: candle's matrix product, through the
//! `gemm` crate. `gemm` picks its code path from the operands' shapes (matrix-vector,
//! small, cache-blocked; blocks sized from the running CPU's caches) and its microkernel from
//! the CPU's extensions (FMA or scalar on x86_64; its AVX-512 kernels are compiled only with
//! its `x86-v4` feature, which nothing in this workspace enables). Extension and cache sizes
//! cannot be forced from outside the crate, but every shape path can: each is run here on
//! the running CPU and checked against a float64 oracle within the textbook forward-error
//! bound of a float32 dot product, `|c - c_ref| <= gamma_k sum_i |a_i b_i|` with
//! `gamma_k = k u / (1 - k u)`, `u = 2^-24`, which holds for any summation order, so for any
//! blocking and any microkernel. (mte's own kernels, `mte_policy::kernels`, accumulate in a
//! fixed order in float64 and have no CPU-dependent path.)

use candle_core::DType;

mod common;

/// Checks `a (m x k) * b (k x n)` in float32 against the float64 oracle, elementwise.
fn check(m: usize, k: usize, n: usize, seed: u64) {
    let a = common::randn(seed, &[m, k], 1.0, DType::F64);
    let b = common::randn(seed + 1, &[k, n], 1.0, DType::F64);
    let c32 = a
        .to_dtype(DType::F32)
        .and_then(|a32| a32.matmul(&b.to_dtype(DType::F32)?))
        .and_then(|c| c.to_dtype(DType::F64))
        .expect("f32 matmul");
    // The oracle: float64 products of the float32-rounded inputs, summed in float64.
    let (a32, b32) = (
        a.to_dtype(DType::F32).and_then(|t| t.to_dtype(DType::F64)),
        b.to_dtype(DType::F32).and_then(|t| t.to_dtype(DType::F64)),
    );
    let (a32, b32) = (a32.expect("a"), b32.expect("b"));
    let reference = a32.matmul(&b32).expect("f64 matmul");
    let abs = a32
        .abs()
        .and_then(|x| x.matmul(&b32.abs()?))
        .expect("|a||b|");
    let u = 2f64.powi(-24);
    let gamma = (k + 1) as f64 * u / (1.0 - (k + 1) as f64 * u); // + 1: the final rounding
    let (c, r, s): (Vec<f64>, Vec<f64>, Vec<f64>) = (
        c32.flatten_all().and_then(|t| t.to_vec1()).expect("c"),
        reference
            .flatten_all()
            .and_then(|t| t.to_vec1())
            .expect("r"),
        abs.flatten_all().and_then(|t| t.to_vec1()).expect("s"),
    );
    for (i, ((c, r), s)) in c.iter().zip(&r).zip(&s).enumerate() {
        // The float64 oracle's own error (k 2^-53 s) is below 1e-8 of the bound.
        assert!(
            (c - r).abs() <= gamma * s * (1.0 + 1e-6),
            "{m}x{k}x{n}, element {i}: {c} vs {r}, bound {}",
            gamma * s
        );
    }
}

#[test]
fn every_gemm_shape_path_is_within_the_float32_error_bound() {
    let shapes = [
        (1, 64, 1),      // dot product
        (1, 300, 37),    // row vector times matrix (gemv)
        (41, 300, 1),    // matrix times column vector (gemv)
        (3, 5, 7),       // small: below every block size
        (16, 33, 16),    // one microkernel tile, odd k
        (64, 1024, 48),  // k beyond any L1-sized k-block: blocked summation
        (257, 513, 129), // every dimension one past a power of two: edge tiles
        (128, 4096, 8),  // k beyond L2-sized blocks
    ];
    for (i, &(m, k, n)) in shapes.iter().enumerate() {
        check(m, k, n, 10 * i as u64);
    }
}

#[test]
fn batched_and_transposed_operands_take_the_strided_paths() {
    let a = common::randn(1, &[4, 33, 65], 1.0, DType::F32);
    let b = common::randn(2, &[4, 17, 65], 1.0, DType::F32);
    // b transposed: a non-contiguous right operand.
    let c = a
        .matmul(&b.transpose(1, 2).expect("t"))
        .expect("batched matmul");
    let c_contig = a
        .matmul(
            &b.transpose(1, 2)
                .and_then(|t| t.contiguous())
                .expect("copy"),
        )
        .expect("contiguous matmul");
    assert_eq!(c.dims(), &[4, 33, 17]);
    // Same operands, another memory layout: within the float32 bound of each other (twice
    // the one-sided bound, k = 65, |a||b| <= 65 * max|a| * max|b| ~ 65 * 25).
    let d = common::max_abs_diff(&c, &c_contig);
    let bound = 2.0 * 66.0 * 2f32.powi(-24) * 65.0 * 25.0;
    assert!(d <= bound, "{d} > {bound}");
}
