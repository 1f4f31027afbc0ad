//! Row-major f32 matrix products on the `gemm` crate (AVX-512 kernels with the workspace's
//! `x86-v4` feature), shared by the fused convolution here and the transformer's kernels.

use std::mem::MaybeUninit;

use rayon::prelude::*;

use crate::par::{new_written, par_new, SharedMut};

/// A matrix operand: row-major values, read transposed when the flag is set.
pub type Operand<'a> = (&'a [f32], bool);

/// `dst (+)= scale · op(lhs) · op(rhs)` for row-major matrices: `op(lhs)` is m×k (stored
/// k×m when transposed), `op(rhs)` is k×n (stored n×k when transposed), `dst` is m×n and
/// is added to when `accumulate`. Single-threaded unless `parallel`.
pub fn gemm_with(
    dst: &mut [f32],
    lhs: Operand,
    rhs: Operand,
    (m, n, k): (usize, usize, usize),
    flags: (bool, f32, bool),
) {
    assert!(dst.len() >= m * n);
    // SAFETY: `dst` holds the m×n product and is initialised.
    unsafe { gemm_raw(dst.as_mut_ptr(), lhs, rhs, (m, n, k), flags) }
}

/// `op(lhs) · op(rhs)` as a new row-major m×n matrix, on several threads when large. The
/// product writes every value, so the matrix is not zero-filled first (for the largest
/// buffers of a backward pass, that fill cost as much as copying them).
pub fn gemm_new(lhs: Operand, rhs: Operand, (m, n, k): (usize, usize, usize)) -> Vec<f32> {
    if k == 0 {
        return vec![0f32; m * n];
    }
    // SAFETY: without `accumulate` gemm writes every one of the m·n values and reads none
    // (its `read_dst` is off).
    let write =
        |dst: SharedMut| unsafe { gemm_raw(dst.0, lhs, rhs, (m, n, k), (false, 1.0, true)) };
    // SAFETY: as above, every value is written.
    unsafe { new_written(m * n, write) }.0
}

/// How a weight gradient's product `aᵀ · b` reads `a` (stored k×m: an output gradient, one
/// row per frame).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TransposedLhs {
    /// gemm reads `a` transposed where it lies.
    InPlace,
    /// `a` is transposed into a new matrix first.
    Copied,
}

impl TransposedLhs {
    /// The way this process uses: `MOTIONSCALE_TRANSPOSED_LHS` (`in-place` or `copied`) when
    /// set, else whichever ran faster here, measured once at first use. Both give the same
    /// values (gemm packs either into the same panels and sums in the same order); only the
    /// speed differs by machine: on a Xeon (model 167) transposing 6400 × 768 values took as
    /// long as two thirds of the product, where on the AMD class reading in place was the
    /// slower.
    pub fn chosen() -> Self {
        static CHOICE: std::sync::OnceLock<TransposedLhs> = std::sync::OnceLock::new();
        *CHOICE.get_or_init(
            || match std::env::var("MOTIONSCALE_TRANSPOSED_LHS").as_deref() {
                Ok("in-place") => Self::InPlace,
                Ok("copied") => Self::Copied,
                _ => Self::measured(),
            },
        )
    }

    /// The faster way at a mid-sized weight gradient (4096 frames, 512 × 256), best of three
    /// alternated runs each.
    fn measured() -> Self {
        let (m, n, k) = (512, 256, 4096);
        let a: Vec<f32> = (0..k * m).map(|i| (i % 7) as f32).collect();
        let b: Vec<f32> = (0..k * n).map(|i| (i % 5) as f32).collect();
        let time = |way: Self| {
            let start = std::time::Instant::now();
            std::hint::black_box(way.product(&a, &b, (m, n, k)));
            start.elapsed()
        };
        let mut best = [std::time::Duration::MAX; 2];
        for _ in 0..3 {
            best[0] = best[0].min(time(Self::InPlace));
            best[1] = best[1].min(time(Self::Copied));
        }
        if best[0] <= best[1] {
            Self::InPlace
        } else {
            Self::Copied
        }
    }

    /// The name `MOTIONSCALE_TRANSPOSED_LHS` takes (and the bench's machine record shows).
    pub fn name(self) -> &'static str {
        match self {
            Self::InPlace => "in-place",
            Self::Copied => "copied",
        }
    }

    /// `aᵀ · b` (`a` stored k×m, `b` k×n) as a new row-major m×n matrix, read this way.
    pub fn product(self, a: &[f32], b: &[f32], (m, n, k): (usize, usize, usize)) -> Vec<f32> {
        match self {
            Self::InPlace => gemm_new((a, true), (b, false), (m, n, k)),
            Self::Copied => gemm_new((&transpose(a, k, m), false), (b, false), (m, n, k)),
        }
    }
}

