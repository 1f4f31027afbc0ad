//! Fused ops of the graph executor, each with the backward candle's autograd calls: RMSNorm,
//! SwiGLU, the QKV split with rotary embedding into the attention grid, the prefix-LM masked
//! softmax, and the weighted cross-entropy of logit rows. Composed of candle's ops, each of
//! these is 5–15 kernels and as many fresh tensors in the forward and again in the backward
//! (the GPU step measured in `docs/results/gpu.md`); fused, it is one kernel each way.
//!
//! One definition, two executors, as in `tokenizer/src/conv.rs`: the CPU side runs the cpu
//! executor's kernels ([`crate::lm_kernels`]) where one exists, the GPU side
//! `kernels/fused_ops.cu` (built to PTX with the `cuda` feature); [`crate::device_check`]
//! compares the two on a device. Every op takes contiguous f32 operands (u32 ids) and gives f32. Tables,
//! ids and weights (`cos`, `sin`, prefix lengths, targets, row weights) are constants: they
//! get no gradient and must not depend on a variable.

use crate::cpu_f32::contiguous_f32;
use crate::lm_kernels::{
    cross_entropy_row, gate_sigmoid, swiglu, swiglu_backward, target_log_prob,
};
use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Result, Shape, Tensor};

#[cfg(feature = "cuda")]
pub(crate) mod gpu;

/// Additive mask of a score the layout does not allow: finite, so that a padding row with no
/// allowed key stays finite (its output is dropped).
const MASKED: f32 = -1e9;

/// `x · rstd(x) · w` over the last dimension (`x`: rows × d, `w`: d).
pub fn rms_norm(x: &Tensor, w: &Tensor, eps: f32) -> Result<Tensor> {
    x.contiguous()?.apply_op2(w, RmsNorm { eps })
}

/// `silu(a) · b` of the rows `[a | b]` (rows × 2f → rows × f).
pub fn swiglu_rows(ab: &Tensor) -> Result<Tensor> {
    ab.contiguous()?.apply_op1(Swiglu)
}

/// QKV rows (`batch·slots × 3·heads·head_dim`, slot-major per sequence) as rotated queries,
/// rotated keys and values in the attention grid `(3, batch, heads, slots, head_dim)`,
/// rotate-half by each row's `cos`, `sin` (`rows × head_dim/2`).
pub fn qkv_heads(
    qkv: &Tensor,
    cos: &Tensor,
    sin: &Tensor,
    batch: usize,
    heads: usize,
) -> Result<Tensor> {
    let op = QkvHeads {
        batch,
        heads,
        backward: false,
    };
    qkv.contiguous()?.apply_op3(cos, sin, op)
}

/// `Σ x²` of an f32 tensor, as a one-element tensor (no gradient): on a GPU over many
/// blocks (candle's `sum_all` reduces with a single block).
pub fn sum_of_squares(x: &Tensor) -> Result<Tensor> {
    x.contiguous()?.apply_op1_no_bwd(&SumOfSquares)
}

struct SumOfSquares;

impl CustomOp1 for SumOfSquares {
    fn name(&self) -> &'static str {
        "fused-sum-of-squares"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = contiguous_f32(s, l, "x")?;
        f32_out(vec![x.iter().map(|v| v * v).sum()], 1)
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s: &candle_core::CudaStorage,
        l: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        Ok((gpu::sum_of_squares(s, l)?, 1.into()))
    }
}

/// Where a block of attention queries sits in a prefix-LM layout: the prefix slots (keys
/// `< prefix_slots` are caption slots, attended by every query up to the sequence's caption
/// length; later keys causally by motion queries only) and the slot of the first query.
#[derive(Debug, Clone, Copy)]
pub struct PrefixMask {
    pub prefix_slots: usize,
    pub first_query: usize,
    /// Applied to the scores before the mask (1/√head_dim).
    pub scale: f32,
}

impl PrefixMask {
    fn allowed(&self, prefix_len: usize, i: usize, j: usize) -> bool {
        crate::seq_layout::prefix_lm_allows(self.prefix_slots, prefix_len, i, j)
    }
}

