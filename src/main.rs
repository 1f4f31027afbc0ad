//! `motionscale`: the command-line front of the toolkit. Thin: parse arguments, call the crates,
//! print results and choose exit codes (0 ok, 1 failure, 2 partial: some inputs rejected).

mod bench;
mod cl2gen_cmd;
mod commands;
mod continual_cmd;
mod device_args;
mod eval_cmd;
mod fit;
mod fit_laws;
mod generate_batch;
mod lm_cmd;
mod memory;
mod plan_args;
mod planner_cmd;
mod quickstart;
mod report;
mod report_page;
mod sweep_cmd;
mod text_cmd;
mod tokenizer_cmd;

use clap::{Parser, Subcommand};
use std::path::PathBuf;
use std::process::ExitCode;

/// `--version`: the package version and the source revision the binary was built from (the
/// one its result rows record).
fn version() -> &'static str {
    static VERSION: std::sync::OnceLock<String> = std::sync::OnceLock::new();
    VERSION.get_or_init(|| {
        let revision = experiments::run::git_revision();
        format!("{} ({revision})", env!("CARGO_PKG_VERSION"))
    })
}

#[derive(Parser)]
#[command(
    name = "motionscale",
    version = version(),
    about = "Motion corpora, motion tokenizers and the scaling laws of text-to-motion transformers",
    long_about = "motionscale turns heterogeneous motion capture into a HumanML3D-conformant \
                  text-motion corpus (Parquet shards + manifest + mean/std + rejects), and \
                  exports it to the layouts other tools read."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The whole study on built-in data: corpus, caption embeddings, tokenizer, micro IsoFLOP
    /// sweep, fit, predict, a BVH from a caption, eval and the HTML report.
    Quickstart(quickstart::QuickstartArgs),
    /// Embed every distinct caption of a corpus with a frozen text encoder.
    EmbedText(text_cmd::EmbedTextArgs),
    /// Build a corpus from motion sources (bvh:DIR, joints:DIR, amass:DIR, hml3d:DIR, synth:CLIPS[:SEED]).
    Ingest(commands::IngestArgs),
    /// Inspect or check a corpus.
    #[command(subcommand)]
    Corpus(CorpusCommand),
    /// Export corpus clips to other tools' formats.
    #[command(subcommand)]
    Export(ExportCommand),
    /// Build a corpus of labelled synthetic motion (same as `ingest --source synth:CLIPS:SEED`).
    Synth(commands::SynthArgs),
    /// Cut a labelled corpus into L²-EMG scenario datasets (unseen: one per scenario; mixed: equal chunks).
    Scenarios(commands::ScenariosArgs),
    /// Write the small built-in demo inputs (generated BVH clips with captions) to a folder.
    Demo {
        /// Folder to write into.
        #[arg(long)]
        out: PathBuf,
    },
    /// Motion tokenizers (FSQ / VQ VAEs): train, evaluate, sweep codebook sizes, decode tokens.
    #[command(subcommand)]
    Tokenizer(TokenizerCommand),
    /// Turn every clip of a corpus into token ids with a trained tokenizer (a token set).
    Tokenize(tokenizer_cmd::TokenizeArgs),
    /// Fit scaling laws to a sweep's results table: fits.json + plots.
    Fit(fit::FitArgs),
    /// Predict model size, vocabulary, data and loss at a compute budget.
    Predict(fit::PredictArgs),
    /// Measure throughput against the reference figures.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Inspect prefix-LM shapes: parameters and FLOPs.
    #[command(subcommand)]
    Model(ModelCommand),
    /// Train (or resume) a text-prefix autoregressive motion transformer on a token set.
    Train(lm_cmd::TrainArgs),
    /// Generate motion for a text with a trained prefix LM.
    Generate(lm_cmd::GenerateArgs),
    /// Train the text–motion evaluator that `eval` scores motions with.
    #[command(subcommand)]
    Evaluator(EvaluatorCommand),
    /// Generation metrics (FID, R-precision, matching score, diversity, multimodality,
    /// emotion F1, action accuracy) of a motion set, with 95% intervals over repeats.
    Eval(eval_cmd::EvalArgs),
    /// Continual learning to generate (BI-CTVAE): class-incremental tasks over the corpus's
    /// action labels with mode-based generative (or real) replay.
    Cl2gen(Box<cl2gen_cmd::Cl2GenArgs>),
    /// Continual expert training over scenario datasets (es-moe, seq-lora, replay, o-lora, lwf-lora, mtl) with the
    /// f/r/d/mm/wf matrices and AF/AR/AD/AMM/AWF/FR; `continual compare RUNS…` tabulates runs.
    Continual(Box<continual_cmd::ContinualArgs>),
    /// IsoFLOP sweeps: plan, run (local pool or Slurm array), status, collect.
    #[command(subcommand)]
    Sweep(SweepCommand),
    /// One self-contained HTML page of a study: corpus, tokenizers, sweep status, IsoFLOP
    /// curves, laws with intervals, predictions and their consistency checks.
    Report(report::ReportArgs),
}

