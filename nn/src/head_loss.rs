//! The LM head fused with its cross-entropy: `logits = x · headᵀ` is computed only for the
//! rows that have a target, a block of rows at a time, and each block's logits are turned
//! into their gradient and consumed (into the gradients of `x` and `head`) while they are
//! still in cache.
//!
//! The unfused path writes a `rows × V` logits matrix and its gradient through memory, and
//! a prefix-LM batch pads every clip to the longest one, so most of its rows are padding:
//! with V in the thousands and a narrow model, that matrix is most of a training step.
//! The blocks and the parts the rows are split into depend only on the shapes, never on the
//! number of threads, so the result is the same on any machine.

use crate::kernels::matmul;
use crate::lm_kernels::{cross_entropy_row, target_log_prob, IGNORE};
use crate::matmul::gemm_with;
use rayon::prelude::*;

/// Bytes of logits one block holds (about a core's L2; at least 64 rows, for the gemm).
const BLOCK_BYTES: usize = 1 << 20;
/// Rows of targets per part (parts run in parallel, each with its own `head` gradient).
const PART_ROWS: usize = 128;
/// At most this many parts.
const MAX_PARTS: usize = 8;
/// At most this many bytes of per-part `head` gradients.
const PARTS_BYTES: usize = 64 << 20;

/// How [`linear_cross_entropy`] splits its rows.
#[derive(Debug, Clone, Copy)]
struct Split {
    /// Rows per block (a multiple of 16, the gemm kernel's height).
    block: usize,
    /// Rows per part.
    part: usize,
}

impl Split {
    /// The split for `rows` rows with a target, `vocab` columns and `d`-wide rows.
    fn new(rows: usize, vocab: usize, d: usize) -> Self {
        let block = (BLOCK_BYTES / 4 / vocab.max(1)).clamp(64, 256) / 16 * 16;
        let by_memory = (PARTS_BYTES / (4 * vocab * d).max(1)).max(1);
        let parts = rows.div_ceil(PART_ROWS).clamp(1, MAX_PARTS.min(by_memory));
        Self {
            block,
            part: rows.div_ceil(parts).max(1),
        }
    }
}

/// Mean cross-entropy of `logits = x · headᵀ` over the rows whose target is not [`IGNORE`]
/// (`x` is `rows × d`, `head` is `V × d`), and its gradients with respect to `x` (zero on
/// the ignored rows) and `head`: the same values as [`crate::lm_kernels::cross_entropy`] of
/// the full logits followed by the two gradient products, without the logits matrix.
pub fn linear_cross_entropy(
    x: &[f32],
    head: &[f32],
    d: usize,
    targets: &[u32],
) -> (f32, Vec<f32>, Vec<f32>) {
    let rows = target_rows(targets);
    let split = Split::new(rows.len(), head.len() / d, d);
    linear_cross_entropy_split(x, head, d, targets, &rows, split)
}

/// [`linear_cross_entropy`] over the target rows `rows`, split by `split`.
fn linear_cross_entropy_split(
    x: &[f32],
    head: &[f32],
    d: usize,
    targets: &[u32],
    rows: &[usize],
    split: Split,
) -> (f32, Vec<f32>, Vec<f32>) {
    let vocab = head.len() / d;
    let scale = 1.0 / rows.len().max(1) as f32;
    let parts: Vec<(Vec<f64>, Vec<f32>, Vec<f32>)> = rows
        .par_chunks(split.part)
        .map(|part| {
            let (mut losses, mut g_x) =
                (Vec::with_capacity(part.len()), vec![0f32; part.len() * d]);
            let mut g_head = vec![0f32; vocab * d];
            let mut xb = vec![0f32; split.block * d];
            let mut logits = vec![0f32; split.block * vocab];
            for (b, block) in part.chunks(split.block).enumerate() {
                let n = block.len();
                gather(x, d, block, &mut xb);
                let (xb, logits) = (&xb[..n * d], &mut logits[..n * vocab]);
                matmul(logits, (xb, false), (head, true), (n, vocab, d), 1.0);
                for (row, &r) in logits.chunks_mut(vocab).zip(block) {
                    losses.push(cross_entropy_row(row, targets[r] as usize, scale));
                }
                let g_xb = &mut g_x[b * split.block * d..][..n * d];
                matmul(g_xb, (logits, false), (head, false), (n, d, vocab), 1.0);
                gemm_with(
                    &mut g_head,
                    (logits, true),
                    (xb, false),
                    (vocab, d, n),
                    (true, 1.0, false),
                );
            }
            (losses, g_x, g_head)
        })
        .collect();
    let mut grad_x = vec![0f32; x.len()];
    let mut grad_head = vec![0f32; head.len()];
    let mut loss = 0f64;
    for ((losses, g_x, g_head), part) in parts.iter().zip(rows.chunks(split.part)) {
        loss += losses.iter().sum::<f64>();
        for (&r, g) in part.iter().zip(g_x.chunks(d)) {
            grad_x[r * d..][..d].copy_from_slice(g);
        }
        grad_head.iter_mut().zip(g_head).for_each(|(a, b)| *a += b);
    }
    ((loss * f64::from(scale)) as f32, grad_x, grad_head)
}

