//! The CPU executor of the prefix LM: the fused kernels of [`nn::lm_kernels`] on the
//! weights' f32 CPU storage, a forward pass that records what the backward needs, and the
//! backward written out (no autograd graph).

use super::{BlockWeights, ExtraLoss, LmBatch, PrefixLm, PrefixLmConfig, Weights};
use candle_core::backprop::GradStore;
use candle_core::{CpuStorage, Layout, Result, Storage, Tensor};
use nn::dropout::Branch;
use nn::head_loss;
use nn::lm_kernels::{self, LayerCache};
use nn::panels::{PackedMatrix, Weight};
use nn::seq_layout::SeqLayout;

impl BlockWeights<&[f32]> {
    /// The four matrices as the forward products read them: each `W` (`out × in`) transposed.
    fn forward_mats(&self) -> [Weight<'_>; 4] {
        [self.wqkv, self.wo, self.w13, self.w2].map(|m| Weight::Dense((m, true)))
    }
}

/// What the backward pass needs from a block's forward pass.
struct BlockTrace {
    h: Vec<f32>,
    qkv: Vec<f32>,
    probs: Vec<f32>,
    a: Vec<f32>,
    h1: Vec<f32>,
    ab: Vec<f32>,
    sig: Vec<f32>,
    /// The dropout scales of the attention and FFN outputs, when training drops values.
    dropped: Option<[Vec<f32>; 2]>,
}

/// The block on rows `h` (`rows × d`) with its matrices read as `mats` (Wqkvᵀ, Woᵀ,
/// W13ᵀ, W2ᵀ: [`BlockWeights::forward_mats`] or a decoding cache's packed copies); `attend` maps
/// the packed QKV rows to the attention output and its softmax probabilities; `dropped`, when
/// training drops values, scales the attention and FFN outputs before the residual adds them.
fn block_forward(
    c: &PrefixLmConfig,
    w: &BlockWeights<&[f32]>,
    [wqkv, wo, w13, w2]: [Weight; 4],
    (h, dropped): (Vec<f32>, Option<[Vec<f32>; 2]>),
    attend: impl FnOnce(&[f32]) -> (Vec<f32>, Vec<f32>),
) -> (Vec<f32>, BlockTrace) {
    let (d, f, eps) = (c.d_model, c.ffn_hidden, c.norm_eps as f32);
    let rows = h.len() / d;
    let xn = lm_kernels::rms_norm(&h, w.n1, eps);
    let qkv = wqkv.product(&xn, (rows, 3 * d, d));
    let (a, probs) = attend(&qkv);
    let scales = dropped
        .as_ref()
        .map(|[att, ffn]| (att.as_slice(), ffn.as_slice()));
    let h1 = add_branch(&h, (&a, wo), (rows, d, d), scales.map(|s| s.0));
    let xn = lm_kernels::rms_norm(&h1, w.n2, eps);
    let ab = w13.product(&xn, (rows, 2 * f, d));
    let sig = lm_kernels::gate_sigmoid(&ab, f);
    let act = lm_kernels::swiglu(&ab, &sig, f);
    let h2 = add_branch(&h1, (&act, w2), (rows, d, f), scales.map(|s| s.1));
    let trace = BlockTrace {
        h,
        qkv,
        probs,
        a,
        h1,
        ab,
        sig,
        dropped,
    };
    (h2, trace)
}

/// `h + x·W` (`x` rows × k, `W` read as `w`), the product scaled value by value by `scales`
/// when training drops values.
fn add_branch(
    h: &[f32],
    (x, w): (&[f32], Weight),
    (rows, d, k): (usize, usize, usize),
    scales: Option<&[f32]>,
) -> Vec<f32> {
    match scales {
        None => {
            let mut out = h.to_vec();
            w.product_add(&mut out, x, (rows, d, k));
            out
        }
        Some(scales) => {
            let branch = w.product(x, (rows, d, k));
            (h.iter().zip(branch).zip(scales))
                .map(|((h, b), s)| h + b * s)
                .collect()
        }
    }
}