/// `softmax(scale · scores + mask)` over the keys of `scores` (`batch, heads, queries, keys`)
/// under the prefix-LM mask, with each sequence's caption length in `prefix_lens` (u32).
pub fn masked_softmax(scores: &Tensor, prefix_lens: &Tensor, mask: PrefixMask) -> Result<Tensor> {
    scores
        .contiguous()?
        .apply_op2(prefix_lens, MaskedSoftmax(mask))
}

/// Per row of `logits` (rows × vocab): `weight · −log softmax(logits)[target]` (`targets`
/// u32; a row of weight 0 gives 0 and no gradient).
pub fn weighted_cross_entropy(
    logits: &Tensor,
    targets: &Tensor,
    weight: &Tensor,
) -> Result<Tensor> {
    logits
        .contiguous()?
        .apply_op3(targets, weight, CrossEntropy)
}

/// The backward of [`rms_norm`] written out: the gradients of `x` and `w` given that of the
/// output (for an executor without autograd).
pub fn rms_norm_backward(x: &Tensor, w: &Tensor, g: &Tensor, eps: f32) -> Result<(Tensor, Tensor)> {
    let (rows, d) = (x.elem_count() / w.elem_count(), w.elem_count());
    let out = x
        .contiguous()?
        .apply_op3_no_bwd(w, &g.contiguous()?, &RmsNormGrad { eps })?;
    Ok((
        out.narrow(0, 0, rows)?.reshape(x.shape())?,
        out.narrow(0, rows, 1)?.reshape(d)?,
    ))
}

/// The backward of [`swiglu_rows`]: the gradient of `[a | b]` given that of the output.
pub fn swiglu_backward_rows(ab: &Tensor, g: &Tensor) -> Result<Tensor> {
    ab.contiguous()?
        .apply_op2_no_bwd(&g.contiguous()?, &SwigluGrad)
}

/// The backward of [`qkv_heads`]: the gradient of the QKV rows given that of the grid.
pub fn qkv_heads_backward(
    g: &Tensor,
    cos: &Tensor,
    sin: &Tensor,
    batch: usize,
    heads: usize,
) -> Result<Tensor> {
    let op = QkvHeads {
        batch,
        heads,
        backward: true,
    };
    g.contiguous()?.apply_op3_no_bwd(cos, sin, &op)
}

/// The backward of [`masked_softmax`] from its output `probs`: the gradient of the scores
/// (the scale included) given that of the probabilities.
pub fn masked_softmax_backward(probs: &Tensor, g: &Tensor, mask: PrefixMask) -> Result<Tensor> {
    probs
        .contiguous()?
        .apply_op2_no_bwd(&g.contiguous()?, &SoftmaxGrad { scale: mask.scale })
}

/// The backward of [`weighted_cross_entropy`] given each row's weight times its loss
/// gradient, `grad_weight`: `grad_weight · (softmax − onehot)` per row.
pub fn weighted_cross_entropy_backward(
    logits: &Tensor,
    targets: &Tensor,
    grad_weight: &Tensor,
) -> Result<Tensor> {
    logits
        .contiguous()?
        .apply_op3_no_bwd(targets, &grad_weight.detach(), &CrossEntropyGrad)
}

fn u32s<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> Result<&'a [u32]> {
    let (start, end) = l
        .contiguous_offsets()
        .ok_or_else(|| candle_core::Error::Msg(format!("fused op: {what} must be contiguous")))?;
    Ok(&s.as_slice::<u32>()?[start..end])
}

/// The last dimension of a layout and the rows before it.
fn rows_cols(l: &Layout) -> (usize, usize) {
    let cols = l.dims().last().copied().unwrap_or(1);
    (l.shape().elem_count() / cols.max(1), cols)
}

fn f32_out(values: Vec<f32>, shape: impl Into<Shape>) -> Result<(CpuStorage, Shape)> {
    Ok((CpuStorage::F32(values), shape.into()))
}

