//! The GPU executor of the prefix LM's training step: the graph executor's model (same
//! weights, casts and fused ops of `nn::fused_ops`) with the structure of the cpu executor:
//! the forward records what the backward needs, and the backward is written out, so no
//! autograd graph is built (candle's backward allocates a zero tensor and adds into it for
//! every edge). Runs wherever candle's tensors do; the default for training off the CPU.
//! Inference (logits, log-probabilities, decoding) is the graph executor's.
//!
//! Every product is `linear`: `x` cast to the compute dtype times `Wᵀ`, f32 out; its
//! backward casts the output gradient once and gives `dx = (dy · W)` and `dW = dyᵀ · x` in
//! f32, as the graph executor's autograd does through the same casts.

use super::grid::{
    cast, cast_linear as linear, dropout_scales, grid_inputs, target_rows, AttentionInputs, Grid,
};
use super::{BlockWeights, LmBatch, PrefixLm, Weights};
use candle_core::backprop::GradStore;
use candle_core::{DType, Result, Tensor};
use nn::fused_ops::{
    masked_softmax, masked_softmax_backward, qkv_heads, qkv_heads_backward, rms_norm,
    rms_norm_backward, swiglu_backward_rows, swiglu_rows, weighted_cross_entropy,
    weighted_cross_entropy_backward,
};

/// Told as each stage of a training step ends (by [`PrefixLm::loss_and_grads_timed`]): what a
/// bench's stage timer implements, synchronising the device to time each stage apart.
pub trait StageClock {
    /// `stage` has been queued (and, for a timer, run: it may wait for the device).
    fn stage_done(&self, stage: &'static str) -> Result<()>;
}

/// The backward of `linear` (the graph executor's `cast_linear`) from its cast input `xc`: `(dx, dW)`, both f32.
fn linear_backward(xc: &Tensor, w: &Tensor, dy: &Tensor) -> Result<(Tensor, Tensor)> {
    let dyc = dy.to_dtype(w.dtype())?;
    let dx = dyc.matmul(w)?.to_dtype(DType::F32)?;
    let dw = dyc.t()?.matmul(xc)?.to_dtype(DType::F32)?;
    Ok((dx, dw))
}

/// What one block's backward needs from its forward.
struct BlockTape {
    h: Tensor,
    a1: Tensor,
    /// Rotated queries, rotated keys and values in the compute dtype.
    qkv: [Tensor; 3],
    probs: Tensor,
    probs_c: Tensor,
    o_rows: Tensor,
    h1: Tensor,
    a2: Tensor,
    ab: Tensor,
    act: Tensor,
}

/// One training pass: the model, its weights as cast, the attention tables.
struct Step<'a> {
    model: &'a PrefixLm,
    w: Weights<Tensor>,
    at: AttentionInputs,
    batch: usize,
    clock: Option<&'a dyn StageClock>,
    /// Per block, the dropout scales of the attention and FFN outputs (training with
    /// dropout), on the grid.
    dropped: Option<Vec<[Tensor; 2]>>,
}

