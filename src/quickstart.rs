//! `motionscale quickstart`: the whole pipeline on built-in synthetic data, end to end —
//! synthetic corpus → verify → caption embeddings → scenario datasets → HumanML3D export.

use crate::text::{embed, load_encoder, EncoderArgs};
use anyhow::Result;
use ingest::corpus::Corpus;
use ingest::pipeline::{IngestOptions, SourceSpec};
use ingest::scenarios::{self, ScenarioSplit};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

/// Arguments of `motionscale quickstart`.
#[derive(clap::Args, Debug)]
pub struct QuickstartArgs {
    /// Output folder (corpus/, scenarios/, humanml3d/).
    #[arg(long)]
    pub out: PathBuf,
    /// Synthetic clips (before mirroring).
    #[arg(long, default_value_t = 2000)]
    pub clips: usize,
    /// Seed of the synthetic stream and of the mixed scenario chunks.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Encoder choice for the caption embeddings.
    #[command(flatten)]
    pub encoder: EncoderArgs,
}

fn step(n: usize, what: &str) {
    println!("\n[{n}/5] {what}");
}

/// Run the quickstart.
pub fn quickstart(args: QuickstartArgs) -> Result<ExitCode> {
    let started = Instant::now();
    let corpus_dir = args.out.join("corpus");

    step(
        1,
        &format!(
            "synthetic corpus: {} clips (seed {}) + mirrored copies",
            args.clips, args.seed
        ),
    );
    let source: SourceSpec = format!("synth:{}:{}", args.clips, args.seed)
        .parse()
        .map_err(anyhow::Error::msg)?;
    let opts = IngestOptions {
        mirror: true,
        ..IngestOptions::default()
    };
    let bar = crate::commands::progress_bar("ingest", "clips");
    let report = ingest::pipeline::ingest(&[source], &corpus_dir, &opts, &|done, total| {
        bar.set_length(total);
        bar.set_position(done);
    })
    .map_err(anyhow::Error::msg)?;
    bar.finish_and_clear();
    println!(
        "      {} clips, {:.2} h of motion, {} shards → {}",
        report.clips,
        report.frames as f64 / opts.fps / 3600.0,
        report.shards,
        corpus_dir.display()
    );

    step(2, "verify the corpus");
    let check = ingest::corpus::verify::verify(&corpus_dir);
    if !check.problems.is_empty() {
        anyhow::bail!("corpus verify found problems: {:?}", check.problems);
    }
    println!(
        "      {} shards, {} clips, {} frames: checksums, schema, shapes and values sound",
        check.shards, check.clips, check.frames
    );

    step(3, "caption embeddings (frozen text encoder)");
    let encoder = load_encoder(&args.encoder, &corpus_dir)?;
    let emb = embed(&corpus_dir, encoder.as_ref(), 64, false)?;
    println!(
        "      {} distinct captions with {} (dim {}) → {}",
        emb.captions,
        emb.encoder,
        emb.dim,
        emb.dir.display()
    );

    step(4, "L²-EMG scenario datasets (unseen, mixed)");
    let corpus = Corpus::open(&corpus_dir).map_err(anyhow::Error::msg)?;
    for split in [ScenarioSplit::Unseen, ScenarioSplit::Mixed] {
        let sets =
            scenarios::build(&corpus, split, args.seed, 0.6, None).map_err(anyhow::Error::msg)?;
        let dir = args
            .out
            .join("scenarios")
            .join(format!("{split:?}").to_lowercase());
        scenarios::write(&dir, &sets).map_err(anyhow::Error::msg)?;
        print!("{}", scenarios::table(&sets));
        println!("      → {}", dir.display());
    }

    step(5, "HumanML3D layout export");
    let hml = args.out.join("humanml3d");
    crate::commands::export_hml3d(&corpus_dir, &hml, Default::default())?;

    println!(
        "\nquickstart done in {:.1} s: corpus {}, scenarios {}, HumanML3D layout {}",
        started.elapsed().as_secs_f64(),
        corpus_dir.display(),
        args.out.join("scenarios").display(),
        hml.display()
    );
    Ok(ExitCode::SUCCESS)
}