/// `g` scaled value by value by `scales`, or `g` itself without dropout.
fn through_dropout<'a>(g: &'a [f32], scales: Option<&Vec<f32>>) -> std::borrow::Cow<'a, [f32]> {
    match scales {
        None => g.into(),
        Some(s) => g
            .iter()
            .zip(s)
            .map(|(g, s)| g * s)
            .collect::<Vec<_>>()
            .into(),
    }
}

/// Backward through the block: `gh` holds the gradient of its output on entry and of its
/// input on return; returns the weights' gradients.
fn block_backward(
    c: &PrefixLmConfig,
    w: &BlockWeights<&[f32]>,
    t: &BlockTrace,
    attn: &lm_kernels::Attention,
    gh: &mut [f32],
) -> BlockWeights<Vec<f32>> {
    let (d, f, eps) = (c.d_model, c.ffn_hidden, c.norm_eps as f32);
    let rows = gh.len() / d;
    let [g_att_scales, g_ffn_scales] = match &t.dropped {
        Some([att, ffn]) => [Some(att), Some(ffn)],
        None => [None, None],
    };
    // h2 = h1 + swiglu(ab)·W2ᵀ (⊙ dropout scales).
    let act = lm_kernels::swiglu(&t.ab, &t.sig, f);
    let g_out = through_dropout(gh, g_ffn_scales);
    let g_w2 = lm_kernels::gemm_new((&g_out, true), (&act, false), (d, f, rows));
    let g_act = lm_kernels::gemm_new((&g_out, false), (w.w2, false), (rows, f, d));
    let g_ab = lm_kernels::swiglu_backward(&t.ab, &t.sig, &g_act, f);
    // ab = RMSNorm(h1)·W13ᵀ.
    let xn = lm_kernels::rms_norm(&t.h1, w.n2, eps);
    let g_w13 = lm_kernels::gemm_new((&g_ab, true), (&xn, false), (2 * f, d, rows));
    let g_xn = lm_kernels::gemm_new((&g_ab, false), (w.w13, false), (rows, d, 2 * f));
    let g_n2 = lm_kernels::rms_norm_backward(&t.h1, w.n2, &g_xn, eps, gh);
    // h1 = h + a·Woᵀ (⊙ dropout scales).
    let g_out = through_dropout(gh, g_att_scales);
    let g_wo = lm_kernels::gemm_new((&g_out, true), (&t.a, false), (d, d, rows));
    let g_a = lm_kernels::gemm_new((&g_out, false), (w.wo, false), (rows, d, d));
    let g_qkv = attn.backward(&t.qkv, &t.probs, &g_a);
    // qkv = RMSNorm(h)·Wqkvᵀ.
    let xn = lm_kernels::rms_norm(&t.h, w.n1, eps);
    let g_wqkv = lm_kernels::gemm_new((&g_qkv, true), (&xn, false), (3 * d, d, rows));
    let g_xn = lm_kernels::gemm_new((&g_qkv, false), (w.wqkv, false), (rows, d, 3 * d));
    let g_n1 = lm_kernels::rms_norm_backward(&t.h, w.n1, &g_xn, eps, gh);
    BlockWeights {
        n1: g_n1,
        wqkv: g_wqkv,
        wo: g_wo,
        n2: g_n2,
        w13: g_w13,
        w2: g_w2,
    }
}

/// The f32 values of a contiguous CPU tensor's storage.
fn cpu_values<'a>(storage: &'a Storage, layout: &Layout) -> Result<&'a [f32]> {
    match (storage, layout.contiguous_offsets()) {
        (Storage::Cpu(CpuStorage::F32(v)), Some((start, end))) => Ok(&v[start..end]),
        _ => candle_core::bail!("the cpu executor runs on contiguous f32 CPU weights"),
    }
}

/// What the backward pass needs from the forward pass.
struct Trace {
    blocks: Vec<BlockTrace>,
    /// The last block's output.
    h: Vec<f32>,
}

/// The CPU values of every weight, by name.
type Values<'a> = Weights<&'a [f32]>;

/// The loss of the normalised motion rows `xn` and its gradients with respect to `xn` and
/// the head weight.
type HeadLoss<'a> = dyn Fn(&Values<'_>, &[f32]) -> (f32, Vec<f32>, Vec<f32>) + Sync + 'a;

