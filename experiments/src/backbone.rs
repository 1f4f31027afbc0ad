//! The backbone of a continual run, sized by a scaling law (issue #59): the adopted law's
//! N_opt at a budget C, the model of a ladder nearest it (in log N_nv), trained for C as a
//! one-point sweep, or reused from a sweep folder whose plan has that point (trained there
//! when it is not yet). What was chosen, and from which fit, is recorded with the run.

use crate::centring::{self, Centre};
use crate::data_ladder::DataSource;
use crate::error::SweepError;
use crate::plan::{self, IsoFlopPlan, PlanPoint, PlanRequest, TrainSettings, VocabSource};
use crate::run::{run_point, Outcome};
use candle_core::Device;
use fits::data_value::{predict_data, Hours};
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
    /// The train clips it learns from: all of them, or only the captured (real) or synthetic
    /// ones (a backbone that has not seen the datasets its experts will learn).
    pub data: DataSource,
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
    /// D over one epoch of its train clips.
    #[serde(default)]
    pub epochs: f64,
    /// The train clips it learned from.
    #[serde(default)]
    pub data: DataSource,
    /// Its run folder (`…/<run_id>/train`).
    pub run: PathBuf,
    /// Whether it came from the given sweep folder.
    pub reused: bool,
}

/// The data a backbone trains on, as the laws read it.
#[derive(Debug, Clone, Copy)]
pub struct TrainData {
    /// Loss positions of one epoch of the train split (U).
    pub unique_tokens: f64,
    /// Its hours per source, in the units of the fit's hours column.
    pub hours: Hours,
}