/// `log p(target)` of every row of `logits = x · headᵀ` (NaN where the target is
/// [`IGNORE`]), computing logits only for the rows with a target.
pub fn linear_target_log_probs(x: &[f32], head: &[f32], d: usize, targets: &[u32]) -> Vec<f32> {
    let vocab = head.len() / d;
    let rows = target_rows(targets);
    let block = Split::new(rows.len(), vocab, d).block;
    let found: Vec<Vec<f32>> = rows
        .par_chunks(block)
        .map(|block| {
            let (mut xb, mut logits) =
                (vec![0f32; block.len() * d], vec![0f32; block.len() * vocab]);
            gather(x, d, block, &mut xb);
            let mnk = (block.len(), vocab, d);
            matmul(&mut logits, (&xb, false), (head, true), mnk, 1.0);
            logits
                .chunks(vocab)
                .zip(block)
                .map(|(row, &r)| target_log_prob(row, targets[r] as usize))
                .collect()
        })
        .collect();
    let mut out = vec![f32::NAN; targets.len()];
    for (&r, lp) in rows.iter().zip(found.into_iter().flatten()) {
        out[r] = lp;
    }
    out
}

/// The rows whose target is not [`IGNORE`], in order.
fn target_rows(targets: &[u32]) -> Vec<usize> {
    (0..targets.len())
        .filter(|&r| targets[r] != IGNORE)
        .collect()
}

/// Copy the `d`-wide rows `rows` of `x` into the front of `out`.
fn gather(x: &[f32], d: usize, rows: &[usize], out: &mut [f32]) {
    for (&r, o) in rows.iter().zip(out.chunks_mut(d)) {
        o.copy_from_slice(&x[r * d..][..d]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gradcheck::max_abs_diff;
    use crate::lm_kernels::{cross_entropy, gemm_new, target_log_probs};

    fn values(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = motionscale_core::rng::SplitMix64(seed);
        (0..n).map(|_| rng.range(-1.0, 1.0) as f32).collect()
    }

    /// The unfused path: full logits, cross-entropy, then both gradient products.
    fn unfused(x: &[f32], head: &[f32], d: usize, targets: &[u32]) -> (f32, Vec<f32>, Vec<f32>) {
        let (rows, vocab) = (x.len() / d, head.len() / d);
        let logits = gemm_new((x, false), (head, true), (rows, vocab, d));
        let (loss, g) = cross_entropy(&logits, vocab, targets);
        let g_x = gemm_new((&g, false), (head, false), (rows, d, vocab));
        let g_head = gemm_new((&g, true), (x, false), (vocab, d, rows));
        (loss, g_x, g_head)
    }

    #[test]
    fn fused_head_loss_equals_the_unfused_one_over_any_split() {
        let mut rng = motionscale_core::rng::SplitMix64(3);
        for (case, &(rows, vocab, d)) in [(1, 5, 2), (37, 9, 4), (70, 300, 8), (200, 33, 16)]
            .iter()
            .enumerate()
        {
            let x = values(rows * d, 10 + case as u64);
            let head = values(vocab * d, 20 + case as u64);
            // Every third row is padding, except in the one-row case.
            let targets: Vec<u32> = (0..rows)
                .map(|r| {
                    if rows > 1 && r % 3 == 1 {
                        IGNORE
                    } else {
                        rng.below(vocab as u64) as u32
                    }
                })
                .collect();
            let (loss, g_x, g_head) = unfused(&x, &head, d, &targets);
            let valid: Vec<usize> = (0..rows).filter(|&r| targets[r] != IGNORE).collect();
            for split in [
                Split::new(valid.len(), vocab, d),
                Split { block: 16, part: 5 },
                Split { block: 32, part: 1 },
            ] {
                let (fl, fx, fh) =
                    linear_cross_entropy_split(&x, &head, d, &targets, &valid, split);
                assert!(
                    (fl - loss).abs() < 1e-5,
                    "{case} {split:?}: loss {fl} vs {loss}"
                );
                assert!(max_abs_diff(&fx, &g_x) < 1e-6, "{case} {split:?}: grad x");
                assert!(
                    max_abs_diff(&fh, &g_head) < 1e-6,
                    "{case} {split:?}: grad head"
                );
                for &r in &valid {
                    assert!(fx[r * d..][..d].iter().any(|&g| g != 0.0));
                }
            }
            let logits = gemm_new((&x, false), (&head, true), (rows, vocab, d));
            let lp = target_log_probs(&logits, vocab, &targets);
            let flp = linear_target_log_probs(&x, &head, d, &targets);
            for (a, b) in lp.iter().zip(&flp) {
                assert!(
                    a.is_nan() && b.is_nan() || (a - b).abs() < 1e-5,
                    "{a} vs {b}"
                );
            }
        }
    }

    #[test]
    fn a_batch_without_targets_has_zero_loss_and_gradients() {
        let (x, head) = (values(12, 1), values(20, 2));
        let (loss, g_x, g_head) = linear_cross_entropy(&x, &head, 4, &[IGNORE; 3]);
        assert_eq!(loss, 0.0);
        assert!(g_x.iter().chain(&g_head).all(|&g| g == 0.0));
        assert!(linear_target_log_probs(&x, &head, 4, &[IGNORE; 3])
            .iter()
            .all(|v| v.is_nan()));
    }
}
