//! Generic CPU kernels that every hand-written executor shares (the prefix LM's, the text
//! encoder's, the GRU's): the product of all rows through `gemm`, one small product, a dot
//! product, column sums, the fixed row block of the row-wise kernels and the rayon pool they
//! start in (their parallel writers are [`crate::par`]'s). Every reduction runs in a fixed
//! order, so results never depend on scheduling.

use crate::matmul::{gemm_with, Operand};
use rayon::prelude::*;

/// Run `f` on a thread of the rayon pool. A step of many small parallel kernels (a decoded
/// token, an LM training step) started there forks each kernel cheaply; started outside the
/// pool, each kernel is a cross-thread hand-off and a sleep.
pub fn in_pool<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    rayon::scope(|_| f())
}

/// Rows per parallel work item of the row-wise kernels (fixed, so reductions are too).
pub const ROW_BLOCK: usize = 32;

/// Sum of `a[i]·b[i]` with eight partial sums (vectorises; fixed order). Inlined across
/// crates, so callers compiled for wider vectors (AVX2) get them here too.
#[inline]
pub fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for i in 0..8 {
            acc[i] += x[i] * y[i];
        }
    }
    let tail: f32 = ra.iter().zip(rb).map(|(x, y)| x * y).sum();
    acc.iter().sum::<f32>() + tail
}

/// One large product over all rows, spread over the rayon threads (`dst (+)= lhs · rhs`).
pub fn gemm(
    dst: &mut [f32],
    lhs: Operand,
    rhs: Operand,
    mnk: (usize, usize, usize),
    accumulate: bool,
) {
    gemm_with(dst, lhs, rhs, mnk, (accumulate, 1.0, true));
}

/// One small single-threaded product (`dst = scale · lhs · rhs`) of the kernels that run
/// many of them in parallel (attention per sequence and head, the fused head per part).
pub(crate) fn matmul(
    dst: &mut [f32],
    lhs: Operand,
    rhs: Operand,
    mnk: (usize, usize, usize),
    scale: f32,
) {
    gemm_with(dst, lhs, rhs, mnk, (false, scale, false));
}

/// Column sums of a `rows × cols` matrix, each in row order (so the same bits on any number
/// of threads): bands of columns in parallel when the matrix is large (a GRU layer's bias
/// gradients summed 3h columns over every step on one thread while the other waited).
pub fn column_sums(x: &[f32], cols: usize) -> Vec<f32> {
    const BAND: usize = 64;
    const PARALLEL_MIN: usize = 1 << 16;
    let sum_band = |c0: usize, band: &mut [f32]| {
        for row in x.chunks(cols) {
            let row = row.get(c0..).unwrap_or_default();
            band.iter_mut().zip(row).for_each(|(o, v)| *o += v);
        }
    };
    let mut out = vec![0f32; cols];
    if x.len() < PARALLEL_MIN {
        sum_band(0, &mut out);
    } else {
        out.par_chunks_mut(BAND)
            .enumerate()
            .for_each(|(i, band)| sum_band(i * BAND, band));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each column is summed in row order whether the bands run in parallel or not.
    #[test]
    fn column_sums_add_each_column_in_row_order_on_any_thread_count() {
        let (rows, cols) = (700, 150);
        let x: Vec<f32> = (0..rows * cols)
            .map(|i| ((i * 7919) % 1000) as f32 * 1e-3 - 0.5)
            .collect();
        let in_order: Vec<f32> = (0..cols)
            .map(|c| (0..rows).fold(0f32, |sum, r| sum + x[r * cols + c]))
            .collect();
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let sums = pool.install(|| column_sums(&x, cols));
            assert_eq!(crate::simd::bits(&sums), crate::simd::bits(&in_order));
        }
    }
}
