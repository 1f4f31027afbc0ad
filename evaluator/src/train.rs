//! Training of the evaluator on a corpus: random windows of each clip's features with one
//! of its captions, symmetric InfoNCE between the two encoders plus the emotion and action
//! classifiers' cross-entropy, AdamW with warm-up and cosine decay, validation on the `val`
//! split, and checkpoints a re-run resumes from.
//!
//! ```text
//! OUT/config.json          EvaluatorFile: shape, labels, corpus (+ id), text encoder, settings, device
//! OUT/model.safetensors    weights (PyTorch names: motion.conv.0, motion.gru.weight_ih_l0_reverse…)
//! OUT/mean.npy, std.npy    the feature statistics it normalises with (the corpus's)
//! OUT/state.json           last committed step (written last); OUT/resume/<step>/ its files
//! OUT/log.jsonl            every validation
//! ```

use crate::metrics;
use crate::model::{
    corpus_id, init_evaluator, labelled_cross_entropy, EvaluatorConfig, EvaluatorFile, Padded,
    TrainedEvaluator, FORMAT, UNIT,
};
use candle_core::{Device, Tensor};
use candle_nn::VarMap;
use ingest::corpus::reader::{ClipMeta, Corpus};
use ingest::corpus::schema::FEATURE_DIM;
use motionscale_core::files::{append_json_line, check_same_run, read_json, write_json};
use motionscale_core::rng::SplitMix64;
use nn::checkpoint::{save_safetensors, ResumeFiles};
use nn::device::device_name;
use nn::optim::{AdamW, AdamWConfig, LrSchedule};
use nn::ModelError;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use text::embed::{clip_captions, CaptionEmbeddings};
use text::resolve_encoder;

/// Evaluator training settings (the CLI flags).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvaluatorTrainConfig {
    /// Corpus folder.
    pub corpus: PathBuf,
    /// Text encoder id of the caption embeddings (default: the corpus's only one).
    pub text_encoder: Option<String>,
    /// Output folder.
    pub out: PathBuf,
    /// GRU and convolution width.
    pub hidden: usize,
    /// Shared-space width.
    pub embed_dim: usize,
    /// Longest training window, in frames.
    pub max_frames: usize,
    /// Longest caption, in tokens.
    pub max_text_tokens: usize,
    /// Contrastive temperature.
    pub temperature: f64,
    /// Weight of the two classifier losses.
    pub classifier_weight: f64,
    /// Clips per batch.
    pub batch: usize,
    /// Optimiser steps.
    pub steps: u64,
    /// Peak learning rate.
    pub lr: f64,
    /// Steps between validations and checkpoints.
    pub eval_every: u64,
    /// Seed of initialisation, batches, caption choice and windows.
    pub seed: u64,
    /// Stop (with a checkpoint) after this many steps; a re-run continues.
    #[serde(skip)]
    pub stop_after: Option<u64>,
}

/// One clip as the evaluator sees it.
#[derive(Debug, Clone)]
pub struct LabelledClip {
    /// Clip id.
    pub motion_id: String,
    /// Source kind (`bvh`, `synth`…).
    pub source: String,
    /// De-normalised features, frames × 263.
    pub features: Vec<f32>,
    /// Captions.
    pub captions: Vec<String>,
    /// Emotion label.
    pub emotion: Option<String>,
    /// Action label.
    pub action: Option<String>,
}

/// Every clip of `corpus_dir` that `keep` accepts, with features, captions and labels.
pub fn corpus_clips(
    corpus_dir: &Path,
    keep: impl Fn(&ClipMeta) -> bool,
) -> Result<Vec<LabelledClip>, ModelError> {
    let corpus = Corpus::open(corpus_dir).map_err(|e| ModelError::corpus(corpus_dir, e))?;
    let meta = corpus
        .clip_metadata()
        .map_err(|e| ModelError::corpus(corpus_dir, e))?;
    let mut captions = clip_captions(corpus_dir)?;
    let features = corpus
        .features_where(|i| keep(&meta[i]))
        .map_err(|e| ModelError::corpus(corpus_dir, e))?;
    Ok(features
        .into_iter()
        .map(|(i, features)| {
            let m = &meta[i];
            LabelledClip {
                motion_id: m.motion_id.clone(),
                source: m.source.clone(),
                features,
                captions: captions.remove(&m.motion_id).unwrap_or_default(),
                emotion: m.labels.emotion.clone(),
                action: m.labels.action.clone(),
            }
        })
        .collect())
}

