//! Subcommand bodies: each turns arguments into a crate call and a printed result.

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use ingest::corpus::verify::verify as verify_corpus;
use ingest::corpus::Corpus;
use ingest::export::text_process::PosTagger;
use ingest::hml263::Hml263Options;
use ingest::pipeline::{IngestOptions, SourceSpec, DEFAULT_STATIC_THRESHOLD};
use ingest::scenarios::ScenarioSplit;
use ingest::source::retarget::RigMap;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Arguments of `motionscale ingest`.
#[derive(clap::Args, Debug)]
pub struct IngestArgs {
    /// A source as KIND:PATH (bvh:DIR, joints:DIR, amass:DIR, hml3d:DIR, synth:CLIPS[:SEED]); repeatable.
    #[arg(long = "source", required = true, value_parser = parse_source)]
    pub sources: Vec<SourceSpec>,
    /// Output corpus folder (created; a re-run over the same inputs rewrites identical bytes).
    #[arg(long)]
    pub out: PathBuf,
    /// Corpus frame rate; sources are resampled by time.
    #[arg(long, default_value_t = 20.0)]
    pub fps: f64,
    /// Add left/right mirrored copies (ids prefixed with M, captions' left/right swapped).
    #[arg(long)]
    pub mirror: bool,
    /// Split longer clips into balanced consecutive segments of at most this many seconds.
    #[arg(long, default_value_t = 10.0)]
    pub max_seconds: f64,
    /// Reject clips with fewer feature frames than this (training stages filter further).
    #[arg(long, default_value_t = 20)]
    pub min_frames: usize,
    /// Reject clips whose fastest joint moves slower than this on average (m/s) as static.
    #[arg(long, default_value_t = DEFAULT_STATIC_THRESHOLD)]
    pub static_threshold: f64,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub workers: Option<usize>,
    /// TOML rig map for BVH rigs the built-in maps (Bandai Namco, CMU, Mixamo) do not cover.
    #[arg(long)]
    pub map: Option<PathBuf>,
    /// Frame rate of joints:DIR inputs.
    #[arg(long, default_value_t = 20.0)]
    pub src_fps: f64,
    /// SMPL+H / SMPL-X body model .npz for amass:DIR sources.
    #[arg(long)]
    pub body_model: Option<PathBuf>,
    /// Inputs processed (and held in memory) at a time; larger builds spill sorted runs to
    /// a temporary folder in the output and merge them.
    #[arg(long, default_value_t = IngestOptions::default().chunk_units)]
    pub chunk_units: usize,
    /// Correct the HumanML3D hip-order quirk (features are then NOT HumanML3D-compatible).
    #[arg(long)]
    pub fix_facing: bool,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

fn parse_source(s: &str) -> Result<SourceSpec, String> {
    s.parse()
}

/// A progress bar for a long step, counting `unit`s (hidden when stderr is not a terminal).
pub fn progress_bar(step: &str, unit: &str) -> ProgressBar {
    ProgressBar::new(0).with_style(
        ProgressStyle::with_template(&format!(
            "{{spinner}} {step} [{{bar:30}}] {{pos}}/{{len}} {unit} {{per_sec}} eta {{eta}}"
        ))
        .expect("template")
        .progress_chars("=> "),
    )
}

/// Build the ingest options from the command line.
pub fn ingest_options(args: &IngestArgs) -> Result<IngestOptions> {
    let map = match &args.map {
        Some(p) => Some(RigMap::load(p)?),
        None => None,
    };
    Ok(IngestOptions {
        fps: args.fps,
        mirror: args.mirror,
        max_seconds: args.max_seconds,
        min_frames: args.min_frames,
        static_threshold: args.static_threshold,
        features: Hml263Options {
            fix_facing: args.fix_facing,
            ..Hml263Options::default()
        },
        src_fps: args.src_fps,
        map,
        body_model: args.body_model.clone(),
        chunk_units: args.chunk_units,
        ..IngestOptions::default()
    })
}

/// A worker pool of `workers` threads (all cores when unset).
pub fn thread_pool(workers: Option<usize>) -> Result<rayon::ThreadPool> {
    let mut b = rayon::ThreadPoolBuilder::new();
    if let Some(n) = workers {
        b = b.num_threads(n.max(1));
    }
    b.build().context("starting worker threads")
}

/// Arguments of `motionscale synth`.
#[derive(clap::Args, Debug)]
pub struct SynthArgs {
    /// Number of synthetic clips (before mirroring).
    #[arg(long)]
    pub clips: usize,
    /// Seed of the clip stream (same seed → same clips).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output corpus folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Add left/right mirrored copies.
    #[arg(long)]
    pub mirror: bool,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub workers: Option<usize>,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
}

/// `motionscale synth`: a corpus from `synth:CLIPS:SEED` with the default options.
pub fn synth(args: SynthArgs) -> Result<ExitCode> {
    let source = format!("synth:{}:{}", args.clips, args.seed);
    let mut argv = vec![
        "ingest".to_string(),
        "--source".into(),
        source,
        "--out".into(),
    ];
    argv.push(args.out.display().to_string());
    if args.mirror {
        argv.push("--mirror".into());
    }
    if let Some(n) = args.workers {
        argv.extend(["--workers".into(), n.to_string()]);
    }
    if args.json {
        argv.push("--json".into());
    }
    let parsed = <IngestCli as clap::Parser>::try_parse_from(argv)?;
    ingest(parsed.args)
}

/// Parses `ingest` arguments on their own (used to express `synth` as an ingest).
#[derive(clap::Parser, Debug)]
struct IngestCli {
    #[command(flatten)]
    args: IngestArgs,
}

/// `motionscale ingest`.
pub fn ingest(args: IngestArgs) -> Result<ExitCode> {
    let opts = ingest_options(&args)?;
    let bar = ProgressBar::new(0).with_style(
        ProgressStyle::with_template(
            "{spinner} ingest [{bar:30}] {pos}/{len} files {elapsed} eta {eta}",
        )
        .expect("template")
        .progress_chars("=> "),
    );
    if args.json {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let started = std::time::Instant::now();
    let report = thread_pool(args.workers)?.install(|| {
        ingest::pipeline::ingest(&args.sources, &args.out, &opts, &|done, total| {
            bar.set_length(total);
            bar.set_position(done);
        })
    });
    bar.finish_and_clear();
    let report = report?;
    let secs = started.elapsed().as_secs_f64();
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "ingested {} clips ({} frames, {:.2} h) from {} inputs into {} shards; {} rejected (see {}); {secs:.1} s",
            report.clips,
            report.frames,
            report.frames as f64 / opts.fps / 3600.0,
            report.inputs,
            report.shards,
            report.rejects,
            args.out.join("rejects.jsonl").display(),
        );
    }
    Ok(if report.rejects > 0 {
        ExitCode::from(2)
    } else {
        ExitCode::SUCCESS
    })
}

