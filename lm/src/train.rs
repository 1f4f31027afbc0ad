//! Training of the prefix LM: AdamW (`nn::optim`) with linear warm-up and cosine decay
//! sized to the token budget D, global gradient-norm clipping, seeded batches, periodic
//! evaluation on the test split, and atomic checkpoints a re-run resumes from.
//!
//! ```text
//! OUT/config.json           format, the train config, the resolved model config, text encoder,
//!                           tokenizer, schedule (total/warm-up steps), accounting
//! OUT/model.safetensors     weights (PyTorch key names, see prefix_lm)
//! OUT/state.json            step, tokens seen, executed FLOPs, data position (written last:
//!                           it commits the checkpoint)
//! OUT/resume/<step>/        that step's model.safetensors and optimizer.safetensors (AdamW)
//! OUT/eval.json             the latest evaluation (test, validation, and the validation-selected
//!                           evaluation so far); OUT/evals.jsonl every evaluation
//! ```
//!
//! A run is a pure function of its config: batch k is fixed by the seed, every kernel reduces
//! in a fixed order, so killing a run and re-running the same command ends with the same
//! weights as an uninterrupted run.

use crate::accounting::{self, Accounting, SequenceShape};
use crate::es_moe::train::{EsMoeTrainer, MoeExample};
use crate::es_moe::EsMoe;
use crate::eval_record::EvalRecord;
use crate::lm_data::{Limits, LmData};
use crate::load::{clip_emotions, resume, Paths, MODEL_FILE, OPTIMIZER_FILE};
use crate::lora::{adapter_a_matrices, base_weights, LoraAdapter, ADAPTER_FILE};
use crate::prefix_lm::{init_model, Compute, LmBatch, PrefixLm, PrefixLmConfig};
use crate::selection;
use crate::test_loss::evaluate;
use crate::MotionLm;
use candle_core::{Device, Tensor};
use motionscale_core::files::{append_json_line, read_json, write_json};
use motionscale_core::rng::SplitMix64;
use nn::checkpoint::save_safetensors;
use nn::dropout::Dropout;
use nn::optim::{AdamW, AdamWConfig, LrSchedule};
use nn::ModelError;
use std::collections::HashMap;
use std::time::Instant;

// The run's settings and records (`run_config`) and the loaders of a trained run (`load`)
// keep their `lm::train` paths.
pub use crate::load::{load_lm, load_model, run_tokenizer};
pub use crate::run_config::{
    Hyperparams, ModelShape, RunConfig, TrainConfig, TrainEvent, TrainReport, TrainState,
    DISTILLATION_TEMPERATURE, FORMAT, HYPERPARAMS,
};

/// Stream of the generator that masks older ES-MoE experts (per step).
const MASK_STREAM: u64 = 0x6d61_736b;
/// Stream of the dropout seeds (one per step).
const DROPOUT_STREAM: u64 = 0x6472_6f70;

/// Train (or resume) the run `config` describes on `device`, calling `on_event` as it goes.
pub fn train(
    config: &TrainConfig,
    device: &Device,
    on_event: &mut dyn FnMut(&TrainEvent),
) -> Result<TrainReport, ModelError> {
    let mut run = Run::start(config, device)?;
    let total = run.config.schedule.total;
    on_event(&TrainEvent::Started {
        from: run.state.step,
        total,
        run: Box::new(run.config.clone()),
    });
    let end = config.stop_after.map_or(total, |s| total.min(s));
    let every = |n: Option<u64>| n.unwrap_or(total.div_ceil(10)).max(1);
    let mut last_eval = None;
    while run.state.step < end {
        let event = run.step()?;
        if let TrainEvent::Step { loss, .. } = event {
            run.state.loss_sum += f64::from(loss);
            run.state.loss_steps += 1;
        }
        on_event(&event);
        let (step, done) = (run.state.step, run.state.step == end);
        let scheduled = step % every(config.eval_every) == 0 || step == total;
        if scheduled || done {
            let mean = run.state.loss_sum / run.state.loss_steps.max(1) as f64;
            let record = run.evaluate(mean, scheduled)?;
            // An evaluation only because `stop_after` ends the run early keeps the window:
            // the resumed run's next evaluation then averages the same steps as it would have.
            if scheduled {
                (run.state.loss_sum, run.state.loss_steps) = (0.0, 0);
            }
            on_event(&TrainEvent::Eval(Box::new(record.clone())));
            last_eval = Some(record);
        }
        if step % every(config.checkpoint_every) == 0 || done {
            run.checkpoint()?;
        }
    }
    let eval = match last_eval {
        Some(e) => e,
        None => read_json(&run.paths.eval)?,
    };
    Ok(TrainReport {
        steps: run.state.step,
        total_steps: total,
        eval,
        out: config.out.clone(),
        device: run.config.device.clone(),
    })
}