struct RmsNorm {
    eps: f32,
}

impl CustomOp2 for RmsNorm {
    fn name(&self) -> &'static str {
        "fused-rms-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (x, w) = (contiguous_f32(s1, l1, "x")?, contiguous_f32(s2, l2, "w")?);
        f32_out(
            crate::lm_kernels::rms_norm(x, w, self.eps),
            l1.shape().clone(),
        )
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        Ok((gpu::rms_norm(s1, l1, s2, l2, self.eps)?, l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _y: &Tensor,
        g: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (dx, dw) = rms_norm_backward(x, w, g, self.eps)?;
        Ok((Some(dx), Some(dw)))
    }
}

/// RMSNorm's backward: `(rows + 1) × d`, the gradient of `x` and then that of `w`.
struct RmsNormGrad {
    eps: f32,
}

impl CustomOp3 for RmsNormGrad {
    fn name(&self) -> &'static str {
        "fused-rms-norm-grad"
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
        let (x, w) = (contiguous_f32(s1, l1, "x")?, contiguous_f32(s2, l2, "w")?);
        let g = contiguous_f32(s3, l3, "gradient")?;
        let mut out = vec![0f32; x.len()];
        let gw = crate::lm_kernels::rms_norm_backward(x, w, g, self.eps, &mut out);
        out.extend(gw);
        f32_out(out, (x.len() / w.len() + 1, w.len()))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        let (rows, d) = rows_cols(l1);
        Ok((
            gpu::rms_norm_grad([s1, s2, s3], [l1, l2, l3], self.eps)?,
            (rows + 1, d).into(),
        ))
    }
}

struct Swiglu;

impl CustomOp1 for Swiglu {
    fn name(&self) -> &'static str {
        "fused-swiglu"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let ab = contiguous_f32(s, l, "ab")?;
        let (rows, f) = (rows_cols(l).0, rows_cols(l).1 / 2);
        f32_out(swiglu(ab, &gate_sigmoid(ab, f), f), (rows, f))
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s: &candle_core::CudaStorage,
        l: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        let (rows, cols) = rows_cols(l);
        Ok((gpu::swiglu(s, l, None)?, (rows, cols / 2).into()))
    }

    fn bwd(&self, ab: &Tensor, _y: &Tensor, g: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(swiglu_backward_rows(ab, g)?))
    }
}

/// SwiGLU's backward: the gradient of `[a | b]`.
struct SwigluGrad;

impl CustomOp2 for SwigluGrad {
    fn name(&self) -> &'static str {
        "fused-swiglu-grad"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (ab, g) = (
            contiguous_f32(s1, l1, "ab")?,
            contiguous_f32(s2, l2, "gradient")?,
        );
        let f = rows_cols(l1).1 / 2;
        f32_out(
            swiglu_backward(ab, &gate_sigmoid(ab, f), g, f),
            l1.shape().clone(),
        )
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        Ok((gpu::swiglu(s1, l1, Some((s2, l2)))?, l1.shape().clone()))
    }
}

/// [`qkv_heads`] (`backward: false`) and its inverse map, the gradient of the QKV rows from
/// that of the grid (`backward: true`).
#[derive(Debug, Clone, Copy)]
struct QkvHeads {
    batch: usize,
    heads: usize,
    backward: bool,
}

/// The sizes of a [`QkvHeads`] call: rows, slots per sequence, half a head.
struct QkvDims {
    batch: usize,
    slots: usize,
    heads: usize,
    half: usize,
}

impl QkvHeads {
    fn dims(&self, src: &Layout, cos: &Layout) -> QkvDims {
        let (rows, half) = rows_cols(cos);
        let d = src.shape().elem_count() / rows / 3;
        QkvDims {
            batch: self.batch,
            slots: rows / self.batch,
            heads: self.heads,
            half: d / self.heads / 2,
        }
        .checked(half)
    }