/// Clips and hours of motion in one group of a corpus.
#[derive(Default, serde::Serialize)]
pub struct Bucket {
    /// Clips.
    pub clips: u64,
    /// Hours of motion.
    pub hours: f64,
}

/// What `corpus stats` reports: totals and the clips by source, split, label and mirroring.
#[derive(serde::Serialize)]
pub struct CorpusStats {
    /// Clips.
    pub clips: usize,
    /// Hours of motion.
    pub hours: f64,
    /// Inputs rejected at ingest.
    pub rejects: u64,
    /// Grouping (`source`, `split`, `action`, …) → group value → its clips and hours.
    pub by: BTreeMap<&'static str, BTreeMap<String, Bucket>>,
}

/// Count the clips and hours of the corpus in `dir` by source, split, label and mirroring.
pub fn corpus_stats(dir: &Path) -> Result<CorpusStats> {
    let corpus = Corpus::open(dir)?;
    let meta = corpus.clip_metadata()?;
    let mut by: BTreeMap<&str, BTreeMap<String, Bucket>> = BTreeMap::new();
    let mut total_hours = 0.0;
    for m in &meta {
        let hours = m.num_frames as f64 / m.fps as f64 / 3600.0;
        total_hours += hours;
        let keys = [
            ("source", Some(m.source.clone())),
            ("split", Some(m.split.clone())),
            ("action", m.labels.action.clone()),
            ("style", m.labels.style.clone()),
            ("emotion", m.labels.emotion.clone()),
            ("scenario", m.labels.scenario.clone()),
            ("mirrored", Some(m.mirrored.to_string())),
        ];
        for (table, key) in keys {
            let e = by
                .entry(table)
                .or_default()
                .entry(key.unwrap_or_else(|| "(none)".into()))
                .or_default();
            e.clips += 1;
            e.hours += hours;
        }
    }
    Ok(CorpusStats {
        clips: meta.len(),
        hours: total_hours,
        rejects: corpus.manifest().rejects,
        by,
    })
}