/// Per-token embeddings of every caption of `clips`, by caption (an `Encoder` error names the
/// first caption the corpus has no embedding for).
pub fn caption_table(
    embeddings: &CaptionEmbeddings,
    captions: impl IntoIterator<Item = String>,
) -> Result<HashMap<String, Vec<f32>>, ModelError> {
    let captions: Vec<String> = captions.into_iter().collect();
    let mut stored = embeddings.get_many(captions.iter().map(String::as_str))?;
    let mut table = HashMap::new();
    for caption in captions {
        if table.contains_key(&caption) {
            continue;
        }
        let tokens = stored.remove(&caption).ok_or_else(|| {
            ModelError::encoder(
                embeddings.encoder(),
                format!("caption {caption:?} has no embedding; run `motionscale embed-text` on the corpus"),
            )
        })?;
        table.insert(caption, tokens.embeddings);
    }
    Ok(table)
}

/// Index of `label` in `classes`.
pub fn class_of(classes: &[String], label: &Option<String>) -> Option<u32> {
    let label = label.as_ref()?;
    classes.iter().position(|c| c == label).map(|i| i as u32)
}

/// One validation of training.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Validation {
    /// Optimiser steps done.
    pub step: u64,
    /// Mean training loss since the previous validation.
    pub train_loss: f64,
    /// Top-1 R-precision on the `val` split (pools of 32, first caption, first window).
    pub r_precision_top1: f64,
    /// Emotion accuracy on labelled `val` clips.
    pub emotion_accuracy: f64,
    /// Action accuracy on labelled `val` clips.
    pub action_accuracy: f64,
}

/// What training reports as it goes.
pub enum EvaluatorEvent<'a> {
    /// A step finished with this loss.
    Step(u64, u64, f32),
    /// A validation finished.
    Validated(&'a Validation),
}

#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
struct TrainState {
    step: u64,
}

const MODEL_FILE: &str = "model.safetensors";
const OPTIMIZER_FILE: &str = "optimizer.safetensors";

/// The configuration file of an evaluator trained by `config` on `train` (its emotion and
/// action classes are the labels the train clips carry) over `text_dim`-wide caption
/// embeddings of `encoder`, on `device`.
fn evaluator_file(
    config: &EvaluatorTrainConfig,
    train: &[LabelledClip],
    text_dim: usize,
    encoder: String,
    device: &Device,
) -> Result<EvaluatorFile, ModelError> {
    let labels = |f: fn(&LabelledClip) -> &Option<String>| -> Vec<String> {
        let set: BTreeSet<String> = train.iter().filter_map(|c| f(c).clone()).collect();
        set.into_iter().collect()
    };
    Ok(EvaluatorFile {
        format: FORMAT.into(),
        config: EvaluatorConfig {
            feature_dim: FEATURE_DIM,
            text_dim,
            hidden: config.hidden,
            embed_dim: config.embed_dim,
            max_frames: config.max_frames / UNIT * UNIT,
            max_text_tokens: config.max_text_tokens,
            temperature: config.temperature,
            emotions: labels(|c| &c.emotion),
            actions: labels(|c| &c.action),
        },
        corpus: config.corpus.clone(),
        corpus_id: corpus_id(&config.corpus)?,
        text_encoder: encoder,
        train: serde_json::to_value(config).map_err(|e| ModelError::invalid(&config.out, e))?,
        device: device_name(device),
    })
}

/// Copy the corpus statistic `name` (`mean.npy`, `std.npy`) into the evaluator folder and
/// return its values.
fn copy_stats(config: &EvaluatorTrainConfig, name: &str) -> Result<Vec<f32>, ModelError> {
    let path = config.corpus.join("stats").join(name);
    let array = ingest::npy::read(&path).map_err(|e| ModelError::invalid(&path, e))?;
    let dst = config.out.join(name);
    std::fs::copy(&path, &dst).map_err(|e| ModelError::io(&dst, e))?;
    Ok(array.data.iter().map(|&v| v as f32).collect())
}

