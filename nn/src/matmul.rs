//! Row-major f32 matrix products on the `gemm` crate (AVX-512 kernels with the workspace's
//! `x86-v4` feature), shared by the fused convolution here and the transformer's kernels.

use rayon::prelude::*;

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
    let threads = rayon::current_num_threads();
    let macs = m * n * k;
    let parallel = parallel && threads > 1;
    let block = Block {
        dst: dst.as_mut_ptr(),
        row_stride: n,
        lhs: (lhs, lhs_t),
        rhs: (rhs, rhs_t),
        m,
        k,
    };
    if parallel && (SPLIT_MIN_MACS..PARALLEL_MIN_MACS).contains(&macs) && n >= 2 * SPLIT_COLUMNS {
        // SAFETY: the assert above bounds the whole product.
        return unsafe { block.run_in_column_bands((accumulate, scale), threads) };
    }
    // Small products (decoding a few rows) lose more to waking threads than they gain.
    let parallelism = if parallel && macs >= PARALLEL_MIN_MACS {
        gemm::Parallelism::Rayon(threads)
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: the assert above bounds every index gemm reads or writes.
    unsafe { block.run((0, n), (accumulate, scale), parallelism) }
}

/// One product `dst[.., cols] (+)= scale · op(lhs) · op(rhs)[.., cols]` (row-major `dst` of
/// `row_stride` columns), shared by the serial and the column-split paths.
struct Block<'a> {
    dst: *mut f32,
    row_stride: usize,
    lhs: Operand<'a>,
    rhs: Operand<'a>,
    m: usize,
    k: usize,
}

// SAFETY: threads write disjoint column bands of `dst` (see `Block::run_in_column_bands`).
unsafe impl Sync for Block<'_> {}

impl Block<'_> {
    /// Mid-sized products (a batch of decoded rows: m ≈ 32) are too small for gemm's own
    /// threading, which splits along m; each thread takes a band of columns instead. Every
    /// output still sums over the whole of k in one call, so the values equal the serial ones.
    ///
    /// # Safety
    /// `dst`, `lhs` and `rhs` hold the whole product.
    unsafe fn run_in_column_bands(&self, (accumulate, scale): (bool, f32), threads: usize) {
        let n = self.row_stride;
        let band = n.div_ceil(threads).next_multiple_of(SPLIT_COLUMNS);
        (0..n.div_ceil(band)).into_par_iter().for_each(|i| {
            let cols = (i * band, ((i + 1) * band).min(n));
            // SAFETY: the caller's contract; bands of columns are disjoint.
            unsafe { self.run(cols, (accumulate, scale), gemm::Parallelism::None) }
        });
    }

    /// # Safety
    /// `dst`, `lhs` and `rhs` hold the whole product; no one else touches `dst[.., cols]`.
    unsafe fn run(
        &self,
        (c0, c1): (usize, usize),
        (accumulate, scale): (bool, f32),
        par: gemm::Parallelism,
    ) {
        let (m, k, n) = (self.m, self.k, self.row_stride);
        let ((lhs, lhs_t), (rhs, rhs_t)) = (self.lhs, self.rhs);
        let (lhs_rs, lhs_cs) = if lhs_t { (1, m) } else { (k, 1) };
        let (rhs_rs, rhs_cs) = if rhs_t { (1, k) } else { (n, 1) };
        // SAFETY: the caller's contract; column c0 of op(rhs) starts c0 · rhs_cs in.
        unsafe {
            gemm::gemm(
                m,
                c1 - c0,
                k,
                self.dst.add(c0),
                1,
                n as isize,
                accumulate,
                lhs.as_ptr(),
                lhs_cs as isize,
                lhs_rs as isize,
                rhs.as_ptr().add(c0 * rhs_cs),
                rhs_cs as isize,
                rhs_rs as isize,
                if accumulate { 1.0 } else { 0.0 },
                scale,
                false,
                false,
                false,
                par,
            )
        }
    }
}

/// `x` (`rows × cols`, row-major) transposed: `cols × rows`.
///
/// Products with only a few rows (a GRU step, a decoding step) want their weight stored this
/// way: gemm repacks a transposed right-hand operand on every call, which at 16–32 rows
/// takes two to three times as long as the product itself.
pub fn transpose(x: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    assert_eq!(x.len(), rows * cols);
    // Tiles of 32 × 32, so the strided writes stay within a few cache lines at a time.
    const TILE: usize = 32;
    let mut t = vec![0f32; x.len()];
    for r0 in (0..rows).step_by(TILE) {
        for c0 in (0..cols).step_by(TILE) {
            for r in r0..(r0 + TILE).min(rows) {
                for c in c0..(c0 + TILE).min(cols) {
                    t[c * rows + r] = x[r * cols + c];
                }
            }
        }
    }
    t
}

/// Multiply-adds from which a product is split into column bands over the threads.
const SPLIT_MIN_MACS: usize = 1 << 20;

/// Column bands are multiples of this (whole AVX-512 register tiles).
const SPLIT_COLUMNS: usize = 32;

/// Multiply-adds below which one product runs on one thread.
const PARALLEL_MIN_MACS: usize = 1 << 24;

#[cfg(test)]
mod tests {
    use super::*;
    use motionscale_core::rng::SplitMix64;

    fn random(len: usize, rng: &mut SplitMix64) -> Vec<f32> {
        (0..len).map(|_| rng.range(-1.0, 1.0) as f32).collect()
    }

    #[test]
    fn transpose_moves_every_value_across_tile_edges() {
        let (rows, cols) = (33, 70);
        let x: Vec<f32> = (0..rows * cols).map(|i| i as f32).collect();
        let t = transpose(&x, rows, cols);
        for r in 0..rows {
            for c in 0..cols {
                assert_eq!(t[c * rows + r], x[r * cols + c]);
            }
        }
    }

    /// The column-split path (mid-sized products on several threads) gives the serial bits.
    #[test]
    fn column_split_products_equal_serial_ones() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        let mut rng = SplitMix64(5);
        for (m, n, k) in [
            (32, 768, 256),
            (31, 1027, 96),
            (64, 100, 200),
            (7, 4379, 160),
        ] {
            assert!((SPLIT_MIN_MACS..PARALLEL_MIN_MACS).contains(&(m * n * k)));
            for (lhs_t, rhs_t, accumulate) in [
                (false, false, false),
                (true, true, true),
                (false, true, true),
            ] {
                let (lhs, rhs) = (random(m * k, &mut rng), random(k * n, &mut rng));
                let start = random(m * n, &mut rng);
                let (mut serial, mut split) = (start.clone(), start);
                let args = ((&lhs[..], lhs_t), (&rhs[..], rhs_t), (m, n, k));
                gemm_with(
                    &mut serial,
                    args.0,
                    args.1,
                    args.2,
                    (accumulate, 0.5, false),
                );
                pool.install(|| {
                    gemm_with(&mut split, args.0, args.1, args.2, (accumulate, 0.5, true))
                });
                assert_eq!(serial, split, "{m}x{n}x{k} lhs_t {lhs_t} rhs_t {rhs_t}");
            }
        }
    }
}
