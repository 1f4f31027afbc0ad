//! Fused CPU kernels of the prefix LM as candle custom ops with backward passes: the
//! sublayers `RMSNorm → linear`, `linear + residual` and `SwiGLU → linear + residual`,
//! prefix-LM attention (rotary positions, mask, softmax, both matmuls) and cross-entropy.
//!
//! candle 0.11's RMSNorm, softmax and rope ops have no backward pass, and its autograd adds
//! a zero-initialised gradient buffer, an allocation and a full pass for every edge of the
//! graph. Fusing each sublayer into one op (its matmuls through `gemm` over all rows at
//! once, elementwise work in rayon-parallel row blocks) leaves five graph nodes per block.
//! Every reduction runs in a fixed order, so results never depend on thread scheduling: a
//! resumed run reproduces an uninterrupted one bit for bit. CPU only (no CUDA/Metal kernels).

use crate::prefix_lm::SeqLayout;
use candle_core::{bail, CpuStorage, CustomOp1, CustomOp3, Layout, Result, Shape};
use candle_core::{DType, Device, Storage, Tensor};
use rayon::prelude::*;
use std::sync::{Arc, OnceLock};

/// Target id of a position without loss (padding).
pub const IGNORE: u32 = u32::MAX;

/// Rows per parallel work item of the row-wise kernels (fixed, so reductions are too).
const ROW_BLOCK: usize = 32;

fn f32s<'a>(storage: &'a CpuStorage, layout: &Layout, op: &str) -> Result<&'a [f32]> {
    let CpuStorage::F32(values) = storage else {
        bail!("{op}: expected f32 values")
    };
    match layout.contiguous_offsets() {
        Some((start, end)) => Ok(&values[start..end]),
        None => bail!("{op}: expected a contiguous tensor"),
    }
}

/// Sum of `a[i]·b[i]` with eight partial sums (vectorises; fixed order).
fn dot(a: &[f32], b: &[f32]) -> f32 {
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

fn rstd(x: &[f32], eps: f32) -> f32 {
    1.0 / (dot(x, x) / x.len() as f32 + eps).sqrt()
}

/// Raw pointer that worker threads write disjoint parts through.
#[derive(Clone, Copy)]
struct SharedMut(*mut f32);
// SAFETY: every user writes a disjoint set of indices, documented at each use.
unsafe impl Send for SharedMut {}
unsafe impl Sync for SharedMut {}

impl SharedMut {
    /// The pointer `offset` elements in (a method, so closures capture the whole wrapper).
    fn at(self, offset: usize) -> *mut f32 {
        self.0.wrapping_add(offset)
    }
}

/// A matrix operand: row-major values, read transposed when the flag is set.
type Operand<'a> = (&'a [f32], bool);

