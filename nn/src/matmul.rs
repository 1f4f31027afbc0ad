//! Row-major f32 matrix products on the `gemm` crate (AVX-512 kernels with the workspace's
//! `x86-v4` feature), shared by the fused convolution here and the transformer's kernels.

/// A matrix operand: row-major values, read transposed when the flag is set.
pub type Operand<'a> = (&'a [f32], bool);

/// `dst (+)= scale · op(lhs) · op(rhs)` for row-major matrices: `op(lhs)` is m×k (stored
/// k×m when transposed), `op(rhs)` is k×n (stored n×k when transposed), `dst` is m×n and
/// is added to when `accumulate`. Single-threaded unless `parallel`.
pub fn gemm_with(
    dst: &mut [f32],
    (lhs, lhs_t): Operand,
    (rhs, rhs_t): Operand,
    (m, n, k): (usize, usize, usize),
    (accumulate, scale, parallel): (bool, f32, bool),
) {
    assert!(dst.len() >= m * n && lhs.len() >= m * k && rhs.len() >= k * n);
    let (lhs_rs, lhs_cs) = if lhs_t { (1, m) } else { (k, 1) };
    let (rhs_rs, rhs_cs) = if rhs_t { (1, k) } else { (n, 1) };
    let threads = rayon::current_num_threads();
    // Small products (decoding a few rows) lose more to waking threads than they gain.
    let parallelism = if parallel && threads > 1 && m * n * k >= PARALLEL_MIN_MACS {
        gemm::Parallelism::Rayon(threads)
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: the assert above bounds every index gemm reads or writes.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            lhs.as_ptr(),
            lhs_cs as isize,
            lhs_rs as isize,
            rhs.as_ptr(),
            rhs_cs as isize,
            rhs_rs as isize,
            if accumulate { 1.0 } else { 0.0 },
            scale,
            false,
            false,
            false,
            parallelism,
        )
    }
}

/// Multiply-adds below which one product runs on one thread.
const PARALLEL_MIN_MACS: usize = 1 << 24;
