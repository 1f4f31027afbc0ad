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
use nn::lm_kernels::IGNORE;
use nn::ModelError;
use serde::{Deserialize, Serialize};

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
}

/// L_u of targets with model log-probabilities `log_probs` under the unigram `unigram`:
/// `−mean(log p − log p_u(target))`.
pub fn normalized_loss(log_probs: &[f64], targets: &[u32], unigram: &[f64]) -> f64 {
    let sum: f64 = log_probs
        .iter()
        .zip(targets)
        .map(|(lp, &t)| lp - unigram[t as usize].ln())
        .sum();
    -sum / targets.len().max(1) as f64
}

/// Entropy of a distribution (nats).
pub fn entropy(p: &[f64]) -> f64 {
    -p.iter()
        .filter(|&&v| v > 0.0)
        .map(|v| v * v.ln())
        .sum::<f64>()
}

/// Losses of `lm` on every clip of `split` (first captions), `batch` clips per pass (one
/// when every caption has its own model).
pub fn evaluate(
    lm: &dyn MotionLm,
    data: &LmData,
    split: &str,
    batch: usize,
) -> Result<SplitLoss, ModelError> {
    let items = data.eval_items(split);
    if items.is_empty() {
        return Err(ModelError::Argument(format!(
            "the token set has no {split} clips to evaluate"
        )));
    }
    let codebook = data.codebook_size() as u32;
    let (mut code_lp, mut code_targets, mut all_nll, mut all) =
        (Vec::new(), Vec::new(), 0f64, 0u64);
    let batch = if lm.per_caption() { 1 } else { batch.max(1) };
    for chunk in items.chunks(batch) {
        let b = data.batch(lm.config(), chunk);
        let lp = lm
            .for_caption(data.text_of(&chunk[0]))
            .and_then(|model| model.target_log_probs(&b))
            .map_err(ModelError::inference)?;
        for (&t, &l) in b.targets.iter().zip(&lp) {
            if t == IGNORE {
                continue;
            }
            all_nll -= f64::from(l);
            all += 1;
            if t < codebook {
                code_lp.push(f64::from(l));
                code_targets.push(t);
            }
        }
    }
    let unigram = data.unigram.smoothed_probabilities("train");
    let t = code_targets.len().max(1) as f64;
    let cross_entropy = -code_lp.iter().sum::<f64>() / t;
    let unigram_cross_entropy = -code_targets
        .iter()
        .map(|&c| unigram[c as usize].ln())
        .sum::<f64>()
        / t;
    Ok(SplitLoss {
        split: split.to_string(),
        clips: items.len() as u64,
        code_targets: code_targets.len() as u64,
        cross_entropy,
        cross_entropy_with_eos: all_nll / all.max(1) as f64,
        normalized_loss: normalized_loss(&code_lp, &code_targets, &unigram),
        unigram_cross_entropy,
        unigram_entropy: entropy(&unigram),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let lu = normalized_loss(&[0.6f64.ln(), 0.2f64.ln()], &[0, 2], &unigram);
        assert!((lu + 1.2f64.ln()).abs() < 1e-12, "{lu}");
        assert!((lu - (-0.182_321_556_793_954_6)).abs() < 1e-12);
        // A model that predicts the unigram itself scores exactly 0.
        let lp: Vec<f64> = [0u32, 2, 1]
            .iter()
            .map(|&t| unigram[t as usize].ln())
            .collect();
        assert!(normalized_loss(&lp, &[0, 2, 1], &unigram).abs() < 1e-15);
        assert!((entropy(&[0.5, 0.5]) - 2f64.ln()).abs() < 1e-15);
    }
}