/// Train (or resume, on any device) an evaluator on `device`; returns the last validation.
pub fn train_evaluator(
    config: &EvaluatorTrainConfig,
    device: &Device,
    on_event: &mut dyn FnMut(EvaluatorEvent),
) -> Result<Validation, ModelError> {
    let encoder = resolve_encoder(&config.corpus, config.text_encoder.as_deref())?;
    let embeddings = CaptionEmbeddings::open(&config.corpus, &encoder)?;
    let mut train = corpus_clips(&config.corpus, |m| m.split == "train")?;
    // A clip without a caption has no positive pair.
    train.retain(|c| !c.captions.is_empty());
    let val = corpus_clips(&config.corpus, |m| m.split == "val")?;
    if train.len() < config.batch {
        return Err(ModelError::argument(
            "batch size",
            format!(
                "{}: {} train clips, fewer than one batch of {}",
                config.corpus.display(),
                train.len(),
                config.batch
            ),
        ));
    }
    let all_captions = train.iter().chain(&val).flat_map(|c| c.captions.clone());
    let captions = caption_table(&embeddings, all_captions)?;
    let file = evaluator_file(config, &train, embeddings.dim(), encoder, device)?;
    let net_config = file.config.clone();
    let out = &config.out;
    std::fs::create_dir_all(out).map_err(|e| ModelError::io(out, e))?;
    let (mean, std) = (
        copy_stats(config, "mean.npy")?,
        copy_stats(config, "std.npy")?,
    );

    let (net, varmap) =
        init_evaluator(net_config, config.seed, device).map_err(ModelError::Candle)?;
    let vars = varmap.data().lock().expect("varmap lock").clone();
    let adamw = AdamWConfig {
        weight_decay: 0.0,
        ..AdamWConfig::default()
    };
    let mut opt = AdamW::new(&vars, adamw);
    let resume = ResumeFiles::new(out);
    let config_path = out.join("config.json");
    let mut state = TrainState { step: 0 };
    let log = out.join("log.jsonl");
    let resumed = resume.state_path().is_file();
    if !resumed {
        let _ = std::fs::remove_file(&log);
    } else {
        // The same run may go on on another device.
        check_same_run(&config_path, "an evaluator", |old: EvaluatorFile| {
            EvaluatorFile {
                device: file.device.clone(),
                ..old
            } == file
        })?;
        state = read_json(resume.state_path())?;
        let files = resume.files(state.step);
        let (weights, moments) = (files.join(MODEL_FILE), files.join(OPTIMIZER_FILE));
        varmap
            .clone()
            .load(&weights)
            .map_err(|e| ModelError::invalid(&weights, e))?;
        opt.load(&moments)
            .map_err(|e| ModelError::invalid(&moments, e))?;
        drop_lines_after(&log, state.step)?;
    }
    let end = config
        .stop_after
        .map_or(config.steps, |s| s.min(config.steps));
    // A run with no step left keeps the device it trained on (and so its content id).
    if !resumed || state.step < end {
        write_json(&config_path, &file)?;
    }
    let evaluator = TrainedEvaluator::from_parts(net, file, mean, std);
    let schedule = LrSchedule {
        peak: config.lr,
        warmup: (config.steps / 20).max(1),
        total: config.steps,
        final_ratio: 0.1,
    };
    let mut last = None;
    let (mut loss_sum, mut loss_steps) = (0f64, 0u64);
    while state.step < end {
        let loss = train_step(&evaluator, &train, &captions, config, state.step)
            .map_err(ModelError::Candle)?;
        let (value, grads) = (
            loss.to_scalar::<f32>().map_err(ModelError::Candle)?,
            loss.backward().map_err(ModelError::Candle)?,
        );
        opt.step(&grads, schedule.at(state.step), Some(1.0))
            .map_err(|e| ModelError::invalid(out, e))?;
        state.step += 1;
        (loss_sum, loss_steps) = (loss_sum + f64::from(value), loss_steps + 1);
        on_event(EvaluatorEvent::Step(state.step, config.steps, value));
        if state.step % config.eval_every.max(1) == 0 || state.step == end {
            let mut v = validate(&evaluator, &val, &captions)?;
            v.step = state.step;
            v.train_loss = loss_sum / loss_steps.max(1) as f64;
            (loss_sum, loss_steps) = (0.0, 0);
            append_json_line(&log, &v)?;
            on_event(EvaluatorEvent::Validated(&v));
            checkpoint(&varmap, &mut opt, &resume, out, state)?;
            last = Some(v);
        }
    }
    match last {
        Some(v) => Ok(v),
        None => {
            let text = std::fs::read_to_string(&log).map_err(|e| ModelError::io(&log, e))?;
            let line = text.lines().last().unwrap_or_default();
            serde_json::from_str(line).map_err(|e| ModelError::invalid(&log, e))
        }
    }
}

fn train_frames(clip: &LabelledClip) -> usize {
    (clip.features.len() / FEATURE_DIM).max(1)
}

