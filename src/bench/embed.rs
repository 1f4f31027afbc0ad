//! `motionscale bench embed`: caption embedding with the frozen MiniLM encoder (what
//! `embed-text` spends its time on), captions/s and tokens/s, and with `--reference` the same
//! captions embedded by PyTorch + transformers (`scripts/pytorch_embed_text.py`) in this run,
//! with the ratio.

use crate::device_args::DeviceArgs;
use anyhow::{bail, Context, Result};
use nn::device::device_name;
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use text::TextEncoder;

/// Arguments of `motionscale bench embed`.
#[derive(clap::Args, Debug)]
pub struct BenchEmbedArgs {
    /// Corpus whose distinct captions are embedded.
    #[arg(long)]
    pub corpus: PathBuf,
    /// Embed only the first N distinct captions (sorted), to keep the run short.
    #[arg(long)]
    pub limit: Option<usize>,
    /// BERT encoder folder (default: the fetched all-MiniLM-L6-v2).
    #[arg(long)]
    pub encoder: Option<PathBuf>,
    /// Captions per forward pass (`embed-text --batch`).
    #[arg(long, default_value_t = 64)]
    pub batch: usize,
    /// Untimed passes over the captions first.
    #[arg(long, default_value_t = 1)]
    pub warmup: usize,
    /// Timed passes (the median is reported).
    #[arg(long, default_value_t = 3)]
    pub reps: usize,
    /// Also run scripts/pytorch_embed_text.py (needs torch and transformers) and print the ratio.
    #[arg(long)]
    pub reference: bool,
    /// The caption-embedding PyTorch reference.
    #[arg(long, default_value = "scripts/pytorch_embed_text.py")]
    pub reference_script: PathBuf,
    /// Also write the figures as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Where the encoder runs.
    #[command(flatten)]
    pub device: DeviceArgs,
}

/// The figures of `bench embed` (its `--json`).
#[derive(Debug, Serialize, Deserialize)]
pub struct EmbedFigures {
    /// What was timed: "caption embedding".
    pub what: String,
    /// The encoder's id.
    pub encoder: String,
    /// The corpus's folder name (not its path: a committed figure names no machine's folders).
    pub corpus: Option<String>,
    /// Distinct captions embedded per pass.
    pub captions: usize,
    /// Their tokens.
    pub tokens: usize,
    /// Captions per forward pass.
    pub batch: usize,
    /// Where the encoder ran.
    pub device: String,
    /// Threads of the pool.
    pub threads: usize,
    /// Wall time of one pass over the captions.
    pub time: super::Timing,
    /// Captions per second at the median pass.
    pub captions_per_s: f64,
    /// With `--reference`: the PyTorch + transformers run's output.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub reference: Option<EmbedReference>,
    /// With `--reference`: its median seconds over ours.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub ratio: Option<f64>,
}

/// The output of `scripts/pytorch_embed_text.py`.
#[derive(Debug, Serialize, Deserialize)]
pub struct EmbedReference {
    /// Median seconds of one pass over the captions.
    pub median_s: f64,
    /// The rest of its output (torch version, samples, rates), kept as it wrote them.
    #[serde(flatten)]
    pub other: serde_json::Map<String, serde_json::Value>,
}

/// `motionscale bench embed`.
pub fn bench_embed(args: BenchEmbedArgs) -> Result<ExitCode> {
    let dir = args
        .encoder
        .clone()
        .unwrap_or_else(text::default_encoder_dir);
    let device = args.device.open()?;
    let encoder = text::BertEncoder::load(&dir, &device).with_context(|| {
        format!(
            "loading the encoder in {} (scripts/fetch-text-encoder.sh fetches it)",
            dir.display()
        )
    })?;
    let mut captions = text::embed::corpus_captions(&args.corpus)?;
    captions.truncate(args.limit.unwrap_or(captions.len()));
    if captions.is_empty() {
        bail!("{} has no captions to embed", args.corpus.display());
    }
    let mut tokens = 0;
    let timing = super::time(args.warmup, args.reps, 0.0, || {
        let embedded = text::embed_texts(&encoder, &captions, args.batch, &|_| {})?;
        tokens = embedded.iter().map(|e| e.tokens.len()).sum::<usize>();
        Ok(())
    })?;
    let ours = timing.median_s;
    let mut line = format!(
        "caption embedding, {} ({}), {} captions ({tokens} tokens), batch {}, {}, {} threads: {ours:.2} s, {:.0} captions/s, {:.0} tokens/s",
        encoder.id(),
        dir.display(),
        captions.len(),
        args.batch,
        device_name(&device),
        rayon::current_num_threads(),
        captions.len() as f64 / ours,
        tokens as f64 / ours
    );
    // The corpus's folder name, not its path: a committed figure names no machine's folders.
    let corpus = args
        .corpus
        .file_name()
        .map(|n| n.to_string_lossy().into_owned());
    let mut figures = EmbedFigures {
        what: "caption embedding".into(),
        encoder: encoder.id().to_string(),
        corpus,
        captions: captions.len(),
        tokens,
        batch: args.batch,
        device: device_name(&device),
        threads: rayon::current_num_threads(),
        time: timing,
        captions_per_s: captions.len() as f64 / ours,
        reference: None,
        ratio: None,
    };
    if args.reference {
        let reference = reference(&args, &dir, &captions)?;
        let theirs = reference.median_s;
        line.push_str(&format!(
            "; PyTorch + transformers {theirs:.2} s ({:.0} captions/s) → ratio {:.2}×",
            captions.len() as f64 / theirs,
            theirs / ours
        ));
        figures.reference = Some(reference);
        figures.ratio = Some(theirs / ours);
    }
    println!("{line}");
    super::write_json(args.json.as_ref(), &figures)?;
    Ok(ExitCode::SUCCESS)
}

/// Run the reference on the same captions (one per line in a temporary file), 2 threads.
fn reference(
    args: &BenchEmbedArgs,
    dir: &std::path::Path,
    captions: &[String],
) -> Result<EmbedReference> {
    let mut file = tempfile::NamedTempFile::new()?;
    for caption in captions {
        writeln!(file, "{}", caption.replace('\n', " "))?;
    }
    file.flush()?;
    let (batch, warmup, reps) = (
        args.batch.to_string(),
        args.warmup.to_string(),
        args.reps.to_string(),
    );
    let encoder = dir.to_string_lossy();
    let captions_file = file.path().to_string_lossy();
    super::run_reference(
        &args.reference_script,
        &[
            "--encoder",
            &encoder,
            "--captions",
            &captions_file,
            "--batch",
            &batch,
            "--threads",
            "2",
            "--warmup",
            &warmup,
            "--reps",
            &reps,
        ],
    )
}
