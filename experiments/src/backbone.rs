//! The backbone of a continual run, sized by a scaling law (issue #59): the adopted law's
//! N_opt at a budget C, the model of a ladder nearest it (in log N_nv), trained for C as a
//! one-point sweep, or reused from a sweep folder whose plan has that point (trained there
//! when it is not yet). What was chosen, and from which fit, is recorded with the run.

use crate::centring::{self, Centre};
use crate::error::SweepError;
use crate::plan::{self, IsoFlopPlan, PlanPoint, PlanRequest, TrainSettings, VocabSource};
use crate::run::{run_point, Outcome};
use candle_core::Device;
use fits::family::predict::predict_at;
use fits::family::{family, Axis, Point};
use fits::fit_file::FitFile;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// What a law-sized backbone needs.
#[derive(Debug, Clone)]
pub struct BackboneRequest {
    /// `fit`'s fits.json or laws.json.
    pub fits: PathBuf,
    /// Compute budget C in FLOPs.
    pub budget: f64,
    /// The ladder to choose from (presets, `cpu`, `scamo` or shapes).
    pub models: Vec<String>,
    /// Corpus with the caption embeddings.
    pub corpus: PathBuf,
    /// Token set of the whole corpus (the continual run's).
    pub tokens: PathBuf,
    /// A sweep folder that may hold the chosen point already.
    pub sweep: Option<PathBuf>,
    /// The backbone's training settings.
    pub train: TrainSettings,
}

/// The backbone chosen, recorded in the continual run's config and summary.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BackboneChoice {
    /// The fit it was sized by.
    pub fits: PathBuf,
    /// Where the N_opt came from (the law, or the parabola at this budget).
    pub law: String,
    /// Budget C.
    pub budget: f64,
    /// The fit's N_opt at C.
    pub n_opt: f64,
    /// The ladder model nearest it.
    pub model: String,
    /// Its non-vocabulary parameters.
    pub n_nv: u64,
    /// Its training tokens D = C / (6·N).
    pub tokens: u64,
    /// Its run folder (`…/<run_id>/train`).
    pub run: PathBuf,
    /// Whether it came from the given sweep folder.
    pub reused: bool,
}

/// N_opt at `budget` from `fit`: an IsoFLOP fit's parabola at that budget, else its
/// N_opt ∝ C^b law, else its parametric law; a law family's compute-optimal N (at `unique`
/// tokens where it reads them). A fit without any of these, or whose law reads the vocabulary,
/// is refused naming the file.
pub fn n_opt_at(
    fit: &FitFile,
    path: &Path,
    budget: f64,
    unique: f64,
) -> Result<Centre, SweepError> {
    let refuse = |why: String| SweepError::invalid(path, why);
    match fit {
        FitFile::IsoFlop(fits) => centring::of_fit(fits, budget).map_err(refuse),
        FitFile::Families(report) => {
            let law = family(&report.adopted);
            if law.as_ref().is_some_and(|f| f.needs().contains(&Axis::Nv)) {
                return Err(refuse(format!(
                    "the adopted law {} reads the vocabulary: a backbone is sized by a law of N and D (and U)",
                    report.adopted
                )));
            }
            let at = Point {
                u: Some(unique),
                ..Point::default()
            };
            let p = predict_at(report, budget, at).map_err(|e| refuse(e.to_string()))?;
            Ok(Centre {
                budget,
                n_opt: p.n.value,
                source: format!("the adopted law {}", p.law),
            })
        }
    }
}

/// The one-point plan of the ladder model nearest the fit's N_opt at the budget, and that
/// N_opt.
pub fn plan_backbone(req: &BackboneRequest) -> Result<(IsoFlopPlan, Centre), SweepError> {
    let codebook = tokenizer::TokenSet::open(&req.tokens)
        .map_err(|e| SweepError::invalid(&req.tokens, e))?
        .manifest
        .tokenizer
        .nominal_codebook;
    let grid = plan::plan(&PlanRequest {
        corpus: req.corpus.clone(),
        text_encoder: None,
        budgets: vec![req.budget],
        models: req.models.clone(),
        vocabularies: vec![(
            codebook,
            VocabSource::TokenSet {
                dir: req.tokens.clone(),
            },
        )],
        train: req.train.clone(),
        centring: None,
        max_epochs: None,
        extend: None,
        repeat: Vec::new(),
        repeat_seeds: Vec::new(),
        data_fractions: Vec::new(),
        data_source: crate::data_ladder::DataSource::All,
        data_seed: 0,
        only: Vec::new(),
    })?;
    let unique = grid.vocabularies[0].train_tokens as f64;
    let centre = n_opt_at(&FitFile::read(&req.fits)?, &req.fits, req.budget, unique)?;
    let distance = |p: &PlanPoint| (p.n_nv as f64 / centre.n_opt).ln().abs();
    let nearest = grid
        .points
        .iter()
        .min_by(|a, b| distance(a).total_cmp(&distance(b)))
        .cloned()
        .ok_or_else(|| SweepError::Argument("no model to choose a backbone from".into()))?;
    let mut plan = grid;
    plan.points = vec![PlanPoint {
        index: 0,
        ..nearest
    }];
    Ok((plan, centre))
}

/// The law-sized backbone: reused (or trained) in `req.sweep` when its plan has the point,
/// else trained in `out`.
pub fn backbone(
    req: &BackboneRequest,
    out: &Path,
    device: &Device,
    log: &dyn Fn(&str),
) -> Result<BackboneChoice, SweepError> {
    let (plan, centre) = plan_backbone(req)?;
    let point = &plan.points[0];
    let in_sweep = match &req.sweep {
        Some(dir) => {
            let sweep = plan::read_adopted_plan(dir)?;
            let found = sweep
                .points
                .iter()
                .find(|p| p.run_id == point.run_id)
                .cloned();
            found.map(|p| (dir.clone(), sweep, p))
        }
        None => None,
    };
    let (runs, reused) = match in_sweep {
        Some((dir, sweep, p)) => {
            let outcome = run_point(&sweep, &dir, &p, device, log)?;
            (dir, matches!(outcome, Outcome::AlreadyDone(_)))
        }
        None => {
            plan::adopt_plan(&plan, out)?;
            run_point(&plan, out, point, device, log)?;
            (out.to_path_buf(), false)
        }
    };
    Ok(BackboneChoice {
        fits: req.fits.clone(),
        law: centre.source,
        budget: req.budget,
        n_opt: centre.n_opt,
        model: point.model.clone(),
        n_nv: point.n_nv,
        tokens: point.tokens,
        run: crate::results::run_dir(&runs, &point.run_id).join("train"),
        reused,
    })
}
