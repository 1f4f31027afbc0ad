//! CPU kernels of the prefix LM, forward and backward (the generic products, dot and column
//! sums are `crate::kernels`'s, re-exported here): matmuls over all rows at once through
//! `gemm` (AVX-512), RMSNorm, SwiGLU, prefix-LM attention (rotary positions, mask, softmax,
//! both matmuls, per (sequence, head) in parallel) and cross-entropy, elementwise work in
//! rayon-parallel row blocks.
//!
//! candle 0.11's RMSNorm, softmax and rope ops have no backward pass, and its autograd adds a
//! zero-initialised gradient buffer, an allocation and a pass over memory for every edge of
//! the graph (plus its own elementwise thread pool, which fights rayon's for 2 cores); the
//! model therefore runs its forward and backward passes on these kernels directly
//! (`prefix_lm`). Every reduction runs in a fixed order, so results never depend on thread
//! scheduling: a resumed run reproduces an uninterrupted one bit for bit.

use std::mem::MaybeUninit;

use crate::fast_exp;
use crate::kernels::matmul;
use crate::par::{par_new, SharedMut};
use crate::seq_layout::SeqLayout;
use rayon::prelude::*;

pub use crate::kernels::{column_sums, dot, gemm, in_pool, ROW_BLOCK};
pub use crate::matmul::gemm_new;

/// Target id of a position without loss (padding).
pub const IGNORE: u32 = u32::MAX;

fn rstd(x: &[f32], eps: f32) -> f32 {
    1.0 / (dot(x, x) / x.len() as f32 + eps).sqrt()
}

/// RMSNorm of each `d`-wide row of `x`, scaled by `w` (d = `w.len()`).
pub fn rms_norm(x: &[f32], w: &[f32], eps: f32) -> Vec<f32> {
    let d = w.len();
    let block = d * ROW_BLOCK;
    let fill = |i: usize, yb: &mut [MaybeUninit<f32>]| {
        for (yr, xr) in yb.chunks_mut(d).zip(x[i * block..].chunks(d)) {
            let r = rstd(xr, eps);
            for ((y, x), w) in yr.iter_mut().zip(xr).zip(w) {
                y.write(x * r * w);
            }
        }
    };
    // SAFETY: block i holds the rows of x's block i, each written whole.
    unsafe { par_new(x.len(), block, fill) }
}

/// Backward of [`rms_norm`] given the output gradient `g`: adds the gradient with respect
/// to `x` into `gx` and returns the one with respect to `w`.
pub fn rms_norm_backward(x: &[f32], w: &[f32], g: &[f32], eps: f32, gx: &mut [f32]) -> Vec<f32> {
    let d = w.len();
    let partials: Vec<Vec<f32>> = gx
        .par_chunks_mut(d * ROW_BLOCK)
        .zip(x.par_chunks(d * ROW_BLOCK))
        .zip(g.par_chunks(d * ROW_BLOCK))
        .map(|((gxb, xb), gb)| {
            let mut gw = vec![0f32; d];
            let mut gxw = vec![0f32; d];
            for ((gxr, xr), gr) in gxb.chunks_mut(d).zip(xb.chunks(d)).zip(gb.chunks(d)) {
                let r = rstd(xr, eps);
                for ((t, g), w) in gxw.iter_mut().zip(gr).zip(w) {
                    *t = g * w;
                }
                // y = x·r·w with r = (mean(x²) + eps)^(-1/2): dx = r·g·w − x·r³·(g·w·x)/d.
                let c = r * r * r * dot(&gxw, xr) / d as f32;
                for i in 0..d {
                    gxr[i] += r * gxw[i] - c * xr[i];
                    gw[i] += gr[i] * xr[i] * r;
                }
            }
            gw
        })
        .collect();
    let mut gw = vec![0f32; d];
    for part in partials {
        gw.iter_mut().zip(&part).for_each(|(a, b)| *a += b);
    }
    gw
}

/// `sigmoid(a)` of the first halves `a` of the `2f`-wide rows `[a | b]`.
pub fn gate_sigmoid(ab: &[f32], f: usize) -> Vec<f32> {
    let fill = |i: usize, sb: &mut [MaybeUninit<f32>]| {
        let abb = &ab[i * 2 * f * ROW_BLOCK..];
        for (sr, abr) in sb.chunks_mut(f).zip(abb.chunks(2 * f)) {
            sigmoid_into(sr, &abr[..f]);
        }
    };
    // SAFETY: block i holds the rows of ab's block i, each written whole.
    unsafe { par_new(ab.len() / 2, f * ROW_BLOCK, fill) }
}

