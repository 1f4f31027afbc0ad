//! A k3 "same" convolution (stride 1, padding = dilation) as Winograd's minimal filtering
//! F(2, 3): two output frames from four products instead of six.
//!
//! Output frames `t0` and `t0 + d` of a tile read input frames `x0..x3 = t0 − d, t0, t0 + d,
//! t0 + 2d`. With the input transform `X̃ = (x0 − x2, x1 + x2, x2 − x1, x1 − x3)`, the weight
//! transform `W̃ = (w0, (w0 + w1 + w2)/2, (w0 − w1 + w2)/2, w2)` of taps `w0, w1, w2` and one
//! product per component `M_j = X̃_j · W̃_j`, the outputs are `y0 = M0 + M1 + M2` and
//! `y1 = M1 − M2 − M3`. Per component, the tiles of the whole batch are one product of
//! (tiles·batch) rows, so a pass costs 4 products per tile where one product per tap costs 3
//! per output frame (less the taps that read padding): a third fewer multiply-adds for
//! dilation 1. Both gradients are products of the same shapes: `dW̃_j = dM_jᵀ · X̃_j` and
//! `dX̃_j = dM_j · W̃_jᵀ`, with `dM = (dy0, dy0 + dy1, dy0 − dy1, −dy1)`; the transposes of
//! the transforms take them back to taps and frames. The transforms' constants are 0, ±1 and
//! ±½ (F(2,3) is the smallest Winograd tile, Lavin & Gray 2016), so the values differ from
//! the direct products by rounding only.
//!
//! Frames are tiled along each residue class modulo the dilation (`r, r + d, r + 2d, …`,
//! paired from the first); a tile whose second output is past the end computes it and drops
//! it, and frames before the start or past the end read as zero.

use super::ConvWeights;
use crate::matmul::{gemm_new, TransposedLhs};
use crate::par::par_new;
use rayon::prelude::*;
use std::mem::MaybeUninit;
use std::ops::Range;

/// One Winograd F(2,3) convolution over a batch of whole sequences.
pub(super) struct Winograd<'a> {
    w: &'a ConvWeights,
    dilation: usize,
    relu_input: bool,
    batch: usize,
    frames: usize,
    /// First output frame of each tile (its second is `dilation` later).
    tiles: Vec<usize>,
}

/// The four transformed components of one block of values, to be written.
type Components<'s> = (
    &'s mut [MaybeUninit<f32>],
    &'s mut [MaybeUninit<f32>],
    &'s mut [MaybeUninit<f32>],
    &'s mut [MaybeUninit<f32>],
);