impl Step<'_> {
    fn lap(&self, stage: &'static str) -> Result<()> {
        self.clock.map_or(Ok(()), |c| c.stage_done(stage))
    }

    /// `x` (block `i`'s output of `branch`, 0 attention, 1 FFN, or its gradient) times its
    /// dropout scales, or `x` without dropout.
    fn scaled(&self, x: Tensor, i: usize, branch: usize) -> Result<Tensor> {
        match &self.dropped {
            Some(scales) => x * &scales[i][branch],
            None => Ok(x),
        }
    }

    fn eps(&self) -> f32 {
        self.model.config.norm_eps as f32
    }

    fn block_forward(&self, i: usize, h: Tensor) -> Result<(Tensor, BlockTape)> {
        let bw = &self.w.blocks[i];
        let (c, dtype) = (&self.model.config, bw.wqkv.dtype());
        let (a1, qkv) = linear(&rms_norm(&h, &bw.n1, self.eps())?, &bw.wqkv)?;
        let grid = qkv_heads(&qkv, &self.at.cos, &self.at.sin, self.batch, c.n_heads)?;
        let [q, k, v] = [0, 1, 2].map(|p| grid.get(p).and_then(|t| t.to_dtype(dtype)));
        let (q, k, v) = (q?, k?, v?);
        self.lap("forward: norm, QKV product, rotary heads")?;
        let scores = q.matmul(&k.t()?)?.to_dtype(DType::F32)?;
        let probs = masked_softmax(&scores, &self.at.prefix_lens, self.at.mask)?;
        let probs_c = probs.to_dtype(dtype)?;
        let (b, _, n, _) = q.dims4()?;
        let o = probs_c
            .matmul(&v)?
            .transpose(1, 2)?
            .reshape((b * n, c.d_model))?;
        self.lap("forward: scores, masked softmax, values")?;
        let (o_rows, att) = linear(&o, &bw.wo)?;
        let h1 = (&h + self.scaled(att, i, 0)?)?;
        self.lap("forward: output product, residual")?;
        let (a2, ab) = linear(&rms_norm(&h1, &bw.n2, self.eps())?, &bw.w13)?;
        let (act, out) = linear(&swiglu_rows(&ab)?, &bw.w2)?;
        let h2 = (&h1 + self.scaled(out, i, 1)?)?;
        self.lap("forward: norm, SwiGLU FFN, residual")?;
        let tape = BlockTape {
            h,
            a1,
            qkv: [q, k, v],
            probs,
            probs_c,
            o_rows,
            h1,
            a2,
            ab,
            act,
        };
        Ok((h2, tape))
    }

    /// The gradient of the block's input from that of its output `dh2`, and the gradients
    /// of its weights.
    fn block_backward(
        &self,
        i: usize,
        t: BlockTape,
        dh2: Tensor,
    ) -> Result<(Tensor, BlockWeights<Option<Tensor>>)> {
        let bw = &self.w.blocks[i];
        let (c, eps) = (&self.model.config, self.eps());
        let (dact, dw2) = linear_backward(&t.act, &bw.w2, &self.scaled(dh2.clone(), i, 1)?)?;
        let dab = swiglu_backward_rows(&t.ab, &dact)?;
        let (da2, dw13) = linear_backward(&t.a2, &bw.w13, &dab)?;
        let (dh1_norm, dn2) = rms_norm_backward(&t.h1, &bw.n2, &da2, eps)?;
        let dh1 = (dh2 + dh1_norm)?;
        self.lap("backward: SwiGLU FFN, norm")?;
        let (do_rows, dwo) = linear_backward(&t.o_rows, &bw.wo, &self.scaled(dh1.clone(), i, 0)?)?;
        let [q, k, v] = &t.qkv;
        let (b, h, n, hd) = q.dims4()?;
        let d_o = do_rows
            .reshape((b, n, h, hd))?
            .transpose(1, 2)?
            .to_dtype(q.dtype())?
            .contiguous()?;
        let dprobs = d_o.matmul(&v.t()?)?.to_dtype(DType::F32)?;
        let dv = t.probs_c.t()?.matmul(&d_o)?;
        let dscores =
            masked_softmax_backward(&t.probs, &dprobs, self.at.mask)?.to_dtype(q.dtype())?;
        let dq = dscores.matmul(k)?;
        let dk = dscores.t()?.matmul(q)?;
        let dgrid = Tensor::stack(&[dq, dk, dv], 0)?.to_dtype(DType::F32)?;
        self.lap("backward: output product, attention")?;
        let dqkv = qkv_heads_backward(&dgrid, &self.at.cos, &self.at.sin, self.batch, c.n_heads)?;
        let (da1, dwqkv) = linear_backward(&t.a1, &bw.wqkv, &dqkv)?;
        let (dh_norm, dn1) = rms_norm_backward(&t.h, &bw.n1, &da1, eps)?;
        let dh = (dh1 + dh_norm)?;
        self.lap("backward: rotary heads, QKV product, norm")?;
        let grads = BlockWeights {
            n1: Some(dn1),
            wqkv: Some(dwqkv),
            wo: Some(dwo),
            n2: Some(dn2),
            w13: Some(dw13),
            w2: Some(dw2),
        };
        Ok((dh, grads))
    }
}