/// What a run trains.
enum Trainee {
    /// A whole model.
    Model(PrefixLm),
    /// A LoRA adapter on a frozen base.
    Lora(Box<LoraRun>),
    /// An ES-MoE expert and the gate on a frozen base.
    Moe(Box<EsMoeTrainer>),
}

/// A run in progress: data, what it trains, optimiser and where it stands.
struct Run {
    config: RunConfig,
    data: LmData,
    trainee: Trainee,
    /// The trained variables: the model's, or the adapter's (and gate's) on a frozen base.
    vars: HashMap<String, candle_core::Var>,
    opt: AdamW,
    state: TrainState,
    paths: Paths,
}

/// The variables a run trains and how: a new model, a LoRA adapter on a frozen base (with
/// its orthogonality and distillation partners), or an ES-MoE expert and the gate.
fn build_trainee(
    config: &TrainConfig,
    run: &RunConfig,
    data: &LmData,
    device: &Device,
) -> Result<(Trainee, HashMap<String, candle_core::Var>), ModelError> {
    let compute = config.compute;
    Ok(match &config.model {
        ModelShape::Lora {
            base,
            lora,
            expert,
            init,
            orthogonal_to,
            orthogonality,
            distill_from,
            distillation,
        } => {
            let adapter = LoraAdapter::new(&run.model, *lora, expert, config.hyper.seed, device)
                .map_err(ModelError::Candle)?;
            if let Some(file) = init {
                adapter.load(file)?;
            }
            let mut previous = Vec::new();
            for file in orthogonal_to {
                previous.extend(adapter_a_matrices(file, device)?);
            }
            let teacher = match distill_from {
                Some(dir) => Some(load_model(dir, device)?.0.with_compute(compute)),
                None => None,
            };
            let vars = adapter.vars();
            let lora = LoraRun {
                adapter,
                base: base_weights(&base.join(MODEL_FILE), device)?,
                compute,
                previous,
                orthogonality: *orthogonality,
                teacher,
                distillation: *distillation as f32,
            };
            (Trainee::Lora(Box::new(lora)), vars)
        }
        ModelShape::EsMoe {
            base,
            previous,
            expert,
            moe,
        } => {
            let train_texts: Vec<&[f32]> = data
                .split("train")
                .iter()
                .flat_map(|e| &e.captions)
                .map(|&c| data.text[c].as_slice())
                .collect();
            let mut trainer = EsMoeTrainer::new(
                &run.model,
                *moe,
                &base.join(MODEL_FILE),
                previous.as_deref(),
                expert,
                &clip_emotions(&run.corpus)?,
                &train_texts,
                config.hyper.seed,
                device,
            )?;
            trainer.moe.set_compute(compute);
            let vars = trainer.vars();
            (Trainee::Moe(Box::new(trainer)), vars)
        }
        ModelShape::Preset(_) | ModelShape::Custom { .. } => {
            let (model, varmap) =
                init_model(&run.model, config.hyper.seed, device).map_err(ModelError::Candle)?;
            let vars = varmap.data().lock().expect("varmap lock").clone();
            (Trainee::Model(model.with_compute(compute)), vars)
        }
    })
}

