//! Residual dropout (Srivastava et al. 2014, "Dropout: a simple way to prevent neural networks
//! from overfitting"), where GPT-2 and nanoGPT put it in a pre-norm block: on the attention
//! output and on the FFN output, before each is added to the residual stream. A value is kept
//! with probability 1 − p and scaled by 1/(1 − p) (inverted dropout, as `torch.nn.Dropout`).
//!
//! Each value's fate is drawn from the step's seed, the block, the branch and the value's
//! (sequence, slot, column), never from its row number, so an executor on packed rows and one
//! on the dense (sequence, slot) grid drop the same values and agree on the loss and every
//! gradient.

use crate::seq_layout::SeqLayout;
use motionscale_core::rng::SplitMix64;

/// The output of a block that dropout scales.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Branch {
    /// `attention · Woᵀ`.
    Attention,
    /// `swiglu · W2ᵀ`.
    Ffn,
}

/// The dropout of one training step: its probability and seed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dropout {
    /// Probability that a value is dropped, in [0, 1).
    pub p: f32,
    /// Seed of the step (the run's seed and the step number mixed).
    pub seed: u64,
}

impl Dropout {
    /// Fill `out` with the scales (0 or 1/(1 − p)) of slot `s` of sequence `b` in block
    /// `layer`'s `branch`. Four values per draw of 64 bits (16 bits each: p to 1/65,536).
    fn row(&self, layer: usize, branch: Branch, (b, s): (usize, usize), out: &mut [f32]) {
        let site = ((layer as u64) << 41) ^ ((branch as u64) << 40) ^ ((b as u64) << 20) ^ s as u64;
        let mut rng = SplitMix64::stream(self.seed, site);
        let threshold = (self.p * 65_536.0).round() as u64;
        let kept = 1.0 / (1.0 - self.p);
        for chunk in out.chunks_mut(4) {
            let bits = rng.next_u64();
            for (i, v) in chunk.iter_mut().enumerate() {
                let draw = (bits >> (16 * i)) & 0xFFFF;
                *v = if draw < threshold { 0.0 } else { kept };
            }
        }
    }

    /// The scales of every real row of `layout` in its row order (motion rows, then text
    /// rows), `d` per row: what the packed CPU executor multiplies by.
    pub fn packed(&self, layout: &SeqLayout, layer: usize, branch: Branch, d: usize) -> Vec<f32> {
        let mut out = vec![0f32; layout.rows() * d];
        for b in 0..layout.batch {
            for s in 0..layout.slots() {
                if let Some(r) = layout.row(b, s) {
                    self.row(layer, branch, (b, s), &mut out[r * d..][..d]);
                }
            }
        }
        out
    }

    /// The scales of the dense grid, `batch · slots` rows (sequence-major, slot by slot),
    /// `d` per row, padding slots included: what the grid executors multiply by.
    pub fn grid(&self, layout: &SeqLayout, layer: usize, branch: Branch, d: usize) -> Vec<f32> {
        let slots = layout.slots();
        let mut out = vec![0f32; layout.batch * slots * d];
        for b in 0..layout.batch {
            for s in 0..slots {
                self.row(layer, branch, (b, s), &mut out[(b * slots + s) * d..][..d]);
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn packed_and_grid_rows_drop_the_same_values() {
        let layout = SeqLayout::packed(vec![2, 3], vec![3, 1]);
        let dropout = Dropout { p: 0.3, seed: 9 };
        let d = 10;
        let packed = dropout.packed(&layout, 1, Branch::Ffn, d);
        let grid = dropout.grid(&layout, 1, Branch::Ffn, d);
        for b in 0..layout.batch {
            for s in 0..layout.slots() {
                if let Some(r) = layout.row(b, s) {
                    let g = (b * layout.slots() + s) * d;
                    assert_eq!(
                        packed[r * d..][..d],
                        grid[g..][..d],
                        "sequence {b} slot {s}"
                    );
                }
            }
        }
        let other = dropout.packed(&layout, 1, Branch::Attention, d);
        assert_ne!(packed, other, "the branches share a mask");
    }

    #[test]
    fn values_are_dropped_at_the_rate_p_and_the_rest_rescaled() {
        let layout = SeqLayout::packed(vec![16; 8], vec![64; 8]);
        let dropout = Dropout { p: 0.1, seed: 3 };
        let scales = dropout.packed(&layout, 0, Branch::Attention, 256);
        let dropped = scales.iter().filter(|&&v| v == 0.0).count() as f64 / scales.len() as f64;
        // 163,840 draws: the rate within 4 standard errors (0.003) of p.
        assert!((dropped - 0.1).abs() < 0.003, "dropped {dropped}");
        let mean = scales.iter().map(|&v| f64::from(v)).sum::<f64>() / scales.len() as f64;
        assert!((mean - 1.0).abs() < 0.004, "mean scale {mean}");
        let none = Dropout { p: 0.0, seed: 3 }.packed(&layout, 0, Branch::Attention, 256);
        assert!(none.iter().all(|&v| v == 1.0));
    }
}
