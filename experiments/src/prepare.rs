//! The first stage of a sweep: every vocabulary's token set, made once and shared by all
//! its points. A tokenizer the plan trains goes to `RUNS/tokenizers/<codebook>/` (resumable:
//! `tokenizer::train::train` continues its checkpoint), the corpus is tokenized into
//! `RUNS/tokens/<codebook>/` (complete once its manifest, written last, exists). One process
//! at a time prepares a vocabulary (`RUNS/tokens/.<codebook>.lock`); the others wait for it.

use crate::plan::{IsoFlopPlan, VocabSource, Vocabulary};
use crate::SweepError;
use ingest::corpus::Corpus;
use motionscale_core::lock::FileLock;
use std::path::{Path, PathBuf};

/// The token set folder of `vocab`, made first (the tokenizer trained and run on `device`)
/// when the sweep owns it; `log` sees progress.
pub fn prepare_vocabulary(
    plan: &IsoFlopPlan,
    vocab: &Vocabulary,
    runs: &Path,
    device: &candle_core::Device,
    log: &dyn Fn(&str),
) -> Result<PathBuf, SweepError> {
    let tokens = vocab.tokens_dir(runs);
    let complete = |dir: &Path| dir.join(tokenizer::tokens::MANIFEST).is_file();
    if complete(&tokens) {
        return Ok(tokens);
    }
    let Some(tokenizer_dir) = vocab.tokenizer_dir(runs) else {
        return Err(SweepError::invalid(
            &tokens,
            "the plan's token set has no manifest.json (run `motionscale tokenize` first)",
        ));
    };
    let lock_path = runs
        .join("tokens")
        .join(format!(".{}.lock", vocab.codebook));
    let _lock = FileLock::acquire_or_wait(&lock_path, || {
        log(&format!(
            "vocabulary {}: being prepared by another process, waiting",
            vocab.codebook
        ))
    })?;
    if complete(&tokens) {
        return Ok(tokens);
    }
    if let VocabSource::Train { tokenizer, train } = &vocab.source {
        log(&format!(
            "vocabulary {}: training the {} tokenizer ({} steps) → {}",
            vocab.codebook,
            tokenizer.quantizer_name(),
            train.steps,
            tokenizer_dir.display()
        ));
        let state = tokenizer::train::train(
            &plan.corpus,
            &tokenizer_dir,
            (**tokenizer).clone(),
            (**train).clone(),
            device,
            |r| {
                if let Some(val) = r.val {
                    log(&format!(
                        "vocabulary {}: step {}/{}: train loss {:.4}, val L1 {:.4}",
                        vocab.codebook, r.step, r.steps, r.loss, val.l1
                    ));
                }
            },
        )?;
        log(&format!(
            "vocabulary {}: tokenizer trained ({} steps, {:.0} s)",
            vocab.codebook, state.step, state.wall_s
        ));
    }
    let corpus = Corpus::open(&plan.corpus).map_err(|e| SweepError::invalid(&plan.corpus, e))?;
    let manifest =
        tokenizer::evaluate::write_token_set(&tokenizer_dir, &corpus, &tokens, device, |_, _| {})?;
    let train = manifest.splits.get("train").copied().unwrap_or_default();
    log(&format!(
        "vocabulary {}: tokenized {} train clips ({} tokens) → {}",
        vocab.codebook,
        train.clips,
        train.tokens,
        tokens.display()
    ));
    Ok(tokens)
}