/// The dropout probability is in [0, 1), and zero for ES-MoE experts.
fn check_dropout(config: &TrainConfig) -> Result<(), ModelError> {
    let p = config.hyper.dropout;
    if !(0.0..1.0).contains(&p) {
        return Err(ModelError::argument(
            "dropout",
            format!("{p} is not in [0, 1)"),
        ));
    }
    if p > 0.0 && matches!(config.model, ModelShape::EsMoe { .. }) {
        let why = "ES-MoE experts train without dropout (their masks are the method's own)";
        return Err(ModelError::argument("dropout", why));
    }
    Ok(())
}

impl Run {
    /// Load the data, resolve the run, build the model and optimiser, and restore the
    /// checkpoint in the output folder if there is one.
    fn start(config: &TrainConfig, device: &Device) -> Result<Self, ModelError> {
        check_dropout(config)?;
        let corpus = match &config.corpus {
            Some(c) => c.clone(),
            None => {
                tokenizer::TokenSet::open(&config.tokens)
                    .map_err(|e| ModelError::invalid(&config.tokens, e))?
                    .manifest
                    .corpus
            }
        };
        let limits = Limits {
            text_tokens: config.hyper.max_text_tokens,
            motion_tokens: config.hyper.max_motion_tokens,
        };
        let encoder = config.text_encoder.as_deref();
        let splits = ingest::corpus::split::SplitAssignment::from_dir(config.splits.as_deref())
            .map_err(|e| ModelError::argument("splits", e))?;
        let data = LmData::load(&config.tokens, &corpus, encoder, limits, &splits)?;
        let model_config = config.model.resolve(data.codebook_size(), data.text_dim)?;
        let total = data
            .steps_for_tokens(
                config.tokens_budget,
                config.hyper.batch_size,
                config.hyper.seed,
            )
            .ok_or_else(|| {
                ModelError::argument("token set", "no train clips with motion tokens")
            })?;
        let seq = SequenceShape {
            prefix: config.hyper.max_text_tokens,
            motion: config.hyper.max_motion_tokens + 1,
        };
        let run = RunConfig {
            format: FORMAT.into(),
            train: config.clone(),
            accounting: Accounting::of(&model_config, seq),
            model: model_config,
            corpus,
            text_encoder: data.encoder.clone(),
            tokenizer: data.tokens.tokenizer.clone(),
            schedule: LrSchedule {
                peak: config.hyper.lr,
                warmup: ((total as f64 * config.hyper.warmup_fraction).round() as u64).max(1),
                total,
                final_ratio: config.hyper.final_lr_ratio,
            },
            device: nn::device::device_name(device),
        };
        std::fs::create_dir_all(&config.out).map_err(|e| ModelError::io(&config.out, e))?;
        let (trainee, vars) = build_trainee(config, &run, &data, device)?;
        let (beta1, beta2) = config.betas;
        let adamw = AdamWConfig {
            beta1,
            beta2,
            eps: 1e-8,
            weight_decay: config.hyper.weight_decay,
        };
        let mut opt = AdamW::new(&vars, adamw);
        let paths = Paths::new(&config.out);
        let state = resume(&paths, &run, &vars, &mut opt, device)?;
        write_json(&paths.config, &run)?;
        Ok(Self {
            config: run,
            data,
            trainee,
            vars,
            opt,
            state,
            paths,
        })
    }

