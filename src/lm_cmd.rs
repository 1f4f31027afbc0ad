//! `motionscale model info|presets`, `motionscale train` and `motionscale generate`: the
//! text-prefix autoregressive motion transformer.

use anyhow::{bail, Context, Result};
use ingest::corpus::split::SplitAssignment;
use ingest::npy;
use lm::accounting::{Accounting, SequenceShape};
use lm::generate::Sampling;
use lm::lm_data::{Limits, LmData};
use lm::prefix_lm::{PrefixLmConfig, PRESETS};
use lm::train::{Hyperparams, ModelShape, RunConfig, TrainConfig, TrainEvent, TrainReport};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// A model shape on the command line: `--preset P` or `--width W --layers L --heads H`.
#[derive(clap::Args, Debug, Clone)]
pub struct ShapeArgs {
    /// A named preset (ScaMo's 44M, 111M, 343M, 775M, 1.4B, 3B, or a cpu-… ladder size).
    #[arg(long, conflicts_with_all = ["width", "layers", "heads"])]
    pub preset: Option<String>,
    /// Model width d.
    #[arg(long, requires_all = ["layers", "heads"])]
    pub width: Option<usize>,
    /// Blocks.
    #[arg(long)]
    pub layers: Option<usize>,
    /// Attention heads.
    #[arg(long)]
    pub heads: Option<usize>,
    /// SwiGLU width (default round(8d/3)).
    #[arg(long)]
    pub ffn: Option<usize>,
    /// Train a LoRA adapter on this trained run (its weights frozen) instead of a new model.
    #[arg(long, conflicts_with_all = ["preset", "width"])]
    pub base: Option<PathBuf>,
    /// LoRA rank r.
    #[arg(long, default_value_t = 8, requires = "base")]
    pub lora_rank: usize,
    /// LoRA α (the update is scaled by α/r).
    #[arg(long, default_value_t = 16.0, requires = "base")]
    pub lora_alpha: f64,
    /// Expert name of the adapter (its key prefix in adapter.safetensors).
    #[arg(long, default_value = "expert0", requires = "base")]
    pub expert: String,
    /// Start from this adapter file's expert (e.g. the previous scenario's
    /// adapter.safetensors: sequential LoRA) instead of a new adapter.
    #[arg(long, requires = "base")]
    pub lora_init: Option<PathBuf>,
    /// Keep the adapter's `lora_A` subspaces orthogonal to these adapter files' (O-LoRA).
    #[arg(long, value_delimiter = ',', requires = "base")]
    pub lora_orthogonal_to: Vec<PathBuf>,
    /// Weight λ of the O-LoRA orthogonality loss.
    #[arg(long, default_value_t = 0.5, requires = "lora_orthogonal_to")]
    pub lora_orthogonality: f64,
    /// Distil towards this trained run's outputs on the new data (LwF).
    #[arg(long, requires = "base")]
    pub distill_from: Option<PathBuf>,
    /// Weight of the distillation loss (temperature 2).
    #[arg(long, default_value_t = 1.0, requires = "distill_from")]
    pub distillation: f64,
}

impl ShapeArgs {
    fn shape(&self) -> Result<ModelShape> {
        if let Some(base) = &self.base {
            return Ok(ModelShape::Lora {
                base: base.clone(),
                lora: lm::lora::LoraConfig {
                    rank: self.lora_rank,
                    alpha: self.lora_alpha,
                },
                expert: self.expert.clone(),
                init: self.lora_init.clone(),
                orthogonal_to: self.lora_orthogonal_to.clone(),
                orthogonality: if self.lora_orthogonal_to.is_empty() {
                    0.0
                } else {
                    self.lora_orthogonality
                },
                distill_from: self.distill_from.clone(),
                distillation: if self.distill_from.is_some() {
                    self.distillation
                } else {
                    0.0
                },
            });
        }
        match (&self.preset, self.width, self.layers, self.heads) {
            (Some(p), ..) => Ok(ModelShape::Preset(p.clone())),
            (None, Some(d_model), Some(n_layers), Some(n_heads)) => Ok(ModelShape::Custom {
                d_model,
                n_layers,
                n_heads,
                ffn_hidden: self.ffn,
            }),
            _ => bail!("give --preset P, --width W --layers L --heads H, or --base RUN"),
        }
    }
}