/// The loss of training step `step`: its batch, captions and windows are fixed by the seed.
fn train_step(
    evaluator: &TrainedEvaluator,
    clips: &[LabelledClip],
    captions: &HashMap<String, Vec<f32>>,
    config: &EvaluatorTrainConfig,
    step: u64,
) -> candle_core::Result<Tensor> {
    let per_epoch = (clips.len() / config.batch) as u64;
    let (epoch, position) = (step / per_epoch, (step % per_epoch) as usize);
    let mut order: Vec<usize> = (0..clips.len()).collect();
    SplitMix64::stream(config.seed, epoch).shuffle(&mut order);
    let mut rng = SplitMix64::stream(config.seed ^ 0x5eed, step);
    let net = &evaluator.net;
    let c = &net.config;
    let mut windows = Vec::with_capacity(config.batch);
    let mut texts = Vec::with_capacity(config.batch);
    let mut chosen = Vec::with_capacity(config.batch);
    let (mut emotion, mut action) = (Vec::new(), Vec::new());
    for &i in &order[position * config.batch..][..config.batch] {
        let clip = &clips[i];
        let frames = train_frames(clip);
        let len = frames.min(c.max_frames) / UNIT * UNIT;
        let start = rng.index(frames - len.max(1) + 1);
        windows.push(evaluator.window(&clip.features, start, len));
        let caption = clip.captions[rng.index(clip.captions.len())].clone();
        let tokens = &captions[&caption];
        texts.push(&tokens[..tokens.len().min(c.max_text_tokens * c.text_dim)]);
        chosen.push(caption);
        emotion.push(class_of(&c.emotions, &clip.emotion));
        action.push(class_of(&c.actions, &clip.action));
    }
    let device = net.device();
    let rows: Vec<&[f32]> = windows.iter().map(Vec::as_slice).collect();
    let motion = net.encode_motion(&Padded::new(&rows, c.feature_dim, device)?)?;
    let text = net.encode_text(&Padded::new(&texts, c.text_dim, device)?)?;
    let same: Vec<Vec<bool>> = chosen
        .iter()
        .map(|a| chosen.iter().map(|b| a == b).collect())
        .collect();
    let contrastive = net.contrastive_loss(&text, &motion.embedding, &same)?;
    let classifiers = (labelled_cross_entropy(&motion.emotion, &emotion)?
        + labelled_cross_entropy(&motion.action, &action)?)?;
    contrastive + (classifiers * config.classifier_weight)?
}

/// R-precision and classifier accuracy on `val` (first caption of each clip).
fn validate(
    evaluator: &TrainedEvaluator,
    val: &[LabelledClip],
    captions: &HashMap<String, Vec<f32>>,
) -> Result<Validation, ModelError> {
    let usable: Vec<&LabelledClip> = val.iter().filter(|c| !c.captions.is_empty()).collect();
    let motions: Vec<&[f32]> = usable.iter().map(|c| c.features.as_slice()).collect();
    let predicted = evaluator.embed_motions(&motions, 64)?;
    let texts: Vec<&[f32]> = usable
        .iter()
        .map(|c| captions[&c.captions[0]].as_slice())
        .collect();
    let text = evaluator.embed_texts(&texts, 64)?;
    let [top1] = metrics::r_precision::<1>(&text, &predicted.embeddings, 32);
    let c = &evaluator.net.config;
    let labelled_accuracy =
        |classes: &[String], f: fn(&LabelledClip) -> &Option<String>, pred: &[usize]| {
            let (p, t): (Vec<usize>, Vec<usize>) = usable
                .iter()
                .zip(pred)
                .filter_map(|(clip, &p)| class_of(classes, f(clip)).map(|t| (p, t as usize)))
                .unzip();
            metrics::accuracy(&p, &t)
        };
    Ok(Validation {
        step: 0,
        train_loss: 0.0,
        r_precision_top1: top1,
        emotion_accuracy: labelled_accuracy(&c.emotions, |c| &c.emotion, &predicted.emotion),
        action_accuracy: labelled_accuracy(&c.actions, |c| &c.action, &predicted.action),
    })
}

/// Write the weights others load, then the resume files, committed by `state.json`.
fn checkpoint(
    varmap: &VarMap,
    opt: &mut AdamW,
    resume: &ResumeFiles,
    out: &Path,
    state: TrainState,
) -> Result<(), ModelError> {
    let weights = nn::checkpoint::var_tensors(&varmap.data().lock().expect("varmap lock"));
    let model = out.join(MODEL_FILE);
    save_safetensors(&weights, &model).map_err(|e| ModelError::invalid(&model, e))?;
    let invalid = |e: &dyn std::fmt::Display| ModelError::invalid(resume.state_path(), e);
    let stage = resume.stage().map_err(|e| invalid(&e))?;
    save_safetensors(&weights, &stage.join(MODEL_FILE)).map_err(|e| invalid(&e))?;
    opt.save(&stage.join(OPTIMIZER_FILE))
        .map_err(|e| invalid(&e))?;
    resume.commit(state.step, &state).map_err(|e| invalid(&e))
}

/// Drop validations logged after the committed step (a kill between the log line and the
/// commit leaves one; it will be redone).
fn drop_lines_after(log: &Path, step: u64) -> Result<(), ModelError> {
    if !log.is_file() {
        return Ok(());
    }
    let text = std::fs::read_to_string(log).map_err(|e| ModelError::io(log, e))?;
    let kept: String = text
        .lines()
        .filter(|l| serde_json::from_str::<Validation>(l).is_ok_and(|v| v.step <= step))
        .map(|l| format!("{l}\n"))
        .collect();
    motionscale_core::write_atomic(log, kept.as_bytes()).map_err(|e| ModelError::io(log, e))
}
