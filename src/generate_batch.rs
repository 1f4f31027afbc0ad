//! `motionscale generate --captions-from C`: the captions of a corpus split animated into a
//! HumanML3D-layout folder (`lm::caption_set` documents the files).

use anyhow::Result;
use lm::caption_set::{generate_caption_set, CaptionSetOptions};
use lm::train::RunConfig;
use lm::MotionLm;
use std::path::Path;
use std::process::ExitCode;
use text::TextEncoder;
use tokenizer::model::MotionTokenizer;

/// `motionscale generate --captions-from`: `options` animated by the model of `run` (whose
/// tokens `tokenizer` decodes) into the folder `out`.
pub fn generate_batch(
    options: &CaptionSetOptions,
    model: &dyn MotionLm,
    run: &RunConfig,
    tokenizer: &MotionTokenizer,
    encoder: &dyn TextEncoder,
    out: &Path,
) -> Result<ExitCode> {
    let bar = crate::commands::progress_bar("generate", "motions");
    let report = generate_caption_set(
        model,
        run,
        tokenizer,
        Some(encoder),
        options,
        out,
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
        out.display()
    );
    Ok(if report.rejected == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(2)
    })
}