/// `dst (+)= scale · op(lhs) · op(rhs)` for row-major matrices: `op(lhs)` is m×k (stored
/// k×m when transposed), `op(rhs)` is k×n (stored n×k when transposed), `dst` is m×n and
/// is added to when `accumulate`. Single-threaded unless `parallel`.
fn gemm_with(
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
    let parallelism = if parallel && threads > 1 {
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

/// One large product over all rows, spread over the rayon threads (`dst (+)= lhs · rhs`).
fn gemm(dst: &mut [f32], lhs: Operand, rhs: Operand, mnk: (usize, usize, usize), accumulate: bool) {
    gemm_with(dst, lhs, rhs, mnk, (accumulate, 1.0, true));
}

/// One small single-threaded product of the attention kernels (`dst = scale · lhs · rhs`),
/// which run many of them in parallel.
fn matmul(dst: &mut [f32], lhs: Operand, rhs: Operand, mnk: (usize, usize, usize), scale: f32) {
    gemm_with(dst, lhs, rhs, mnk, (false, scale, false));
}

/// Run `f` on the f32 values of contiguous CPU tensors.
fn with_values<R>(tensors: &[&Tensor], f: impl FnOnce(&[&[f32]]) -> Result<R>) -> Result<R> {
    let guards: Vec<_> = tensors.iter().map(|t| t.storage_and_layout()).collect();
    let slices = guards
        .iter()
        .map(|(storage, layout)| match &**storage {
            Storage::Cpu(cpu) => f32s(cpu, layout, "prefix LM kernel"),
            _ => bail!("the prefix LM kernels run on the CPU only"),
        })
        .collect::<Result<Vec<_>>>()?;
    f(&slices)
}

fn tensor(values: Vec<f32>, shape: impl Into<Shape>) -> Result<Tensor> {
    Tensor::from_vec(values, shape, &Device::Cpu)
}

/// RMSNorm of each `d`-wide row of `x`, scaled by `w`.
fn rms_rows(x: &[f32], w: &[f32], eps: f32) -> Vec<f32> {
    let d = w.len();
    let mut y = vec![0f32; x.len()];
    y.par_chunks_mut(d * ROW_BLOCK)
        .zip(x.par_chunks(d * ROW_BLOCK))
        .for_each(|(yb, xb)| {
            for (yr, xr) in yb.chunks_mut(d).zip(xb.chunks(d)) {
                let r = rstd(xr, eps);
                for ((y, x), w) in yr.iter_mut().zip(xr).zip(w) {
                    *y = x * r * w;
                }
            }
        });
    y
}

/// Gradients of [`rms_rows`] with respect to `x` and `w` given the output gradient `g`.
fn rms_rows_grad(x: &[f32], w: &[f32], g: &[f32], eps: f32) -> (Vec<f32>, Vec<f32>) {
    let d = w.len();
    let mut gx = vec![0f32; x.len()];
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
                    gxr[i] = r * gxw[i] - c * xr[i];
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
    (gx, gw)
}

/// `sigmoid(a)` of the first halves `a` of the `2f`-wide rows `[a | b]`.
fn gate_sigmoid(ab: &[f32], f: usize) -> Vec<f32> {
    let mut s = vec![0f32; ab.len() / 2];
    s.par_chunks_mut(f * ROW_BLOCK)
        .zip(ab.par_chunks(2 * f * ROW_BLOCK))
        .for_each(|(sb, abb)| {
            for (sr, abr) in sb.chunks_mut(f).zip(abb.chunks(2 * f)) {
                for (s, a) in sr.iter_mut().zip(&abr[..f]) {
                    *s = 1.0 / (1.0 + (-a).exp());
                }
            }
        });
    s
}

/// SwiGLU `silu(a)·b = a·σ(a)·b` of the rows `[a | b]`, given `σ(a)`.
fn swiglu_rows(ab: &[f32], sig: &[f32], f: usize) -> Vec<f32> {
    let mut y = vec![0f32; sig.len()];
    y.par_chunks_mut(f * ROW_BLOCK)
        .zip(ab.par_chunks(2 * f * ROW_BLOCK))
        .zip(sig.par_chunks(f * ROW_BLOCK))
        .for_each(|((yb, abb), sb)| {
            for ((yr, abr), sr) in yb.chunks_mut(f).zip(abb.chunks(2 * f)).zip(sb.chunks(f)) {
                let (a, b) = abr.split_at(f);
                for i in 0..f {
                    yr[i] = a[i] * sr[i] * b[i];
                }
            }
        });
    y
}

/// Gradient of [`swiglu_rows`] with respect to `[a | b]` given the output gradient `g`.
fn swiglu_rows_grad(ab: &[f32], sig: &[f32], g: &[f32], f: usize) -> Vec<f32> {
    let mut out = vec![0f32; ab.len()];
    out.par_chunks_mut(2 * f * ROW_BLOCK)
        .zip(ab.par_chunks(2 * f * ROW_BLOCK))
        .zip(
            sig.par_chunks(f * ROW_BLOCK)
                .zip(g.par_chunks(f * ROW_BLOCK)),
        )
        .for_each(|((ob, abb), (sb, gb))| {
            let rows = ob.chunks_mut(2 * f).zip(abb.chunks(2 * f));
            for ((or, abr), (sr, gr)) in rows.zip(sb.chunks(f).zip(gb.chunks(f))) {
                let (a, b) = abr.split_at(f);
                let (ga, gb) = or.split_at_mut(f);
                for i in 0..f {
                    let s = sr[i];
                    ga[i] = gr[i] * b[i] * s * (1.0 + a[i] * (1.0 - s));
                    gb[i] = gr[i] * a[i] * s;
                }
            }
        });
    out
}

/// Rows and width of a 2-D layout.
fn dims2(l: &Layout) -> Result<(usize, usize)> {
    l.shape().dims2()
}

// ---------------------------------------------------------------------------------------
// Sublayers

/// `RMSNorm(h; norm) · wᵀ` for `h` (rows × d), `norm` (d), `w` (out × d).
pub fn norm_linear(h: &Tensor, norm: &Tensor, w: &Tensor, eps: f32) -> Result<Tensor> {
    h.contiguous()?
        .apply_op3(&norm.contiguous()?, &w.contiguous()?, NormLinear { eps })
}

struct NormLinear {
    eps: f32,
}

impl CustomOp3 for NormLinear {
    fn name(&self) -> &'static str {
        "prefix-lm-norm-linear"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let h = f32s(s1, l1, self.name())?;
        let norm = f32s(s2, l2, self.name())?;
        let w = f32s(s3, l3, self.name())?;
        let ((rows, d), (out, d_w)) = (dims2(l1)?, dims2(l3)?);
        if d != d_w || norm.len() != d {
            bail!(
                "norm_linear: {rows}×{d} input, norm {}, weight {out}×{d_w}",
                norm.len()
            )
        }
        let xn = rms_rows(h, norm, self.eps);
        let mut y = vec![0f32; rows * out];
        gemm(&mut y, (&xn, false), (w, true), (rows, out, d), false);
        Ok((CpuStorage::F32(y), Shape::from((rows, out))))
    }

    fn bwd(
        &self,
        h: &Tensor,
        norm: &Tensor,
        w: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        let ((rows, d), (out, _)) = (h.dims2()?, w.dims2()?);
        with_values(&[h, norm, w, &grad], |v| {
            let (h, norm, w, g) = (v[0], v[1], v[2], v[3]);
            let xn = rms_rows(h, norm, self.eps);
            let mut gw = vec![0f32; out * d];
            gemm(&mut gw, (g, true), (&xn, false), (out, d, rows), false);
            let mut gxn = xn;
            gemm(&mut gxn, (g, false), (w, false), (rows, d, out), false);
            let (gh, gnorm) = rms_rows_grad(h, norm, &gxn, self.eps);
            Ok((
                Some(tensor(gh, (rows, d))?),
                Some(tensor(gnorm, d)?),
                Some(tensor(gw, (out, d))?),
            ))
        })
    }
}

/// `h + x · wᵀ` for `x` (rows × in), `w` (out × in), `h` (rows × out).
pub fn linear_residual(x: &Tensor, w: &Tensor, h: &Tensor) -> Result<Tensor> {
    let op = LinearResidual::new(false);
    x.contiguous()?
        .apply_op3(&w.contiguous()?, &h.contiguous()?, op)
}

/// `h + swiglu(ab) · wᵀ` for `ab` (rows × 2f, `[a | b]`), `w` (out × f), `h` (rows × out).
pub fn swiglu_linear_residual(ab: &Tensor, w: &Tensor, h: &Tensor) -> Result<Tensor> {
    let op = LinearResidual::new(true);
    ab.contiguous()?
        .apply_op3(&w.contiguous()?, &h.contiguous()?, op)
}

/// `h + act(x) · wᵀ`, act = identity or SwiGLU of the halves of x.
struct LinearResidual {
    swiglu: bool,
    /// SwiGLU: σ(a) of the forward pass, kept for the backward (saves two passes of exp).
    sigmoid: OnceLock<Vec<f32>>,
}

impl LinearResidual {
    fn new(swiglu: bool) -> Self {
        Self {
            swiglu,
            sigmoid: OnceLock::new(),
        }
    }

    /// `(rows, out, inner)` of the inputs, checked.
    fn dims(&self, x: &Layout, w: &Layout, h: &Layout) -> Result<(usize, usize, usize)> {
        let ((rows, width), (out, inner), (h_rows, h_out)) = (dims2(x)?, dims2(w)?, dims2(h)?);
        let act_width = if self.swiglu { width / 2 } else { width };
        if act_width != inner || h_rows != rows || h_out != out || (self.swiglu && width % 2 != 0) {
            bail!("linear_residual: x {rows}×{width}, w {out}×{inner}, h {h_rows}×{h_out}")
        }
        Ok((rows, out, inner))
    }

    /// σ(a) of `x` (SwiGLU only), computed once.
    fn sigmoid(&self, x: &[f32], inner: usize) -> &[f32] {
        self.sigmoid.get_or_init(|| gate_sigmoid(x, inner))
    }
}

impl CustomOp3 for LinearResidual {
    fn name(&self) -> &'static str {
        "prefix-lm-linear-residual"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let x = f32s(s1, l1, self.name())?;
        let w = f32s(s2, l2, self.name())?;
        let h = f32s(s3, l3, self.name())?;
        let (rows, out, inner) = self.dims(l1, l2, l3)?;
        let mut y = h.to_vec();
        if self.swiglu {
            let act = swiglu_rows(x, self.sigmoid(x, inner), inner);
            gemm(&mut y, (&act, false), (w, true), (rows, out, inner), true);
        } else {
            gemm(&mut y, (x, false), (w, true), (rows, out, inner), true);
        }
        Ok((CpuStorage::F32(y), Shape::from((rows, out))))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _h: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        let (rows, width) = x.dims2()?;
        let (out, inner) = w.dims2()?;
        let (gx, gw) = with_values(&[x, w, &grad], |v| {
            let (x, w, g) = (v[0], v[1], v[2]);
            let mut gw = vec![0f32; out * inner];
            let mut ga = vec![0f32; rows * inner];
            gemm(&mut ga, (g, false), (w, false), (rows, inner, out), false);
            if !self.swiglu {
                gemm(&mut gw, (g, true), (x, false), (out, inner, rows), false);
                return Ok((ga, gw));
            }
            let sig = self.sigmoid(x, inner);
            let act = swiglu_rows(x, sig, inner);
            gemm(&mut gw, (g, true), (&act, false), (out, inner, rows), false);
            Ok((swiglu_rows_grad(x, sig, &ga, inner), gw))
        })?;
        Ok((
            Some(tensor(gx, (rows, width))?),
            Some(tensor(gw, (out, inner))?),
            Some(grad),
        ))
    }
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

    /// Rotate `x` (one head) to position `pos`, or back when `inverse` (the transpose).
    fn rotate(&self, x: &mut [f32], pos: usize, inverse: bool) {
        let h = self.half;
        let (cos, sin) = (
            &self.cos[pos * h..(pos + 1) * h],
            &self.sin[pos * h..(pos + 1) * h],
        );
        let (x1, x2) = x.split_at_mut(h);
        for i in 0..h {
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

/// Prefix-LM self-attention over packed `qkv` rows (`rows × 3d`, `[q | k | v]`, heads
/// contiguous in each) laid out by `layout`: rotary positions on q and k, the prefix-LM mask,
/// softmax and both matmuls. Returns `rows × d`.
pub fn prefix_attention(
    qkv: &Tensor,
    layout: &Arc<SeqLayout>,
    rope: &Arc<Rope>,
    heads: usize,
) -> Result<Tensor> {
    qkv.contiguous()?.apply_op1(PrefixAttention {
        layout: layout.clone(),
        rope: rope.clone(),
        heads,
        probs: OnceLock::new(),
    })
}

struct PrefixAttention {
    layout: Arc<SeqLayout>,
    rope: Arc<Rope>,
    heads: usize,
    /// Softmax probabilities of the forward pass, (batch, head, slot, slot), for the backward.
    probs: OnceLock<Vec<f32>>,
}

impl PrefixAttention {
    /// `(d, head_dim)` of a `rows × 3d` input, checked against the layout.
    fn dims(&self, layout: &Layout) -> Result<(usize, usize)> {
        let (rows, three_d) = layout.shape().dims2()?;
        let d = three_d / 3;
        if rows != self.layout.rows() || three_d % 3 != 0 || d % self.heads != 0 {
            bail!(
                "prefix attention: qkv {rows}×{three_d} does not fit {} rows of {} heads",
                self.layout.rows(),
                self.heads
            )
        }
        if self.layout.max_position() >= self.rope.max_positions() {
            bail!(
                "prefix attention: position {} beyond the rotary table ({} positions)",
                self.layout.max_position(),
                self.rope.max_positions()
            )
        }
        Ok((d, d / self.heads))
    }

    /// Copy head `h` of sample `b` (slot order) out of `qkv` into `scr.q/k/v`, q and k rotated.
    fn gather(&self, qkv: &[f32], b: usize, h: usize, d: usize, scr: &mut HeadScratch) {
        let hd = d / self.heads;
        for s in 0..self.layout.slots() {
            let row = &qkv[self.layout.row(b, s) * 3 * d..][..3 * d];
            let pos = self.layout.position(b, s);
            let dst = s * hd..(s + 1) * hd;
            scr.q[dst.clone()].copy_from_slice(&row[h * hd..][..hd]);
            scr.k[dst.clone()].copy_from_slice(&row[d + h * hd..][..hd]);
            scr.v[dst.clone()].copy_from_slice(&row[2 * d + h * hd..][..hd]);
            self.rope.rotate(&mut scr.q[dst.clone()], pos, false);
            self.rope.rotate(&mut scr.k[dst], pos, false);
        }
    }
}

impl CustomOp1 for PrefixAttention {
    fn name(&self) -> &'static str {
        "prefix-lm-attention"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let qkv = f32s(s, l, self.name())?;
        let (d, hd) = self.dims(l)?;
        let (slots, heads) = (self.layout.slots(), self.heads);
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
                    self.gather(qkv, b, h, d, scr);
                    matmul(
                        p,
                        (&scr.q, false),
                        (&scr.k, true),
                        (slots, slots, hd),
                        scale,
                    );
                    masked_softmax(p, slots, |i, j| self.layout.allowed(b, i, j));
                    matmul(
                        &mut scr.o,
                        (p, false),
                        (&scr.v, false),
                        (slots, hd, slots),
                        1.0,
                    );
                    for s in 0..slots {
                        let at = self.layout.row(b, s) * d + h * hd;
                        // SAFETY: (row of sample b, columns of head h) is written by this
                        // (b, h) item only, and lies inside `out` (rows × d).
                        unsafe {
                            std::ptr::copy_nonoverlapping(
                                scr.o[s * hd..].as_ptr(),
                                out_ptr.at(at),
                                hd,
                            )
                        };
                    }
                },
            );
        // The forward runs once per op; a second run would only recompute the same values.
        let _ = self.probs.set(probs);
        Ok((CpuStorage::F32(out), Shape::from((self.layout.rows(), d))))
    }

    fn bwd(&self, qkv: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let grad = grad.contiguous()?;
        let (d, hd) = self.dims(qkv.layout())?;
        let out = with_values(&[qkv, &grad], |v| self.backward(v[0], v[1], d, hd))?;
        Ok(Some(tensor(out, qkv.shape())?))
    }
}