crate::vectorised!(
    /// `dst = σ(src)` (same length), through the vectorised exp at the CPU's widest vectors;
    /// `dst` need not be initialised.
    fn sigmoid_into / sigmoid_into_at(dst: &mut [MaybeUninit<f32>], src: &[f32]) = sigmoid_body;
);

#[inline(always)]
fn sigmoid_body(dst: &mut [MaybeUninit<f32>], src: &[f32]) {
    for (s, a) in dst.iter_mut().zip(src) {
        s.write(1.0 / (1.0 + fast_exp::exp(-a)));
    }
}

/// SwiGLU `silu(a)·b = a·σ(a)·b` of the rows `[a | b]`, given `σ(a)`.
pub fn swiglu(ab: &[f32], sig: &[f32], f: usize) -> Vec<f32> {
    let block = f * ROW_BLOCK;
    let fill = |i: usize, yb: &mut [MaybeUninit<f32>]| {
        let (abb, sb) = (&ab[i * 2 * block..], &sig[i * block..]);
        for ((yr, abr), sr) in yb.chunks_mut(f).zip(abb.chunks(2 * f)).zip(sb.chunks(f)) {
            let (a, b) = abr.split_at(f);
            for i in 0..f {
                yr[i].write(a[i] * sr[i] * b[i]);
            }
        }
    };
    // SAFETY: block i holds the rows of sig's block i, each written whole.
    unsafe { par_new(sig.len(), block, fill) }
}

/// Gradient of [`swiglu`] with respect to `[a | b]` given the output gradient `g`.
pub fn swiglu_backward(ab: &[f32], sig: &[f32], g: &[f32], f: usize) -> Vec<f32> {
    let block = f * ROW_BLOCK;
    let fill = |i: usize, ob: &mut [MaybeUninit<f32>]| {
        let rows = ob.chunks_mut(2 * f).zip(ab[i * 2 * block..].chunks(2 * f));
        let given = sig[i * block..].chunks(f).zip(g[i * block..].chunks(f));
        for ((or, abr), (sr, gr)) in rows.zip(given) {
            let (a, b) = abr.split_at(f);
            let (ga, gb) = or.split_at_mut(f);
            for i in 0..f {
                let s = sr[i];
                ga[i].write(gr[i] * b[i] * s * (1.0 + a[i] * (1.0 - s)));
                gb[i].write(gr[i] * a[i] * s);
            }
        }
    };
    // SAFETY: block i holds the rows of ab's block i, each written whole (both halves).
    unsafe { par_new(ab.len(), 2 * block, fill) }
}

// ---------------------------------------------------------------------------------------
// Rotary positions

/// Rotary position tables (rotate-half form, as LLaMA and the PyTorch reference).
#[derive(Debug, Clone)]
pub struct Rope {
    half: usize,
    cos: Vec<f32>,
    sin: Vec<f32>,
}

impl Rope {
    /// Tables for positions `0..max_positions` of heads of width `head_dim` (even).
    pub fn new(head_dim: usize, base: f64, max_positions: usize) -> Self {
        let half = head_dim / 2;
        let inv: Vec<f32> = (0..half)
            .map(|i| 1.0 / (base as f32).powf((2 * i) as f32 / head_dim as f32))
            .collect();
        let mut cos = Vec::with_capacity(max_positions * half);
        let mut sin = Vec::with_capacity(max_positions * half);
        for p in 0..max_positions {
            for &f in &inv {
                let angle = p as f32 * f;
                cos.push(angle.cos());
                sin.push(angle.sin());
            }
        }
        Self { half, cos, sin }
    }

    /// Number of positions covered.
    pub fn max_positions(&self) -> usize {
        self.cos.len() / self.half.max(1)
    }

    /// `(cos, sin)` of position `pos`, one value per pair of rotated channels.
    pub fn at(&self, pos: usize) -> (&[f32], &[f32]) {
        let h = self.half;
        (&self.cos[pos * h..][..h], &self.sin[pos * h..][..h])
    }

