//! Evaluation of the prefix LM: test cross-entropy and the normalised loss of ScaMo Eq. 8
//! (Tao et al.), which subtracts the log unigram frequency of each target so that losses
//! compare across vocabulary sizes.
//!
//! Both are means over the **motion-code** targets of a split (EOS targets have no unigram
//! frequency in the token counts; the cross-entropy with EOS, the training objective, is
//! reported beside them). With p_u the add-one smoothed unigram of the train split,
//! `L_u = −(1/T) Σ_t [log p(m_t | m<t, S) − log p_u(m_t)] = CE − CE_u`, where CE_u is the
//! cross-entropy of the context-free unigram model on the same targets.

use crate::lm_data::LmData;
use crate::MotionLm;
use ingest::corpus::Origin;
use nn::lm_kernels::IGNORE;
use nn::ModelError;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Losses of a model on one split.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SplitLoss {
    /// Split evaluated.
    pub split: String,
    /// Clips.
    pub clips: u64,
    /// Motion-code targets T.
    pub code_targets: u64,
    /// Mean cross-entropy over the code targets (nats).
    pub cross_entropy: f64,
    /// Mean cross-entropy over every target, EOS included (the training objective).
    pub cross_entropy_with_eos: f64,
    /// Normalised loss L_u (ScaMo Eq. 8) over the code targets.
    pub normalized_loss: f64,
    /// Cross-entropy of the smoothed train unigram on the same targets (CE − L_u).
    pub unigram_cross_entropy: f64,
    /// Entropy of the smoothed train unigram distribution.
    pub unigram_entropy: f64,
    /// The same losses over the split's clips of each origin, when it has both (their
    /// code-target-weighted means are the split's).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub by_origin: BTreeMap<Origin, SplitLoss>,
}

/// Entropy of a distribution (nats).
pub fn entropy(p: &[f64]) -> f64 {
    -p.iter()
        .filter(|&&v| v > 0.0)
        .map(|v| v * v.ln())
        .sum::<f64>()
}

/// Running sums of one group of evaluated clips (the split, or its clips of one origin).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct LossSums {
    clips: u64,
    /// Σ log p over the code targets.
    code_log_prob: f64,
    /// Σ log p_u over the same targets.
    code_unigram_log_prob: f64,
    /// Σ (log p − log p_u) over the same targets (L_u summed in target order).
    code_excess: f64,
    code_targets: u64,
    /// Σ −log p over every target, EOS included.
    nll: f64,
    targets: u64,
}

impl LossSums {
    /// Add one target of log-probability `log_prob`; `unigram` is p_u of a code target.
    fn add(&mut self, log_prob: f64, unigram: Option<f64>) {
        self.nll -= log_prob;
        self.targets += 1;
        if let Some(p) = unigram {
            self.code_log_prob += log_prob;
            self.code_unigram_log_prob += p.ln();
            self.code_excess += log_prob - p.ln();
            self.code_targets += 1;
        }
    }

    /// The losses of these sums (means over the code targets).
    fn finish(&self, split: &str, unigram_entropy: f64) -> SplitLoss {
        let t = self.code_targets.max(1) as f64;
        let (cross_entropy, unigram_cross_entropy) =
            (-self.code_log_prob / t, -self.code_unigram_log_prob / t);
        SplitLoss {
            split: split.to_string(),
            clips: self.clips,
            code_targets: self.code_targets,
            cross_entropy,
            cross_entropy_with_eos: self.nll / self.targets.max(1) as f64,
            normalized_loss: -self.code_excess / t,
            unigram_cross_entropy,
            unigram_entropy,
            by_origin: BTreeMap::new(),
        }
    }
}

/// Losses of `lm` on every clip of `split` (first captions), `batch` clips per pass (one
/// when every caption has its own model); with clips of both origins, also per origin.
pub fn evaluate(
    lm: &dyn MotionLm,
    data: &LmData,
    split: &str,
    batch: usize,
) -> Result<SplitLoss, ModelError> {
    evaluate_ensemble(&[lm], data, split, batch)
}

/// Losses of the ensemble of `lms` on `split`, as [`evaluate`]: each target's probability is
/// the mean of the members' (log p = log Σ_k p_k − log K, token-level ensembling). The members
/// must read the same batches (one codebook, one prefix and motion length).
pub fn evaluate_ensemble(
    lms: &[&dyn MotionLm],
    data: &LmData,
    split: &str,
    batch: usize,
) -> Result<SplitLoss, ModelError> {
    let items = data.eval_items(split);
    if items.is_empty() {
        return Err(ModelError::argument(
            "split",
            format!("the token set has no {split} clips to evaluate"),
        ));
    }
    let first = *lms
        .first()
        .ok_or_else(|| ModelError::argument("models", "an ensemble needs at least one model"))?;
    let codebook = data.codebook_size() as u32;
    let unigram = data.unigram.smoothed_probabilities("train");
    // The split's sums in clip order (as before origins were told apart), and per origin.
    let (mut mix, mut by_origin) = (LossSums::default(), BTreeMap::<Origin, LossSums>::new());
    let batch = match lms.iter().any(|lm| lm.per_caption()) {
        true => 1,
        false => batch.max(1),
    };
    for chunk in items.chunks(batch) {
        let b = data.batch(first.config(), chunk);
        let lp = ensemble_log_probs(lms, data, chunk, &b)?;
        let mut start = 0;
        for (item, &n) in chunk.iter().zip(&b.layout.motion_lens) {
            let slots = start..start + n;
            start += n;
            let sums = by_origin.entry(item.0.origin).or_default();
            sums.clips += 1;
            mix.clips += 1;
            for (&t, &l) in b.targets[slots.clone()].iter().zip(&lp[slots]) {
                if t != IGNORE {
                    let code = (t < codebook).then(|| unigram[t as usize]);
                    sums.add(l, code);
                    mix.add(l, code);
                }
            }
        }
    }
    let unigram_entropy = entropy(&unigram);
    let mut loss = mix.finish(split, unigram_entropy);
    if by_origin.len() > 1 {
        loss.by_origin = by_origin
            .iter()
            .map(|(origin, s)| (*origin, s.finish(split, unigram_entropy)))
            .collect();
    }
    Ok(loss)
}