/// `motionscale corpus stats`.
pub fn stats(dir: &Path, json: bool) -> Result<ExitCode> {
    let stats = corpus_stats(dir)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&stats)?);
    } else {
        println!(
            "{}: {} clips, {:.2} hours, {} rejected inputs",
            dir.display(),
            stats.clips,
            stats.hours,
            stats.rejects
        );
        for (table, rows) in &stats.by {
            println!("\nby {table}:");
            for (k, b) in rows {
                println!("  {k:<28} {:>8} clips {:>9.3} h", b.clips, b.hours);
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `motionscale corpus verify`.
pub fn verify(dir: &Path, json: bool) -> Result<ExitCode> {
    let v = verify_corpus(dir);
    if json {
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        for p in &v.problems {
            println!("problem: {p}");
        }
        println!(
            "{}: {} shards, {} clips, {} frames checked; {} problems",
            dir.display(),
            v.shards,
            v.clips,
            v.frames,
            v.problems.len()
        );
    }
    Ok(if v.problems.is_empty() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// `motionscale export hml3d`: the summary as JSON on stdout, its warnings also on stderr.
pub fn export_hml3d(dir: &Path, out: &Path, tagger: PosTagger) -> Result<ExitCode> {
    let corpus = Corpus::open(dir)?;
    let mut writer = ingest::export::hml3d::Hml3dWriter::new(out, tagger)
        .with_context(|| format!("creating {}", out.display()))?;
    for shard in 0..corpus.manifest().shards.len() {
        for clip in corpus.shard_records(shard)? {
            writer
                .add(&clip)
                .with_context(|| format!("writing clip {} to {}", clip.motion_id, out.display()))?;
        }
    }
    let summary = writer
        .finish(corpus.mean(), corpus.std())
        .with_context(|| format!("finishing {}", out.display()))?;
    for warning in &summary.warnings {
        eprintln!("warning: {warning}");
    }
    println!("{}", serde_json::to_string(&summary)?);
    Ok(ExitCode::SUCCESS)
}

/// `motionscale export bvh`.
pub fn export_bvh(dir: &Path, motion_id: &str, out: &Path) -> Result<ExitCode> {
    let corpus = Corpus::open(dir)?;
    let Some(index) = corpus.find(motion_id) else {
        bail!("{}: no clip with motion_id {motion_id:?}", dir.display());
    };
    let clip = corpus.clip(index)?;
    let poses = clip.poses();
    ingest::export::bvh::write_bvh_file(out, &poses, clip.fps as f64)
        .with_context(|| format!("writing {}", out.display()))?;
    println!(
        "wrote {} ({} frames at {} fps)",
        out.display(),
        poses.len(),
        clip.fps
    );
    Ok(ExitCode::SUCCESS)
}

/// Arguments of `motionscale scenarios`.
#[derive(clap::Args, Debug)]
pub struct ScenariosArgs {
    /// Corpus folder (clips need scenario labels).
    #[arg(long)]
    pub corpus: PathBuf,
    /// unseen (one dataset per scenario) or mixed (equal-size chunks, a primary scenario each).
    #[arg(long, value_parser = |s: &str| s.parse::<ScenarioSplit>())]
    pub split: ScenarioSplit,
    /// Output folder: datasets.json and D??_name/{train,val,test}.txt.
    #[arg(long)]
    pub out: PathBuf,
    /// Seed of the mixed chunking.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Share of a mixed chunk taken from its primary scenario.
    #[arg(long, default_value_t = 0.6)]
    pub primary_fraction: f64,
    /// Only clips of this source kind (synth, bvh…).
    #[arg(long)]
    pub source: Option<String>,
}

/// `motionscale scenarios`.
pub fn scenarios(args: ScenariosArgs) -> Result<ExitCode> {
    if !(0.0..=1.0).contains(&args.primary_fraction) {
        bail!(
            "--primary-fraction must be within 0..1, got {}",
            args.primary_fraction
        );
    }
    let corpus = Corpus::open(&args.corpus)?;
    let sets = ingest::scenarios::build(
        &corpus,
        args.split,
        args.seed,
        args.primary_fraction,
        args.source.as_deref(),
    )?;
    for d in &sets.datasets {
        for split in ["train", "test"] {
            if d.clips.get(split).is_none_or(Vec::is_empty) {
                eprintln!(
                    "warning: {} has no {split} clip (each clip keeps its corpus split)",
                    d.name
                );
            }
        }
    }
    ingest::scenarios::write(&args.out, &sets)?;
    print!("{}", ingest::scenarios::table(&sets));
    println!(
        "{} datasets written to {} ({} clips without a scenario label left out)",
        sets.datasets.len(),
        args.out.display(),
        sets.unlabelled_clips
    );
    Ok(ExitCode::SUCCESS)
}

/// `motionscale demo`.
pub fn demo(out: &Path) -> Result<ExitCode> {
    let files = ingest::demo::write_demo_inputs(out)
        .with_context(|| format!("writing demo inputs to {}", out.display()))?;
    println!(
        "wrote {} demo BVH clips (with caption sidecars) to {}",
        files.len(),
        out.display()
    );
    Ok(ExitCode::SUCCESS)
}

/// Extract the `.tar.zst` archive `archive` into the folder `into` (with tar).
pub fn extract(archive: &Path, into: &Path) -> Result<()> {
    let status = std::process::Command::new("tar")
        .arg("--zstd")
        .arg("-xf")
        .arg(archive)
        .arg("-C")
        .arg(into)
        .status()
        .with_context(|| format!("running tar on {}", archive.display()))?;
    if !status.success() {
        bail!("tar failed on {} ({status})", archive.display());
    }
    Ok(())
}
