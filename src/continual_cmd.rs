//! `motionscale continual`: continual (lifelong) expert training over scenario datasets, and
//! `motionscale continual compare` for the paper's Table-2-shaped comparison.

use anyhow::{bail, Context, Result};
use candle_core::Device;
use experiments::backbone::{backbone, BackboneChoice, BackboneRequest};
use experiments::continual::{compare_table, run_continual, ContinualConfig, Method};
use experiments::plan::TrainSettings;
use lm::es_moe::EsMoeConfig;
use lm::lora::LoraConfig;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Arguments of `motionscale continual`.
#[derive(clap::Args, Debug)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct ContinualArgs {
    /// `compare RUNS…` instead of a run.
    #[command(subcommand)]
    pub compare: Option<CompareCommand>,
    /// Scenario datasets folder (`motionscale scenarios --out`).
    #[arg(long, required = true)]
    pub scenarios: Option<PathBuf>,
    /// Method: es-moe, seq-lora, replay, o-lora, lwf-lora or mtl.
    #[arg(long, required = true)]
    pub method: Option<String>,
    /// Trained backbone run (`motionscale train --out`), frozen; or size it by a law with
    /// --fits and --budget.
    #[arg(long, required_unless_present = "fits", conflicts_with = "fits")]
    pub base: Option<PathBuf>,
    /// Size the backbone by a law: `fit`'s fits.json or laws.json. Its N_opt at --budget picks
    /// the nearest model of --models, trained for C on --tokens in OUT/backbone (or reused from
    /// --sweep when its plan has that point), frozen; the choice is recorded in the summary.
    #[arg(long, value_name = "FITS_JSON", requires = "budget")]
    pub fits: Option<PathBuf>,
    /// With --fits: the backbone's compute budget C in FLOPs.
    #[arg(long, requires = "fits")]
    pub budget: Option<f64>,
    /// With --fits: the models to choose from (presets, `cpu`, `scamo` or WIDTHxLAYERS).
    #[arg(long, value_delimiter = ',', default_value = "cpu", requires = "fits")]
    pub models: Vec<String>,
    /// With --fits: a sweep folder whose run of the chosen point is the backbone (trained
    /// there first if it is not yet).
    #[arg(long, requires = "fits")]
    pub sweep: Option<PathBuf>,
    /// With --fits: the corpus with the caption embeddings (default: the token set's).
    #[arg(long, requires = "fits")]
    pub corpus: Option<PathBuf>,
    /// With --fits: the train clips the backbone learns from: all, real (captured) or synth. A
    /// backbone that never saw the scenario datasets' source (e.g. real with `scenarios
    /// --source synth`) has something left for its experts to learn.
    #[arg(long, default_value = "all", requires = "fits")]
    pub backbone_data: experiments::data_ladder::DataSource,
    /// Token set of the whole corpus (`motionscale tokenize`).
    #[arg(long, required = true)]
    pub tokens: Option<PathBuf>,
    /// Evaluator folder (`motionscale evaluator train`).
    #[arg(long, required = true)]
    pub evaluator: Option<PathBuf>,
    /// Dataset orders averaged over (order 0 as listed, the others seeded shuffles).
    #[arg(long, default_value_t = 3)]
    pub orders: usize,
    /// Seed of replay buffers, training, sampling and evaluation (the orders are the same for
    /// every seed: repeat a run with --seed 1, 2… and `compare` gives the interval over seeds).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Motion tokens trained on per step.
    #[arg(long, default_value_t = 100_000, conflicts_with = "expert_epochs")]
    pub tokens_budget: u64,
    /// Instead of --tokens-budget: each step trains this many epochs of its train clips, or
    /// `backbone`: as many as the law-sized backbone trained on its own (its D over U).
    #[arg(long)]
    pub expert_epochs: Option<String>,
    /// Clips per batch.
    #[arg(long, default_value_t = 32)]
    pub batch: usize,
    /// Peak learning rate.
    #[arg(long, default_value_t = 1e-3)]
    pub lr: f64,
    /// LoRA rank.
    #[arg(long, default_value_t = 8)]
    pub lora_rank: usize,
    /// LoRA α.
    #[arg(long, default_value_t = 16.0)]
    pub lora_alpha: f64,
    /// Share of each earlier dataset's train clips replayed (`replay`).
    #[arg(long, default_value_t = 0.05)]
    pub replay_fraction: f64,
    /// Weight λ of the orthogonality loss (`o-lora`).
    #[arg(long, default_value_t = 0.5)]
    pub orthogonality: f64,
    /// Weight of the distillation loss (`lwf-lora`, temperature 2).
    #[arg(long, default_value_t = 1.0)]
    pub distillation: f64,
    /// ES-MoE: experts kept per caption by the gate (renormalised).
    #[arg(long, default_value_t = 2)]
    pub top_k: usize,
    /// ES-MoE: initial probability of masking each older expert in training (falls to 0
    /// over each step).
    #[arg(long, default_value_t = 0.5)]
    pub mask_probability: f64,
    /// ES-MoE: weight λ of the emotion loss.
    #[arg(long, default_value_t = 0.1)]
    pub emotion_weight: f64,
    /// ES-MoE ablation: no-cged (h is a plain projection, no emotion loss), single-lora (one
    /// shared expert, no gate) or no-emotion-loss (λ = 0).
    #[arg(long, value_parser = ["no-cged", "single-lora", "no-emotion-loss"])]
    pub ablation: Option<String>,
    /// Evaluation repeats.
    #[arg(long, default_value_t = 10)]
    pub repeats: usize,
    /// R-precision pool size.
    #[arg(long, default_value_t = 32)]
    pub pool: usize,
    /// Texts per dataset with 10 samples each (multimodality).
    #[arg(long, default_value_t = 10)]
    pub mm_texts: usize,
    /// After each step score only the datasets learned so far (what AF, AR and FR read),
    /// not the ones still to come: about half the evaluation.
    #[arg(long)]
    pub eval_learned_only: bool,
    /// Split of each dataset that is evaluated.
    #[arg(long, default_value = "test")]
    pub eval_split: String,
    /// Keep every step's generated motions (large) instead of only their eval JSON.
    #[arg(long)]
    pub keep_motions: bool,
    /// Output folder; re-running resumes.
    #[arg(long, required = true)]
    pub out: Option<PathBuf>,
    /// Where the evaluator runs.
    #[command(flatten)]
    pub device: crate::device_args::DeviceArgs,
}

