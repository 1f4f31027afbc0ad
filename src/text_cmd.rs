//! `motionscale embed-text`: choose a frozen text encoder and embed a corpus's captions.

use crate::device_args::DeviceArgs;
use anyhow::Result;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use text::{EncoderChoice, TextEncoder};

/// Which encoder to use (default: the fetched MiniLM; without it, an error unless `--fallback`).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct EncoderArgs {
    /// A BERT-family encoder folder (config.json, tokenizer.json, model.safetensors).
    #[arg(long, conflicts_with_all = ["t5", "fallback"])]
    pub encoder: Option<PathBuf>,
    /// A T5 encoder folder (config.json, tokenizer.json, model.safetensors).
    #[arg(long, conflicts_with = "fallback")]
    pub t5: Option<PathBuf>,
    /// Use the untrained word-table fallback (required when no trained encoder is present).
    #[arg(long)]
    pub fallback: bool,
    /// Width of the fallback's word embeddings.
    #[arg(long, default_value_t = 256)]
    pub fallback_dim: usize,
    /// Seed of the fallback's initial table.
    #[arg(long, default_value_t = 0)]
    pub fallback_seed: u64,
}

/// Arguments of `motionscale embed-text`.
#[derive(clap::Args, Debug)]
pub struct EmbedTextArgs {
    /// Corpus folder.
    #[arg(long)]
    pub corpus: PathBuf,
    /// Encoder choice.
    #[command(flatten)]
    pub encoder: EncoderArgs,
    /// Captions per forward pass.
    #[arg(long, default_value_t = 64)]
    pub batch: usize,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
    /// Where a transformer encoder runs.
    #[command(flatten)]
    pub device: DeviceArgs,
}

impl EncoderArgs {
    /// The encoder these arguments choose.
    pub fn choice(&self) -> EncoderChoice {
        match (&self.encoder, &self.t5, self.fallback) {
            (Some(dir), _, _) => EncoderChoice::Bert(dir.clone()),
            (None, Some(dir), _) => EncoderChoice::T5(dir.clone()),
            (None, None, true) => EncoderChoice::Fallback {
                dim: self.fallback_dim,
                seed: self.fallback_seed,
            },
            (None, None, false) => EncoderChoice::Default,
        }
    }
}

/// Embed every distinct caption of `corpus` with `encoder`, with a progress bar.
pub fn embed(
    corpus: &Path,
    encoder: &dyn TextEncoder,
    batch: usize,
    quiet: bool,
) -> Result<text::EmbedReport> {
    let bar = crate::commands::progress_bar("embed-text", "captions");
    if quiet {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let report = text::embed_corpus(corpus, encoder, batch, &|done, total| {
        bar.set_length(total);
        bar.set_position(done);
    });
    bar.finish_and_clear();
    Ok(report?)
}

/// `motionscale embed-text`.
pub fn embed_text(args: EmbedTextArgs) -> Result<ExitCode> {
    let device = args.device.open()?;
    let encoder = args.encoder.choice().load(&args.corpus, &device)?;
    let report = embed(&args.corpus, encoder.as_ref(), args.batch, args.json)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "embedded {} of {} distinct captions with {} (dim {}) into {} ({} shards, {} kept from an earlier run)",
            report.embedded,
            report.captions,
            report.encoder,
            report.dim,
            report.dir.display(),
            report.shards,
            report.skipped_shards
        );
    }
    Ok(ExitCode::SUCCESS)
}