/// One call: the model (shape, rotary table) and the values of its weights.
struct Pass<'a> {
    model: &'a PrefixLm,
    w: Values<'a>,
}

/// Run `f` on a pass over `model`'s weights, read-locked while it runs.
fn with_pass<R>(model: &PrefixLm, f: impl FnOnce(&Pass) -> Result<R>) -> Result<R> {
    let guards = model.weights.map(Tensor::storage_and_layout);
    let w = guards.try_map(|_, (storage, layout)| cpu_values(storage, layout))?;
    f(&Pass { model, w })
}

impl Pass<'_> {
    fn config(&self) -> &PrefixLmConfig {
        &self.model.config
    }

    /// The text rows projected to the model's width, with `projᵀ` read as `proj_t`.
    fn project_text(&self, text: &[f32], proj_t: Weight) -> Vec<f32> {
        let (d, e) = (self.config().d_model, self.config().text_dim);
        let rows = text.len() / e;
        let mut out = proj_t.product(text, (rows, d, e));
        out.chunks_mut(d)
            .for_each(|r| r.iter_mut().zip(self.w.proj_b).for_each(|(x, b)| *x += b));
        out
    }

    /// Rows of the input embedding for `tokens`.
    fn embed(&self, tokens: &[u32]) -> Vec<f32> {
        let d = self.config().d_model;
        tokens
            .iter()
            .flat_map(|&t| &self.w.tok_emb[t as usize * d..][..d])
            .copied()
            .collect()
    }

    /// Forward pass through the blocks: the last block's output and, when `keep` (training),
    /// the blocks' traces; training applies the batch's dropout.
    fn run(&self, batch: &LmBatch, keep: bool) -> Result<Trace> {
        let layout = &batch.layout;
        self.model.check(layout)?;
        let attn = self.attention(layout);
        let mut h = self.embed(&batch.inputs);
        h.extend(self.project_text(&batch.text, Weight::Dense((self.w.proj_w, true))));
        let mut blocks = Vec::new();
        let dropout = batch.dropout.filter(|_| keep);
        let d = self.config().d_model;
        for (i, bw) in self.w.blocks.iter().enumerate() {
            let mats = bw.forward_mats();
            let dropped = dropout.map(|p| {
                [Branch::Attention, Branch::Ffn].map(|branch| p.packed(layout, i, branch, d))
            });
            let (next, trace) = block_forward(self.config(), bw, mats, (h, dropped), |qkv| {
                attn.forward(qkv)
            });
            if keep {
                blocks.push(trace);
            }
            h = next;
        }
        Ok(Trace { blocks, h })
    }

    /// `RMSNorm(h; norm)` of the motion slots' rows of the last block's output.
    fn final_norm(&self, batch: &LmBatch, trace: &Trace) -> Vec<f32> {
        let c = self.config();
        let rows = batch.inputs.len() * c.d_model;
        lm_kernels::rms_norm(&trace.h[..rows], self.w.norm, c.norm_eps as f32)
    }

    fn attention<'a>(&'a self, layout: &'a SeqLayout) -> lm_kernels::Attention<'a> {
        lm_kernels::Attention {
            layout,
            rope: &self.model.rope,
            heads: self.config().n_heads,
            d: self.config().d_model,
        }
    }

    /// `RMSNorm(h; norm) · headᵀ`, with `headᵀ` read as `head_t`.
    fn head(&self, h: &[f32], head_t: Weight) -> Vec<f32> {
        let c = self.config();
        let (d, v) = (c.d_model, c.vocab_size());
        let xn = lm_kernels::rms_norm(h, self.w.norm, c.norm_eps as f32);
        head_t.product(&xn, (h.len() / d, v, d))
    }

    /// Backward pass from the gradients of the normalised motion rows and of the head: the
    /// gradient of every weight.
    fn backward(
        &self,
        batch: &LmBatch,
        trace: &Trace,
        g_xn: &[f32],
        g_head: Vec<f32>,
    ) -> Weights<Vec<f32>> {
        let c = self.config();
        let (d, v, e, eps) = (c.d_model, c.vocab_size(), c.text_dim, c.norm_eps as f32);
        let motion = batch.inputs.len();
        let attn = self.attention(&batch.layout);
        let hm = &trace.h[..motion * d];
        let mut gh = vec![0f32; trace.h.len()];
        let norm = lm_kernels::rms_norm_backward(hm, self.w.norm, g_xn, eps, &mut gh[..motion * d]);
        let mut blocks: Vec<_> = self
            .w
            .blocks
            .iter()
            .zip(&trace.blocks)
            .rev()
            .map(|(bw, bt)| block_backward(c, bw, bt, &attn, &mut gh))
            .collect();
        blocks.reverse();
        // Inputs: embedding rows of the motion inputs, projection of the text rows.
        let mut tok_emb = vec![0f32; v * d];
        for (&t, g) in batch.inputs.iter().zip(gh.chunks(d)) {
            let row = &mut tok_emb[t as usize * d..][..d];
            row.iter_mut().zip(g).for_each(|(a, b)| *a += b);
        }
        let gt = &gh[motion * d..];
        Weights {
            tok_emb,
            proj_w: lm_kernels::gemm_new((gt, true), (&batch.text, false), (d, e, gt.len() / d)),
            proj_b: lm_kernels::column_sums(gt, d),
            blocks,
            norm,
            head: g_head,
        }
    }
}