    /// Rotate `x` (one head) to position `pos`, or back when `inverse` (the transpose).
    fn rotate(&self, x: &mut [f32], pos: usize, inverse: bool) {
        let (cos, sin) = self.at(pos);
        let (x1, x2) = x.split_at_mut(self.half);
        for i in 0..self.half {
            let s = if inverse { -sin[i] } else { sin[i] };
            let (a, b) = (x1[i], x2[i]);
            x1[i] = a * cos[i] - b * s;
            x2[i] = b * cos[i] + a * s;
        }
    }
}

// ---------------------------------------------------------------------------------------
// Prefix-LM attention

/// Softmax of each row of `p` (rows × cols) over the allowed columns; rows with no allowed
/// column become zeros.
fn masked_softmax(p: &mut [f32], cols: usize, allowed: impl Fn(usize, usize) -> bool) {
    for (i, row) in p.chunks_mut(cols).enumerate() {
        let mut max = f32::NEG_INFINITY;
        for (j, v) in row.iter_mut().enumerate() {
            if allowed(i, j) {
                max = max.max(*v);
            } else {
                *v = f32::NEG_INFINITY;
            }
        }
        if max == f32::NEG_INFINITY {
            row.fill(0.0);
            continue;
        }
        let mut sum = 0f32;
        for v in row.iter_mut() {
            *v = (*v - max).exp();
            sum += *v;
        }
        let inv = 1.0 / sum;
        row.iter_mut().for_each(|v| *v *= inv);
    }
}

/// Per-head scratch of the attention kernels.
struct HeadScratch {
    q: Vec<f32>,
    k: Vec<f32>,
    v: Vec<f32>,
    o: Vec<f32>,
    p: Vec<f32>,
}

impl HeadScratch {
    fn new(slots: usize, hd: usize) -> Self {
        Self {
            q: vec![0.0; slots * hd],
            k: vec![0.0; slots * hd],
            v: vec![0.0; slots * hd],
            o: vec![0.0; slots * hd],
            p: vec![0.0; slots * slots],
        }
    }
}

/// Multi-head prefix-LM self-attention over packed `qkv` rows (`rows × 3d`, `[q | k | v]`,
/// heads contiguous in each) laid out by `layout`.
pub struct Attention<'a> {
    /// How the rows form sequences (mask and positions).
    pub layout: &'a SeqLayout,
    /// Rotary tables.
    pub rope: &'a Rope,
    /// Heads.
    pub heads: usize,
    /// Model width d.
    pub d: usize,
}

