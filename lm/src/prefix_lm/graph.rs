//! The graph executor of the prefix LM: the model written in candle's differentiable ops, so
//! it runs on any device and dtype and `loss.backward()` gives its gradients. The norms, the
//! SwiGLU, the rotary QKV split, the masked softmax and the loss are `nn::fused_ops`: one
//! kernel each way with its own backward, where candle's composed ops took 5–15 kernels and
//! tensors each (never candle's fused `rms_norm`, `softmax_last_dim` or `rope`: they have no
//! backward, see `../shared/docs/pitfalls.md`).
//!
//! The model runs on the dense (sequence, slot) grid of a [`SeqLayout`], padding slots
//! included (masked as keys, their own outputs dropped): a row gather per block would cost a
//! scatter-add in the backward, which candle's GPU kernel runs one index at a time. Motion
//! tokens enter as a one-hot product with the embedding (its gradient is one matrix product,
//! where `embedding` would scatter-add by id), text rows by a gather of the (constant)
//! caption embeddings, and the loss is a masked mean over the grid's target rows.
//!
//! Precision: the residual stream, norms, softmax and loss are f32; with bf16 the matrix
//! products take bf16 operands (weights cast from their f32 masters on every call, so the
//! gradients reach the masters in f32), as PyTorch's autocast does.

use super::grid::{cast, dropout_scales, grid_inputs, linear, target_rows, AttentionInputs, Grid};
use super::{ExtraLoss, LmBatch, PrefixLm, Weights};
use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Result, Tensor, Var, D};
use nn::fused_ops::{masked_softmax, qkv_heads, rms_norm, swiglu_rows, weighted_cross_entropy};
use nn::seq_layout::SeqLayout;

/// One forward call: the model, its weights as cast, and the product dtype.
struct Pass<'a> {
    model: &'a PrefixLm,
    w: Weights<Tensor>,
    dtype: DType,
}

impl Pass<'_> {
    fn eps(&self) -> f32 {
        self.model.config.norm_eps as f32
    }

    /// Split QKV rows (`batch · slots × 3d`, slot-major per sequence) into rotated queries,
    /// rotated keys and values, each `(batch, heads, slots, head_dim)` in the product dtype.
    fn heads(&self, qkv: &Tensor, at: &AttentionInputs, batch: usize) -> Result<[Tensor; 3]> {
        let grid = qkv_heads(qkv, &at.cos, &at.sin, batch, self.model.config.n_heads)?;
        let part = |i: usize| grid.get(i)?.to_dtype(self.dtype);
        Ok([part(0)?, part(1)?, part(2)?])
    }

    /// Softmax attention of `q` against `k`, `v` (`(batch, heads, ·, head_dim)`) under the
    /// mask; the output as rows (`batch · queries × d`, f32).
    fn attend(&self, q: &Tensor, k: &Tensor, v: &Tensor, at: &AttentionInputs) -> Result<Tensor> {
        let (b, _, n, _) = q.dims4()?;
        let scores = q.matmul(&k.t()?)?.to_dtype(DType::F32)?;
        let probs = masked_softmax(&scores, &at.prefix_lens, at.mask)?.to_dtype(self.dtype)?;
        probs
            .matmul(v)?
            .to_dtype(DType::F32)?
            .transpose(1, 2)?
            .reshape((b * n, self.model.config.d_model))
    }

    /// The block's FFN and attention around `attention` (QKV rows → attention output rows);
    /// `dropped` (training with dropout) scales the attention and FFN outputs.
    fn block(
        &self,
        (i, dropped): (usize, Option<&[Tensor; 2]>),
        h: Tensor,
        attention: impl FnOnce(&Tensor) -> Result<Tensor>,
    ) -> Result<Tensor> {
        let bw = &self.w.blocks[i];
        let scaled = |x: Tensor, branch: usize| match dropped {
            Some(scales) => x * &scales[branch],
            None => Ok(x),
        };
        let qkv = linear(&rms_norm(&h, &bw.n1, self.eps())?, &bw.wqkv)?;
        let h = (&h + scaled(linear(&attention(&qkv)?, &bw.wo)?, 0)?)?;
        let ab = linear(&rms_norm(&h, &bw.n2, self.eps())?, &bw.w13)?;
        &h + scaled(linear(&swiglu_rows(&ab)?, &bw.w2)?, 1)?
    }

    /// `text · Wᵀ + b` of text rows (`rows × E`).
    fn project_text(&self, text: &[f32], device: &Device) -> Result<Tensor> {
        let e = self.model.config.text_dim;
        let text = Tensor::from_slice(text, (text.len() / e, e), device)?;
        linear(&text, &self.w.proj_w)?.broadcast_add(&self.w.proj_b)
    }

    /// Embedding rows of `tokens` (decoding: no backward).
    fn embed(&self, tokens: &[u32], device: &Device) -> Result<Tensor> {
        self.w.tok_emb.embedding(&Tensor::new(tokens, device)?)
    }

    /// The block inputs of the grid ([`grid_inputs`]).
    fn inputs(&self, batch: &LmBatch, grid: &Grid, device: &Device) -> Result<Tensor> {
        let text_dim = self.model.config.text_dim;
        Ok(grid_inputs(&self.w, text_dim, batch, grid, device)?.0)
    }

    /// The last block's output of every slot of `batch`'s grid, and the grid.
    fn hidden(&self, batch: &LmBatch, train: bool) -> Result<(Tensor, Grid)> {
        let (l, device) = (&batch.layout, self.w.head.device());
        let grid = Grid::new(batch, device)?;
        let mut h = self.inputs(batch, &grid, device)?;
        let at = AttentionInputs::new(self.model, l, (0, l.slots()), device)?;
        for i in 0..self.w.blocks.len() {
            let dropped = match batch.dropout.filter(|_| train) {
                Some(dropout) => Some(dropout_scales(
                    &dropout,
                    l,
                    i,
                    self.model.config.d_model,
                    device,
                )?),
                None => None,
            };
            h = self.block((i, dropped.as_ref()), h, |qkv| {
                let [q, k, v] = self.heads(qkv, &at, l.batch)?;
                self.attend(&q, &k, &v, &at)
            })?;
        }
        Ok((h, grid))
    }

    /// `RMSNorm(h; norm) · headᵀ` (f32 logits).
    fn head(&self, h: &Tensor) -> Result<Tensor> {
        linear(&rms_norm(h, &self.w.norm, self.eps())?, &self.w.head)
    }

    /// Logits of every real motion row, in the layout's row order.
    fn motion_logits(&self, batch: &LmBatch) -> Result<Tensor> {
        let (h, grid) = self.hidden(batch, false)?;
        self.head(&h.index_select(&grid.all_motion_rows()?, 0)?)
    }
}