/// [`PrefixLm::loss_and_grads`] without an extra loss, for a batch with targets; `clock`,
/// when given, is told as each stage ends.
pub(super) fn loss_and_grads(
    model: &PrefixLm,
    batch: &LmBatch,
    clock: Option<&dyn StageClock>,
) -> Result<(f32, GradStore)> {
    model.check(&batch.layout)?;
    let (rows, targets) = target_rows(batch);
    let dtype = model.compute.precision.compute_dtype();
    let device = model.device();
    let l = &batch.layout;
    let step = Step {
        model,
        w: cast(&model.weights.map(Tensor::detach), dtype)?,
        at: AttentionInputs::new(model, l, (0, l.slots()), device)?,
        batch: l.batch,
        clock,
        dropped: match batch.dropout {
            Some(dropout) => Some(
                (0..model.config.n_layers)
                    .map(|i| dropout_scales(&dropout, l, i, model.config.d_model, device))
                    .collect::<Result<_>>()?,
            ),
            None => None,
        },
    };
    let grid = Grid::new(batch, device)?;
    let (mut h, input_tape) = grid_inputs(&step.w, model.config.text_dim, batch, &grid, device)?;
    step.lap("inputs: weights cast, grid, embedding, captions")?;
    let mut tapes = Vec::with_capacity(step.w.blocks.len());
    for i in 0..step.w.blocks.len() {
        let (next, tape) = step.block_forward(i, h)?;
        tapes.push(tape);
        h = next;
    }
    let normed = rms_norm(&h, &step.w.norm, step.eps())?;
    let (normed_c, logits) = linear(&normed, &step.w.head)?;
    let (dense, weight) = grid.targets(&rows, &targets)?;
    let n = targets.len().max(1) as f64;
    let loss = weighted_cross_entropy(&logits, &dense, &weight)?
        .sum_all()?
        .affine(1.0 / n, 0.0)?;
    let dlogits = weighted_cross_entropy_backward(&logits, &dense, &weight.affine(1.0 / n, 0.0)?)?;
    let (dnormed, dhead) = linear_backward(&normed_c, &step.w.head, &dlogits)?;
    let (mut dh, dnorm) = rms_norm_backward(&h, &step.w.norm, &dnormed, step.eps())?;
    step.lap("head and loss, both ways")?;
    let mut blocks = Vec::with_capacity(tapes.len());
    for (i, tape) in tapes.into_iter().enumerate().rev() {
        let (prev, grads) = step.block_backward(i, tape, dh)?;
        blocks.push(grads);
        dh = prev;
    }
    blocks.reverse();
    let (proj_w, proj_b) = match &input_tape.text {
        Some((text_c, mask)) => {
            let dprojected = dh.broadcast_mul(mask)?;
            let (_, dproj_w) = linear_backward(text_c, &step.w.proj_w, &dprojected)?;
            (Some(dproj_w), Some(dprojected.sum(0)?))
        }
        None => (None, None),
    };
    let grads = Weights {
        tok_emb: Some(input_tape.one_hot.t()?.matmul(&dh)?),
        proj_w,
        proj_b,
        blocks,
        norm: Some(dnorm),
        head: Some(dhead),
    };
    step.lap("backward: inputs")?;
    let store = model.weights.grad_store(grads)?;
    let loss = loss.to_scalar::<f32>()?;
    step.lap("loss")?;
    Ok((loss, store))
}