impl PrefixAttention {
    /// Gradient with respect to the packed `qkv` input, given the output gradient `grad`.
    fn backward(&self, qkv: &[f32], grad: &[f32], d: usize, hd: usize) -> Result<Vec<f32>> {
        let Some(probs) = self.probs.get() else {
            bail!("prefix attention: backward before forward")
        };
        let (slots, heads) = (self.layout.slots(), self.heads);
        let scale = 1.0 / (hd as f32).sqrt();
        let mut out = vec![0f32; qkv.len()];
        let out_ptr = SharedMut(out.as_mut_ptr());
        (0..self.layout.batch * heads)
            .into_par_iter()
            .for_each_init(
                || (HeadScratch::new(slots, hd), HeadScratch::new(slots, hd)),
                |(scr, gs), bh| {
                    let (b, h) = (bh / heads, bh % heads);
                    let p = &probs[bh * slots * slots..][..slots * slots];
                    self.gather(qkv, b, h, d, scr);
                    // gs.o = dO (slots × hd).
                    for s in 0..slots {
                        let at = self.layout.row(b, s) * d + h * hd;
                        gs.o[s * hd..(s + 1) * hd].copy_from_slice(&grad[at..at + hd]);
                    }
                    // dV = Pᵀ dO; dP = dO Vᵀ.
                    matmul(
                        &mut gs.v,
                        (p, true),
                        (&gs.o, false),
                        (slots, hd, slots),
                        1.0,
                    );
                    matmul(
                        &mut gs.p,
                        (&gs.o, false),
                        (&scr.v, true),
                        (slots, slots, hd),
                        1.0,
                    );
                    // dS = P ⊙ (dP − rowsum(P ⊙ dP)), times the score scale.
                    for (dp, pr) in gs.p.chunks_mut(slots).zip(p.chunks(slots)) {
                        let c = dot(dp, pr);
                        for (x, &pv) in dp.iter_mut().zip(pr) {
                            *x = pv * (*x - c) * scale;
                        }
                    }
                    // dQ = dS K; dK = dSᵀ Q (rotated frame).
                    matmul(
                        &mut gs.q,
                        (&gs.p, false),
                        (&scr.k, false),
                        (slots, hd, slots),
                        1.0,
                    );
                    matmul(
                        &mut gs.k,
                        (&gs.p, true),
                        (&scr.q, false),
                        (slots, hd, slots),
                        1.0,
                    );
                    for s in 0..slots {
                        let pos = self.layout.position(b, s);
                        let r = s * hd..(s + 1) * hd;
                        self.rope.rotate(&mut gs.q[r.clone()], pos, true);
                        self.rope.rotate(&mut gs.k[r.clone()], pos, true);
                        let at = self.layout.row(b, s) * 3 * d + h * hd;
                        for (part, src) in [&gs.q, &gs.k, &gs.v].into_iter().enumerate() {
                            // SAFETY: (row of sample b, q/k/v columns of head h) is written by
                            // this (b, h) item only, inside `out` (rows × 3d).
                            unsafe {
                                std::ptr::copy_nonoverlapping(
                                    src[r.clone()].as_ptr(),
                                    out_ptr.at(at + part * d),
                                    hd,
                                )
                            };
                        }
                    }
                },
            );
        Ok(out)
    }
}

