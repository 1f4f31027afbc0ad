//! The dense (sequence, slot) grid that both candle executors of the prefix LM run on (the
//! graph executor, `graph.rs`, and the GPU executor with hand-written backwards, `gpu.rs`): the
//! weights as one call casts them, where a batch's real slots sit in the grid, the inputs
//! gathered onto it, the attention's inputs and the rows that carry a target.

use super::{LmBatch, PrefixLm, Role, Weights};
use candle_core::{DType, Device, Result, Tensor};
use nn::dropout::{Branch, Dropout};
use nn::fused_ops::PrefixMask;
use nn::lm_kernels::IGNORE;
use nn::seq_layout::SeqLayout;

/// The weights as one call uses them: matrices in the product dtype `dtype`, the rest f32.
pub(super) fn cast(w: &Weights<Tensor>, dtype: DType) -> Result<Weights<Tensor>> {
    w.try_map(|role, t| match role {
        Role::Matrix => t.to_dtype(dtype),
        Role::Embedding | Role::Vector => t.to_dtype(DType::F32),
    })
}

/// The dropout scales of block `layer`'s attention and FFN outputs on the dense grid of
/// `layout` (`batch · slots × d`, f32 on `device`).
pub(super) fn dropout_scales(
    dropout: &Dropout,
    layout: &SeqLayout,
    layer: usize,
    d: usize,
    device: &Device,
) -> Result<[Tensor; 2]> {
    let rows = layout.batch * layout.slots();
    let grid = |branch| Tensor::from_vec(dropout.grid(layout, layer, branch, d), (rows, d), device);
    Ok([grid(Branch::Attention)?, grid(Branch::Ffn)?])
}

/// `x · Wᵀ` of f32 rows with `W` in its compute dtype; f32 out.
pub(super) fn linear(x: &Tensor, w: &Tensor) -> Result<Tensor> {
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
    w: &Weights<Tensor>,
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
    pub(super) fn motion_rows(&self, rows: &[u32]) -> Result<Tensor> {
        let picked: Vec<u32> = rows
            .iter()
            .map(|&r| self.motion_grid_rows[r as usize])
            .collect();
        Tensor::new(picked, &self.device)
    }

    /// The grid rows of every motion row of the layout, in its order.
    pub(super) fn all_motion_rows(&self) -> Result<Tensor> {
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