/// A pass over `model`'s own weights.
fn pass(model: &PrefixLm) -> Result<Pass<'_>> {
    pass_over(model, &model.weights)
}

/// A pass of `model` over `weights` (its own, or leaves standing for them).
fn pass_over<'a>(model: &'a PrefixLm, weights: &Weights<Tensor>) -> Result<Pass<'a>> {
    let dtype = model.compute.precision.compute_dtype();
    Ok(Pass {
        model,
        w: cast(weights, dtype)?,
        dtype,
    })
}

/// [`PrefixLm::forward`].
pub(super) fn forward(model: &PrefixLm, batch: &LmBatch) -> Result<Tensor> {
    model.check(&batch.layout)?;
    pass(model)?.motion_logits(batch)
}

/// [`PrefixLm::target_log_probs`].
pub(super) fn target_log_probs(model: &PrefixLm, batch: &LmBatch) -> Result<Vec<f32>> {
    model.check(&batch.layout)?;
    let p = pass(model)?;
    let mut out = vec![f32::NAN; batch.inputs.len()];
    let (rows, targets) = target_rows(batch);
    if rows.is_empty() {
        return Ok(out);
    }
    let device = model.device();
    let (h, grid) = p.hidden(batch, false)?;
    let picked = h.index_select(&grid.motion_rows(&rows)?, 0)?;
    let log_probs = candle_nn::ops::log_softmax(&p.head(&picked)?, D::Minus1)?
        .gather(&Tensor::new(targets, device)?.unsqueeze(1)?, 1)?
        .flatten_all()?
        .to_vec1::<f32>()?;
    for (r, lp) in rows.into_iter().zip(log_probs) {
        out[r as usize] = lp;
    }
    Ok(out)
}

/// [`PrefixLm::loss_and_grads`] and [`PrefixLm::loss_and_grads_with`]: mean cross-entropy
/// (plus `extra`'s term) and the gradient of every weight, keyed by the model's tensors.
pub(super) fn loss_and_grads(
    model: &PrefixLm,
    batch: &LmBatch,
    extra: Option<&ExtraLoss<'_>>,
) -> Result<(f32, GradStore)> {
    model.check(&batch.layout)?;
    // Every weight a leaf of the graph: candle keeps the gradients of variables only, and a
    // merged LoRA weight is an intermediate tensor.
    let leaves = model.weights.try_map(|_, t| match t.is_variable() {
        true => Ok(t.clone()),
        false => Ok(Var::from_tensor(t)?.into_inner()),
    })?;
    let p = pass_over(model, &leaves)?;
    let device = model.device();
    let (rows, targets) = target_rows(batch);
    let (hidden, grid) = p.hidden(batch, true)?;
    let (loss, objective) = match extra {
        None => {
            // Over the whole grid, so that the backward has no row scatter.
            let (dense, weight) = grid.targets(&rows, &targets)?;
            let ce = masked_cross_entropy(&p.head(&hidden)?, &dense, &weight, targets.len())?;
            (ce.to_scalar::<f32>()?, ce)
        }
        Some(extra) => {
            let logits = p.head(&hidden.index_select(&grid.all_motion_rows()?, 0)?)?;
            let picked = logits.index_select(&Tensor::new(rows.as_slice(), device)?, 0)?;
            let ce = cross_entropy(&picked, &targets, device)?;
            let mut loss = ce.to_scalar::<f32>()?;
            let objective = match extra(&logits.flatten_all()?.to_vec1::<f32>()?) {
                // Σ logits ⊙ G has gradient G with respect to the logits.
                Some((term, g)) => {
                    loss += term;
                    let g = Tensor::from_vec(g, logits.shape(), device)?;
                    (ce + (logits * g)?.sum_all()?)?
                }
                None => ce,
            };
            (loss, objective)
        }
    };
    let grads = objective.backward()?;
    let grads = leaves.map(|leaf| grads.get(leaf).cloned());
    Ok((loss, model.weights.grad_store(grads)?))
}