/// Key/value cache of one layer: rotated keys and values, (batch, head, slot, head_dim).
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

/// Attention of new slots `from..to` of every sample against the cache (filled below
/// `from`): `qkv` holds the new rows sample-major (`batch · (to − from) × 3d`). Stores their
/// rotated keys and values in `cache` and returns the attention output, same row order × d.
#[allow(clippy::too_many_arguments)]
pub fn cached_attention(
    qkv: &[f32],
    cache: &mut LayerCache,
    layout: &SeqLayout,
    rope: &Rope,
    heads: usize,
    d: usize,
    (from, to): (usize, usize),
) -> Vec<f32> {
    let (hd, slots, n_new) = (d / heads, layout.slots(), to - from);
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
                matmul(p, (&scr.q, false), (kc, true), (n_new, to, hd), scale);
                masked_softmax(p, to, |i, j| layout.allowed(b, from + i, j));
                matmul(&mut scr.o, (p, false), (vc, false), (n_new, hd, to), 1.0);
                for i in 0..n_new {
                    let at = (b * n_new + i) * d + h * hd;
                    // SAFETY: (new row of sample b, columns of head h) belongs to this item.
                    unsafe {
                        std::ptr::copy_nonoverlapping(scr.o[i * hd..].as_ptr(), out_ptr.at(at), hd)
                    };
                }
            },
        );
    out
}

