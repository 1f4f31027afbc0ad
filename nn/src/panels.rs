//! Products `x · W` of a few rows (a decoding step's) by a weight matrix packed once into
//! column panels. A panel holds [`PANEL`] columns of `W`, its k rows one after another, so
//! a tile streams it front to back: a decoding step reads every weight from L3 or memory,
//! and read in place a k×n matrix jumps a whole row between the 48 values a tile uses,
//! which the prefetchers do not follow.
//!
//! Every value is one fused multiply-add chain over k in order, added once to `dst` when
//! accumulating (as `gemm` does for k ≤ its depth block). A row's values therefore do not
//! depend on the rows beside it, the thread count or the vector level, so decoding may split
//! its batch into groups freely (`lm::generate`); gemm's own paths change with the shape.

use rayon::prelude::*;

use crate::kernels::gemm;
use crate::matmul::{gemm_new, Operand};
use crate::par::{new_written, SharedMut};
use crate::simd::{isa, Isa};

/// A weight matrix as a product reads it.
#[derive(Debug, Clone, Copy)]
pub enum Weight<'a> {
    /// Row-major values, read transposed when the flag is set, multiplied by gemm.
    Dense(Operand<'a>),
    /// Packed into column panels.
    Packed(&'a PackedMatrix),
}

impl Weight<'_> {
    /// `x · W` (x: m×k, W read as k×n) as a new row-major m×n matrix.
    pub fn product(self, x: &[f32], (m, n, k): (usize, usize, usize)) -> Vec<f32> {
        match self {
            Weight::Dense(w) => gemm_new((x, false), w, (m, n, k)),
            Weight::Packed(w) => {
                w.check((k, n));
                w.product(x, m)
            }
        }
    }

    /// `dst += x · W` (dst: m×n).
    pub fn product_add(self, dst: &mut [f32], x: &[f32], (m, n, k): (usize, usize, usize)) {
        match self {
            Weight::Dense(w) => gemm(dst, (x, false), w, (m, n, k), true),
            Weight::Packed(w) => {
                w.check((k, n));
                w.product_add(dst, x, m)
            }
        }
    }
}

/// Columns per panel: three AVX-512 vectors.
pub const PANEL: usize = 48;

/// A k×n matrix packed into column panels of [`PANEL`] columns, the last one zero-padded.
#[derive(Debug, Clone)]
pub struct PackedMatrix {
    values: Vec<f32>,
    k: usize,
    n: usize,
}

impl PackedMatrix {
    /// `op(w)` (k×n: `w` is stored n×k when `transposed`, as a linear layer's out × in
    /// weight) packed into panels.
    pub fn new((w, transposed): Operand, (k, n): (usize, usize)) -> Self {
        assert!(w.len() >= k * n, "a {k}×{n} matrix from {} values", w.len());
        let mut values = vec![0f32; n.div_ceil(PANEL) * k * PANEL];
        values
            .par_chunks_mut((k * PANEL).max(1))
            .enumerate()
            .for_each(|(c, panel)| {
                for l in 0..PANEL.min(n - c * PANEL) {
                    let j = c * PANEL + l;
                    // Read along w's rows: a transposed matrix's column j is row j of w.
                    for (p, v) in panel.iter_mut().skip(l).step_by(PANEL).enumerate() {
                        *v = if transposed {
                            w[j * k + p]
                        } else {
                            w[p * n + j]
                        };
                    }
                }
            });
        Self { values, k, n }
    }

    fn check(&self, (k, n): (usize, usize)) {
        assert_eq!((self.k, self.n), (k, n), "a packed matrix of another shape");
    }

    /// `x · W` for `m` rows of `x` (row-major m×k), as a new row-major m×n matrix, its panels
    /// spread over the rayon threads.
    pub fn product(&self, x: &[f32], m: usize) -> Vec<f32> {
        // SAFETY: without accumulating, every panel writes all its columns of every row.
        unsafe { new_written(m * self.n, |dst| self.run(dst, x, m, false)) }.0
    }

    /// `dst += x · W` for `m` rows of `x` (`dst` row-major m×n).
    pub fn product_add(&self, dst: &mut [f32], x: &[f32], m: usize) {
        assert!(dst.len() >= m * self.n);
        // SAFETY: `dst` holds m·n initialised values.
        unsafe { self.run(SharedMut(dst.as_mut_ptr()), x, m, true) }
    }

    /// # Safety
    /// `dst` points to m·n writable values, initialised when `accumulate`.
    unsafe fn run(&self, dst: SharedMut, x: &[f32], m: usize, accumulate: bool) {
        let (k, n) = (self.k, self.n);
        assert!(x.len() >= m * k, "{m} rows of {k} from {} values", x.len());
        let tile_rows = tile_rows(isa());
        (0..n.div_ceil(PANEL)).into_par_iter().for_each(|c| {
            let panel = &self.values[c * k * PANEL..][..k * PANEL];
            let dims = PanelDims {
                m,
                k,
                n,
                c,
                tile_rows,
            };
            panel_product(dst, x, panel, dims, accumulate);
        });
    }
}

/// Rows per tile at a vector level: as many as its registers hold sums for (8 × 3 AVX-512
/// vectors; 2 × 6 AVX2 ones).
fn tile_rows(level: Isa) -> usize {
    if level == Isa::Avx512 {
        8
    } else {
        2
    }
}

/// The shape of one panel's product: `m` rows of depth `k` into a row stride of `n`, panel
/// `c`, tiles of `tile_rows` rows (what the vector level's registers hold).
#[derive(Clone, Copy)]
struct PanelDims {
    m: usize,
    k: usize,
    n: usize,
    c: usize,
    tile_rows: usize,
}