/// Mean cross-entropy of the f32 `logits` rows of weight 1 against their `targets` (`n` of
/// them; 0 without any).
fn masked_cross_entropy(
    logits: &Tensor,
    targets: &Tensor,
    weight: &Tensor,
    n: usize,
) -> Result<Tensor> {
    if n == 0 {
        return logits.sum_all()? * 0.0;
    }
    weighted_cross_entropy(logits, targets, weight)?
        .sum_all()?
        .affine(1.0 / n as f64, 0.0)
}

/// Mean cross-entropy of f32 `logits` rows against `targets` (0 without targets).
fn cross_entropy(logits: &Tensor, targets: &[u32], device: &Device) -> Result<Tensor> {
    if targets.is_empty() {
        return logits.sum_all()? * 0.0;
    }
    candle_nn::loss::cross_entropy(logits, &Tensor::new(targets, device)?)
}

/// Each layer's rotated keys and values so far, `(batch, heads, slots, head_dim)`, and the
/// weights as the first step cast them (every later step multiplies by the same).
pub(super) struct GraphCache {
    layers: Vec<Option<(Tensor, Tensor)>>,
    weights: Option<Weights<Tensor>>,
}

impl GraphCache {
    /// An empty cache for `layers` blocks.
    pub(super) fn new(layers: usize) -> Self {
        Self {
            layers: vec![None; layers],
            weights: None,
        }
    }

    /// Slots filled so far.
    fn filled(&self) -> Result<usize> {
        match &self.layers[0] {
            Some((k, _)) => k.dim(2),
            None => Ok(0),
        }
    }
}

/// [`PrefixLm::forward_cached`] (arguments checked there).
pub(super) fn forward_cached(
    model: &PrefixLm,
    cache: &mut GraphCache,
    layout: &SeqLayout,
    text: &[f32],
    tokens: &[u32],
    (from, to): (usize, usize),
) -> Result<Tensor> {
    if cache.filled()? != from {
        candle_core::bail!("the cache holds {} slots, not {from}", cache.filled()?)
    }
    let (p, n_new, device) = (layout.prefix_slots, to - from, model.device());
    let pass = match cache.weights.take() {
        Some(w) => Pass {
            model,
            w,
            dtype: model.compute.precision.compute_dtype(),
        },
        None => pass(model)?,
    };
    // New rows sequence-major: the new text slots' projections, then the new motion slots.
    let per_seq = to - from.max(p);
    let mut parts = vec![pass.embed(tokens, device)?];
    let mut pick = Vec::with_capacity(layout.batch * n_new);
    let text_base = (layout.batch * per_seq) as u32;
    for b in 0..layout.batch {
        pick.extend((from..to.min(p)).map(|s| text_base + (b * p + s) as u32));
        pick.extend((0..per_seq).map(|t| (b * per_seq + t) as u32));
    }
    if from < p {
        parts.push(pass.project_text(text, device)?);
    }
    let rows = Tensor::cat(&parts, 0)?;
    let mut h = rows.index_select(&Tensor::new(pick, device)?, 0)?;
    let at = AttentionInputs::new(model, layout, (from, to), device)?;
    for (i, layer) in cache.layers.iter_mut().enumerate() {
        h = pass.block((i, None), h, |qkv| {
            let [q, k, v] = pass.heads(qkv, &at, layout.batch)?;
            let (k, v) = match layer.take() {
                Some((ck, cv)) => (Tensor::cat(&[&ck, &k], 2)?, Tensor::cat(&[&cv, &v], 2)?),
                None => (k, v),
            };
            let out = pass.attend(&q, &k, &v, &at)?;
            *layer = Some((k, v));
            Ok(out)
        })?;
    }
    let last: Vec<u32> = (0..layout.batch)
        .map(|b| (b * n_new + n_new - 1) as u32)
        .collect();
    let logits = pass.head(&h.index_select(&Tensor::new(last, device)?, 0)?)?;
    cache.weights = Some(pass.w);
    Ok(logits)
}