// ---------------------------------------------------------------------------------------
// Cross-entropy

/// `log p(target)` of one row of logits (log-softmax at the target).
fn target_log_prob(row: &[f32], target: usize) -> f32 {
    let max = row.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
    let sum: f32 = row.iter().map(|&v| (v - max).exp()).sum();
    row[target] - max - sum.ln()
}

/// `log p(target)` of every row of `logits` (rows × V); NaN where the target is [`IGNORE`].
pub fn target_log_probs(logits: &Tensor, targets: &[u32]) -> Result<Vec<f32>> {
    let (rows, vocab) = logits.dims2()?;
    if rows != targets.len() {
        bail!("{rows} rows of logits for {} targets", targets.len())
    }
    let values = logits
        .to_dtype(DType::F32)?
        .flatten_all()?
        .to_vec1::<f32>()?;
    Ok(values
        .par_chunks(vocab)
        .zip(targets.par_iter())
        .map(|(row, &t)| {
            if t == IGNORE {
                f32::NAN
            } else {
                target_log_prob(row, t as usize)
            }
        })
        .collect())
}

/// Mean cross-entropy of `logits` (rows × V) over the rows whose target is not [`IGNORE`].
pub fn cross_entropy(logits: &Tensor, targets: &Arc<Vec<u32>>) -> Result<Tensor> {
    logits.contiguous()?.apply_op1(CrossEntropy {
        targets: targets.clone(),
    })
}