/// `motionscale continual compare`.
#[derive(clap::Subcommand, Debug)]
pub enum CompareCommand {
    /// Print one row per method (summary metrics averaged over its orders, and for ES-MoE the
    /// gate's mean weight on the new expert for the dataset just learned) as a Markdown table;
    /// runs that differ only in --seed share a row: mean ± 95% interval over seeds.
    Compare {
        /// Continual run folders.
        #[arg(required = true)]
        runs: Vec<PathBuf>,
        /// Put runs scored by different evaluators in one table (refused by default).
        #[arg(long)]
        mixed_evaluators: bool,
    },
}

/// The backbone that the law in --fits picks at --budget, trained in OUT/backbone or reused
/// from --sweep.
fn law_backbone(
    args: &ContinualArgs,
    tokens: &Path,
    out: &Path,
    device: &Device,
) -> Result<BackboneChoice> {
    let (Some(fits), Some(budget)) = (&args.fits, args.budget) else {
        bail!("give the backbone: --base RUN, or --fits FITS_JSON with --budget C");
    };
    let corpus = match &args.corpus {
        Some(corpus) => corpus.clone(),
        None => {
            let set = tokenizer::TokenSet::open(tokens)
                .with_context(|| format!("token set {}", tokens.display()))?;
            set.manifest.corpus
        }
    };
    let request = BackboneRequest {
        fits: fits.clone(),
        budget,
        models: args.models.clone(),
        corpus,
        tokens: tokens.to_path_buf(),
        sweep: args.sweep.clone(),
        data: args.backbone_data,
        train: TrainSettings::default(),
    };
    let choice = backbone(&request, &out.join("backbone"), device, &|l| {
        eprintln!("{l}")
    })?;
    eprintln!(
        "backbone at C = {:.3e}: N_opt {:.3e} by {}; {} (N_nv {}, D {}) {} {}",
        choice.budget,
        choice.n_opt,
        choice.law,
        choice.model,
        choice.n_nv,
        choice.tokens,
        if choice.reused {
            "reused from"
        } else {
            "trained in"
        },
        choice.run.display()
    );
    Ok(choice)
}

