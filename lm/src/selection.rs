//! The validation-selected checkpoint of a run: its scheduled evaluation with the lowest
//! validation cross-entropy (the earliest of equals).
//!
//! The cross-entropy is taken on the clips the run selects on: all validation clips, or,
//! for a run trained on one origin only (captured or synthetic), that origin's validation
//! clips, so that it is never chosen on clips of a kind it never trained on. The trainer
//! selects as it goes; [`reselect`] selects again from a finished run's `evals.jsonl`, by
//! the same rule, e.g. under another choice of clips.

use crate::eval_record::{BestEval, EvalRecord};
use crate::test_loss::SplitLoss;
use ingest::corpus::Origin;
use motionscale_core::files::read_json_lines;
use nn::ModelError;
use std::path::Path;

/// Cross-entropy of `val` on its clips of origin `on`, with the origin it was taken on: a
/// split of one origin has no per-origin losses and selects on its whole (origin none, as
/// for `on` none); one of both origins gives none when `on` is neither of them.
pub fn selection_loss(val: &SplitLoss, on: Option<Origin>) -> Option<(f64, Option<Origin>)> {
    match on {
        Some(origin) if !val.by_origin.is_empty() => val
            .by_origin
            .get(&origin)
            .map(|l| (l.cross_entropy, Some(origin))),
        _ => Some((val.cross_entropy, None)),
    }
}

/// `record` as a candidate for the selection on `on`: none for an unscheduled evaluation or
/// one without validation clips of that origin.
pub fn candidate(record: &EvalRecord, on: Option<Origin>) -> Option<BestEval> {
    if record.unscheduled {
        return None;
    }
    let (val_cross_entropy, selected_on) = selection_loss(record.val.as_ref()?, on)?;
    Some(BestEval {
        step: record.step,
        val_cross_entropy,
        test: record.test.clone(),
        selected_on,
    })
}

/// The better of the selection so far and a later candidate: the candidate only when its
/// validation cross-entropy is strictly lower (so the earliest of equals stays).
pub fn keep_better(best: Option<BestEval>, later: BestEval) -> BestEval {
    match best {
        Some(b) if later.val_cross_entropy < b.val_cross_entropy => later,
        Some(b) => b,
        None => later,
    }
}

/// The selection on `on` among `records` (in step order).
pub fn select<'a>(
    records: impl IntoIterator<Item = &'a EvalRecord>,
    on: Option<Origin>,
) -> Option<BestEval> {
    records
        .into_iter()
        .filter_map(|r| candidate(r, on))
        .fold(None, |best, c| Some(keep_better(best, c)))
}

/// The selection on `on` among the evaluations in the run folder `out`'s `evals.jsonl`.
pub fn reselect(out: &Path, on: Option<Origin>) -> Result<Option<BestEval>, ModelError> {
    let records: Vec<EvalRecord> = read_json_lines(&out.join("evals.jsonl"))?;
    Ok(select(&records, on))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    fn loss(ce: f64) -> SplitLoss {
        SplitLoss {
            split: "val".into(),
            clips: 4,
            code_targets: 100,
            cross_entropy: ce,
            cross_entropy_with_eos: ce,
            normalized_loss: ce - 8.0,
            unigram_cross_entropy: 8.0,
            unigram_entropy: 7.0,
            by_origin: BTreeMap::new(),
        }
    }

    /// A split whose whole cross-entropy is the token-weighted mean of the two origins'.
    fn split(real: f64, synth: f64) -> SplitLoss {
        SplitLoss {
            by_origin: BTreeMap::from([(Origin::Real, loss(real)), (Origin::Synth, loss(synth))]),
            ..loss((real + synth) / 2.0)
        }
    }

    fn record(step: u64, val: SplitLoss, unscheduled: bool) -> EvalRecord {
        EvalRecord {
            step,
            tokens_seen: step * 10,
            train_loss: 5.0,
            test: loss(step as f64),
            val: Some(val),
            best: None,
            unscheduled,
            flops_6n: 0.0,
            flops_exact: 0.0,
            n_nv: 1,
            n_v: 1,
            tied: false,
            expert_weights: None,
        }
    }

    #[test]
    fn each_origin_selects_on_its_own_clips_and_the_earliest_of_equals_wins() {
        // Captured clips are best at step 200; the mix at 300, where synthetic clips still fall.
        let records = [
            record(100, split(3.0, 3.0), false),
            record(200, split(2.0, 2.6), false),
            record(300, split(2.3, 1.5), false),
            record(400, split(2.0, 1.9), false),
        ];
        let step = |on| select(&records, on).map(|b| b.step);
        assert_eq!(step(None), Some(300));
        assert_eq!(step(Some(Origin::Real)), Some(200));
        assert_eq!(step(Some(Origin::Synth)), Some(300));
        let best = select(&records, Some(Origin::Real)).unwrap();
        assert_eq!(
            (best.val_cross_entropy, best.test.cross_entropy),
            (2.0, 200.0)
        );
        assert_eq!(best.selected_on, Some(Origin::Real));
    }

    #[test]
    fn unscheduled_evaluations_are_never_selected_and_a_one_origin_split_selects_on_its_whole() {
        let records = [
            record(100, split(3.0, 3.0), false),
            record(150, split(0.5, 0.5), true),
            record(200, loss(1.0), false),
        ];
        assert_eq!(select(&records, None).map(|b| b.step), Some(200));
        assert_eq!(
            select(&records, Some(Origin::Synth)).map(|b| b.step),
            Some(200)
        );
        assert_eq!(select(&records[1..2], None), None);
        assert_eq!(
            select(&records, Some(Origin::Real)).map(|b| b.selected_on),
            Some(None)
        );
        let both = split(3.0, 1.0);
        assert_eq!(
            selection_loss(&both, Some(Origin::Synth)),
            Some((1.0, Some(Origin::Synth)))
        );
        assert_eq!(selection_loss(&both, None), Some((2.0, None)));
    }
}