    /// One optimiser step on the next batch.
    fn step(&mut self) -> Result<TrainEvent, ModelError> {
        let (c, started) = (&self.config.train, Instant::now());
        let items = self
            .data
            .train_items(self.state.step, c.hyper.batch_size, c.hyper.seed);
        let mut batch = self.data.batch(&self.config.model, &items);
        if c.hyper.dropout > 0.0 {
            let mut rng = SplitMix64::stream(c.hyper.seed ^ DROPOUT_STREAM, self.state.step);
            batch.dropout = Some(Dropout {
                p: c.hyper.dropout as f32,
                seed: rng.next_u64(),
            });
        }
        let (loss, grads) = match &self.trainee {
            Trainee::Model(model) => model.loss_and_grads(&batch),
            Trainee::Lora(l) => l.loss_and_grads(&self.config.model, &batch),
            Trainee::Moe(t) => {
                let examples: Vec<MoeExample> = items
                    .iter()
                    .map(|item| MoeExample {
                        motion_id: &item.0.motion_id,
                        text: self.data.text_of(item),
                        tokens: &item.0.tokens,
                        ends: item.0.ends,
                    })
                    .collect();
                // Older experts are masked less and less as the step's schedule runs.
                let progress = self.state.step as f64 / self.config.schedule.total as f64;
                let p = t.moe.config.mask_probability * (1.0 - progress);
                let mut rng = SplitMix64::stream(c.hyper.seed ^ MASK_STREAM, self.state.step);
                t.loss_and_grads(&examples, Some((&mut rng, p)))
                    .map(|(l, g)| (l.total(t.moe.config.emotion_weight), g))
            }
        }
        .map_err(ModelError::Candle)?;
        let lr = self.config.schedule.at(self.state.step);
        self.opt.step(&grads, lr, Some(c.hyper.grad_clip))?;
        let tokens: u64 = items.iter().map(|(e, _)| e.targets()).sum();
        let layout = &batch.layout;
        let flops: f64 = (layout.prefix_lens.iter().zip(&layout.motion_lens))
            .map(|(&prefix, &motion)| {
                let shape = SequenceShape { prefix, motion };
                accounting::train_flops_exact(&self.config.model, shape)
            })
            .sum();
        let s = &mut self.state;
        s.step += 1;
        s.tokens_seen += tokens;
        s.data_position += c.hyper.batch_size as u64;
        s.flops_exact += flops;
        Ok(TrainEvent::Step {
            step: s.step,
            loss,
            lr,
            tokens_seen: s.tokens_seen,
            tokens_per_s: tokens as f64 / started.elapsed().as_secs_f64(),
        })
    }

    /// Evaluate the test (and validation) split and record it in `eval.json` and
    /// `evals.jsonl`; a `scheduled` evaluation may become the validation-selected one (one only
    /// because `stop_after` ends the run early may not: a resumed run would not have made it).
    fn evaluate(&mut self, train_loss: f64, scheduled: bool) -> Result<EvalRecord, ModelError> {
        // A LoRA run evaluates the base with the adapter as it now stands merged in.
        let merged;
        let (lm, expert_weights): (&dyn MotionLm, _) = match &self.trainee {
            Trainee::Model(model) => (model, None),
            Trainee::Lora(l) => {
                merged = l.model(&self.config.model).map_err(ModelError::Candle)?.0;
                (&merged, None)
            }
            Trainee::Moe(t) => (&t.moe, Some(self.expert_weights(&t.moe)?)),
        };
        let batch = self.config.train.hyper.batch_size;
        let test = evaluate(lm, &self.data, "test", batch)?;
        let val = match self.data.split("val").is_empty() {
            true => None,
            false => Some(evaluate(lm, &self.data, "val", batch)?),
        };
        let params = self.config.accounting.params;
        let mut record = EvalRecord {
            step: self.state.step,
            tokens_seen: self.state.tokens_seen,
            train_loss,
            test,
            val,
            best: None,
            unscheduled: !scheduled,
            flops_6n: accounting::budget(&self.config.model, self.state.tokens_seen as f64),
            flops_exact: self.state.flops_exact,
            n_nv: params.n_nv,
            n_v: params.n_v,
            tied: params.tied,
            expert_weights,
        };
        if let Some(c) = selection::candidate(&record, self.config.train.select_on) {
            self.state.best = Some(selection::keep_better(self.state.best.take(), c));
        }
        record.best = self.state.best.clone();
        write_json(&self.paths.eval, &record)?;
        append_json_line(&self.paths.evals, &record)?;
        Ok(record)
    }