/// A new buffer of four components of `len` values each, one after another, that `fill`
/// writes in parallel blocks of `block` values of each component (`fill(block index,
/// components)`: one sequence's tiles, or one row of a weight). Not zero-filled first: every
/// transform writes every value.
///
/// # Safety
/// `fill` writes every value of the four components it is given.
unsafe fn components_new(
    len: usize,
    block: usize,
    fill: impl Fn(usize, Components<'_>) + Sync + Send,
) -> Vec<f32> {
    let mut buffer = Vec::with_capacity(4 * len);
    let (first, rest) = buffer.spare_capacity_mut()[..4 * len].split_at_mut(len);
    let (second, rest) = rest.split_at_mut(len);
    let (third, fourth) = rest.split_at_mut(len);
    first
        .par_chunks_mut(block)
        .zip(second.par_chunks_mut(block))
        .zip(third.par_chunks_mut(block))
        .zip(fourth.par_chunks_mut(block))
        .enumerate()
        .for_each(|(i, (((a, b), c), d))| fill(i, (a, b, c, d)));
    // SAFETY: the caller's contract: every value has been written.
    unsafe { buffer.set_len(4 * len) };
    buffer
}

/// Writes the four values of one position of the four components.
fn put(components: &mut Components<'_>, at: usize, values: [f32; 4]) {
    let (c0, c1, c2, c3) = components;
    c0[at].write(values[0]);
    c1[at].write(values[1]);
    c2[at].write(values[2]);
    c3[at].write(values[3]);
}

/// Values `at` of each of the four products.
fn rows_at(products: &[Vec<f32>], at: Range<usize>) -> [&[f32]; 4] {
    [0, 1, 2, 3].map(|j| &products[j][at.clone()])
}

/// Values `at` of each of the four components of `block`.
fn slice_components<'s>(block: &'s mut Components<'_>, at: Range<usize>) -> Components<'s> {
    let (c0, c1, c2, c3) = block;
    (
        &mut c0[at.clone()],
        &mut c1[at.clone()],
        &mut c2[at.clone()],
        &mut c3[at],
    )
}

impl<'a> Winograd<'a> {
    /// The convolution of `w` (kernel 3) with dilation `dilation` and the input ReLU.
    pub(super) fn new(
        w: &'a ConvWeights,
        (dilation, relu_input): (usize, bool),
        (batch, frames): (usize, usize),
    ) -> Self {
        assert_eq!(w.dims.2, 3, "Winograd F(2,3) needs kernel 3");
        Self {
            w,
            dilation,
            relu_input,
            batch,
            frames,
            tiles: tiles(frames, dilation),
        }
    }

    /// Whether F(2,3) takes at most 80% of the products of one product per tap (which skips
    /// the taps that read padding), enough to pay for its transforms: timed per conv at batch
    /// 64, width 512, the shapes at 67–76% of the products ran faster this way, dilation 3 over
    /// 16 frames (86%) slower.
    pub(super) fn pays_off(frames: usize, dilation: usize) -> bool {
        let per_tap = frames + 2 * frames.saturating_sub(dilation);
        5 * 4 * tiles(frames, dilation).len() <= 4 * per_tap
    }

    /// Rows of each component's product: sequence-major (`b · tiles + i`), so one sequence's
    /// tiles are adjacent in every component.
    fn rows(&self) -> usize {
        self.tiles.len() * self.batch
    }

    /// Frame `f` of sequence `b` in the batch-major `x` (`width` channels), if inside.
    fn frame<'x>(&self, x: &'x [f32], b: usize, f: isize, width: usize) -> Option<&'x [f32]> {
        let inside = (0..self.frames as isize).contains(&f);
        inside.then(|| &x[(b * self.frames + f as usize) * width..][..width])
    }

    /// The transformed input `X̃` (4 × tiles·batch × in) of the batch-major `x`, through the
    /// input ReLU: what the products read, kept for the weight gradient.
    pub(super) fn transform_input(&self, x: &[f32]) -> Vec<f32> {
        let inp = self.w.dims.1;
        assert_eq!(x.len(), self.batch * self.frames * inp, "conv input size");
        let zeros = vec![0f32; inp];
        let relu = self.relu_input;
        let d = self.dilation as isize;
        let fill = |b: usize, mut block: Components<'_>| {
            let read = |f| self.frame(x, b, f, inp).unwrap_or(&zeros);
            for (i, &t0) in self.tiles.iter().enumerate() {
                let t0 = t0 as isize;
                let (x0, x1, x2, x3) = (read(t0 - d), read(t0), read(t0 + d), read(t0 + 2 * d));
                let mut tile = slice_components(&mut block, i * inp..(i + 1) * inp);
                for c in 0..inp {
                    let act = |v: f32| if relu { v.max(0.0) } else { v };
                    let (v0, v1, v2, v3) = (act(x0[c]), act(x1[c]), act(x2[c]), act(x3[c]));
                    put(&mut tile, c, [v0 - v2, v1 + v2, v2 - v1, v1 - v3]);
                }
            }
        };
        // SAFETY: every tile of every sequence is written whole.
        unsafe { components_new(self.rows() * inp, self.tiles.len() * inp, fill) }
    }

    /// The output (batch-major, with the bias) of the transformed input `xt`.
    pub(super) fn forward(&self, xt: &[f32]) -> Vec<f32> {
        let (out, inp, _) = self.w.dims;
        let rows = self.rows();
        // W̃_j as (in × out), from the taps-major transposed weight `(3·in, out)`.
        let tap = |k: usize, r: usize| &self.w.taps_t[(k * inp + r) * out..][..out];
        let wt = transform_weight(inp * out, out, |r| [tap(0, r), tap(1, r), tap(2, r)]);
        self.transform_output(&component_products(xt, &wt, (rows, out, inp)))
    }

    /// `y = bias + A·M`: each output frame from its tile's four products.
    fn transform_output(&self, m: &[Vec<f32>]) -> Vec<f32> {
        let out = self.w.dims.0;
        let slots = self.slots();
        let fill = |b: usize, yb: &mut [MaybeUninit<f32>]| {
            for (dst, &(i, second)) in yb.chunks_exact_mut(out).zip(&slots) {
                let row = b * self.tiles.len() + i;
                let [m0, m1, m2, m3] = rows_at(m, row * out..(row + 1) * out);
                let bias = &self.w.bias[..out];
                let dst = dst.iter_mut().enumerate();
                match second {
                    false => dst.for_each(|(c, d)| {
                        d.write(bias[c] + (m0[c] + m1[c] + m2[c]));
                    }),
                    true => dst.for_each(|(c, d)| {
                        d.write(bias[c] + (m1[c] - m2[c] - m3[c]));
                    }),
                }
            }
        };
        // SAFETY: block b is sequence b's frames, each one slot's output, written whole.
        unsafe { par_new(self.batch * self.frames * out, self.frames * out, fill) }
    }

    /// For each output frame, its tile and whether it is the tile's second output.
    fn slots(&self) -> Vec<(usize, bool)> {
        let mut slots = vec![(0, false); self.frames];
        for (i, &t0) in self.tiles.iter().enumerate() {
            slots[t0] = (i, false);
            if t0 + self.dilation < self.frames {
                slots[t0 + self.dilation] = (i, true);
            }
        }
        slots
    }

    /// The gradients for the output gradient `dy` (batch-major) of [`Self::forward`] on the
    /// batch-major input `x` with transformed input `xt`: the weight's (taps-major) and, when
    /// `input_grad`, the input's (batch-major, through the ReLU's mask).
    pub(super) fn backward(
        &self,
        (x, xt): (&[f32], &[f32]),
        dy: &[f32],
        input_grad: bool,
    ) -> (Vec<f32>, Option<Vec<f32>>) {
        let dm = self.transform_output_grad(dy);
        let weight = self.weight_grad(&dm, xt);
        (weight, input_grad.then(|| self.input_grad(&dm, x)))
    }

    /// `dM = Aᵀ·dy` (4 × tiles·batch × out); an output past the end has no gradient.
    fn transform_output_grad(&self, dy: &[f32]) -> Vec<f32> {
        let out = self.w.dims.0;
        let zeros = vec![0f32; out];
        let d = self.dilation as isize;
        let fill = |b: usize, mut block: Components<'_>| {
            for (i, &t0) in self.tiles.iter().enumerate() {
                let t0 = t0 as isize;
                let g0 = self.frame(dy, b, t0, out).unwrap_or(&zeros);
                let g1 = self.frame(dy, b, t0 + d, out).unwrap_or(&zeros);
                let mut tile = slice_components(&mut block, i * out..(i + 1) * out);
                for c in 0..out {
                    put(&mut tile, c, [g0[c], g0[c] + g1[c], g0[c] - g1[c], -g1[c]]);
                }
            }
        };
        // SAFETY: every tile of every sequence is written whole.
        unsafe { components_new(self.rows() * out, self.tiles.len() * out, fill) }
    }

    /// The weight gradient, taps-major `(out, 3·in)`: `dW̃_j = dM_jᵀ · X̃_j`, then `Gᵀ·dW̃`.
    fn weight_grad(&self, dm: &[f32], xt: &[f32]) -> Vec<f32> {
        let (out, inp, _) = self.w.dims;
        let rows = self.rows();
        let dwt: Vec<Vec<f32>> = (0..4)
            .map(|j| {
                TransposedLhs::chosen().product(
                    &dm[j * rows * out..][..rows * out],
                    &xt[j * rows * inp..][..rows * inp],
                    (out, inp, rows),
                )
            })
            .collect();
        let fill = |o: usize, g: &mut [MaybeUninit<f32>]| {
            let [d0, d1, d2, d3] = rows_at(&dwt, o * inp..(o + 1) * inp);
            let (g0, rest) = g.split_at_mut(inp);
            let (g1, g2) = rest.split_at_mut(inp);
            for c in 0..inp {
                let (half_sum, half_diff) = (0.5 * (d1[c] + d2[c]), 0.5 * (d1[c] - d2[c]));
                g0[c].write(d0[c] + half_sum);
                g1[c].write(half_diff);
                g2[c].write(half_sum + d3[c]);
            }
        };
        // SAFETY: block o is output channel o's three taps, each written whole.
        unsafe { par_new(out * 3 * inp, 3 * inp, fill) }
    }

    /// The input gradient (batch-major, through the input ReLU's mask): `dX̃_j = dM_j · W̃_jᵀ`,
    /// then each input frame gathers what its tiles' `Bᵀ` sends it.
    fn input_grad(&self, dm: &[f32], x: &[f32]) -> Vec<f32> {
        let (out, inp, _) = self.w.dims;
        let rows = self.rows();
        // W̃_jᵀ as (out × in), from the taps-major weight `(out, 3·in)`.
        let tap = |k: usize, o: usize| &self.w.taps[(3 * o + k) * inp..][..inp];
        let wt = transform_weight(out * inp, inp, |o| [tap(0, o), tap(1, o), tap(2, o)]);
        self.gather_input_grad(&component_products(dm, &wt, (rows, inp, out)), x)
    }

    /// `dx = Bᵀ·dX̃` frame by frame: a frame is one role (position in the tile) of at most
    /// two tiles along its residue class.
    fn gather_input_grad(&self, dxt: &[Vec<f32>], x: &[f32]) -> Vec<f32> {
        let inp = self.w.dims.1;
        let readers = self.readers();
        let mut dx = vec![0f32; x.len()];
        dx.par_chunks_mut(self.frames * inp)
            .enumerate()
            .for_each(|(b, dxb)| {
                for (s, dst) in dxb.chunks_exact_mut(inp).enumerate() {
                    for &(i, role) in &readers[s] {
                        let row = b * self.tiles.len() + i;
                        add_role(dst, role, rows_at(dxt, row * inp..(row + 1) * inp));
                    }
                    if self.relu_input {
                        let xs = &x[(b * self.frames + s) * inp..][..inp];
                        // A select, not a conditional store, so that it vectorises.
                        dst.iter_mut()
                            .zip(xs)
                            .for_each(|(d, &v)| *d = if v <= 0.0 { 0.0 } else { *d });
                    }
                }
            });
        dx
    }

    /// For each input frame, the tiles that read it and its role there (0–3: `t0 − d, t0,
    /// t0 + d, t0 + 2d`).
    fn readers(&self) -> Vec<Vec<(usize, usize)>> {
        let mut readers = vec![Vec::new(); self.frames];
        for (i, &t0) in self.tiles.iter().enumerate() {
            for role in 0..4 {
                let f = (t0 + role * self.dilation).checked_sub(self.dilation);
                if let Some(f) = f.filter(|&f| f < self.frames) {
                    readers[f].push((i, role));
                }
            }
        }
        readers
    }
}