/// Epochs per step of --expert-epochs: a positive number, or the law-sized backbone's own.
fn expert_epochs(arg: Option<&str>, backbone: Option<&BackboneChoice>) -> Result<Option<f64>> {
    let epochs = match (arg, backbone) {
        (None, _) => return Ok(None),
        (Some("backbone"), Some(choice)) => choice.epochs,
        (Some("backbone"), None) => {
            bail!("--expert-epochs backbone needs a law-sized backbone (--fits, --budget)")
        }
        (Some(e), _) => e
            .parse()
            .with_context(|| format!("--expert-epochs {e:?}: a number or `backbone`"))?,
    };
    if !(epochs.is_finite() && epochs > 0.0) {
        bail!("--expert-epochs: {epochs} epochs; need a positive number");
    }
    Ok(Some(epochs))
}

/// `motionscale continual`.
pub fn continual(args: ContinualArgs) -> Result<ExitCode> {
    if let Some(CompareCommand::Compare {
        runs,
        mixed_evaluators,
    }) = &args.compare
    {
        print!("{}", compare_table(runs, *mixed_evaluators)?);
        return Ok(ExitCode::SUCCESS);
    }
    let required = |v: Option<PathBuf>, flag: &str| match v {
        Some(p) => Ok(p),
        None => bail!("--{flag} is required"),
    };
    let name = args.method.clone().unwrap_or_default();
    let Some(method) = Method::parse(&name) else {
        bail!("--method {name:?}: one of es-moe, seq-lora, replay, o-lora, lwf-lora, mtl");
    };
    if args.ablation.is_some() && method != Method::EsMoe {
        bail!("--ablation applies to --method es-moe");
    }
    let ablation = args.ablation.as_deref();
    let es_moe = (method == Method::EsMoe).then(|| EsMoeConfig {
        top_k: args.top_k,
        mask_probability: args.mask_probability,
        emotion_weight: if ablation == Some("no-emotion-loss") {
            0.0
        } else {
            args.emotion_weight
        },
        cged: ablation != Some("no-cged"),
        mixture: ablation != Some("single-lora"),
        ..EsMoeConfig::default()
    });
    crate::memory::keep_freed_memory();
    let device = args.device.open()?;
    let out = required(args.out.clone(), "out")?;
    let tokens = required(args.tokens.clone(), "tokens")?;
    let (base, backbone) = match (&args.base, &args.fits) {
        (Some(base), _) => (base.clone(), None),
        (None, _) => {
            let choice = law_backbone(&args, &tokens, &out, &device)?;
            (choice.run.clone(), Some(choice))
        }
    };
    let config = ContinualConfig {
        scenarios: required(args.scenarios, "scenarios")?,
        tokens,
        base,
        evaluator: required(args.evaluator, "evaluator")?,
        method,
        orders: args.orders.max(1),
        seed: args.seed,
        tokens_budget: args.tokens_budget,
        expert_epochs: expert_epochs(args.expert_epochs.as_deref(), backbone.as_ref())?,
        batch_size: args.batch,
        lr: args.lr,
        lora: LoraConfig {
            rank: args.lora_rank,
            alpha: args.lora_alpha,
        },
        replay_fraction: args.replay_fraction,
        orthogonality: if method == Method::OLora {
            args.orthogonality
        } else {
            0.0
        },
        distillation: if method == Method::LwfLora {
            args.distillation
        } else {
            0.0
        },
        es_moe,
        repeats: args.repeats.max(1),
        pool: args.pool,
        mm_texts: args.mm_texts,
        eval_learned_only: args.eval_learned_only,
        eval_split: args.eval_split,
        keep_motions: args.keep_motions,
        out,
        backbone,
    };
    let started = std::time::Instant::now();
    let report = run_continual(&config, &device, |line| eprintln!("{line}"))?;
    let s = report.mean;
    let opt = |v: Option<f64>| v.map_or_else(|| "–".into(), |v| format!("{v:.3}"));
    println!(
        "{}, {} orders, {:.0} s: AF {:.4}, AR {:.3}, AD {}, AMM {}, AWF {}, FR {} → {}",
        config.label(),
        report.orders.len(),
        started.elapsed().as_secs_f64(),
        s.af,
        s.ar,
        opt(s.ad),
        opt(s.amm),
        opt(s.awf),
        opt(s.fr),
        config.out.display()
    );
    Ok(ExitCode::SUCCESS)
}