    fn out_shape(&self, q: &QkvDims) -> Shape {
        let hd = 2 * q.half;
        match self.backward {
            false => (3, q.batch, q.heads, q.slots, hd).into(),
            true => (q.batch * q.slots, 3 * q.heads * hd).into(),
        }
    }
}

impl QkvDims {
    fn checked(self, half: usize) -> Self {
        debug_assert_eq!(self.half, half, "rotary tables and head size disagree");
        self
    }
}

/// The CPU side of [`QkvHeads`], index for index the kernel `qkv_heads`.
fn qkv_heads_cpu(src: &[f32], cos: &[f32], sin: &[f32], q: &QkvDims, backward: bool) -> Vec<f32> {
    let (half, hd, d) = (q.half, 2 * q.half, q.heads * 2 * q.half);
    let sign = if backward { -1.0 } else { 1.0 };
    let mut dst = vec![0f32; src.len()];
    for part in 0..3 {
        for b in 0..q.batch {
            for h in 0..q.heads {
                for s in 0..q.slots {
                    let row = b * q.slots + s;
                    let rows_at = row * 3 * d + part * d + h * hd;
                    let grid_at = (((part * q.batch + b) * q.heads + h) * q.slots + s) * hd;
                    let (from, to) = if backward {
                        (grid_at, rows_at)
                    } else {
                        (rows_at, grid_at)
                    };
                    for i in 0..half {
                        let (x1, x2) = (src[from + i], src[from + half + i]);
                        let (c, sn) = match part {
                            2 => (1.0, 0.0),
                            _ => (cos[row * half + i], sign * sin[row * half + i]),
                        };
                        dst[to + i] = x1 * c - x2 * sn;
                        dst[to + half + i] = x2 * c + x1 * sn;
                    }
                }
            }
        }
    }
    dst
}

impl CustomOp3 for QkvHeads {
    fn name(&self) -> &'static str {
        "fused-qkv-heads"
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
        let q = self.dims(l1, l2);
        let (src, cos) = (
            contiguous_f32(s1, l1, "qkv")?,
            contiguous_f32(s2, l2, "cos")?,
        );
        let sin = contiguous_f32(s3, l3, "sin")?;
        f32_out(
            qkv_heads_cpu(src, cos, sin, &q, self.backward),
            self.out_shape(&q),
        )
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        let q = self.dims(l1, l2);
        let out = gpu::qkv_heads([s1, s2, s3], [l1, l2, l3], &q, self.backward)?;
        Ok((out, self.out_shape(&q)))
    }

    fn bwd(
        &self,
        _qkv: &Tensor,
        cos: &Tensor,
        sin: &Tensor,
        _res: &Tensor,
        g: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let grad = qkv_heads_backward(g, cos, sin, self.batch, self.heads)?;
        Ok((Some(grad), None, None))
    }
}

struct MaskedSoftmax(PrefixMask);

impl CustomOp2 for MaskedSoftmax {
    fn name(&self) -> &'static str {
        "fused-masked-softmax"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (scores, lens) = (
            contiguous_f32(s1, l1, "scores")?,
            u32s(s2, l2, "prefix lengths")?,
        );
        let (_, heads, queries, keys) = l1.shape().dims4()?;
        let mut probs = scores.to_vec();
        for (r, row) in probs.chunks_mut(keys).enumerate() {
            let (i, plen) = (
                self.0.first_query + r % queries,
                lens[r / (queries * heads)] as usize,
            );
            for (j, v) in row.iter_mut().enumerate() {
                *v = *v * self.0.scale
                    + if self.0.allowed(plen, i, j) {
                        0.0
                    } else {
                        MASKED
                    };
            }
            let max = row.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
            row.iter_mut().for_each(|v| *v = (*v - max).exp());
            let inv = 1.0 / row.iter().sum::<f32>();
            row.iter_mut().for_each(|v| *v *= inv);
        }
        f32_out(probs, l1.shape().clone())
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        Ok((
            gpu::masked_softmax(s1, l1, s2, l2, self.0)?,
            l1.shape().clone(),
        ))
    }

    fn bwd(
        &self,
        _s: &Tensor,
        _lens: &Tensor,
        probs: &Tensor,
        g: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        Ok((Some(masked_softmax_backward(probs, g, self.0)?), None))
    }
}

