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

use super::{ExtraLoss, LmBatch, PrefixLm};
use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Result, Tensor, Var, D};
use nn::fused_ops::{
    masked_softmax, qkv_heads, rms_norm, swiglu_rows, weighted_cross_entropy, PrefixMask,
};
use nn::lm_kernels::IGNORE;
use nn::seq_layout::SeqLayout;

/// The weights as one call uses them: matrices in the compute dtype, the rest f32.
pub(super) struct GraphWeights {
    pub(super) tok_emb: Tensor,
    pub(super) proj_w: Tensor,
    pub(super) proj_b: Tensor,
    /// Per block: n1, Wqkv, Wo, n2, W13, W2.
    pub(super) blocks: Vec<[Tensor; 6]>,
    pub(super) norm: Tensor,
    pub(super) head: Tensor,
}

impl GraphWeights {
    /// `tensors` (in [`PrefixLm::tensors`] order) cast for `dtype` products.
    pub(super) fn cast(tensors: &[Tensor], dtype: DType) -> Result<Self> {
        let f32 = |t: &Tensor| t.to_dtype(DType::F32);
        let mat = |t: &Tensor| t.to_dtype(dtype);
        let n = tensors.len();
        let blocks = tensors[3..n - 2]
            .chunks(6)
            .map(|b| {
                Ok([
                    f32(&b[0])?,
                    mat(&b[1])?,
                    mat(&b[2])?,
                    f32(&b[3])?,
                    mat(&b[4])?,
                    mat(&b[5])?,
                ])
            })
            .collect::<Result<_>>()?;
        Ok(Self {
            tok_emb: f32(&tensors[0])?,
            proj_w: mat(&tensors[1])?,
            proj_b: f32(&tensors[2])?,
            blocks,
            norm: f32(&tensors[n - 2])?,
            head: mat(&tensors[n - 1])?,
        })
    }
}

/// `x · Wᵀ` of f32 rows with `W` in its compute dtype; f32 out.
fn linear(x: &Tensor, w: &Tensor) -> Result<Tensor> {
    Ok(cast_linear(x, w)?.1)
}

/// [`linear`], with the input as cast to `W`'s dtype (what the product's backward reads).
pub(super) fn cast_linear(x: &Tensor, w: &Tensor) -> Result<(Tensor, Tensor)> {
    let xc = x.to_dtype(w.dtype())?;
    let y = xc.matmul(&w.t()?)?.to_dtype(DType::F32)?;
    Ok((xc, y))
}

/// What the backward of [`grid_inputs`] needs: the one-hot motion tokens, and the cast
/// caption rows with their mask when the batch has captions.
pub(super) struct InputTape {
    pub(super) one_hot: Tensor,
    pub(super) text: Option<(Tensor, Tensor)>,
}

/// The block inputs of the grid: one-hot motion tokens times the embedding, plus the
/// projected captions (`text_dim` wide) on real text slots; zero on padding slots.
pub(super) fn grid_inputs(
    w: &GraphWeights,
    text_dim: usize,
    batch: &LmBatch,
    grid: &Grid,
    device: &Device,
) -> Result<(Tensor, InputTape)> {
    let one_hot = grid.one_hot(w.tok_emb.dim(0)?)?;
    let h = one_hot.matmul(&w.tok_emb)?;
    if batch.text.is_empty() {
        let tape = InputTape {
            one_hot,
            text: None,
        };
        return Ok((h, tape));
    }
    let text = grid.caption_rows(&batch.text, text_dim, device)?;
    let (text_c, projected) = cast_linear(&text, &w.proj_w)?;
    let projected = projected.broadcast_add(&w.proj_b)?;
    let h = (h + projected.broadcast_mul(&grid.text_mask)?)?;
    let text = Some((text_c, grid.text_mask.clone()));
    Ok((h, InputTape { one_hot, text }))
}

/// Rotary tables, one row per query slot, and the mask of one attention call.
pub(super) struct AttentionInputs {
    pub(super) cos: Tensor,
    pub(super) sin: Tensor,
    /// Each sequence's caption length (u32), for the mask.
    pub(super) prefix_lens: Tensor,
    pub(super) mask: PrefixMask,
}