#[derive(Subcommand)]
enum SweepCommand {
    /// Plan every (budget, model, vocabulary) point: D = C / (6·(N_nv + N_v)), as TOML.
    Plan(Box<plan_args::PlanArgs>),
    /// Run every missing point of a plan (resumable; kill it at any time and run it again).
    Run(sweep_cmd::RunArgs),
    /// Done / running / failed / pending per point of a sweep folder.
    Status(sweep_cmd::StatusArgs),
    /// Submit the plan as a Slurm job array plus a collect-and-fit job (afterok).
    Submit(sweep_cmd::SubmitArgs),
    /// Rebuild results.csv / results.parquet from every run's result.json.
    Collect(sweep_cmd::CollectArgs),
    /// Replay a planning policy (active, grid, random, oracle) on a finished table: the target's
    /// interval and error against compute spent, on real runs only.
    Replay(planner_cmd::ReplayArgs),
}

#[derive(Subcommand)]
enum EvaluatorCommand {
    /// Train an evaluator on a corpus (contrastive text–motion encoders + emotion and action
    /// classifiers); re-running resumes.
    Train(eval_cmd::EvaluatorTrainArgs),
    /// Write the evaluator's motion and caption embeddings and classifier predictions of a
    /// motion set (.npy + JSON lines).
    Embed(eval_cmd::EmbedArgs),
}

#[derive(Subcommand)]
enum ModelCommand {
    /// N_nv, N_v, N and FLOPs per token (6N and exact) of one shape.
    Info(Box<lm_cmd::InfoArgs>),
    /// The preset table at one codebook size.
    Presets(lm_cmd::PresetsArgs),
    /// A trained model's logits on a few clips, with their inputs (for cross-framework checks).
    Logits(lm_cmd::LogitsArgs),
    /// A trained model's cross-entropy and L_u on a split of its token set, per origin; given
    /// several runs, their ensemble's (the mean of their next-token probabilities).
    Loss(lm_cmd::LossArgs),
    /// The executors side by side: the graph and GPU executors on --device against the cpu
    /// executor on the CPU (loss, every gradient, logits, KV-cached decoding), and each fused
    /// op and the AdamW update on --device against the CPU; exit 1 beyond the tolerances.
    Executors(lm_cmd::ExecutorsArgs),
}