/// Each target's log-probability under the mean of the members' distributions, for the
/// batch `b` of `chunk` (built for the first member; every other member must build the same).
fn ensemble_log_probs(
    lms: &[&dyn MotionLm],
    data: &LmData,
    chunk: &[(&crate::lm_data::Example, Option<usize>)],
    b: &crate::LmBatch,
) -> Result<Vec<f64>, ModelError> {
    let mut members = Vec::with_capacity(lms.len());
    for (k, lm) in lms.iter().enumerate() {
        // `b` is the first member's batch: only the others build (and check) their own.
        let own = (k > 0).then(|| data.batch(lm.config(), chunk));
        if own.as_ref().is_some_and(|own| own.targets != b.targets) {
            return Err(ModelError::argument(
                "models",
                format!("ensemble member {k} reads other batches than the first (another codebook or sequence length)"),
            ));
        }
        let lp = lm
            .for_caption(data.text_of(&chunk[0]))
            .and_then(|model| model.target_log_probs(own.as_ref().unwrap_or(b)))
            .map_err(ModelError::Candle)?;
        members.push(lp);
    }
    let ln_k = (lms.len() as f64).ln();
    Ok((0..b.targets.len())
        .map(|i| {
            let max = members
                .iter()
                .map(|m| f64::from(m[i]))
                .fold(f64::NEG_INFINITY, f64::max);
            let sum: f64 = members.iter().map(|m| (f64::from(m[i]) - max).exp()).sum();
            max + sum.ln() - ln_k
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The sums of code targets `targets` with model log-probabilities `log_probs`.
    fn sums(log_probs: &[f64], targets: &[u32], unigram: &[f64]) -> LossSums {
        let mut s = LossSums {
            clips: 1,
            ..LossSums::default()
        };
        for (&lp, &t) in log_probs.iter().zip(targets) {
            s.add(lp, Some(unigram[t as usize]));
        }
        s
    }

    #[test]
    fn normalized_loss_of_a_toy_distribution_by_hand() {
        // Train counts [2, 1, 0] smoothed: p_u = [3/6, 2/6, 1/6]. The model gives the targets
        // 0 and 2 probabilities 0.6 and 0.2: L_u = −½[ln(0.6/0.5) + ln(0.2/(1/6))] = −ln 1.2.
        let unigram = tokenizer::UnigramCounts::of(
            &[tokenizer::TokenClip {
                motion_id: "a".into(),
                split: "train".into(),
                tokens: vec![0, 0, 1],
            }],
            3,
        )
        .unwrap()
        .smoothed_probabilities("train");
        let loss = sums(&[0.6f64.ln(), 0.2f64.ln()], &[0, 2], &unigram).finish("test", 0.0);
        let lu = loss.normalized_loss;
        assert!((lu + 1.2f64.ln()).abs() < 1e-12, "{lu}");
        assert!((lu - (-0.182_321_556_793_954_6)).abs() < 1e-12);
        assert!((loss.cross_entropy - loss.unigram_cross_entropy - lu).abs() < 1e-15);
        // A model that predicts the unigram itself scores exactly 0.
        let lp: Vec<f64> = [0u32, 2, 1]
            .iter()
            .map(|&t| unigram[t as usize].ln())
            .collect();
        let own = sums(&lp, &[0, 2, 1], &unigram).finish("test", 0.0);
        assert!(own.normalized_loss.abs() < 1e-15);
        assert!((entropy(&[0.5, 0.5]) - 2f64.ln()).abs() < 1e-15);
    }

    #[test]
    fn per_origin_losses_weighted_by_their_targets_give_the_mix() {
        let unigram = [0.5, 0.3, 0.2];
        let real = (vec![-0.2, -1.5, -0.9, -2.2, -0.1], vec![0u32, 1, 2, 0, 1]);
        let synth = (vec![-3.0, -0.05], vec![2u32, 2]);
        let mut mix = LossSums::default();
        for (lp, t) in [&real, &synth] {
            for (&l, &t) in lp.iter().zip(t) {
                mix.add(l, Some(unigram[t as usize]));
            }
        }
        // An EOS target (no unigram) counts in the EOS-inclusive loss only.
        mix.add(-0.7, None);
        let (r, s) = (
            sums(&real.0, &real.1, &unigram).finish("test", 1.0),
            sums(&synth.0, &synth.1, &unigram).finish("test", 1.0),
        );
        let m = mix.finish("test", 1.0);
        assert_eq!(m.code_targets, r.code_targets + s.code_targets);
        let weighted = |f: fn(&SplitLoss) -> f64| {
            (f(&r) * r.code_targets as f64 + f(&s) * s.code_targets as f64)
                / (r.code_targets + s.code_targets) as f64
        };
        assert!((weighted(|l| l.cross_entropy) - m.cross_entropy).abs() < 1e-12);
        assert!((weighted(|l| l.normalized_loss) - m.normalized_loss).abs() < 1e-12);
        assert!((weighted(|l| l.unigram_cross_entropy) - m.unigram_cross_entropy).abs() < 1e-12);
        assert!((m.cross_entropy_with_eos - (m.cross_entropy * 7.0 + 0.7) / 8.0).abs() < 1e-12);
    }
}