impl AttentionInputs {
    /// Tables for the query slots `queries` (each `(sequence, slot)`) of `layout`.
    pub(super) fn new(
        model: &PrefixLm,
        layout: &SeqLayout,
        queries: (usize, usize),
        device: &Device,
    ) -> Result<Self> {
        let (from, to) = queries;
        let half = model.config.head_dim() / 2;
        let rows = layout.batch * (to - from);
        let (mut cos, mut sin) = (
            Vec::with_capacity(rows * half),
            Vec::with_capacity(rows * half),
        );
        for b in 0..layout.batch {
            for s in from..to {
                let (c, si) = model.rope.at(layout.position(b, s));
                cos.extend_from_slice(c);
                sin.extend_from_slice(si);
            }
        }
        let prefix_lens: Vec<u32> = layout.prefix_lens.iter().map(|&n| n as u32).collect();
        Ok(Self {
            cos: Tensor::from_vec(cos, (rows, half), device)?,
            sin: Tensor::from_vec(sin, (rows, half), device)?,
            prefix_lens: Tensor::new(prefix_lens, device)?,
            mask: PrefixMask {
                prefix_slots: layout.prefix_slots,
                first_query: from,
                scale: 1.0 / (model.config.head_dim() as f32).sqrt(),
            },
        })
    }
}