/// [`gemm_with`] into `dst`.
///
/// # Safety
/// `dst` points to m·n writable values, initialised when `accumulate`.
unsafe fn gemm_raw(
    dst: *mut f32,
    (lhs, lhs_t): Operand,
    (rhs, rhs_t): Operand,
    (m, n, k): (usize, usize, usize),
    (accumulate, scale, parallel): (bool, f32, bool),
) {
    assert!(lhs.len() >= m * k && rhs.len() >= k * n);
    // The view of an operand whose op(·) is rows × cols (stored cols × rows when transposed).
    let view = |values, t: bool, (rows, cols): (usize, usize)| match t {
        true => Strided::rows(values, 0, rows).t(),
        false => Strided::rows(values, 0, cols),
    };
    let block = Block {
        dst,
        dst_row_stride: n,
        lhs: view(lhs, lhs_t, (m, k)),
        rhs: view(rhs, rhs_t, (k, n)),
        m,
        n,
        k,
    };
    // SAFETY: the caller's contract and the assert above bound the whole product.
    unsafe { block.dispatch((accumulate, scale), parallel) }
}

/// One product `dst (+)= scale · lhs · rhs` (m×k times k×n views; `dst` m×n with rows
/// `dst_row_stride` apart), run whole or by bands of its rows or columns.
struct Block<'a> {
    dst: *mut f32,
    dst_row_stride: usize,
    lhs: Strided<'a>,
    rhs: Strided<'a>,
    m: usize,
    n: usize,
    k: usize,
}

// SAFETY: threads write disjoint bands of `dst` (see `Block::dispatch`).
unsafe impl Sync for Block<'_> {}