struct CrossEntropy {
    targets: Arc<Vec<u32>>,
}

impl CrossEntropy {
    fn check(&self, l: &Layout) -> Result<(usize, usize)> {
        let (rows, vocab) = l.shape().dims2()?;
        if rows != self.targets.len() {
            bail!("{rows} rows of logits for {} targets", self.targets.len())
        }
        if let Some(t) = self
            .targets
            .iter()
            .find(|&&t| t != IGNORE && t as usize >= vocab)
        {
            bail!("target {t} outside the vocabulary of {vocab}")
        }
        Ok((rows, vocab))
    }

    fn valid(&self) -> usize {
        self.targets.iter().filter(|&&t| t != IGNORE).count()
    }
}

impl CustomOp1 for CrossEntropy {
    fn name(&self) -> &'static str {
        "prefix-lm-cross-entropy"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let logits = f32s(s, l, self.name())?;
        let (_, vocab) = self.check(l)?;
        let losses: Vec<f64> = logits
            .par_chunks(vocab)
            .zip(self.targets.par_iter())
            .map(|(row, &t)| {
                if t == IGNORE {
                    0.0
                } else {
                    -f64::from(target_log_prob(row, t as usize))
                }
            })
            .collect();
        let mean = losses.iter().sum::<f64>() / self.valid().max(1) as f64;
        Ok((CpuStorage::F32(vec![mean as f32]), Shape::from(())))
    }

    fn bwd(&self, logits: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let scale = grad.to_dtype(DType::F32)?.to_scalar::<f32>()? / self.valid().max(1) as f32;
        let (_, vocab) = self.check(logits.layout())?;
        let out = with_values(&[logits], |v| {
            let mut out = vec![0f32; v[0].len()];
            out.par_chunks_mut(vocab)
                .zip(v[0].par_chunks(vocab))
                .zip(self.targets.par_iter())
                .for_each(|((o, row), &t)| {
                    if t == IGNORE {
                        return;
                    }
                    // (softmax − onehot) · scale.
                    let max = row.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
                    let mut sum = 0f32;
                    for (o, &v) in o.iter_mut().zip(row) {
                        *o = (v - max).exp();
                        sum += *o;
                    }
                    let inv = scale / sum;
                    o.iter_mut().for_each(|v| *v *= inv);
                    o[t as usize] -= scale;
                });
            Ok(out)
        })?;
        Ok(Some(tensor(out, logits.shape())?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var, D};

    fn randn(shape: &[usize], seed: u64) -> Tensor {
        let n: usize = shape.iter().product();
        let mut rng = ingest::rng::SplitMix64(seed);
        let values: Vec<f32> = (0..n).map(|_| rng.range(-1.0, 1.0) as f32).collect();
        Tensor::from_vec(values, shape, &Device::Cpu).unwrap()
    }

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    }

    /// Gradient of `sum(f(x) ⊙ r)` with respect to `x`.
    fn grad_of(x: &Var, y: &Tensor, r: &Tensor) -> Tensor {
        let grads = (y * r).unwrap().sum_all().unwrap().backward().unwrap();
        grads.get(x.as_tensor()).unwrap().clone()
    }

    /// Largest difference between the gradients of `sum(y1 ⊙ r)` and `sum(y2 ⊙ r)` over `vars`.
    fn grad_diff(vars: &[&Var], y1: &Tensor, y2: &Tensor, r: &Tensor) -> f32 {
        let g1 = (y1 * r).unwrap().sum_all().unwrap().backward().unwrap();
        let g2 = (y2 * r).unwrap().sum_all().unwrap().backward().unwrap();
        vars.iter()
            .map(|v| {
                max_diff(
                    g1.get(v.as_tensor()).unwrap(),
                    g2.get(v.as_tensor()).unwrap(),
                )
            })
            .fold(0.0, f32::max)
    }

    #[test]
    fn norm_linear_matches_composite_ops_and_their_gradients() {
        let h = Var::from_tensor(&randn(&[5, 12], 1)).unwrap();
        let n = Var::from_tensor(&(randn(&[12], 2) + 1.0).unwrap()).unwrap();
        let w = Var::from_tensor(&randn(&[7, 12], 3)).unwrap();
        let r = randn(&[5, 7], 4);
        let fused = norm_linear(h.as_tensor(), n.as_tensor(), w.as_tensor(), 1e-6).unwrap();
        let xn = candle_nn::ops::rms_norm_slow(h.as_tensor(), n.as_tensor(), 1e-6).unwrap();
        let slow = xn.matmul(&w.as_tensor().t().unwrap()).unwrap();
        assert!(max_diff(&fused, &slow) < 1e-5);
        assert!(grad_diff(&[&h, &n, &w], &fused, &slow, &r) < 1e-4);
    }

    #[test]
    fn linear_residuals_match_composite_ops_and_their_gradients() {
        let x = Var::from_tensor(&(randn(&[6, 10], 5) * 3.0).unwrap()).unwrap();
        let w = Var::from_tensor(&randn(&[4, 10], 6)).unwrap();
        let w_half = Var::from_tensor(&randn(&[4, 5], 7)).unwrap();
        let h = Var::from_tensor(&randn(&[6, 4], 8)).unwrap();
        let r = randn(&[6, 4], 9);
        let fused = linear_residual(x.as_tensor(), w.as_tensor(), h.as_tensor()).unwrap();
        let slow =
            (h.as_tensor() + x.as_tensor().matmul(&w.as_tensor().t().unwrap()).unwrap()).unwrap();
        assert!(max_diff(&fused, &slow) < 1e-5);
        assert!(grad_diff(&[&x, &w, &h], &fused, &slow, &r) < 1e-4);
        let fused =
            swiglu_linear_residual(x.as_tensor(), w_half.as_tensor(), h.as_tensor()).unwrap();
        let (a, b) = (
            x.as_tensor().narrow(1, 0, 5).unwrap(),
            x.as_tensor().narrow(1, 5, 5).unwrap(),
        );
        let act = (candle_nn::ops::silu(&a).unwrap() * b).unwrap();
        let slow = (h.as_tensor() + act.matmul(&w_half.as_tensor().t().unwrap()).unwrap()).unwrap();
        assert!(max_diff(&fused, &slow) < 1e-5);
        assert!(grad_diff(&[&x, &w_half, &h], &fused, &slow, &r) < 1e-4);
    }

    #[test]
    fn cross_entropy_matches_log_softmax_and_ignores_padding() {
        let logits = Var::from_tensor(&(randn(&[4, 6], 6) * 4.0).unwrap()).unwrap();
        let targets = Arc::new(vec![2, IGNORE, 5, 0]);
        let fused = cross_entropy(logits.as_tensor(), &targets).unwrap();
        let rows = Tensor::new(&[0u32, 2, 3], &Device::Cpu).unwrap();
        let picked = logits.as_tensor().index_select(&rows, 0).unwrap();
        let t = Tensor::new(&[2u32, 5, 0], &Device::Cpu).unwrap();
        let slow = candle_nn::loss::cross_entropy(&picked, &t).unwrap();
        assert!(max_diff(&fused, &slow) < 1e-6);
        let gf = fused.backward().unwrap();
        let gs = slow.backward().unwrap();
        let gf = gf.get(logits.as_tensor()).unwrap();
        let gs = gs.get(logits.as_tensor()).unwrap();
        assert!(max_diff(gf, gs) < 1e-6);
        assert_eq!(
            gf.get(1)
                .unwrap()
                .abs()
                .unwrap()
                .sum_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap(),
            0.0
        );
        let lp = target_log_probs(logits.as_tensor(), &targets).unwrap();
        assert!(lp[1].is_nan());
        let mean = -(lp[0] + lp[2] + lp[3]) / 3.0;
        assert!((mean - fused.to_scalar::<f32>().unwrap()).abs() < 1e-6);
    }

    /// The attention of one sequence with candle's composite ops, in slot order
    /// (slots × d), from its qkv rows in slot order.
    fn composite_attention(
        qkv: &Tensor,
        layout: &SeqLayout,
        b: usize,
        heads: usize,
        rope: &Rope,
    ) -> Tensor {
        let (slots, three_d) = qkv.dims2().unwrap();
        let (d, hd) = (three_d / 3, three_d / 3 / heads);
        let half = hd / 2;
        let (mut cos, mut sin) = (Vec::new(), Vec::new());
        for s in 0..slots {
            let p = layout.position(b, s);
            for c in 0..hd {
                cos.push(rope.cos[p * half + c % half]);
                sin.push(rope.sin[p * half + c % half]);
            }
        }
        let cos = Tensor::from_vec(cos, (slots, hd), &Device::Cpu).unwrap();
        let sin = Tensor::from_vec(sin, (slots, hd), &Device::Cpu).unwrap();
        let rot = |x: &Tensor| {
            let x1 = x.narrow(1, 0, half).unwrap();
            let x2 = x.narrow(1, half, half).unwrap();
            let rh = Tensor::cat(&[&x2.neg().unwrap(), &x1], 1).unwrap();
            ((x * &cos).unwrap() + (rh * &sin).unwrap()).unwrap()
        };
        let mask: Vec<f32> = (0..slots * slots)
            .map(|ij| {
                if layout.allowed(b, ij / slots, ij % slots) {
                    0.0
                } else {
                    -1e9
                }
            })
            .collect();
        let mask = Tensor::from_vec(mask, (slots, slots), &Device::Cpu).unwrap();
        let outs: Vec<Tensor> = (0..heads)
            .map(|h| {
                let q = rot(&qkv.narrow(1, h * hd, hd).unwrap());
                let k = rot(&qkv.narrow(1, d + h * hd, hd).unwrap());
                let v = qkv.narrow(1, 2 * d + h * hd, hd).unwrap();
                let s = (q.matmul(&k.t().unwrap()).unwrap() / (hd as f64).sqrt()).unwrap();
                let p = candle_nn::ops::softmax(&(s + &mask).unwrap(), D::Minus1).unwrap();
                p.matmul(&v).unwrap()
            })
            .collect();
        Tensor::cat(&outs, 1).unwrap()
    }

    #[test]
    fn attention_matches_composite_ops_with_mask_rope_and_gradients() {
        let layout = Arc::new(SeqLayout::new(vec![3, 1], 4));
        let (heads, d) = (2, 8);
        let rope = Arc::new(Rope::new(d / heads, 10_000.0, 16));
        let qkv = Var::from_tensor(&randn(&[layout.rows(), 3 * d], 7)).unwrap();
        let r = randn(&[layout.rows(), d], 8);
        let fused = prefix_attention(qkv.as_tensor(), &layout, &rope, heads).unwrap();
        let mut slow_rows = vec![None; layout.rows()];
        for b in 0..layout.batch {
            let rows: Vec<u32> = (0..layout.slots())
                .map(|s| layout.row(b, s) as u32)
                .collect();
            let idx = Tensor::new(rows.as_slice(), &Device::Cpu).unwrap();
            let out = composite_attention(
                &qkv.as_tensor().index_select(&idx, 0).unwrap(),
                &layout,
                b,
                heads,
                &rope,
            );
            for (s, &row) in rows.iter().enumerate() {
                slow_rows[row as usize] = Some(out.get(s).unwrap());
            }
        }
        let slow_rows: Vec<Tensor> = slow_rows.into_iter().map(Option::unwrap).collect();
        let slow = Tensor::stack(&slow_rows, 0).unwrap();
        // Padded text slots (sequence 1, slots 1 and 2) are never read; compare real rows.
        let real: Vec<u32> = (0..layout.rows() as u32)
            .filter(|&row| row != layout.row(1, 1) as u32 && row != layout.row(1, 2) as u32)
            .collect();
        let real = Tensor::new(real.as_slice(), &Device::Cpu).unwrap();
        let pick = |t: &Tensor| t.index_select(&real, 0).unwrap();
        assert!(max_diff(&pick(&fused), &pick(&slow)) < 1e-5);
        let rr = pick(&r);
        let (gf, gs) = (
            grad_of(&qkv, &pick(&fused), &rr),
            grad_of(&qkv, &pick(&slow), &rr),
        );
        assert!(max_diff(&gf, &gs) < 1e-5, "{}", max_diff(&gf, &gs));
    }

    #[test]
    fn text_slots_attend_both_ways_and_never_to_motion() {
        let layout = Arc::new(SeqLayout::new(vec![3], 4));
        let (heads, d) = (2, 8);
        let rope = Arc::new(Rope::new(d / heads, 10_000.0, 16));
        let qkv = randn(&[layout.rows(), 3 * d], 9);
        let out = |qkv: &Tensor| prefix_attention(qkv, &layout, &rope, heads).unwrap();
        let base = out(&qkv);
        let bump = |row: usize| {
            let mut v = qkv.to_vec2::<f32>().unwrap();
            v[row].iter_mut().for_each(|x| *x += 0.5);
            out(&Tensor::new(v, &Device::Cpu).unwrap())
        };
        let row_diff = |a: &Tensor, b: &Tensor, row: usize| {
            max_diff(&a.get(row).unwrap(), &b.get(row).unwrap())
        };
        // The last text slot changes the first (text attends forwards) and vice versa.
        let last = bump(layout.row(0, 2));
        assert!(row_diff(&base, &last, layout.row(0, 0)) > 1e-4);
        let first = bump(layout.row(0, 0));
        assert!(row_diff(&base, &first, layout.row(0, 2)) > 1e-4);
        // A motion slot changes no text slot.
        let motion = bump(layout.row(0, 4));
        for s in 0..3 {
            assert_eq!(row_diff(&base, &motion, layout.row(0, s)), 0.0);
        }
    }
}