/// One forward call: the model, its weights as cast, and the product dtype.
struct Pass<'a> {
    model: &'a PrefixLm,
    w: GraphWeights,
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

    /// The block's FFN and attention around `attention` (QKV rows → attention output rows).
    fn block(
        &self,
        i: usize,
        h: Tensor,
        attention: impl FnOnce(&Tensor) -> Result<Tensor>,
    ) -> Result<Tensor> {
        let [n1, wqkv, wo, n2, w13, w2] = &self.w.blocks[i];
        let qkv = linear(&rms_norm(&h, n1, self.eps())?, wqkv)?;
        let h = (&h + linear(&attention(&qkv)?, wo)?)?;
        let ab = linear(&rms_norm(&h, n2, self.eps())?, w13)?;
        &h + linear(&swiglu_rows(&ab)?, w2)?
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
    fn hidden(&self, batch: &LmBatch) -> Result<(Tensor, Grid)> {
        let (l, device) = (&batch.layout, self.w.head.device());
        let grid = Grid::new(batch, device)?;
        let mut h = self.inputs(batch, &grid, device)?;
        let at = AttentionInputs::new(self.model, l, (0, l.slots()), device)?;
        for i in 0..self.w.blocks.len() {
            h = self.block(i, h, |qkv| {
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
        let (h, grid) = self.hidden(batch)?;
        self.head(&h.index_select(&grid.all_motion_rows()?, 0)?)
    }
}

/// Where a batch's real slots sit in its dense (sequence, slot) grid.
pub(super) struct Grid {
    /// Per grid row: its motion input token, or the vocabulary size (no one-hot column) on a
    /// text or padding slot.
    tokens: Tensor,
    /// Per grid row: the caption row it reads, or the zero row after them.
    text_rows: Tensor,
    /// Per grid row: 1 on a real text slot, else 0 (`rows × 1`, f32).
    pub(super) text_mask: Tensor,
    /// The grid row of each motion row of the layout.
    motion_grid_rows: Vec<u32>,
    device: Device,
}

impl Grid {
    pub(super) fn new(batch: &LmBatch, device: &Device) -> Result<Self> {
        let l = &batch.layout;
        let (slots, motion) = (l.slots(), l.motion_rows());
        let vocab_end = u32::MAX;
        let (mut tokens, mut text_rows, mut text_mask) = (Vec::new(), Vec::new(), Vec::new());
        let mut motion_grid_rows = vec![0u32; motion];
        for b in 0..l.batch {
            for s in 0..slots {
                let (mut token, mut text, mut mask) = (vocab_end, (l.rows() - motion) as u32, 0f32);
                match l.row(b, s) {
                    Some(r) if r < motion => {
                        token = batch.inputs[r];
                        motion_grid_rows[r] = tokens.len() as u32;
                    }
                    Some(r) => (text, mask) = ((r - motion) as u32, 1.0),
                    None => {}
                }
                tokens.push(token);
                text_rows.push(text);
                text_mask.push(mask);
            }
        }
        let rows = tokens.len();
        Ok(Self {
            tokens: Tensor::new(tokens, device)?,
            text_rows: Tensor::new(text_rows, device)?,
            text_mask: Tensor::from_vec(text_mask, (rows, 1), device)?,
            motion_grid_rows,
            device: device.clone(),
        })
    }

    /// The grid's motion tokens one-hot over `vocab` columns (`rows × vocab`, f32; a zero row
    /// on text and padding slots).
    pub(super) fn one_hot(&self, vocab: usize) -> Result<Tensor> {
        let columns = Tensor::arange(0, vocab as u32, &self.device)?.unsqueeze(0)?;
        self.tokens
            .unsqueeze(1)?
            .broadcast_eq(&columns)?
            .to_dtype(DType::F32)
    }

    /// Per grid row, the caption embedding it reads (zero off real text slots; `rows × E`).
    /// `text`: the batch's caption rows, `text_dim` wide.
    pub(super) fn caption_rows(
        &self,
        text: &[f32],
        text_dim: usize,
        device: &Device,
    ) -> Result<Tensor> {
        let e = text_dim;
        Tensor::cat(
            &[
                Tensor::from_slice(text, (text.len() / e, e), device)?,
                Tensor::zeros((1, e), DType::F32, device)?,
            ],
            0,
        )?
        .index_select(&self.text_rows, 0)
    }

    /// The grid rows of the layout's motion rows `rows`.
    fn motion_rows(&self, rows: &[u32]) -> Result<Tensor> {
        let picked: Vec<u32> = rows
            .iter()
            .map(|&r| self.motion_grid_rows[r as usize])
            .collect();
        Tensor::new(picked, &self.device)
    }

    /// The grid rows of every motion row of the layout, in its order.
    fn all_motion_rows(&self) -> Result<Tensor> {
        Tensor::new(self.motion_grid_rows.as_slice(), &self.device)
    }

    /// Per grid row, the target of a motion row with one (else 0) and its weight (1, else
    /// 0), from the layout's motion `rows` and their `targets`.
    pub(super) fn targets(&self, rows: &[u32], targets: &[u32]) -> Result<(Tensor, Tensor)> {
        let n = self.tokens.dim(0)?;
        let (mut dense, mut weight) = (vec![0u32; n], vec![0f32; n]);
        for (&r, &t) in rows.iter().zip(targets) {
            let g = self.motion_grid_rows[r as usize] as usize;
            (dense[g], weight[g]) = (t, 1.0);
        }
        Ok((
            Tensor::new(dense, &self.device)?,
            Tensor::new(weight, &self.device)?,
        ))
    }
}

/// A pass over `model`'s own weights.
fn pass(model: &PrefixLm) -> Result<Pass<'_>> {
    let tensors: Vec<Tensor> = model.tensors().into_iter().cloned().collect();
    pass_over(model, &tensors)
}

fn pass_over<'a>(model: &'a PrefixLm, tensors: &[Tensor]) -> Result<Pass<'a>> {
    let dtype = model.compute.precision.compute_dtype();
    Ok(Pass {
        model,
        w: GraphWeights::cast(tensors, dtype)?,
        dtype,
    })
}

/// The rows of `batch`'s motion slots that have a target, and those targets.
pub(super) fn target_rows(batch: &LmBatch) -> (Vec<u32>, Vec<u32>) {
    batch
        .targets
        .iter()
        .enumerate()
        .filter(|(_, &t)| t != IGNORE)
        .map(|(r, &t)| (r as u32, t))
        .unzip()
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
    let (h, grid) = p.hidden(batch)?;
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
    let own = model.tensors();
    let leaves: Vec<Tensor> = own
        .iter()
        .map(|t| match t.is_variable() {
            true => Ok((*t).clone()),
            false => Ok(Var::from_tensor(t)?.into_inner()),
        })
        .collect::<Result<_>>()?;
    let p = pass_over(model, &leaves)?;
    let device = model.device();
    let (rows, targets) = target_rows(batch);
    let (hidden, grid) = p.hidden(batch)?;
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
    let mut store = GradStore::default();
    for (t, leaf) in own.into_iter().zip(&leaves) {
        if let Some(g) = grads.get(leaf) {
            store.insert(t, g.clone());
        }
    }
    Ok((loss, store))
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
    weights: Option<GraphWeights>,
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
        h = pass.block(i, h, |qkv| {
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
