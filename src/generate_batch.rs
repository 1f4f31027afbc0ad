//! `motionscale generate --captions-from C`: the captions of a corpus split animated into a
//! HumanML3D-layout folder (`model::caption_set` documents the files).

use crate::lm::GenerateArgs;
use anyhow::Result;
use model::caption_set::{generate_caption_set, CaptionSetOptions};
use model::generate::Sampling;
use model::train::RunConfig;
use model::{MotionLm, TextEncoder};
use std::process::ExitCode;

/// `motionscale generate --captions-from`.
pub fn generate_batch(
    args: &GenerateArgs,
    model: &dyn MotionLm,
    run: &RunConfig,
    encoder: &dyn TextEncoder,
    sampling: Sampling,
) -> Result<ExitCode> {
    let options = CaptionSetOptions {
        corpus: args.captions_from.clone().expect("batch mode"),
        split: args.split.clone(),
        splits: args.splits.clone(),
        mm_texts: args.mm_texts,
        mm_samples: args.mm_samples,
        batch: args.batch,
        sampling,
    };
    let tokenizer = model::train::run_tokenizer(run, args.tokenizer.as_deref())?;
    let bar = crate::commands::progress_bar("generate", "motions");
    let report = generate_caption_set(
        model,
        run,
        &tokenizer,
        Some(encoder),
        &options,
        &args.out,
        |done, total| {
            bar.set_length(total as u64);
            bar.set_position(done.min(total) as u64);
        },
    )?;
    bar.finish_and_clear();
    println!(
        "{} motions from {} captions ({} rejected: no motion token) in {:.1} s, {:.0} tokens/s → {}",
        report.motions,
        report.clips,
        report.rejected,
        report.seconds,
        report.motion_tokens as f64 / report.seconds,
        args.out.display()
    );
    Ok(if report.rejected == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(2)
    })
}