crate::vectorised!(
    /// Panel `c`'s columns of `x · W` for every row, written to `dst` or added to it.
    fn panel_product / panel_product_at(
        dst: SharedMut,
        x: &[f32],
        panel: &[f32],
        dims: PanelDims,
        accumulate: bool,
    ) = panel_body;
);

#[inline(always)]
fn panel_body(dst: SharedMut, x: &[f32], panel: &[f32], dims: PanelDims, accumulate: bool) {
    let mut r = 0;
    while r < dims.m {
        let rows = (dims.m - r).min(dims.tile_rows);
        let tile = Tile {
            dst,
            x: &x[r * dims.k..],
            panel,
            row0: r,
            dims,
            accumulate,
        };
        match rows {
            8 => tile.run::<8>(),
            7 => tile.run::<7>(),
            6 => tile.run::<6>(),
            5 => tile.run::<5>(),
            4 => tile.run::<4>(),
            3 => tile.run::<3>(),
            2 => tile.run::<2>(),
            _ => tile.run::<1>(),
        }
        r += rows;
    }
}

/// Rows `row0..` of one panel's product (`x` starts at row `row0`).
struct Tile<'a> {
    dst: SharedMut,
    x: &'a [f32],
    panel: &'a [f32],
    row0: usize,
    dims: PanelDims,
    accumulate: bool,
}

impl Tile<'_> {
    /// `R` rows: R × PANEL sums in registers, one pass over the panel.
    #[inline(always)]
    fn run<const R: usize>(&self) {
        let PanelDims { k, n, c, .. } = self.dims;
        let xs: [&[f32]; R] = std::array::from_fn(|i| &self.x[i * k..][..k]);
        let mut acc = [[0f32; PANEL]; R];
        for (p, w) in self.panel.chunks_exact(PANEL).enumerate() {
            let w: &[f32; PANEL] = w.try_into().expect("whole panel rows");
            for (a, xi) in acc.iter_mut().zip(&xs) {
                let xv = xi[p];
                a.iter_mut()
                    .zip(w)
                    .for_each(|(a, w)| *a = xv.mul_add(*w, *a));
            }
        }
        let cols = PANEL.min(n - c * PANEL);
        for (i, a) in acc.into_iter().enumerate() {
            // `a` is a copy, so `acc` never has its address taken and stays in registers.
            let at = (self.row0 + i) * n + c * PANEL;
            // SAFETY: row row0 + i, columns of panel c, belong to this panel's task alone;
            // they are initialised when accumulating (`PackedMatrix::run`'s contract).
            unsafe {
                if self.accumulate {
                    let row = std::slice::from_raw_parts_mut(self.dst.at(at), cols);
                    row.iter_mut().zip(a).for_each(|(d, a)| *d += a);
                } else {
                    self.dst.put(at, &a[..cols]);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::simd::{assert_levels_agree, available, bits};
    use motionscale_core::rng::SplitMix64;

    fn random(len: usize, seed: u64) -> Vec<f32> {
        let mut rng = SplitMix64(seed);
        (0..len).map(|_| rng.range(-1.0, 1.0) as f32).collect()
    }

    /// Each value is the chain `fma(x_p, w_p, …)` over p in order; stored either way round;
    /// accumulating adds it once; odd shapes leave partial panels and tiles.
    #[test]
    fn products_are_one_fused_chain_per_value() {
        for (m, k, n) in [(11, 37, 101), (16, 256, 48), (1, 5, 3)] {
            let (x, w) = (random(m * k, 1), random(k * n, 2));
            let wt = crate::matmul::transpose(&w, k, n);
            let chain = |i: usize, j: usize| {
                (0..k).fold(0f32, |a, p| x[i * k + p].mul_add(w[p * n + j], a))
            };
            let start = random(m * n, 3);
            for packed in [
                PackedMatrix::new((&w, false), (k, n)),
                PackedMatrix::new((&wt, true), (k, n)),
            ] {
                let (product, mut added) = (packed.product(&x, m), start.clone());
                packed.product_add(&mut added, &x, m);
                for (i, j) in (0..m).flat_map(|i| (0..n).map(move |j| (i, j))) {
                    let want = chain(i, j);
                    assert_eq!(product[i * n + j].to_bits(), want.to_bits(), "({i}, {j})");
                    let sum = start[i * n + j] + want;
                    assert_eq!(added[i * n + j].to_bits(), sum.to_bits(), "({i}, {j})");
                }
            }
        }
    }

    /// A row's values are the same bits alone, among other rows, on one thread or three,
    /// and at every vector level.
    #[test]
    fn rows_do_not_depend_on_their_neighbours_threads_or_level() {
        let (m, k, n) = (19, 683, 130);
        let (x, w) = (random(m * k, 4), random(k * n, 5));
        let packed = PackedMatrix::new((&w, false), (k, n));
        let whole = packed.product(&x, m);
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        for i in 0..m {
            let alone = pool.install(|| packed.product(&x[i * k..][..k], 1));
            assert_eq!(bits(&alone), bits(&whole[i * n..][..n]), "row {i}");
        }
        assert!(available().contains(&Isa::Baseline));
        assert_levels_agree(|level| {
            let mut dst = vec![0f32; m * n];
            for c in 0..n.div_ceil(PANEL) {
                let dims = PanelDims {
                    m,
                    k,
                    n,
                    c,
                    tile_rows: tile_rows(level),
                };
                let panel = &packed.values[c * k * PANEL..][..k * PANEL];
                panel_product_at(level, SharedMut(dst.as_mut_ptr()), &x, panel, dims, false);
            }
            bits(&dst)
        });
    }
}