impl Attention<'_> {
    fn head_dim(&self) -> usize {
        self.d / self.heads
    }

    /// The real slots of sequence `b` with their rows.
    fn rows_of(&self, b: usize) -> impl Iterator<Item = (usize, usize)> + '_ {
        (0..self.layout.slots()).filter_map(move |s| self.layout.row(b, s).map(|r| (s, r)))
    }

    /// Copy head `h` of sequence `b` (slot order) out of `qkv` into `scr.q/k/v`, q and k
    /// rotated; padding slots (no row) get zeros, which the mask keeps out of every real
    /// slot's attention.
    fn gather(&self, qkv: &[f32], b: usize, h: usize, scr: &mut HeadScratch) {
        let (d, hd) = (self.d, self.head_dim());
        for s in 0..self.layout.slots() {
            let dst = s * hd..(s + 1) * hd;
            let Some(r) = self.layout.row(b, s) else {
                for x in [&mut scr.q, &mut scr.k, &mut scr.v] {
                    x[dst.clone()].fill(0.0);
                }
                continue;
            };
            let row = &qkv[r * 3 * d..][..3 * d];
            let pos = self.layout.position(b, s);
            scr.q[dst.clone()].copy_from_slice(&row[h * hd..][..hd]);
            scr.k[dst.clone()].copy_from_slice(&row[d + h * hd..][..hd]);
            scr.v[dst.clone()].copy_from_slice(&row[2 * d + h * hd..][..hd]);
            self.rope.rotate(&mut scr.q[dst.clone()], pos, false);
            self.rope.rotate(&mut scr.k[dst], pos, false);
        }
    }

    /// Rotary positions on q and k, the prefix-LM mask, softmax and both matmuls: the output
    /// (`rows × d`) and the softmax probabilities (sequence, head, slot, slot) the backward
    /// pass needs.
    pub fn forward(&self, qkv: &[f32]) -> (Vec<f32>, Vec<f32>) {
        let (slots, heads, d, hd) = (self.layout.slots(), self.heads, self.d, self.head_dim());
        let scale = 1.0 / (hd as f32).sqrt();
        let mut out = vec![0f32; self.layout.rows() * d];
        let mut probs = vec![0f32; self.layout.batch * heads * slots * slots];
        let out_ptr = SharedMut(out.as_mut_ptr());
        probs
            .par_chunks_mut((slots * slots).max(1))
            .enumerate()
            .for_each_init(
                || HeadScratch::new(slots, hd),
                |scr, (bh, p)| {
                    let (b, h) = (bh / heads, bh % heads);
                    self.gather(qkv, b, h, scr);
                    matmul(
                        p,
                        (&scr.q, false),
                        (&scr.k, true),
                        (slots, slots, hd),
                        scale,
                    );
                    masked_softmax(p, slots, |i, j| self.layout.allowed(b, i, j));
                    let mnk = (slots, hd, slots);
                    matmul(&mut scr.o, (p, false), (&scr.v, false), mnk, 1.0);
                    for (s, r) in self.rows_of(b) {
                        let at = r * d + h * hd;
                        // SAFETY: (row of sequence b, columns of head h) is written by this
                        // (b, h) item only, and lies inside `out` (rows × d).
                        unsafe { out_ptr.put(at, &scr.o[s * hd..][..hd]) };
                    }
                },
            );
        (out, probs)
    }

    /// Gradient with respect to `qkv` given the output gradient `grad` and the forward's
    /// probabilities.
    pub fn backward(&self, qkv: &[f32], probs: &[f32], grad: &[f32]) -> Vec<f32> {
        let (slots, heads, d, hd) = (self.layout.slots(), self.heads, self.d, self.head_dim());
        let scale = 1.0 / (hd as f32).sqrt();
        let mut out = vec![0f32; qkv.len()];
        let out_ptr = SharedMut(out.as_mut_ptr());
        let (sd, ds) = ((slots, hd, slots), (slots, slots, hd));
        (0..self.layout.batch * heads)
            .into_par_iter()
            .for_each_init(
                || (HeadScratch::new(slots, hd), HeadScratch::new(slots, hd)),
                |(scr, gs), bh| {
                    let (b, h) = (bh / heads, bh % heads);
                    let p = &probs[bh * slots * slots..][..slots * slots];
                    self.gather(qkv, b, h, scr);
                    // gs.o = dO (slots × hd), zero on padding slots.
                    gs.o.fill(0.0);
                    for (s, r) in self.rows_of(b) {
                        let at = r * d + h * hd;
                        gs.o[s * hd..(s + 1) * hd].copy_from_slice(&grad[at..at + hd]);
                    }
                    // dV = Pᵀ dO; dP = dO Vᵀ.
                    matmul(&mut gs.v, (p, true), (&gs.o, false), sd, 1.0);
                    matmul(&mut gs.p, (&gs.o, false), (&scr.v, true), ds, 1.0);
                    // dS = P ⊙ (dP − rowsum(P ⊙ dP)), times the score scale.
                    for (dp, pr) in gs.p.chunks_mut(slots).zip(p.chunks(slots)) {
                        let c = dot(dp, pr);
                        for (x, &pv) in dp.iter_mut().zip(pr) {
                            *x = pv * (*x - c) * scale;
                        }
                    }
                    // dQ = dS K; dK = dSᵀ Q (rotated frame), then rotated back.
                    matmul(&mut gs.q, (&gs.p, false), (&scr.k, false), sd, 1.0);
                    matmul(&mut gs.k, (&gs.p, true), (&scr.q, false), sd, 1.0);
                    for (s, row) in self.rows_of(b) {
                        let pos = self.layout.position(b, s);
                        let r = s * hd..(s + 1) * hd;
                        self.rope.rotate(&mut gs.q[r.clone()], pos, true);
                        self.rope.rotate(&mut gs.k[r.clone()], pos, true);
                        let at = row * 3 * d + h * hd;
                        for (part, src) in [&gs.q, &gs.k, &gs.v].into_iter().enumerate() {
                            // SAFETY: (row of sequence b, q/k/v columns of head h) is written by
                            // this (b, h) item only, inside `out` (rows × 3d).
                            unsafe { out_ptr.put(at + part * d, &src[r.clone()]) };
                        }
                    }
                },
            );
        out
    }

    /// Attention of the new slots `from..to` of every sequence against `cache` (filled below
    /// `from`): `qkv` holds the new rows sequence-major (`batch · (to − from) × 3d`). Stores
    /// their rotated keys and values in the cache and returns the output, same rows × d.
    pub fn cached(
        &self,
        qkv: &[f32],
        cache: &mut LayerCache,
        (from, to): (usize, usize),
    ) -> Vec<f32> {
        let (d, hd, slots, n_new) = (self.d, self.head_dim(), self.layout.slots(), to - from);
        let (layout, rope, heads) = (self.layout, self.rope, self.heads);
        let scale = 1.0 / (hd as f32).sqrt();
        let mut out = vec![0f32; layout.batch * n_new * d];
        let out_ptr = SharedMut(out.as_mut_ptr());
        cache
            .k
            .par_chunks_mut(slots * hd)
            .zip(cache.v.par_chunks_mut(slots * hd))
            .enumerate()
            .for_each_init(
                || HeadScratch::new(slots, hd),
                |scr, (bh, (kc, vc))| {
                    let (b, h) = (bh / heads, bh % heads);
                    for s in from..to {
                        let row = &qkv[(b * n_new + s - from) * 3 * d..][..3 * d];
                        let pos = layout.position(b, s);
                        let q = &mut scr.q[(s - from) * hd..][..hd];
                        q.copy_from_slice(&row[h * hd..][..hd]);
                        rope.rotate(q, pos, false);
                        let k = &mut kc[s * hd..(s + 1) * hd];
                        k.copy_from_slice(&row[d + h * hd..][..hd]);
                        rope.rotate(k, pos, false);
                        vc[s * hd..(s + 1) * hd].copy_from_slice(&row[2 * d + h * hd..][..hd]);
                    }
                    let p = &mut scr.p[..n_new * to];
                    new_row_scores(p, &scr.q, kc, (hd, to), scale);
                    masked_softmax(p, to, |i, j| layout.allowed(b, from + i, j));
                    weighted_values(&mut scr.o, p, vc, (hd, to));
                    for i in 0..n_new {
                        let at = (b * n_new + i) * d + h * hd;
                        // SAFETY: (new row of sequence b, columns of head h) belongs to this
                        // item only.
                        unsafe { out_ptr.put(at, &scr.o[i * hd..][..hd]) };
                    }
                },
            );
        out
    }
}