#[derive(Subcommand)]
enum CorpusCommand {
    /// Clip counts by source, label and split, and hours of motion.
    Stats {
        /// Corpus folder.
        corpus: PathBuf,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Check checksums, schema, shapes, NaN/Inf and statistics; exit 1 on any problem.
    Verify {
        /// Corpus folder.
        corpus: PathBuf,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
}

#[derive(Subcommand)]
enum ExportCommand {
    /// Write the HumanML3D layout (new_joint_vecs/, new_joints/, texts/, Mean/Std, split files).
    Hml3d {
        /// Corpus folder.
        corpus: PathBuf,
        /// Output folder.
        out: PathBuf,
        /// Tagger of the texts' word/POS tokens: builtin, or spacy (en_core_web_sm through
        /// python3, byte-exact HumanML3D texts).
        #[arg(long, default_value = "builtin")]
        pos_tagger: ingest::export::text_process::PosTagger,
    },
    /// Write one clip's SMPL-22 joints as a BVH file (Blender, MotionBuilder).
    Bvh {
        /// Corpus folder.
        corpus: PathBuf,
        /// Clip id (see `corpus stats` or the shards' motion_id column).
        motion_id: String,
        /// Output .bvh file.
        out: PathBuf,
    },
}

#[derive(Subcommand)]
enum TokenizerCommand {
    /// Train an FSQ or VQ tokenizer on random 64-frame windows of a corpus (resumable).
    Train(tokenizer_cmd::TrainArgs),
    /// Reconstruction L1, MPJPE, codebook utilisation, entropy and perplexity on a split (JSON).
    Eval(tokenizer_cmd::EvalArgs),
    /// Train and evaluate every (quantizer, codebook) pair with equal steps: table + plots.
    Sweep(tokenizer_cmd::SweepArgs),
    /// Token ids back to features (.npy), joints (.npy --joints) or BVH.
    Decode(tokenizer_cmd::DecodeArgs),
}

/// candle 0.11 runs its large elementwise ops (the autograd's gradient sums among them) on a
/// pool of its own, one thread fewer than the cores, whose workers spin for a while after each
/// op; beside the rayon pool that runs our kernels that oversubscribes the cores (the evaluator
/// step took 0.204–0.230 s against 0.185–0.201 s without it, six alternated pairs on 2 cores).
/// Unless the user set `CANDLE_NUM_THREADS`, candle runs those ops on the calling thread. An
/// elementwise op gives the same values either way.
fn keep_candle_pool_off_our_cores() {
    if std::env::var_os("CANDLE_NUM_THREADS").is_none() {
        // Before any other thread exists, so nothing reads the environment concurrently.
        std::env::set_var("CANDLE_NUM_THREADS", "1");
    }
}

fn main() -> ExitCode {
    keep_candle_pool_off_our_cores();
    memory::end_quietly_on_closed_pipe();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    // Usage errors exit 1 (clap's default 2 is our "some inputs rejected" code).
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            let code = u8::from(e.use_stderr());
            let _ = e.print();
            return ExitCode::from(code);
        }
    };
    let result = match cli.command {
        Command::Ingest(args) => commands::ingest(args),
        Command::Quickstart(args) => quickstart::quickstart(args),
        Command::EmbedText(args) => text_cmd::embed_text(args),
        Command::Corpus(CorpusCommand::Stats { corpus, json }) => commands::stats(&corpus, json),
        Command::Corpus(CorpusCommand::Verify { corpus, json }) => commands::verify(&corpus, json),
        Command::Export(ExportCommand::Hml3d {
            corpus,
            out,
            pos_tagger,
        }) => commands::export_hml3d(&corpus, &out, pos_tagger),
        Command::Export(ExportCommand::Bvh {
            corpus,
            motion_id,
            out,
        }) => commands::export_bvh(&corpus, &motion_id, &out),
        Command::Scenarios(args) => commands::scenarios(args),
        Command::Synth(args) => commands::synth(args),
        Command::Demo { out } => commands::demo(&out),
        Command::Tokenizer(TokenizerCommand::Train(args)) => tokenizer_cmd::train_cmd(args),
        Command::Tokenizer(TokenizerCommand::Eval(args)) => tokenizer_cmd::eval_cmd(args),
        Command::Tokenizer(TokenizerCommand::Decode(args)) => tokenizer_cmd::decode_cmd(args),
        Command::Tokenizer(TokenizerCommand::Sweep(args)) => tokenizer_cmd::sweep_cmd(args),
        Command::Tokenize(args) => tokenizer_cmd::tokenize_cmd(args),
        Command::Bench(command) => bench::run(command),
        Command::Model(ModelCommand::Info(args)) => lm_cmd::info(*args),
        Command::Model(ModelCommand::Presets(args)) => lm_cmd::presets(args),
        Command::Model(ModelCommand::Logits(args)) => lm_cmd::logits(args),
        Command::Model(ModelCommand::Loss(args)) => lm_cmd::loss(args),
        Command::Model(ModelCommand::Executors(args)) => lm_cmd::executors(args),
        Command::Train(args) => lm_cmd::train(args),
        Command::Generate(args) => lm_cmd::generate(args),
        Command::Evaluator(EvaluatorCommand::Train(args)) => eval_cmd::evaluator_train(args),
        Command::Evaluator(EvaluatorCommand::Embed(args)) => eval_cmd::embed(args),
        Command::Eval(args) => eval_cmd::eval(args),
        Command::Cl2gen(args) => cl2gen_cmd::cl2gen(*args),
        Command::Continual(args) => continual_cmd::continual(*args),
        Command::Fit(args) if !args.law.is_empty() => fit_laws::fit_laws(&args),
        Command::Fit(args) => fit::fit(args),
        Command::Predict(args) => fit::predict(args),
        Command::Sweep(SweepCommand::Plan(args)) => sweep_cmd::plan_cmd(*args),
        Command::Sweep(SweepCommand::Run(args)) => sweep_cmd::run_cmd(args),
        Command::Sweep(SweepCommand::Status(args)) => sweep_cmd::status_cmd(args),
        Command::Sweep(SweepCommand::Submit(args)) => sweep_cmd::submit_cmd(args),
        Command::Sweep(SweepCommand::Collect(args)) => sweep_cmd::collect_cmd(args),
        Command::Sweep(SweepCommand::Replay(args)) => planner_cmd::replay_cmd(args),
        Command::Report(args) => report::report(args),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(1)
        }
    }
}