/// N_opt at `budget` from `fit` on `data`: an IsoFLOP fit's data-constrained law at the split's
/// hours when it has one (the N_opt `predict --hours` reports), else its parabola at that
/// budget, else its N_opt ∝ C^b law, else its parametric law; a law family's compute-optimal
/// N (at U where it reads it). A fit without any of these, or whose law reads the vocabulary,
/// is refused naming the file.
pub fn n_opt_at(
    fit: &FitFile,
    path: &Path,
    budget: f64,
    data: TrainData,
) -> Result<Centre, SweepError> {
    let refuse = |why: String| SweepError::invalid(path, why);
    match fit {
        FitFile::IsoFlop(fits) => match &fits.repeated_data {
            Some(rd) => {
                let p = predict_data(rd, budget, data.hours).map_err(refuse)?;
                Ok(Centre {
                    budget,
                    n_opt: p.n_opt.value,
                    source: format!(
                        "the fit's data-constrained law at {:.3} h real + {:.3} h synthetic",
                        data.hours.real, data.hours.synth
                    ),
                })
            }
            None => centring::of_fit(fits, budget).map_err(refuse),
        },
        FitFile::Families(report) => {
            let law = family(&report.adopted);
            if law.as_ref().is_some_and(|f| f.needs().contains(&Axis::Nv)) {
                return Err(refuse(format!(
                    "the adopted law {} reads the vocabulary: a backbone is sized by a law of N and D (and U)",
                    report.adopted
                )));
            }
            let at = Point {
                u: Some(data.unique_tokens),
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
        data_fractions: match req.data {
            DataSource::All => Vec::new(),
            _ => vec![1.0],
        },
        data_source: req.data,
        data_seed: 0,
        only: Vec::new(),
    })?;
    let split = grid
        .data
        .first()
        .or(grid.train_split.as_ref())
        .ok_or_else(|| SweepError::Argument("the plan has no train split".into()))?;
    let unique = match grid.points.first() {
        Some(p) => p.unique_tokens(&grid),
        None => grid.vocabularies[0].train_tokens,
    };
    let data = TrainData {
        unique_tokens: unique as f64,
        hours: Hours {
            real: split.hours - split.synth_hours,
            synth: split.synth_hours,
        },
    };
    let centre = n_opt_at(&FitFile::read(&req.fits)?, &req.fits, req.budget, data)?;
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

/// Whether `candidate`, a point of `sweep`, trains the backbone's `point`: the same budget,
/// model and vocabulary, on every train clip of the same source, with the plan's own seed. A
/// data ladder names its whole-split runs `…-dall-1`, so run ids alone would miss them.
fn trains_point(
    sweep: &IsoFlopPlan,
    candidate: &PlanPoint,
    point: &PlanPoint,
    data: DataSource,
) -> bool {
    let same_data = match &candidate.data {
        None => data == DataSource::All,
        Some(name) => sweep
            .data
            .iter()
            .any(|s| &s.name == name && s.source == data && s.fraction == 1.0),
    };
    candidate.model == point.model
        && candidate.codebook == point.codebook
        && (candidate.budget / point.budget - 1.0).abs() < 1e-9
        && candidate.seed.is_none()
        && same_data
}

/// The law-sized backbone: reused (or trained) in `req.sweep` when its plan has the point,
/// else trained in `out` — with the sweep's training settings (its recipe) when one is given.
pub fn backbone(
    req: &BackboneRequest,
    out: &Path,
    device: &Device,
    log: &dyn Fn(&str),
) -> Result<BackboneChoice, SweepError> {
    let sweep = match &req.sweep {
        Some(dir) => Some((dir.clone(), plan::read_adopted_plan(dir)?)),
        None => None,
    };
    let req = &BackboneRequest {
        train: sweep
            .as_ref()
            .map_or_else(|| req.train.clone(), |(_, s)| s.train.clone()),
        ..req.clone()
    };
    let (plan, centre) = plan_backbone(req)?;
    let point = &plan.points[0];
    let in_sweep = sweep.and_then(|(dir, sweep)| {
        let found = sweep
            .points
            .iter()
            .find(|p| trains_point(&sweep, p, point, req.data))
            .cloned();
        found.map(|p| (dir, sweep, p))
    });
    let (runs, trained, reused) = match in_sweep {
        Some((dir, sweep, p)) => {
            let outcome = run_point(&sweep, &dir, &p, device, log)?;
            (dir, p, matches!(outcome, Outcome::AlreadyDone(_)))
        }
        None => {
            plan::adopt_plan(&plan, out)?;
            run_point(&plan, out, point, device, log)?;
            (out.to_path_buf(), point.clone(), false)
        }
    };
    Ok(BackboneChoice {
        fits: req.fits.clone(),
        law: centre.source,
        budget: req.budget,
        n_opt: centre.n_opt,
        model: trained.model,
        n_nv: trained.n_nv,
        tokens: trained.tokens,
        epochs: trained.epochs,
        data: req.data,
        run: crate::results::run_dir(&runs, &trained.run_id).join("train"),
        reused,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The committed plan at `docs/results/<rel>`.
    fn committed_plan(rel: &str) -> IsoFlopPlan {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../docs/results")
            .join(rel);
        IsoFlopPlan::read(&path).unwrap()
    }

    /// The runs of `ladder` that train the backbone `model` at `budget` on `data`.
    fn backbone_runs(
        ladder: &IsoFlopPlan,
        budget: f64,
        model: &str,
        data: DataSource,
    ) -> Vec<String> {
        let template = ladder.points.iter().find(|p| p.model == model).unwrap();
        let point = PlanPoint {
            run_id: plan::run_id(budget, model, 1024),
            budget,
            data: None,
            seed: None,
            ..template.clone()
        };
        ladder
            .points
            .iter()
            .filter(|p| trains_point(ladder, p, &point, data))
            .map(|p| p.run_id.clone())
            .collect()
    }

    /// The data-law ladder's plan (101 points: three nested fractions, seed repeats) holds
    /// the backbone's point once, as its whole-split run `…-dall-1`; halves, quarters, seed
    /// repeats, other budgets and other models are not it.
    #[test]
    fn a_data_ladder_run_on_the_whole_split_is_the_backbone() {
        let ladder = committed_plan("data-law/recipe/ladder/plan-7.toml");
        let find = |budget, model| backbone_runs(&ladder, budget, model, DataSource::All);
        assert_eq!(find(3e12, "96x1"), ["c3e12-96x1-v1024-dall-1"]);
        assert_eq!(find(3e13, "256x4"), ["c3e13-256x4-v1024-dall-1"]);
        assert_eq!(find(1e13, "128x2"), ["c1e13-128x2-v1024-dall-1"]);
        assert!(find(3e11, "96x1").is_empty(), "no such budget");
        assert!(
            find(1e14, "512x4").is_empty(),
            "halves, quarters and seed repeats only"
        );
    }

    /// The forgetting ladder's plan extends the data ladder with backbones on the captured
    /// clips only: a backbone on real data is its `…-dreal-1` run, never the `…-dall-1` one.
    #[test]
    fn a_backbone_on_one_source_is_that_sources_run() {
        let ladder = committed_plan("continual/ladder/plan-10.toml");
        let find = |budget, model, data| backbone_runs(&ladder, budget, model, data);
        assert_eq!(
            find(1e13, "128x4", DataSource::Real),
            ["c1e13-128x4-v1024-dreal-1"]
        );
        assert_eq!(
            find(1e13, "128x4", DataSource::All),
            ["c1e13-128x4-v1024-dall-1"]
        );
        assert!(find(3e13, "192x4", DataSource::Real).is_empty());
        assert!(find(1e13, "128x4", DataSource::Synth).is_empty());
    }

    /// An IsoFLOP fit with a data-constrained law sizes the backbone by that law at the split's
    /// hours, as `predict --hours` does (the data-law study's stage-3 fit: 1.759e5 at 3·10¹²,
    /// 2.040e6 at 3·10¹³ on 6.083 h real + 5.679 h synthetic), not by the budget's parabola.
    #[test]
    fn a_data_constrained_fit_sizes_by_its_law() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../docs/results/data-law/recipe/ladder/stage3/dc-stopping/fits.json");
        let fit = FitFile::read(&path).unwrap();
        let data = TrainData {
            unique_tokens: 216_640.0,
            hours: Hours {
                real: 6.083222,
                synth: 5.678889,
            },
        };
        for (budget, n_opt) in [(3e12, 1.759e5), (3e13, 2.040e6)] {
            let centre = n_opt_at(&fit, &path, budget, data).unwrap();
            assert!((centre.n_opt / n_opt - 1.0).abs() < 1e-3, "{centre:?}");
            assert!(centre.source.contains("data-constrained law"), "{centre:?}");
        }
    }
}