crate::vectorised!(
    /// Scores `scale · q_i · k_j` of a few new rows against the `to` cached keys
    /// (`dims`: head width, `to`). Decoding has one row per (sequence, head): plain dot
    /// products beat a gemm call of that size.
    fn new_row_scores / new_row_scores_at(
        p: &mut [f32],
        q: &[f32],
        k: &[f32],
        dims: (usize, usize),
        scale: f32,
    ) = new_row_scores_body;
);

#[inline(always)]
fn new_row_scores_body(p: &mut [f32], q: &[f32], k: &[f32], (hd, to): (usize, usize), scale: f32) {
    for (row, qi) in p.chunks_mut(to).zip(q.chunks(hd)) {
        for (v, kj) in row.iter_mut().zip(k.chunks(hd)) {
            *v = scale * dot(qi, kj);
        }
    }
}

crate::vectorised!(
    /// `o_i = Σ_j p_ij · v_j` of the new rows (`dims`: head width, `to`; weights already
    /// softmaxed, masked ones 0 and skipped).
    fn weighted_values / weighted_values_at(o: &mut [f32], p: &[f32], v: &[f32], dims: (usize, usize))
        = weighted_values_body;
);

/// Output columns one pass over the weights accumulates in registers (four AVX-512 vectors).
const VALUE_BLOCK: usize = 64;

#[inline(always)]
fn weighted_values_body(o: &mut [f32], p: &[f32], v: &[f32], (hd, to): (usize, usize)) {
    for (oi, row) in o.chunks_mut(hd).zip(p.chunks(to)) {
        for (c, oc) in oi.chunks_mut(VALUE_BLOCK).enumerate() {
            // Each output value sums its terms in the order j = 0, 1, …, whatever the block.
            let mut acc = [0f32; VALUE_BLOCK];
            let n = oc.len();
            for (&w, vj) in row.iter().zip(v.chunks(hd)) {
                if w == 0.0 {
                    continue;
                }
                match <&[f32; VALUE_BLOCK]>::try_from(&vj[c * VALUE_BLOCK..][..n]) {
                    Ok(vb) => acc.iter_mut().zip(vb).for_each(|(a, b)| *a += w * b),
                    Err(_) => (acc[..n].iter_mut().zip(&vj[c * VALUE_BLOCK..]))
                        .for_each(|(a, b)| *a += w * b),
                }
            }
            oc.copy_from_slice(&acc[..n]);
        }
    }
}