    /// The gate's mean weight of each expert over the test clips' first captions.
    fn expert_weights(&self, moe: &EsMoe) -> Result<Vec<f64>, ModelError> {
        let items = self.data.eval_items("test");
        let mut sum = vec![0f64; moe.experts()];
        for item in &items {
            let w = moe
                .weights(self.data.text_of(item))
                .map_err(ModelError::Candle)?;
            sum.iter_mut().zip(w).for_each(|(s, w)| *s += f64::from(w));
        }
        Ok(sum.iter().map(|s| s / items.len().max(1) as f64).collect())
    }

    /// Write the weights others load, then the resume files, committed by `state.json`.
    fn checkpoint(&mut self) -> Result<(), ModelError> {
        let paths = &self.paths;
        let weights = nn::checkpoint::var_tensors(&self.vars);
        let model = match &self.trainee {
            Trainee::Model(_) => Some(weights.clone()),
            Trainee::Lora(l) => {
                let adapter = self.config.train.out.join(ADAPTER_FILE);
                save_safetensors(&weights, &adapter)
                    .map_err(|e| ModelError::invalid(&adapter, e))?;
                Some(l.model(&self.config.model).map_err(ModelError::Candle)?.1)
            }
            Trainee::Moe(t) => {
                t.moe.save(&self.config.train.out)?;
                None
            }
        };
        if let Some(model) = model {
            save_safetensors(&model, &paths.model)
                .map_err(|e| ModelError::invalid(&paths.model, e))?;
        }
        let invalid = |e: &dyn std::fmt::Display| ModelError::invalid(paths.resume.state_path(), e);
        let stage = paths.resume.stage().map_err(|e| invalid(&e))?;
        save_safetensors(&weights, &stage.join(MODEL_FILE)).map_err(|e| invalid(&e))?;
        self.opt
            .save(&stage.join(OPTIMIZER_FILE))
            .map_err(|e| invalid(&e))?;
        paths
            .resume
            .commit(self.state.step, &self.state)
            .map_err(|e| invalid(&e))
    }
}

/// A LoRA run: the adapter being trained, the frozen base weights (merged models run with
/// `compute`), the earlier adapters' `lora_A` matrices it is kept orthogonal to (with weight
/// `orthogonality`), and the model it is distilled towards (with weight `distillation`).
struct LoraRun {
    adapter: LoraAdapter,
    base: HashMap<String, Tensor>,
    compute: Compute,
    previous: Vec<HashMap<String, Tensor>>,
    orthogonality: f64,
    teacher: Option<PrefixLm>,
    distillation: f32,
}

impl LoraRun {
    /// The merged model and its weights.
    fn model(
        &self,
        config: &PrefixLmConfig,
    ) -> candle_core::Result<(PrefixLm, HashMap<String, Tensor>)> {
        self.adapter.merged_model(config, &self.base, self.compute)
    }

    /// Loss of `batch` and the adapter's gradients.
    fn loss_and_grads(
        &self,
        config: &PrefixLmConfig,
        batch: &LmBatch,
    ) -> candle_core::Result<(f32, candle_core::backprop::GradStore)> {
        let (model, merged) = self.model(config)?;
        let (loss, grads) = match &self.teacher {
            None => model.loss_and_grads(batch)?,
            Some(teacher) => {
                let soft: Vec<f32> = teacher.forward(batch)?.flatten_all()?.to_vec1()?;
                let vocab = config.vocab_size();
                model.loss_and_grads_with(batch, &|logits| {
                    Some(nn::lm_kernels::distillation(
                        logits,
                        &soft,
                        vocab,
                        &batch.targets,
                        self.distillation,
                        DISTILLATION_TEMPERATURE,
                    ))
                })?
            }
        };
        let mut grads = self.adapter.grads(&merged, &grads)?;
        let penalty = if self.previous.is_empty() {
            0.0
        } else {
            self.adapter
                .orthogonality(&self.previous, self.orthogonality, &mut grads)?
        };
        Ok((loss + penalty, grads))
    }
}
