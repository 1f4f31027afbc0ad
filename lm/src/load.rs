//! Reading a run folder that [`train()`](crate::train::train) writes: the trained model
//! ([`load_model`], [`load_lm`]) and the tokenizer of its tokens ([`run_tokenizer`]) for
//! generation and evaluation, a corpus's emotion labels for an ES-MoE run, and the files of a
//! run folder with the checkpoint a re-run resumes from. The public loaders are also reachable
//! as `lm::train::…`.

use crate::es_moe::EsMoe;
use crate::eval_record::EvalRecord;
use crate::lora::base_weights;
use crate::prefix_lm::{Compute, PrefixLm};
use crate::run_config::{ModelShape, RunConfig, TrainState};
use crate::MotionLm;
use candle_core::{DType, Device};
use candle_nn::VarBuilder;
use motionscale_core::files::{check_same_run, read_json};
use motionscale_core::write_atomic;
use nn::checkpoint::ResumeFiles;
use nn::optim::AdamW;
use nn::ModelError;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The weights file of a run folder and of each resume step.
pub(crate) const MODEL_FILE: &str = "model.safetensors";
/// The optimiser state inside a resume step.
pub(crate) const OPTIMIZER_FILE: &str = "optimizer.safetensors";

/// The trained model in `dir` (`model.safetensors`, memory-mapped on the CPU, else copied to
/// `device`) and its run config.
pub fn load_model(dir: &Path, device: &Device) -> Result<(PrefixLm, RunConfig), ModelError> {
    let run: RunConfig = read_json(&dir.join("config.json"))?;
    if matches!(run.train.model, ModelShape::EsMoe { .. }) {
        return Err(ModelError::invalid(
            dir,
            "an ES-MoE run has a model per caption, not one model file (load it with load_lm)",
        ));
    }
    let weights = dir.join(MODEL_FILE);
    // SAFETY: the checkpoint is only read; it must not change while the model lives.
    let vb = unsafe { VarBuilder::from_mmaped_safetensors(&[&weights], DType::F32, device) }
        .map_err(|e| ModelError::invalid(&weights, e))?;
    let model = PrefixLm::new(&run.model, vb).map_err(|e| ModelError::invalid(&weights, e))?;
    Ok((model, run))
}

/// The trained LM in `dir` as generation and evaluation use it (one model, or ES-MoE's
/// experts and gate on their base), on `device`, run with `compute`, and its run config.
pub fn load_lm(
    dir: &Path,
    device: &Device,
    compute: Compute,
) -> Result<(Box<dyn MotionLm>, RunConfig), ModelError> {
    let run: RunConfig = read_json(&dir.join("config.json"))?;
    if let ModelShape::EsMoe { base, moe, .. } = &run.train.model {
        let mut lm = EsMoe::load(dir, &base.join(MODEL_FILE), &run.model, *moe, device)?;
        lm.set_compute(compute);
        return Ok((Box::new(lm), run));
    }
    let (model, run) = load_model(dir, device)?;
    Ok((Box::new(model.with_compute(compute)), run))
}

/// The emotion label of every labelled clip of a corpus, by motion id.
pub(crate) fn clip_emotions(corpus_dir: &Path) -> Result<HashMap<String, String>, ModelError> {
    let corpus = ingest::corpus::reader::Corpus::open(corpus_dir)
        .map_err(|e| ModelError::corpus(corpus_dir, e))?;
    Ok(corpus
        .clip_metadata()
        .map_err(|e| ModelError::corpus(corpus_dir, e))?
        .into_iter()
        .filter_map(|m| Some((m.motion_id, m.labels.emotion?)))
        .collect())
}

/// The run's tokenizer (or the one in `dir`, which must be the same checkpoint) on `device`,
/// for decoding its tokens.
pub fn run_tokenizer(
    run: &RunConfig,
    dir: Option<&Path>,
    device: &Device,
) -> Result<tokenizer::model::MotionTokenizer, ModelError> {
    use tokenizer::model::MotionTokenizer;
    let dir = dir.unwrap_or(&run.tokenizer.dir);
    let id = MotionTokenizer::content_id(dir).map_err(|e| ModelError::invalid(dir, e))?;
    if id != run.tokenizer.id {
        return Err(ModelError::invalid(
            dir,
            format!(
                "tokenizer {id} is not the model's {} (pass --tokenizer DIR)",
                run.tokenizer.id
            ),
        ));
    }
    MotionTokenizer::load(dir, device).map_err(|e| ModelError::invalid(dir, e))
}

/// The files of a run folder.
pub(crate) struct Paths {
    pub(crate) config: PathBuf,
    pub(crate) model: PathBuf,
    pub(crate) resume: ResumeFiles,
    pub(crate) eval: PathBuf,
    pub(crate) evals: PathBuf,
}

impl Paths {
    pub(crate) fn new(out: &Path) -> Self {
        Self {
            config: out.join("config.json"),
            model: out.join(MODEL_FILE),
            resume: ResumeFiles::new(out),
            eval: out.join("eval.json"),
            evals: out.join("evals.jsonl"),
        }
    }
}

/// Restore the checkpoint in the run folder, if any, after checking it belongs to `run`;
/// evaluations recorded after it are dropped (they will be redone).
pub(crate) fn resume(
    paths: &Paths,
    run: &RunConfig,
    vars: &HashMap<String, candle_core::Var>,
    opt: &mut AdamW,
    device: &Device,
) -> Result<TrainState, ModelError> {
    let fresh = TrainState {
        step: 0,
        tokens_seen: 0,
        flops_exact: 0.0,
        data_position: 0,
        loss_sum: 0.0,
        loss_steps: 0,
        best: None,
    };
    if !paths.resume.state_path().is_file() {
        let _ = std::fs::remove_file(&paths.evals);
        return Ok(fresh);
    }
    // The same run on another device resumes: only what was computed must match. The old
    // config is read as today's (a run recorded before devices and precisions were has the
    // defaults: CPU, f32).
    // Compared as written (TrainConfig skips its per-invocation fields).
    check_same_run(&paths.config, "a run", |old: RunConfig| {
        let old = RunConfig {
            device: run.device.clone(),
            ..old
        };
        serde_json::to_value(&old).ok() == serde_json::to_value(run).ok()
    })?;
    let state: TrainState = read_json(paths.resume.state_path())?;
    let files = paths.resume.files(state.step);
    let (weights, moments) = (files.join(MODEL_FILE), files.join(OPTIMIZER_FILE));
    let saved = base_weights(&weights, device)?;
    for (name, var) in vars {
        let t = saved
            .get(name)
            .ok_or_else(|| ModelError::invalid(&weights, format!("no tensor {name}")))?;
        var.set(t).map_err(|e| ModelError::invalid(&weights, e))?;
    }
    opt.load(&moments)
        .map_err(|e| ModelError::invalid(&moments, e))?;
    if paths.evals.is_file() {
        let text =
            std::fs::read_to_string(&paths.evals).map_err(|e| ModelError::io(&paths.evals, e))?;
        let kept: String = text
            .lines()
            .filter(|l| serde_json::from_str::<EvalRecord>(l).is_ok_and(|r| r.step <= state.step))
            .map(|l| format!("{l}\n"))
            .collect();
        write_atomic(&paths.evals, kept.as_bytes()).map_err(|e| ModelError::io(&paths.evals, e))?;
    }
    Ok(state)
}