/// Key/value cache of one layer: rotated keys and values, (sequence, head, slot, head_dim).
#[derive(Debug, Clone)]
pub struct LayerCache {
    k: Vec<f32>,
    v: Vec<f32>,
}

impl LayerCache {
    /// An empty cache for `layout` and `heads` heads of width `head_dim`.
    pub fn new(layout: &SeqLayout, heads: usize, head_dim: usize) -> Self {
        let n = layout.batch * heads * layout.slots() * head_dim;
        Self {
            k: vec![0.0; n],
            v: vec![0.0; n],
        }
    }
}

// ---------------------------------------------------------------------------------------
// Cross-entropy

crate::vectorised!(
    /// `log p(target)` of one row of logits (log-softmax at the target).
    pub(crate) fn target_log_prob / target_log_prob_at(row: &[f32], target: usize) -> f32
        = target_log_prob_body;
);

#[inline(always)]
fn target_log_prob_body(row: &[f32], target: usize) -> f32 {
    let max = row_max(row);
    let mut sums = [0f32; 8];
    let chunks = row.chunks_exact(8);
    let tail = chunks.remainder();
    for c in chunks {
        for i in 0..8 {
            sums[i] += fast_exp::exp(c[i] - max);
        }
    }
    let sum = sums.iter().sum::<f32>() + tail.iter().map(|&v| fast_exp::exp(v - max)).sum::<f32>();
    row[target] - max - sum.ln()
}

/// `log p(target)` of every row of `logits` (rows × `vocab`); NaN where the target is
/// [`IGNORE`].
pub fn target_log_probs(logits: &[f32], vocab: usize, targets: &[u32]) -> Vec<f32> {
    logits
        .par_chunks(vocab)
        .zip(targets.par_iter())
        .map(|(row, &t)| {
            if t == IGNORE {
                f32::NAN
            } else {
                target_log_prob(row, t as usize)
            }
        })
        .collect()
}

/// Knowledge distillation (LwF): `weight · T² · KL(softmax(teacher/T) ‖ softmax(logits/T))`
/// averaged over the rows whose target is not [`IGNORE`], and its gradient with respect to
/// `logits`, `weight · T · (softmax(logits/T) − softmax(teacher/T)) / rows`.
pub fn distillation(
    logits: &[f32],
    teacher: &[f32],
    vocab: usize,
    targets: &[u32],
    weight: f32,
    temperature: f32,
) -> (f32, Vec<f32>) {
    let valid = targets.iter().filter(|&&t| t != IGNORE).count().max(1);
    let softmax = |row: &[f32]| -> Vec<f32> {
        let max = row
            .iter()
            .fold(f32::NEG_INFINITY, |m, &v| m.max(v / temperature));
        let e: Vec<f32> = row.iter().map(|&v| (v / temperature - max).exp()).collect();
        let sum: f32 = e.iter().sum();
        e.into_iter().map(|v| v / sum).collect()
    };
    let mut grad = vec![0f32; logits.len()];
    let scale = weight / valid as f32;
    let losses: Vec<f64> = grad
        .par_chunks_mut(vocab)
        .zip(logits.par_chunks(vocab).zip(teacher.par_chunks(vocab)))
        .zip(targets.par_iter())
        .map(|((g, (student, teacher)), &t)| {
            if t == IGNORE {
                return 0.0;
            }
            let (p, q) = (softmax(student), softmax(teacher));
            let mut kl = 0f64;
            for ((g, &p), &q) in g.iter_mut().zip(&p).zip(&q) {
                *g = scale * temperature * (p - q);
                if q > 0.0 {
                    kl += f64::from(q)
                        * (f64::from(q).ln() - f64::from(p.max(f32::MIN_POSITIVE)).ln());
                }
            }
            kl
        })
        .collect();
    let t2 = f64::from(temperature * temperature);
    let loss = f64::from(weight) * t2 * losses.iter().sum::<f64>() / valid as f64;
    (loss as f32, grad)
}