impl Block<'_> {
    /// Runs the product on the threads in the way its shape runs best: column bands (mid-sized
    /// products), row bands (deep ones), gemm's own threads (other large ones) or one thread
    /// (small ones, or when not `parallel`). Every way gives the serial values.
    ///
    /// # Safety
    /// `dst`, `lhs` and `rhs` hold the whole product.
    unsafe fn dispatch(&self, (accumulate, scale): (bool, f32), parallel: bool) {
        let (m, n, k) = (self.m, self.n, self.k);
        let threads = rayon::current_num_threads();
        let macs = m * n * k;
        let parallel = parallel && threads > 1;
        let flags = (accumulate, scale);
        if parallel && (SPLIT_MIN_MACS..PARALLEL_MIN_MACS).contains(&macs) && n >= 2 * SPLIT_COLUMNS
        {
            // SAFETY: the caller's contract.
            return unsafe { self.run_in_column_bands(flags, threads) };
        }
        if parallel && macs >= PARALLEL_MIN_MACS && k >= m && m >= BAND_ROWS * threads {
            // SAFETY: as above.
            return unsafe { self.run_in_row_bands(flags, threads) };
        }
        // Small products (decoding a few rows) lose more to waking threads than they gain.
        let parallelism = if parallel && macs >= PARALLEL_MIN_MACS {
            gemm::Parallelism::Rayon(threads)
        } else {
            gemm::Parallelism::None
        };
        // SAFETY: as above.
        unsafe { self.run((0, m), (0, n), flags, parallelism) }
    }

    /// Mid-sized products (a batch of decoded rows: m ≈ 32) are too small for gemm's own
    /// threading, which splits along m; each thread takes a band of columns instead. Every
    /// output still sums over the whole of k in one call, so the values equal the serial ones.
    ///
    /// # Safety
    /// `dst`, `lhs` and `rhs` hold the whole product.
    unsafe fn run_in_column_bands(&self, (accumulate, scale): (bool, f32), threads: usize) {
        let n = self.n;
        let band = n.div_ceil(threads).next_multiple_of(SPLIT_COLUMNS);
        (0..n.div_ceil(band)).into_par_iter().for_each(|i| {
            let cols = (i * band, ((i + 1) * band).min(n));
            // SAFETY: the caller's contract; bands of columns are disjoint.
            unsafe {
                self.run(
                    (0, self.m),
                    cols,
                    (accumulate, scale),
                    gemm::Parallelism::None,
                )
            }
        });
    }

    /// Products deeper than they are tall (a weight gradient: k = the batch's rows or
    /// frames) run badly on gemm's own threads, which split each depth block's tiles among
    /// the threads and meet after every block; each thread takes a band of rows over the
    /// whole depth instead, packing the right operand for itself. Every output still sums
    /// over the whole of k in one call, so the values equal the serial ones. (Model 167, the
    /// LM's 2,592 rows: 256 × 256, 256 × 683 and 768 × 256 gradients 146–239 → 198–270
    /// GFLOP/s.)
    ///
    /// # Safety
    /// `dst`, `lhs` and `rhs` hold the whole product.
    unsafe fn run_in_row_bands(&self, (accumulate, scale): (bool, f32), threads: usize) {
        let band = self.m.div_ceil(threads).next_multiple_of(BAND_ROWS);
        (0..self.m.div_ceil(band)).into_par_iter().for_each(|i| {
            let rows = (i * band, ((i + 1) * band).min(self.m));
            let cols = (0, self.n);
            // SAFETY: the caller's contract; bands of rows are disjoint.
            unsafe { self.run(rows, cols, (accumulate, scale), gemm::Parallelism::None) }
        });
    }

    /// `dst[rows, cols]` alone.
    ///
    /// # Safety
    /// `dst`, `lhs` and `rhs` hold the whole product; no one else touches `dst[rows, cols]`.
    unsafe fn run(
        &self,
        (r0, r1): (usize, usize),
        (c0, c1): (usize, usize),
        (accumulate, scale): (bool, f32),
        par: gemm::Parallelism,
    ) {
        let (lhs, rhs, dst_rs) = (self.lhs, self.rhs, self.dst_row_stride);
        // SAFETY: the caller's contract; row r0 of lhs starts r0 · its row stride in, column
        // c0 of rhs c0 · its column stride in.
        unsafe {
            gemm::gemm(
                r1 - r0,
                c1 - c0,
                self.k,
                self.dst.add(r0 * dst_rs + c0),
                1,
                dst_rs as isize,
                accumulate,
                lhs.values.as_ptr().add(lhs.offset + r0 * lhs.row_stride),
                lhs.col_stride as isize,
                lhs.row_stride as isize,
                rhs.values.as_ptr().add(rhs.offset + c0 * rhs.col_stride),
                rhs.col_stride as isize,
                rhs.row_stride as isize,
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

/// A strided view of a matrix: element (i, j) is `values[offset + i·row_stride + j·col_stride]`.
#[derive(Debug, Clone, Copy)]
pub struct Strided<'a> {
    /// The values viewed.
    pub values: &'a [f32],
    /// Index of element (0, 0).
    pub offset: usize,
    /// Step between rows.
    pub row_stride: usize,
    /// Step between columns.
    pub col_stride: usize,
}

impl<'a> Strided<'a> {
    /// Rows `row_stride` apart, starting at `offset`, columns adjacent.
    pub fn rows(values: &'a [f32], offset: usize, row_stride: usize) -> Self {
        Self {
            values,
            offset,
            row_stride,
            col_stride: 1,
        }
    }

    /// The transposed view of the same values.
    pub fn t(self) -> Self {
        Self {
            row_stride: self.col_stride,
            col_stride: self.row_stride,
            ..self
        }
    }

    /// Panics unless a `rows × cols` matrix of this view lies inside its values.
    fn check(&self, (rows, cols): (usize, usize), what: &str) {
        if rows > 0 && cols > 0 {
            let last = self.offset + (rows - 1) * self.row_stride + (cols - 1) * self.col_stride;
            assert!(last < self.values.len(), "gemm: {what} view out of bounds");
        }
    }
}

/// `dst (+)= lhs · rhs` over strided views (m×k times k×n), into the m×n block of `dst`
/// starting at `dst_offset` with rows `dst_row_stride` apart; on gemm's threads when large.
/// For products over windows of larger matrices (a polyphase phase, a convolution tap).
pub fn gemm_strided(
    dst: &mut [f32],
    (dst_offset, dst_row_stride): (usize, usize),
    lhs: Strided,
    rhs: Strided,
    (m, n, k): (usize, usize, usize),
    accumulate: bool,
) {
    if m == 0 || n == 0 {
        return;
    }
    assert!(
        dst_offset + (m - 1) * dst_row_stride + n <= dst.len(),
        "gemm: dst out of bounds"
    );
    lhs.check((m, k), "lhs");
    rhs.check((k, n), "rhs");
    let block = Block {
        // SAFETY: dst_offset is inside `dst` (asserted above).
        dst: unsafe { dst.as_mut_ptr().add(dst_offset) },
        dst_row_stride,
        lhs,
        rhs,
        m,
        n,
        k,
    };
    // SAFETY: the checks above bound every index gemm reads or writes.
    unsafe { block.dispatch((accumulate, 1.0), true) }
}

/// `x` (`rows × cols`, row-major) transposed: `cols × rows`.
///
/// Products with only a few rows (a GRU step, a decoding step) want their weight stored this
/// way: gemm repacks a transposed right-hand operand on every call, which at 16–32 rows
/// takes two to three times as long as the product itself.
pub fn transpose(x: &[f32], rows: usize, cols: usize) -> Vec<f32> {
    assert_eq!(x.len(), rows * cols);
    // Eight output rows per task: each input row gives one contiguous read of eight values
    // and one write to each of the eight rows, which all fill front to back (4096 × 512:
    // 0.9 ms on two threads; 32 × 32 tiles on one thread took 11.7 ms).
    const BAND: usize = 8;
    let fill = |band: usize, out: &mut [MaybeUninit<f32>]| {
        let c0 = band * BAND;
        let mut outs: Vec<&mut [MaybeUninit<f32>]> = out.chunks_exact_mut(rows).collect();
        let width = outs.len();
        for (r, src) in x.chunks_exact(cols).enumerate() {
            for (o, &v) in outs.iter_mut().zip(&src[c0..c0 + width]) {
                o[r].write(v);
            }
        }
    };
    // SAFETY: block i is output rows BAND·i.. (input columns), each written at every input row.
    unsafe { par_new(x.len(), BAND * rows, fill) }
}

/// Multiply-adds from which a product is split into column bands over the threads.
const SPLIT_MIN_MACS: usize = 1 << 20;

/// Column bands are multiples of this (whole AVX-512 register tiles).
const SPLIT_COLUMNS: usize = 32;

/// Row bands are multiples of this many rows, and a product is split into row bands only
/// when every thread gets at least this many.
const BAND_ROWS: usize = 64;

/// Multiply-adds below which one product runs on one thread.
const PARALLEL_MIN_MACS: usize = 1 << 24;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simd::bits;
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

    /// `gemm_with` on `threads` threads gives the serial call's bits at every shape and
    /// (lhs transposed, rhs transposed, accumulate) case.
    fn assert_threaded_equals_serial(
        threads: usize,
        shapes: &[(usize, usize, usize)],
        cases: &[(bool, bool, bool)],
        seed: u64,
    ) {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let mut rng = SplitMix64(seed);
        for &(m, n, k) in shapes {
            for &(lhs_t, rhs_t, accumulate) in cases {
                let (lhs, rhs) = (random(m * k, &mut rng), random(k * n, &mut rng));
                let start = random(m * n, &mut rng);
                let (mut serial, mut threaded) = (start.clone(), start);
                let (l, r) = ((&lhs[..], lhs_t), (&rhs[..], rhs_t));
                gemm_with(&mut serial, l, r, (m, n, k), (accumulate, 0.5, false));
                pool.install(|| gemm_with(&mut threaded, l, r, (m, n, k), (accumulate, 0.5, true)));
                let what = format!("{m}x{n}x{k} lhs_t {lhs_t} rhs_t {rhs_t}");
                assert_eq!(bits(&serial), bits(&threaded), "{what}");
            }
        }
    }

    /// The column-split path (mid-sized products on several threads) gives the serial bits.
    #[test]
    fn column_split_products_equal_serial_ones() {
        let shapes = [
            (32, 768, 256),
            (31, 1027, 96),
            (64, 100, 200),
            (7, 4379, 160),
        ];
        for (m, n, k) in shapes {
            assert!((SPLIT_MIN_MACS..PARALLEL_MIN_MACS).contains(&(m * n * k)));
        }
        let cases = [
            (false, false, false),
            (true, true, true),
            (false, true, true),
        ];
        assert_threaded_equals_serial(3, &shapes, &cases, 5);
    }

    /// The row-band path (products deeper than tall on several threads: weight gradients)
    /// gives the serial bits, with odd row counts, transposed operands and accumulation.
    #[test]
    fn row_band_products_equal_serial_ones() {
        let (threads, shapes) = (3, [(256, 96, 1500), (300, 70, 1000), (200, 130, 700)]);
        for (m, n, k) in shapes {
            assert!(m * n * k >= PARALLEL_MIN_MACS && k >= m && m >= BAND_ROWS * threads);
        }
        let cases = [
            (true, false, false),
            (false, false, true),
            (true, true, true),
        ];
        assert_threaded_equals_serial(threads, &shapes, &cases, 7);
    }

    /// Reading a weight gradient's left operand in place or through a transposed copy gives
    /// the same bits (so the per-machine choice changes speed only): small and odd shapes,
    /// more than one depth block (k > 512), and gemm's threaded path. (With a transposed
    /// right operand too, gemm's path for tiny products sums in another order.)
    #[test]
    fn transposed_lhs_ways_give_the_same_bits() {
        let mut rng = SplitMix64(9);
        for (m, n, k) in [
            (5, 7, 3),
            (1, 9, 40),
            (33, 70, 700),
            (256, 96, 1500),
            (512, 256, 4096),
        ] {
            let (a, b) = (random(k * m, &mut rng), random(k * n, &mut rng));
            let in_place = TransposedLhs::InPlace.product(&a, &b, (m, n, k));
            let copied = TransposedLhs::Copied.product(&a, &b, (m, n, k));
            assert_eq!(bits(&in_place), bits(&copied), "{m}x{n}x{k}");
        }
        assert!([TransposedLhs::InPlace, TransposedLhs::Copied].contains(&TransposedLhs::chosen()));
    }
}