/// [`PrefixLm::forward`].
pub(super) fn forward(model: &PrefixLm, batch: &LmBatch) -> Result<Tensor> {
    let logits = with_pass(model, |p| {
        let trace = p.run(batch, false)?;
        let h = &trace.h[..batch.inputs.len() * model.config.d_model];
        Ok(p.head(h, Weight::Dense((p.w.head, true))))
    })?;
    let rows = batch.inputs.len();
    Tensor::from_vec(logits, (rows, model.config.vocab_size()), model.device())
}

/// [`PrefixLm::target_log_probs`].
pub(super) fn target_log_probs(model: &PrefixLm, batch: &LmBatch) -> Result<Vec<f32>> {
    with_pass(model, |p| {
        let trace = p.run(batch, false)?;
        let xn = p.final_norm(batch, &trace);
        let d = model.config.d_model;
        Ok(head_loss::linear_target_log_probs(
            &xn,
            p.w.head,
            d,
            &batch.targets,
        ))
    })
}

/// [`PrefixLm::loss_and_grads`]: the head and the loss run fused, on the slots with a target
/// only.
pub(super) fn loss_and_grads(model: &PrefixLm, batch: &LmBatch) -> Result<(f32, GradStore)> {
    let d = model.config.d_model;
    loss_and_grads_by(model, batch, &|w, xn| {
        head_loss::linear_cross_entropy(xn, w.head, d, &batch.targets)
    })
}

/// [`PrefixLm::loss_and_grads_with`].
pub(super) fn loss_and_grads_with(
    model: &PrefixLm,
    batch: &LmBatch,
    extra: &ExtraLoss<'_>,
) -> Result<(f32, GradStore)> {
    let (d, v) = (model.config.d_model, model.config.vocab_size());
    loss_and_grads_by(model, batch, &|w, xn| {
        let rows = xn.len() / d;
        let logits = lm_kernels::gemm_new((xn, false), (w.head, true), (rows, v, d));
        let (mut loss, mut g_logits) = lm_kernels::cross_entropy(&logits, v, &batch.targets);
        if let Some((term, g_term)) = extra(&logits) {
            loss += term;
            g_logits.iter_mut().zip(g_term).for_each(|(g, e)| *g += e);
        }
        let g_xn = lm_kernels::gemm_new((&g_logits, false), (w.head, false), (rows, d, v));
        let g_head = lm_kernels::gemm_new((&g_logits, true), (xn, false), (v, d, rows));
        (loss, g_xn, g_head)
    })
}