/// Mean cross-entropy over the rows whose target is not [`IGNORE`], and the gradient of that
/// mean with respect to the logits (`(softmax − onehot) / rows with a target`).
pub fn cross_entropy(logits: &[f32], vocab: usize, targets: &[u32]) -> (f32, Vec<f32>) {
    let valid = targets.iter().filter(|&&t| t != IGNORE).count().max(1);
    let scale = 1.0 / valid as f32;
    let mut grad = vec![0f32; logits.len()];
    let losses: Vec<f64> = grad
        .par_chunks_mut(vocab)
        .zip(logits.par_chunks(vocab))
        .zip(targets.par_iter())
        .map(|((g, row), &t)| {
            if t == IGNORE {
                return 0.0;
            }
            g.copy_from_slice(row);
            cross_entropy_row(g, t as usize, scale)
        })
        .collect();
    let mean = losses.iter().sum::<f64>() / valid as f64;
    (mean as f32, grad)
}

crate::vectorised!(
    /// Cross-entropy of one row of logits at `target`, turning the row into its gradient
    /// scaled by `scale`: `scale · (softmax − onehot)`.
    pub(crate) fn cross_entropy_row / cross_entropy_row_at(
        row: &mut [f32],
        target: usize,
        scale: f32,
    ) -> f64 = cross_entropy_row_body;
);

#[inline(always)]
fn cross_entropy_row_body(row: &mut [f32], target: usize, scale: f32) -> f64 {
    let max = row_max(row);
    let at_target = row[target];
    let mut sums = [0f32; 8];
    let mut chunks = row.chunks_exact_mut(8);
    for c in &mut chunks {
        for i in 0..8 {
            c[i] = fast_exp::exp(c[i] - max);
            sums[i] += c[i];
        }
    }
    let tail = chunks.into_remainder();
    tail.iter_mut().for_each(|v| *v = fast_exp::exp(*v - max));
    let sum = sums.iter().sum::<f32>() + tail.iter().sum::<f32>();
    let inv = scale / sum;
    row.iter_mut().for_each(|v| *v *= inv);
    row[target] -= scale;
    f64::from(max - at_target + sum.ln())
}