/// The masked softmax's backward: `scale · p ⊙ (dp − Σ p·dp)` per row.
struct SoftmaxGrad {
    scale: f32,
}

impl CustomOp2 for SoftmaxGrad {
    fn name(&self) -> &'static str {
        "fused-masked-softmax-grad"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (p, dp) = (
            contiguous_f32(s1, l1, "probs")?,
            contiguous_f32(s2, l2, "gradient")?,
        );
        let keys = rows_cols(l1).1;
        let mut out = vec![0f32; p.len()];
        for ((o, p), dp) in out
            .chunks_mut(keys)
            .zip(p.chunks(keys))
            .zip(dp.chunks(keys))
        {
            let dot: f32 = p.iter().zip(dp).map(|(a, b)| a * b).sum();
            for ((o, &p), &dp) in o.iter_mut().zip(p).zip(dp) {
                *o = self.scale * p * (dp - dot);
            }
        }
        f32_out(out, l1.shape().clone())
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        Ok((
            gpu::softmax_grad(s1, l1, s2, l2, self.scale)?,
            l1.shape().clone(),
        ))
    }
}

struct CrossEntropy;

impl CustomOp3 for CrossEntropy {
    fn name(&self) -> &'static str {
        "fused-cross-entropy"
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
        let (logits, vocab) = (contiguous_f32(s1, l1, "logits")?, rows_cols(l1).1);
        let (targets, weight) = (u32s(s2, l2, "targets")?, contiguous_f32(s3, l3, "weight")?);
        let loss = logits
            .chunks(vocab)
            .zip(targets.iter().zip(weight))
            .map(|(row, (&t, &w))| {
                if w == 0.0 {
                    0.0
                } else {
                    -w * target_log_prob(row, t as usize)
                }
            })
            .collect();
        f32_out(loss, rows_cols(l1).0)
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        let out = gpu::cross_entropy([s1, s2, s3], [l1, l2, l3], false)?;
        Ok((out, rows_cols(l1).0.into()))
    }

    fn bwd(
        &self,
        logits: &Tensor,
        targets: &Tensor,
        weight: &Tensor,
        _loss: &Tensor,
        g: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let grad = weighted_cross_entropy_backward(logits, targets, &(weight * g)?)?;
        Ok((Some(grad), None, None))
    }
}

/// The cross-entropy's backward given each row's weight times its loss gradient:
/// `gw · (softmax − onehot)`.
struct CrossEntropyGrad;

impl CustomOp3 for CrossEntropyGrad {
    fn name(&self) -> &'static str {
        "fused-cross-entropy-grad"
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
        let (logits, vocab) = (contiguous_f32(s1, l1, "logits")?, rows_cols(l1).1);
        let (targets, gw) = (u32s(s2, l2, "targets")?, contiguous_f32(s3, l3, "weight")?);
        let mut out = vec![0f32; logits.len()];
        for ((o, row), (&t, &w)) in out
            .chunks_mut(vocab)
            .zip(logits.chunks(vocab))
            .zip(targets.iter().zip(gw))
        {
            if w != 0.0 {
                o.copy_from_slice(row);
                cross_entropy_row(o, t as usize, w);
            }
        }
        f32_out(out, l1.shape().clone())
    }

    #[cfg(feature = "cuda")]
    fn cuda_fwd(
        &self,
        s1: &candle_core::CudaStorage,
        l1: &Layout,
        s2: &candle_core::CudaStorage,
        l2: &Layout,
        s3: &candle_core::CudaStorage,
        l3: &Layout,
    ) -> Result<(candle_core::CudaStorage, Shape)> {
        let out = gpu::cross_entropy([s1, s2, s3], [l1, l2, l3], true)?;
        Ok((out, l1.shape().clone()))
    }
}

#[cfg(test)]
mod tests;