/// The loss and every weight's gradient, given `head_loss(weights, xn)`: the loss of the
/// normalised motion rows `xn` and its gradients with respect to `xn` and the head.
fn loss_and_grads_by(
    model: &PrefixLm,
    batch: &LmBatch,
    head_loss: &HeadLoss<'_>,
) -> Result<(f32, GradStore)> {
    let (loss, grads) = lm_kernels::in_pool(|| {
        with_pass(model, |p| {
            let trace = p.run(batch, true)?;
            let xn = p.final_norm(batch, &trace);
            let (loss, g_xn, g_head) = head_loss(&p.w, &xn);
            Ok((loss, p.backward(batch, &trace, &g_xn, g_head)))
        })
    })?;
    let mut store = GradStore::default();
    for (t, g) in model.weights.refs().into_iter().zip(grads.into_vec()) {
        store.insert(t, Tensor::from_vec(g, t.shape(), t.device())?);
    }
    Ok((loss, store))
}

/// [`PrefixLm::new_cache`].
pub(super) fn new_cache(model: &PrefixLm, layout: &SeqLayout) -> Result<CpuCache> {
    let c = &model.config;
    let (d, heads, hd, f) = (c.d_model, c.n_heads, c.head_dim(), c.ffn_hidden);
    let packed = with_pass(model, |p| {
        let pack = |w: &[f32], out_in| PackedMatrix::new((w, true), out_in);
        let t = |b: &BlockWeights<&[f32]>| {
            [
                pack(b.wqkv, (d, 3 * d)),
                pack(b.wo, (d, d)),
                pack(b.w13, (d, 2 * f)),
                pack(b.w2, (f, d)),
            ]
        };
        Ok(PackedWeights {
            proj: pack(p.w.proj_w, (c.text_dim, d)),
            blocks: p.w.blocks.iter().map(t).collect(),
            head: pack(p.w.head, (d, c.vocab_size())),
        })
    })?;
    Ok(CpuCache {
        layers: (0..c.n_layers)
            .map(|_| LayerCache::new(layout, heads, hd))
            .collect(),
        packed,
    })
}

/// [`PrefixLm::forward_cached`] (arguments checked there).
pub(super) fn forward_cached(
    model: &PrefixLm,
    cache: &mut CpuCache,
    layout: &SeqLayout,
    text: &[f32],
    tokens: &[u32],
    (from, to): (usize, usize),
) -> Result<Tensor> {
    let (c, p, n_new) = (&model.config, layout.prefix_slots, to - from);
    let d = c.d_model;
    let CpuCache { layers, packed } = cache;
    let logits = with_pass(model, |pass| {
        let projected = match from < p {
            true => pass.project_text(text, Weight::Packed(&packed.proj)),
            false => Vec::new(),
        };
        let motion = pass.embed(tokens);
        let per_seq = to - from.max(p);
        let mut h = Vec::with_capacity(layout.batch * n_new * d);
        for b in 0..layout.batch {
            for s in from..to.min(p) {
                h.extend_from_slice(&projected[(b * p + s) * d..][..d]);
            }
            h.extend_from_slice(&motion[b * per_seq * d..][..per_seq * d]);
        }
        let attn = pass.attention(layout);
        let blocks = pass.w.blocks.iter().zip(&packed.blocks);
        for ((bw, mats), layer) in blocks.zip(layers.iter_mut()) {
            let attend = |qkv: &[f32]| (attn.cached(qkv, layer, (from, to)), Vec::new());
            let mats = mats.each_ref().map(Weight::Packed);
            h = block_forward(c, bw, mats, (h, None), attend).0;
        }
        let last: Vec<f32> = h
            .chunks(n_new * d)
            .flat_map(|rows| &rows[(n_new - 1) * d..])
            .copied()
            .collect();
        Ok(pass.head(&last, Weight::Packed(&packed.head)))
    })?;
    Tensor::from_vec(logits, (layout.batch, c.vocab_size()), model.device())
}

/// What cached decoding keeps between steps on the CPU: each layer's keys and values, and
/// the weights packed into panels.
pub(super) struct CpuCache {
    layers: Vec<LayerCache>,
    packed: PackedWeights,
}

/// Every matrix a decoding step multiplies by, packed once into column panels, so that each
/// step's few-row products stream it (see [`nn::panels`]) and a row's values do not depend on
/// the rows decoded beside it.
struct PackedWeights {
    /// The text projection's Wᵀ.
    proj: PackedMatrix,
    /// Per block: Wqkvᵀ, Woᵀ, W13ᵀ, W2ᵀ.
    blocks: Vec<[PackedMatrix; 4]>,
    head: PackedMatrix,
}