/// The largest value of a row (eight lanes, so it vectorises).
#[inline(always)]
fn row_max(row: &[f32]) -> f32 {
    let mut lanes = [f32::NEG_INFINITY; 8];
    let chunks = row.chunks_exact(8);
    let tail = chunks.remainder();
    for c in chunks {
        for i in 0..8 {
            lanes[i] = if c[i] > lanes[i] { c[i] } else { lanes[i] };
        }
    }
    lanes
        .iter()
        .chain(tail)
        .fold(f32::NEG_INFINITY, |m, &v| m.max(v))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn values(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = motionscale_core::rng::SplitMix64(seed);
        (0..n).map(|_| rng.range(-1.0, 1.0) as f32).collect()
    }

    /// σ, the cross-entropy row and log p(target) give the same bits at every vector level.
    #[test]
    fn row_kernels_agree_at_every_vector_level() {
        let row: Vec<f32> = values(1027, 3).iter().map(|v| v * 9.0).collect();
        crate::simd::assert_levels_agree(|isa| {
            let mut sig = vec![MaybeUninit::uninit(); row.len()];
            sigmoid_into_at(isa, &mut sig, &row);
            // SAFETY: sigmoid_into wrote every value.
            let sig: Vec<f32> = sig
                .into_iter()
                .map(|v| unsafe { v.assume_init() })
                .collect();
            let mut grad = row.clone();
            let ce = cross_entropy_row_at(isa, &mut grad, 17, 0.5);
            let log_p = target_log_prob_at(isa, &row, 17);
            let mut out = crate::simd::bits(&[sig, grad].concat());
            out.extend([
                ce.to_bits() as u32,
                (ce.to_bits() >> 32) as u32,
                log_p.to_bits(),
            ]);
            out
        });
    }

    /// Decoding's scores and weighted values give the same bits at every vector level,
    /// with a head width that leaves a partial block.
    #[test]
    fn decode_attention_kernels_agree_at_every_vector_level() {
        for hd in [64, 80] {
            let (rows, to) = (2, 37);
            let (q, k) = (values(rows * hd, 5), values(to * hd, 6));
            let v = values(to * hd, 7);
            crate::simd::assert_levels_agree(|isa| {
                let mut p = vec![0f32; rows * to];
                new_row_scores_at(isa, &mut p, &q, &k, (hd, to), 0.125);
                masked_softmax(&mut p, to, |i, j| j % 5 != 0 || i == 0);
                let mut o = vec![0f32; rows * hd];
                weighted_values_at(isa, &mut o, &p, &v, (hd, to));
                // The plain sums, term by term in key order.
                for (i, oi) in o.chunks(hd).enumerate() {
                    for (l, &got) in oi.iter().enumerate() {
                        let want = (0..to).fold(0f32, |a, j| match p[i * to + j] {
                            0.0 => a,
                            w => a + w * v[j * hd + l],
                        });
                        assert_eq!(got.to_bits(), want.to_bits(), "{isa:?} ({i}, {l})");
                    }
                }
                crate::simd::bits(&[p, o].concat())
            });
        }
    }

    #[test]
    fn distillation_is_zero_against_itself_and_its_gradient_is_exact() {
        let logits = [0.5f32, -1.0, 2.0, 0.1, 0.3, -0.2];
        let targets = [1u32, IGNORE];
        let (loss, grad) = distillation(&logits, &logits, 3, &targets, 1.0, 2.0);
        assert!(loss.abs() < 1e-7 && grad.iter().all(|g| g.abs() < 1e-7));
        let teacher = [0.0f32, 1.0, -1.0, 5.0, 5.0, 5.0];
        let (loss, grad) = distillation(&logits, &teacher, 3, &targets, 0.5, 2.0);
        assert!(loss > 0.0);
        assert!(grad[3..].iter().all(|&g| g == 0.0), "ignored row");
        for k in 0..3 {
            let eps = 1e-3f32;
            let at = |d: f32| {
                let mut l = logits;
                l[k] += d;
                f64::from(distillation(&l, &teacher, 3, &targets, 0.5, 2.0).0)
            };
            let numeric = (at(eps) - at(-eps)) / (2.0 * f64::from(eps));
            assert!(
                (numeric - f64::from(grad[k])).abs() < 1e-3,
                "{k}: {numeric} vs {}",
                grad[k]
            );
        }
    }

    #[test]
    fn cross_entropy_and_log_probs_agree_and_ignore_padding() {
        let logits = values(4 * 6, 6);
        let targets = [2, IGNORE, 5, 0];
        let (loss, grad) = cross_entropy(&logits, 6, &targets);
        let lp = target_log_probs(&logits, 6, &targets);
        assert!(lp[1].is_nan());
        assert!((loss + (lp[0] + lp[2] + lp[3]) / 3.0).abs() < 1e-6);
        assert!(grad[6..12].iter().all(|&g| g == 0.0));
        // Each row's gradient sums to zero (softmax − onehot).
        for row in grad.chunks(6) {
            assert!(row.iter().sum::<f32>().abs() < 1e-6);
        }
    }

    #[test]
    fn text_slots_attend_both_ways_and_never_to_motion() {
        let layout = SeqLayout::new(vec![3], 4);
        let rope = Rope::new(4, 10_000.0, 16);
        let attn = Attention {
            layout: &layout,
            rope: &rope,
            heads: 2,
            d: 8,
        };
        let qkv = values(layout.rows() * 24, 9);
        let base = attn.forward(&qkv).0;
        let bump = |row: usize| {
            let mut v = qkv.clone();
            v[row * 24..(row + 1) * 24]
                .iter_mut()
                .for_each(|x| *x += 0.5);
            attn.forward(&v).0
        };
        let row_diff = |a: &[f32], b: &[f32], row: usize| {
            (row * 8..(row + 1) * 8)
                .map(|i| (a[i] - b[i]).abs())
                .fold(0.0, f32::max)
        };
        let row = |s: usize| layout.row(0, s).expect("a real slot");
        // The last text slot changes the first (text attends forwards) and vice versa.
        let last = bump(row(2));
        assert!(row_diff(&base, &last, row(0)) > 1e-4);
        let first = bump(row(0));
        assert!(row_diff(&base, &first, row(2)) > 1e-4);
        // A motion slot changes no text slot.
        let motion = bump(row(4));
        for s in 0..3 {
            assert_eq!(row_diff(&base, &motion, row(s)), 0.0);
        }
    }
}