/// Arguments of `motionscale model info`.
#[derive(clap::Args, Debug)]
pub struct InfoArgs {
    /// Model shape.
    #[command(flatten)]
    pub shape: ShapeArgs,
    /// Motion codebook size K (the vocabulary adds BOS, EOS and PAD).
    #[arg(long)]
    pub vocab: usize,
    /// Width of the frozen text embeddings (MiniLM: 384).
    #[arg(long, default_value_t = 384)]
    pub text_dim: usize,
    /// Prefix positions of the exact FLOP count.
    #[arg(long, default_value_t = SequenceShape::BENCH.prefix)]
    pub prefix_len: usize,
    /// Motion positions of the exact FLOP count.
    #[arg(long, default_value_t = SequenceShape::BENCH.motion)]
    pub motion_len: usize,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `motionscale model logits`.
#[derive(clap::Args, Debug)]
pub struct LogitsArgs {
    /// Trained run folder (`motionscale train --out`).
    #[arg(long)]
    pub model: PathBuf,
    /// Split of the run's token set whose first clips are scored (first caption each).
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Clips to score.
    #[arg(long, default_value_t = 4)]
    pub clips: usize,
    /// Output folder: clips.jsonl (motion id, prefix length, motion inputs) and
    /// clip-<k>-text.npy / clip-<k>-logits.npy, for checking the model in another framework.
    #[arg(long)]
    pub out: PathBuf,
    /// Where the model runs.
    #[command(flatten)]
    pub device: crate::device_args::DeviceArgs,
    /// Executor and precision.
    #[command(flatten)]
    pub compute: ComputeArgs,
}

/// Arguments of `motionscale model loss`.
#[derive(clap::Args, Debug)]
pub struct LossArgs {
    /// Trained run folder (`motionscale train --out`); give it more than once for the ensemble
    /// of the runs (each target's probability the mean of theirs). The runs must share a token
    /// set, its splits and their sequence lengths.
    #[arg(long, required = true)]
    pub model: Vec<PathBuf>,
    /// Split scored (first caption of each clip), as training scores it.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
    /// Where the models run.
    #[command(flatten)]
    pub device: crate::device_args::DeviceArgs,
    /// Executor and precision.
    #[command(flatten)]
    pub compute: ComputeArgs,
}

/// The token set of `run` as it trained on it (its encoder and sequence lengths), split by
/// `splits`.
fn run_data(run: &RunConfig, splits: &SplitAssignment) -> Result<LmData> {
    let limits = Limits {
        text_tokens: run.train.hyper.max_text_tokens,
        motion_tokens: run.train.hyper.max_motion_tokens,
    };
    Ok(LmData::load(
        &run.train.tokens,
        &run.corpus,
        Some(&run.text_encoder),
        limits,
        splits,
    )?)
}

/// `motionscale model loss`: the cross-entropy and L_u of a trained model, or of the ensemble
/// of several, on a split of their token set (per origin where it has both), from the weights
/// in each run folder (the last checkpoint).
pub fn loss(args: LossArgs) -> Result<ExitCode> {
    let device = args.device.open()?;
    let mut lms = Vec::new();
    let mut runs: Vec<RunConfig> = Vec::new();
    for dir in &args.model {
        let (lm, run) = lm::train::load_lm(dir, &device, args.compute.compute())?;
        if let Some(first) = runs.first() {
            let key = |r: &RunConfig| {
                (
                    r.train.tokens.clone(),
                    r.train.splits.clone(),
                    r.corpus.clone(),
                    r.text_encoder.clone(),
                    r.train.hyper.max_text_tokens,
                    r.train.hyper.max_motion_tokens,
                )
            };
            if key(first) != key(&run) {
                bail!(
                    "{}: another token set, splits, corpus, text encoder or sequence length than {}",
                    dir.display(),
                    args.model[0].display()
                );
            }
        }
        lms.push(lm);
        runs.push(run);
    }
    let run = &runs[0];
    let splits = SplitAssignment::from_dir(run.train.splits.as_deref())
        .map_err(|e| anyhow::anyhow!("{}: {e}", args.model[0].display()))?;
    let data = run_data(run, &splits)?;
    let members: Vec<&dyn lm::MotionLm> = lms.iter().map(|m| m.as_ref()).collect();
    let batch = run.train.hyper.batch_size;
    let loss = lm::test_loss::evaluate_ensemble(&members, &data, &args.split, batch)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&loss)?);
        return Ok(ExitCode::SUCCESS);
    }
    let what = match members.len() {
        1 => "the model".to_string(),
        k => format!("the ensemble of {k} models"),
    };
    println!(
        "{what} on split {}: {} clips, {} code targets",
        loss.split, loss.clips, loss.code_targets
    );
    for (name, l) in std::iter::once(("all".to_string(), &loss)).chain(
        loss.by_origin
            .iter()
            .map(|(o, l)| (format!("{o:?}").to_lowercase(), l)),
    ) {
        println!(
            "  {name:<6} CE {:.4}  L_u {:.4}  (with EOS {:.4}; {} clips)",
            l.cross_entropy, l.normalized_loss, l.cross_entropy_with_eos, l.clips
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// `motionscale model logits`: the logits of a trained model on a few clips of its token set,
/// with the exact inputs that produced them (`scripts/torch-check-lm.py` reads them).
pub fn logits(args: LogitsArgs) -> Result<ExitCode> {
    let (model, run) = lm::train::load_model(&args.model, &args.device.open()?)?;
    let model = model.with_compute(args.compute.compute());
    let data = run_data(&run, &SplitAssignment::default())?;
    let items = data.eval_items(&args.split);
    if items.is_empty() {
        bail!(
            "{}: no clip in split {:?}",
            run.train.tokens.display(),
            args.split
        );
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let (e, v) = (model.config().text_dim, model.config().vocab_size());
    let mut lines = String::new();
    for (k, item) in items.iter().take(args.clips).enumerate() {
        let batch = data.batch(model.config(), std::slice::from_ref(item));
        let logits = model.forward(&batch)?.flatten_all()?.to_vec1::<f32>()?;
        let text = data.text_of(item);
        for (name, shape, values) in [
            ("text", [text.len() / e, e], text),
            ("logits", [batch.inputs.len(), v], logits.as_slice()),
        ] {
            let path = args.out.join(format!("clip-{k}-{name}.npy"));
            npy::write_f32(&path, &shape, values)
                .with_context(|| format!("writing {}", path.display()))?;
        }
        let line = serde_json::json!({
            "motion_id": item.0.motion_id,
            "prefix_len": text.len() / e,
            "inputs": batch.inputs,
        });
        lines.push_str(&format!("{line}\n"));
    }
    let path = args.out.join("clips.jsonl");
    motionscale_core::write_atomic(&path, lines.as_bytes())
        .with_context(|| format!("writing {}", path.display()))?;
    println!(
        "logits of {} clip(s) of split {} → {}",
        items.len().min(args.clips),
        args.split,
        args.out.display()
    );
    Ok(ExitCode::SUCCESS)
}

/// Arguments of `motionscale model executors`.
#[derive(clap::Args, Debug)]
pub struct ExecutorsArgs {
    /// Model width.
    #[arg(long, default_value_t = 256)]
    pub width: usize,
    /// Blocks.
    #[arg(long, default_value_t = 4)]
    pub layers: usize,
    /// Heads.
    #[arg(long, default_value_t = 4)]
    pub heads: usize,
    /// Motion codes K.
    #[arg(long, default_value_t = 1024)]
    pub vocab: usize,
    /// Sequences in the batch.
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    /// Seed of the weights and the batch.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Largest relative difference of the loss, any gradient and the logits (f32).
    #[arg(long, default_value_t = 1e-5)]
    pub tolerance: f32,
    /// Where the graph and GPU executors run.
    #[command(flatten)]
    pub device: crate::device_args::DeviceArgs,
    /// Print the figures as JSON.
    #[arg(long)]
    pub json: bool,
}

/// `motionscale model executors`.
pub fn executors(args: ExecutorsArgs) -> Result<ExitCode> {
    let device = args.device.open()?;
    let config = lm::PrefixLmConfig::new(args.width, args.layers, args.heads, args.vocab, 384);
    config.validate()?;
    let a = lm::executor_check::compare(&config, args.batch, args.seed, &device)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&a)?);
    } else {
        println!(
            "graph on {} vs cpu on the CPU, d{} × {} layers, batch {}: loss {:.6} (relative Δ {:.1e}), gradients {:.1e} (worst {}), logits {:.1e}, KV-cached logits max |Δ| {:.1e}",
            a.device, args.width, args.layers, args.batch, a.loss, a.loss_relative,
            a.gradient_relative, a.worst_weight, a.logits_relative, a.cached_logits_max_abs
        );
        let (loss, grads, weight) = &a.gpu_step;
        println!(
            "gpu executor on {} vs cpu on the CPU: loss (relative Δ {loss:.1e}), gradients {grads:.1e} (worst {weight})",
            a.device
        );
        for (output, d) in &a.fused_ops {
            println!(
                "fused op on {} vs the CPU: {output}: relative Δ {d:.1e}",
                a.device
            );
        }
    }
    let fused = a.fused_ops.iter().map(|(_, d)| *d);
    let step = [a.gpu_step.0, a.gpu_step.1];
    let ok = [a.loss_relative, a.gradient_relative, a.logits_relative]
        .into_iter()
        .chain(step)
        .chain(fused)
        .all(|d| d <= args.tolerance)
        && a.cached_logits_max_abs <= 10.0 * args.tolerance;
    if !ok {
        eprintln!(
            "error: the executors differ by more than {:e}",
            args.tolerance
        );
    }
    Ok(if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// Arguments of `motionscale model presets`.
#[derive(clap::Args, Debug)]
pub struct PresetsArgs {
    /// Motion codebook size K.
    #[arg(long, default_value_t = 1024)]
    pub vocab: usize,
    /// Width of the frozen text embeddings.
    #[arg(long, default_value_t = 384)]
    pub text_dim: usize,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

fn millions(n: u64) -> String {
    format!("{:.2}M", n as f64 / 1e6)
}

/// `motionscale model info`.
pub fn info(args: InfoArgs) -> Result<ExitCode> {
    let config = args.shape.shape()?.resolve(args.vocab, args.text_dim)?;
    let seq = SequenceShape {
        prefix: args.prefix_len,
        motion: args.motion_len,
    };
    let acc = Accounting::of(&config, seq);
    if args.json {
        let value = serde_json::json!({"config": config, "accounting": acc});
        println!("{}", serde_json::to_string_pretty(&value)?);
        return Ok(ExitCode::SUCCESS);
    }
    let p = acc.params;
    println!(
        "d {} · {} layers · {} heads (head width {}) · SwiGLU {} · vocabulary {} = {} codes + BOS/EOS/PAD · text {}",
        config.d_model,
        config.n_layers,
        config.n_heads,
        config.head_dim(),
        config.ffn_hidden,
        config.vocab_size(),
        config.codebook_size,
        config.text_dim
    );
    println!(
        "N_nv {} (blocks {}, text projection {}, final norm {})",
        millions(p.n_nv),
        millions(p.blocks),
        millions(p.text_projection),
        p.final_norm
    );
    println!(
        "N_v  {} = embedding {} + head {} (untied: both counted)",
        millions(p.n_v),
        millions(p.embedding),
        millions(p.head)
    );
    println!("N    {} ({} parameters)", millions(p.total), p.total);
    println!(
        "FLOPs per motion token: 6N {:.4e}; exact {:.4e} (training, {} prefix + {} motion positions, attention {:.1}% of forward)",
        acc.flops_6n_per_token,
        acc.flops_exact_per_token,
        seq.prefix,
        seq.motion,
        100.0 * acc.forward_per_sequence.attention / acc.forward_per_sequence.total
    );
    println!("budget C = 6·N·D = {:.4e}·D", acc.flops_6n_per_token);
    Ok(ExitCode::SUCCESS)
}

/// `motionscale model presets`.
pub fn presets(args: PresetsArgs) -> Result<ExitCode> {
    let rows: Vec<(String, Option<f64>, PrefixLmConfig, Accounting)> = PRESETS
        .iter()
        .map(|p| {
            let c = PrefixLmConfig::preset(p.name, args.vocab, args.text_dim).expect("preset");
            let acc = Accounting::of(&c, SequenceShape::BENCH);
            (p.name.to_string(), p.nominal_params, c, acc)
        })
        .collect();
    if args.json {
        let value: Vec<_> = rows
            .iter()
            .map(|(name, nominal, c, acc)| {
                serde_json::json!({"preset": name, "nominal_params": nominal, "config": c, "accounting": acc})
            })
            .collect();
        println!("{}", serde_json::to_string_pretty(&value)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "{:<9} {:>6} {:>6} {:>5} {:>6} {:>10} {:>10} {:>10} {:>9}  (K = {}, E = {})",
        "preset",
        "layers",
        "heads",
        "d",
        "ffn",
        "N_nv",
        "N_v",
        "N",
        "nominal",
        args.vocab,
        args.text_dim
    );
    for (name, nominal, c, acc) in &rows {
        let p = acc.params;
        println!(
            "{:<9} {:>6} {:>6} {:>5} {:>6} {:>10} {:>10} {:>10} {:>9}",
            name,
            c.n_layers,
            c.n_heads,
            c.d_model,
            c.ffn_hidden,
            millions(p.n_nv),
            millions(p.n_v),
            millions(p.total),
            nominal.map_or("-".into(), |n| format!("{:.0}M", n / 1e6))
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// Arguments of `motionscale train`.
#[derive(clap::Args, Debug)]
pub struct TrainArgs {
    /// Token set folder (`motionscale tokenize`).
    #[arg(long)]
    pub tokens: PathBuf,
    /// Corpus folder with caption embeddings (default: the token set's corpus).
    #[arg(long)]
    pub corpus: Option<PathBuf>,
    /// Text encoder id of the caption embeddings (default: the corpus's only one).
    #[arg(long)]
    pub text_emb: Option<String>,
    /// Folder of `{train,val,test}.txt` clip lists (e.g. a scenario dataset from
    /// `motionscale scenarios`) replacing the token set's splits.
    #[arg(long)]
    pub splits: Option<PathBuf>,
    /// Model shape.
    #[command(flatten)]
    pub shape: ShapeArgs,
    /// Expected codebook size (checked against the token set).
    #[arg(long)]
    pub vocab: Option<usize>,
    /// Token budget D: motion tokens to train on.
    #[arg(long)]
    pub tokens_budget: u64,
    /// Output folder (a re-run of the same command resumes from its checkpoint).
    #[arg(long)]
    pub out: PathBuf,
    /// Optimisation settings.
    #[command(flatten)]
    pub hyper: Hyperparams,
    /// Evaluate every N steps (default: 10 times per run).
    #[arg(long)]
    pub eval_every: Option<u64>,
    /// Checkpoint every N steps (default: 10 times per run).
    #[arg(long)]
    pub checkpoint_every: Option<u64>,
    /// Stop after this many steps of the schedule (checkpointed; re-run to continue).
    #[arg(long)]
    pub stop_after: Option<u64>,
    /// Print the final report as JSON.
    #[arg(long)]
    pub json: bool,
    /// Where the model trains.
    #[command(flatten)]
    pub device: crate::device_args::DeviceArgs,
    /// Executor and precision.
    #[command(flatten)]
    pub compute: ComputeArgs,
}

/// How the prefix LM computes: `--precision` and `--executor`.
#[derive(clap::Args, Debug, Clone)]
pub struct ComputeArgs {
    /// Arithmetic of the matrix products: f32 (the default), or bf16 from f32 master
    /// weights (f32 optimiser state, norms, softmax and loss); bf16 runs the gpu (training) or graph executor.
    #[arg(long, value_name = "f32|bf16")]
    pub precision: Option<nn::device::Precision>,
    /// Force an executor (default: cpu for f32 on the CPU, gpu otherwise): for comparing
    /// the two.
    #[arg(long, value_enum)]
    pub executor: Option<lm::prefix_lm::Executor>,
}

impl ComputeArgs {
    /// The model's compute settings (f32 unless `--precision` says otherwise).
    pub fn compute(&self) -> lm::prefix_lm::Compute {
        self.compute_or(nn::device::Precision::F32)
    }

    /// The model's compute settings, `precision` unless `--precision` is given.
    pub fn compute_or(&self, precision: nn::device::Precision) -> lm::prefix_lm::Compute {
        lm::prefix_lm::Compute {
            executor: self.executor,
            precision: self.precision.unwrap_or(precision),
        }
    }
}

/// `motionscale train`.
pub fn train(args: TrainArgs) -> Result<ExitCode> {
    crate::memory::keep_freed_memory();
    let config = train_config(&args)?;
    let device = args.device.open()?;
    let bar = crate::commands::progress_bar("train", "steps");
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} train [{bar:30}] {pos}/{len} steps {msg} eta {eta}",
        )?
        .progress_chars("=> "),
    );
    let mut tokens_per_s = 0.0;
    let report = lm::train::train(&config, &device, &mut |event| match event {
        TrainEvent::Started { from, total, run } => {
            bar.set_length(*total);
            bar.set_position(*from);
            check_vocab(args.vocab, run);
            let p = run.accounting.params;
            bar.println(format!(
                    "model d {} × {} layers, N_nv {} N_v {} (untied), vocabulary {}, text {}; {} steps on {} ({}){}",
                    run.model.d_model,
                    run.model.n_layers,
                    p.n_nv,
                    p.n_v,
                    run.model.vocab_size(),
                    run.text_encoder,
                    total,
                    run.device,
                    run.train.compute.precision,
                    if *from > 0 { format!(", resuming at step {from}") } else { String::new() }
                ));
        }
        TrainEvent::Step {
            step,
            loss,
            lr,
            tokens_per_s: tps,
            ..
        } => {
            tokens_per_s = if tokens_per_s == 0.0 {
                *tps
            } else {
                0.9 * tokens_per_s + 0.1 * tps
            };
            bar.set_position(*step);
            bar.set_message(format!(
                "loss {loss:.4} lr {lr:.2e} {tokens_per_s:.0} tok/s"
            ));
        }
        TrainEvent::Eval(e) => bar.println(format!(
            "step {}: train {:.4}, test CE {:.4}, L_u {:.4} (unigram CE {:.4}), D {}, C {:.3e}",
            e.step,
            e.train_loss,
            e.test.cross_entropy,
            e.test.normalized_loss,
            e.test.unigram_cross_entropy,
            e.tokens_seen,
            e.flops_6n
        )),
    });
    bar.finish_and_clear();
    print_train_report(&report?, args.json)?;
    Ok(ExitCode::SUCCESS)
}

/// The run's configuration from the command line.
fn train_config(args: &TrainArgs) -> Result<TrainConfig> {
    let mut config = TrainConfig::new(
        &args.tokens,
        args.shape.shape()?,
        args.tokens_budget,
        &args.out,
    );
    config.corpus = args.corpus.clone();
    config.text_encoder = args.text_emb.clone();
    config.splits = args.splits.clone();
    config.hyper = args.hyper.clone();
    config.stop_after = args.stop_after;
    config.eval_every = args.eval_every;
    config.checkpoint_every = args.checkpoint_every;
    config.compute = args.compute.compute();
    Ok(config)
}

/// The finished run: its report as JSON, or one line of its final evaluation.
fn print_train_report(report: &TrainReport, json: bool) -> Result<()> {
    if json {
        println!("{}", serde_json::to_string_pretty(report)?);
    } else {
        let e = &report.eval;
        println!(
            "{} steps of {}: test CE {:.4} nats (unigram CE {:.4}, entropy {:.4}), L_u {:.4}; D {} tokens, C {:.3e} FLOPs (exact {:.3e}) → {}",
            report.steps,
            report.total_steps,
            e.test.cross_entropy,
            e.test.unigram_cross_entropy,
            e.test.unigram_entropy,
            e.test.normalized_loss,
            e.tokens_seen,
            e.flops_6n,
            e.flops_exact,
            report.out.display()
        );
    }
    Ok(())
}

fn check_vocab(expected: Option<usize>, run: &RunConfig) {
    if let Some(v) = expected {
        let t = &run.tokenizer;
        if v != t.codebook_size && v != t.nominal_codebook {
            eprintln!(
                "warning: --vocab {v} but the token set has {} codes (nominal {})",
                t.codebook_size, t.nominal_codebook
            );
        }
    }
}

/// Arguments of `motionscale generate`.
#[derive(clap::Args, Debug)]
pub struct GenerateArgs {
    /// Trained model folder (`motionscale train --out`).
    #[arg(long)]
    pub model: PathBuf,
    /// Tokenizer checkpoint folder (default: the one that made the model's token set).
    #[arg(long)]
    pub tokenizer: Option<PathBuf>,
    /// The text to animate.
    #[arg(
        long,
        required_unless_present = "captions_from",
        conflicts_with = "captions_from"
    )]
    pub text: Option<String>,
    /// Batch mode: animate one caption of every clip of `--split` in this corpus, into a
    /// HumanML3D-layout folder `--out` that `motionscale eval --motions` reads.
    #[arg(long)]
    pub captions_from: Option<PathBuf>,
    /// Batch mode: the corpus split whose captions to animate.
    #[arg(long, default_value = "test")]
    pub split: String,
    /// Batch mode: take the split's clips from `DIR/<split>.txt` (e.g. a scenario dataset)
    /// instead of the corpus's own split.
    #[arg(long)]
    pub splits: Option<PathBuf>,
    /// Batch mode: texts (drawn by the seed) that get `--mm-samples` samples each, for
    /// multimodality.
    #[arg(long, default_value_t = 100)]
    pub mm_texts: usize,
    /// Batch mode: samples for each multimodality text.
    #[arg(long, default_value_t = 10)]
    pub mm_samples: usize,
    /// Batch mode: sequences generated together.
    #[arg(long, default_value_t = 32)]
    pub batch: usize,
    /// Output: with --text a file, .json (tokens), .npy (n × 263 HumanML3D features,
    /// de-normalised) or .bvh (SMPL-22 hierarchy, 20 fps, centimetres: Blender's import
    /// scale 0.01 gives metres); with --captions-from a folder.
    #[arg(long)]
    pub out: PathBuf,
    /// BERT-family text encoder folder (default: the one the model was trained with).
    #[arg(long)]
    pub encoder: Option<PathBuf>,
    /// Softmax temperature (0: greedy).
    #[arg(long, default_value_t = 1.0)]
    pub temperature: f64,
    /// Sample among the k most likely tokens (0: all).
    #[arg(long, default_value_t = 50)]
    pub top_k: usize,
    /// Nucleus sampling threshold.
    #[arg(long)]
    pub top_p: Option<f64>,
    /// Sampling seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Most motion tokens.
    #[arg(long, default_value_t = 64)]
    pub max_tokens: usize,
    /// Fewest motion tokens: EOS cannot end a sequence before this many (a motion needs one).
    #[arg(long, default_value_t = 1)]
    pub min_tokens: usize,
    /// Recompute the whole sequence every step instead of using the key/value cache.
    #[arg(long)]
    pub no_cache: bool,
    /// Where the model, the text encoder and the tokenizer run.
    #[command(flatten)]
    pub device: crate::device_args::DeviceArgs,
    /// Executor and precision of the model.
    #[command(flatten)]
    pub compute: ComputeArgs,
}

/// Decode `tokens` with the run's tokenizer and write HumanML3D features (.npy) or a BVH
/// of the recovered joints.
fn write_motion(
    tokens: &[u32],
    run: &RunConfig,
    dir: Option<&Path>,
    out: &Path,
    device: &candle_core::Device,
) -> Result<()> {
    let features = lm::train::run_tokenizer(run, dir, device)?.detokenize(tokens)?;
    ingest::export::motion::write_motion(out, &features, false)
        .with_context(|| format!("writing {}", out.display()))
}

/// `motionscale generate`.
pub fn generate(args: GenerateArgs) -> Result<ExitCode> {
    crate::memory::keep_freed_memory();
    let device = args.device.open()?;
    let (model, run) = lm::train::load_lm(&args.model, &device, args.compute.compute())?;
    let encoder = text::encoder_for(
        &run.corpus,
        &run.text_encoder,
        args.encoder.as_deref(),
        &device,
    )?;
    let sampling = Sampling {
        temperature: args.temperature,
        top_k: (args.top_k > 0).then_some(args.top_k),
        top_p: args.top_p,
        seed: args.seed,
        max_tokens: args.max_tokens,
        allow_eos: true,
        min_tokens: args.min_tokens,
        kv_cache: !args.no_cache,
    };
    let Some(caption) = args.text.as_deref() else {
        let options = lm::caption_set::CaptionSetOptions {
            corpus: args.captions_from.clone().expect("batch mode"),
            split: args.split.clone(),
            splits: args.splits.clone(),
            mm_texts: args.mm_texts,
            mm_samples: args.mm_samples,
            batch: args.batch,
            sampling,
        };
        let tokenizer = lm::train::run_tokenizer(&run, args.tokenizer.as_deref(), &device)?;
        return crate::generate_batch::generate_batch(
            &options,
            model.as_ref(),
            &run,
            &tokenizer,
            encoder.as_ref(),
            &args.out,
        );
    };
    let text = encoder.encode(&[caption])?.remove(0);
    let rows = text.len().min(run.train.hyper.max_text_tokens);
    let prefix = &text.embeddings[..rows * text.dim];
    let started = std::time::Instant::now();
    let caption_model = model.for_caption(prefix)?;
    let tokens = lm::generate::generate(&caption_model, &[prefix], &sampling)?.remove(0);
    let seconds = started.elapsed().as_secs_f64();
    let ext = args.out.extension().and_then(|e| e.to_str()).unwrap_or("");
    match ext {
        "json" => {
            let value = serde_json::json!({
                "text": caption,
                "tokens": tokens,
                "model": args.model,
                "text_encoder": run.text_encoder,
                "tokenizer": run.tokenizer,
                "sampling": sampling,
            });
            motionscale_core::write_atomic(
                &args.out,
                serde_json::to_string_pretty(&value)?.as_bytes(),
            )?;
        }
        "npy" | "bvh" => {
            write_motion(&tokens, &run, args.tokenizer.as_deref(), &args.out, &device)?
        }
        _ => bail!("--out must end in .json, .npy or .bvh"),
    }
    println!(
        "{} motion tokens in {:.2} s ({:.0} tokens/s) → {}",
        tokens.len(),
        seconds,
        tokens.len() as f64 / seconds,
        args.out.display()
    );
    Ok(ExitCode::SUCCESS)
}