/// First output frame of each tile: along each residue class modulo `dilation`, every other
/// frame from the first.
fn tiles(frames: usize, dilation: usize) -> Vec<usize> {
    (0..dilation.min(frames))
        .flat_map(|r| (r..frames).step_by(2 * dilation))
        .collect()
}

/// The four products `lhs_j · rhs_j` (m×k times k×n) of components stored one after another.
fn component_products(lhs: &[f32], rhs: &[f32], (m, n, k): (usize, usize, usize)) -> Vec<Vec<f32>> {
    (0..4)
        .map(|j| {
            let (lhs, rhs) = (&lhs[j * m * k..][..m * k], &rhs[j * k * n..][..k * n]);
            gemm_new((lhs, false), (rhs, false), (m, n, k))
        })
        .collect()
}

/// The four components of `W̃ = G·w` (each `len` values, one after another), built row by row:
/// `row(r)` gives row `r` (of `width` values) of the three taps.
fn transform_weight<'t>(
    len: usize,
    width: usize,
    row: impl Fn(usize) -> [&'t [f32]; 3] + Sync,
) -> Vec<f32> {
    let fill = |r: usize, mut components: Components<'_>| {
        let [t0, t1, t2] = row(r);
        for c in 0..width {
            let (half_sum, half_alt) =
                (0.5 * (t0[c] + t1[c] + t2[c]), 0.5 * (t0[c] - t1[c] + t2[c]));
            put(&mut components, c, [t0[c], half_sum, half_alt, t2[c]]);
        }
    };
    // SAFETY: every row of every component is written whole.
    unsafe { components_new(len, width, fill) }
}

/// `dst += (Bᵀ·e)[role]`: what a tile's transformed-input gradients `e` send to the input
/// frame at position `role` of the tile (`Bᵀ`'s columns: x0 − x2, x1 + x2, x2 − x1, x1 − x3).
fn add_role(dst: &mut [f32], role: usize, [e0, e1, e2, e3]: [&[f32]; 4]) {
    let n = dst.len();
    let (e0, e1, e2, e3) = (&e0[..n], &e1[..n], &e2[..n], &e3[..n]);
    match role {
        0 => (0..n).for_each(|c| dst[c] += e0[c]),
        1 => (0..n).for_each(|c| dst[c] += e1[c] - e2[c] + e3[c]),
        2 => (0..n).for_each(|c| dst[c] += e1[c] + e2[c] - e0[c]),
        _ => (0..n).for_each(|c| dst[c] -= e3[c]),
    }
}
