//! The active sweep planner: a posterior over what the IsoFLOP pipeline extrapolates to a
//! target budget C* (log10 N_opt, or the loss at N_opt), and the runs that shrink its interval
//! most per FLOP ("Spend Less, Fit Better", arXiv 2604.22753: sequential design by expected
//! reduction of the extrapolation's uncertainty).
//!
//! The posterior is a residual bootstrap of the pipeline `fit` runs: each budget's envelope
//! parabola is refitted on its fitted values plus residuals drawn from the pooled parabola
//! residuals — the parabolas' misfit, several times the seed noise in our sweeps, so seed noise
//! alone would understate it — the interior vertices give the law in log C, and the law's own
//! scatter at C* is added as s·t_dof·√(1 + 1/k + (x* − x̄)²/Sxx) (for a loss law with a floor
//! or curvature, its delta-method analogue). A proposal's value is the expected interval width
//! after it, over its predictive outcomes (3-point Gauss–Hermite), per FLOP it costs; a budget
//! without a parabola is entered with three sizes straddling its predicted vertex's interval,
//! since fewer sizes there change nothing.

use crate::isoflop::{envelope, group_budget, group_rows};
use crate::loss_shape::Form;
use crate::ols::{distinct, t95, Line, Parabola, Z95};
use crate::FitError;
use motionscale_core::rng::SplitMix64;
use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// An interval the draws cannot bound (no law in over 2.5% of them) counts as this wide.
pub const WIDTH_CAP: f64 = 10.0;

/// Budgets within this many decades are one budget group (as `fit`'s default).
pub const GROUP_TOL_DEX: f64 = 0.05;

/// The budget groups of `c` (within [`GROUP_TOL_DEX`]), ascending.
pub fn budget_groups(c: &[f64]) -> Vec<f64> {
    group_rows(c, None, GROUP_TOL_DEX)
        .iter()
        .map(|g| group_budget(c, g))
        .collect()
}

/// The quantity the planner narrows, both extrapolated to the target budget.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Target {
    /// log10 of the compute-optimal N (the `n_opt_vs_c` law), in decades.
    NOpt,
    /// The loss at N_opt (the law of [`Settings::loss_form`]), in the loss column's units.
    Loss,
}

impl Target {
    /// Parses `n_opt` or `loss`.
    pub fn parse(name: &str) -> Result<Self, FitError> {
        match name {
            "n_opt" => Ok(Self::NOpt),
            "loss" => Ok(Self::Loss),
            other => Err(FitError::UnknownChoice {
                flag: "--target",
                given: other.into(),
                expected: "n_opt or loss (hour_value is `sweep plan --next`'s only)",
            }),
        }
    }

    /// The name `parse` reads.
    pub fn name(self) -> &'static str {
        match self {
            Self::NOpt => "n_opt",
            Self::Loss => "loss",
        }
    }

    /// " (the … law)" after a `loss` target's name, naming the form it extrapolates by.
    pub fn by_law(self, form: Form) -> String {
        match self {
            Self::Loss => format!(" (the {} law)", form.name()),
            Self::NOpt => String::new(),
        }
    }

    /// Units of the target's interval width.
    pub fn unit(self) -> &'static str {
        match self {
            Self::NOpt => "decades",
            Self::Loss => "nats",
        }
    }

    /// What one budget's parabola contributes to the law.
    fn of_vertex(self, p: &Parabola) -> f64 {
        match self {
            Self::NOpt => p.vertex(),
            Self::Loss => p.at(p.vertex()),
        }
    }
}

/// What `sweep plan --next` narrows: an IsoFLOP target, or the value of one more hour of
/// captured motion (`hour_design`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Goal {
    /// N_opt or the loss at N_opt (the IsoFLOP bootstrap).
    IsoFlop(Target),
    /// The loss change of +1 h of captured motion (the data-constrained law's Laplace posterior).
    HourValue,
}

impl Goal {
    /// The name `parse` reads.
    pub fn name(self) -> &'static str {
        match self {
            Self::IsoFlop(t) => t.name(),
            Self::HourValue => "hour_value",
        }
    }

    /// Parses `n_opt`, `loss` or `hour_value`.
    pub fn parse(name: &str) -> Result<Self, FitError> {
        match name {
            "hour_value" => Ok(Self::HourValue),
            other => Target::parse(other)
                .map(Self::IsoFlop)
                .map_err(|_| FitError::UnknownChoice {
                    flag: "--target",
                    given: other.into(),
                    expected: "n_opt, loss or hour_value",
                }),
        }
    }
}

/// One trained run as the planner sees it.
#[derive(Debug, Clone, PartialEq)]
pub struct Observation {
    /// Budget C of its group.
    pub budget: f64,
    /// Model size N.
    pub n: f64,
    /// Vocabulary size, when runs differ in it.
    pub vocab: Option<f64>,
    /// Loss (the fit's loss column).
    pub loss: f64,
}

/// A run the planner may propose.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    /// Run id.
    pub id: String,
    /// Budget C.
    pub budget: f64,
    /// Model size N.
    pub n: f64,
    /// Vocabulary size, when runs differ in it.
    pub vocab: Option<f64>,
    /// FLOPs it costs.
    pub cost: f64,
}

/// Posterior settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Settings {
    /// Bootstrap draws.
    pub draws: usize,
    /// Seed of the draws (draw i uses stream i, the same for every candidate compared).
    pub seed: u64,
    /// Smallest loss noise assumed (the seed noise), used while no parabola has residuals.
    pub misfit_floor: f64,
    /// The form of the loss law the `loss` target extrapolates (`fit` chooses it by
    /// leave-one-budget-out error; the straight log law by default).
    pub loss_form: Form,
}

impl Default for Settings {
    fn default() -> Self {
        Self {
            draws: 200,
            seed: 0,
            misfit_floor: 0.01,
            loss_form: Form::Log,
        }
    }
}

/// JSON has no infinities (they are written as null): null reads back as +∞.
pub fn infinite_if_null<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::INFINITY))
}

/// null reads back as −∞ (a lower bound).
fn neg_infinite_if_null<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NEG_INFINITY))
}

/// null reads back as NaN (a median between −∞ and +∞).
fn nan_if_null<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// The target's posterior: median and 95% interval over the bootstrap draws.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Posterior {
    /// Median.
    #[serde(deserialize_with = "nan_if_null")]
    pub median: f64,
    /// 2.5% quantile (draws without a law count as −∞ or +∞).
    #[serde(deserialize_with = "neg_infinite_if_null")]
    pub low: f64,
    /// 97.5% quantile.
    #[serde(deserialize_with = "infinite_if_null")]
    pub high: f64,
    /// high − low (infinite when the draws cannot bound it).
    #[serde(deserialize_with = "infinite_if_null")]
    pub width: f64,
    /// Draws that had a law (three interior vertices).
    pub valid: usize,
    /// Draws made.
    pub draws: usize,
}

impl Posterior {
    /// The width, at most [`WIDTH_CAP`].
    pub fn capped_width(&self) -> f64 {
        self.width.min(WIDTH_CAP)
    }

    /// What the planner narrows: the capped width plus [`WIDTH_CAP`] × the share of draws
    /// without a law, so that while the interval is unbounded the runs that make the law
    /// exist in more draws still count.
    pub fn spread(&self) -> f64 {
        let missing = (self.draws - self.valid) as f64 / self.draws.max(1) as f64;
        self.capped_width() + WIDTH_CAP * missing
    }
}

/// One budget group of the observations.
#[derive(Debug, Clone)]
struct BudgetFit {
    /// log10 C.
    x: f64,
    /// log10 N of the envelope (lowest loss per N), ascending.
    lx: Vec<f64>,
    /// The envelope's parabola (three distinct N or more).
    parabola: Option<Parabola>,
}

impl BudgetFit {
    /// The parabola when convex.
    fn convex(&self) -> Option<&Parabola> {
        self.parabola.as_ref().filter(|p| p.curvature() > 0.0)
    }

    /// The parabola when its vertex is a minimum inside the sampled sizes.
    fn interior(&self) -> Option<&Parabola> {
        let (lo, hi) = (self.lx[0], self.lx[self.lx.len() - 1]);
        self.convex().filter(|p| (lo..=hi).contains(&p.vertex()))
    }
}

/// Where budgets without a parabola are predicted from: the vertices' lines in log C.
#[derive(Debug, Clone)]
struct Surrogate {
    vertex: Line,
    loss: Line,
    curvature: f64,
    sd: f64,
}

/// The fitted state behind draws and predictions.
#[derive(Debug, Clone)]
struct Model {
    budgets: Vec<BudgetFit>,
    /// Pooled parabola residuals, scaled by √(n / dof).
    pool: Vec<f64>,
    /// Predictive noise of one run: the residuals' RMS, at least the floor.
    sigma: f64,
    floor: f64,
    /// (vocabulary, log10 C, mean excess over that budget's parabola).
    offsets: Vec<(f64, f64, f64)>,
    /// The SD of every excess in `offsets`: a vocabulary's offset SD where its own line has
    /// no residual degrees of freedom.
    offset_spread: f64,
    surrogate: Option<Surrogate>,
}

impl Model {
    fn new(obs: &[Observation], floor: f64) -> Self {
        let c: Vec<f64> = obs.iter().map(|o| o.budget).collect();
        let budgets: Vec<BudgetFit> = group_rows(&c, None, GROUP_TOL_DEX)
            .iter()
            .map(|rows| {
                let n: Vec<f64> = rows.iter().map(|&i| obs[i].n).collect();
                let l: Vec<f64> = rows.iter().map(|&i| obs[i].loss).collect();
                let (lx, y): (Vec<f64>, Vec<f64>) = envelope(&n, &l)
                    .iter()
                    .map(|p| (p[0].log10(), p[1]))
                    .unzip();
                let parabola = Parabola::fit(&lx, &y);
                BudgetFit {
                    x: group_budget(&c, rows).log10(),
                    lx,
                    parabola,
                }
            })
            .collect();
        let pool: Vec<f64> = budgets
            .iter()
            .filter_map(|b| b.parabola.as_ref().filter(|p| p.ols.dof > 0))
            .flat_map(|p| {
                let scale = (p.ols.residuals.len() as f64 / p.ols.dof as f64).sqrt();
                p.ols.residuals.iter().map(move |r| r * scale)
            })
            .collect();
        let rms = (pool.iter().map(|r| r * r).sum::<f64>() / pool.len().max(1) as f64).sqrt();
        let mut model = Self {
            budgets,
            pool,
            sigma: rms.max(floor),
            floor,
            offsets: Vec::new(),
            offset_spread: 0.0,
            surrogate: None,
        };
        model.offsets = model.vocabulary_offsets(obs);
        let excess: Vec<f64> = model.offsets.iter().map(|o| o.2).collect();
        let mean = excess.iter().sum::<f64>() / excess.len().max(1) as f64;
        let square = excess.iter().map(|e| (e - mean).powi(2)).sum::<f64>();
        model.offset_spread = (square / excess.len().max(1) as f64).sqrt();
        model.surrogate = model.surrogate();
        model
    }

    /// Each vocabulary's loss above its budget's parabola, by budget: (vocabulary, log10 C,
    /// mean excess there). The best vocabulary changes with the budget, so the excess is read
    /// off a line in log C (`offset`).
    fn vocabulary_offsets(&self, obs: &[Observation]) -> Vec<(f64, f64, f64)> {
        let mut sums: Vec<(f64, f64, f64, usize)> = Vec::new();
        for o in obs {
            let Some(v) = o.vocab else { continue };
            let Some(b) = self.budget_at(o.budget) else {
                continue;
            };
            let Some(p) = b.convex() else { continue };
            let excess = o.loss - p.at(o.n.log10());
            match sums.iter_mut().find(|s| s.0 == v && s.1 == b.x) {
                Some(s) => (s.2, s.3) = (s.2 + excess, s.3 + 1),
                None => sums.push((v, b.x, excess, 1)),
            }
        }
        sums.into_iter()
            .map(|(v, x, s, k)| (v, x, s / k as f64))
            .collect()
    }

    fn surrogate(&self) -> Option<Surrogate> {
        let inner: Vec<(f64, &Parabola)> = self
            .budgets
            .iter()
            .filter_map(|b| Some((b.x, b.interior()?)))
            .collect();
        let x: Vec<f64> = inner.iter().map(|(x, _)| *x).collect();
        let vertex: Vec<f64> = inner.iter().map(|(_, p)| p.vertex()).collect();
        let loss: Vec<f64> = inner.iter().map(|(_, p)| p.at(p.vertex())).collect();
        let mut curvatures: Vec<f64> = inner.iter().map(|(_, p)| p.curvature()).collect();
        curvatures.sort_by(f64::total_cmp);
        let loss = Line::fit(&x, &loss)?;
        let sd = match loss.ols.dof {
            0 => self.sigma,
            dof => (loss.ols.residuals.iter().map(|r| r * r).sum::<f64>() / dof as f64).sqrt(),
        };
        Some(Surrogate {
            vertex: Line::fit(&x, &vertex)?,
            loss,
            curvature: curvatures[curvatures.len() / 2],
            sd: sd.hypot(self.sigma),
        })
    }

    fn budget_at(&self, c: f64) -> Option<&BudgetFit> {
        let x = c.log10();
        self.budgets
            .iter()
            .find(|b| (b.x - x).abs() <= GROUP_TOL_DEX)
    }

    /// The expected excess of `vocab` at `c` and its SD: the line in log C through its
    /// budgets' excess (their mean with one budget; 0 for a vocabulary not seen yet). The SD
    /// is the line's prediction interval at `c` as a normal (its residual scatter times the
    /// leverage there, widened to the Student-t's 95% interval on the line's few degrees of
    /// freedom), else the spread of every excess seen times the leverage. Read decades past
    /// its budgets the line itself is uncertain: with its residual SD alone, K = 4,096 at 10¹³
    /// came out 6 SDs from its prediction.
    fn offset(&self, vocab: Option<f64>, c: f64) -> (f64, f64) {
        let Some(v) = vocab else { return (0.0, 0.0) };
        let (x, y): (Vec<f64>, Vec<f64>) = self
            .offsets
            .iter()
            .filter(|o| o.0 == v)
            .map(|o| (o.1, o.2))
            .unzip();
        match Line::fit(&x, &y) {
            Some(line) => {
                let scatter = match line.ols.dof {
                    0 => self.offset_spread,
                    dof => {
                        let rss: f64 = line.ols.residuals.iter().map(|r| r * r).sum();
                        // The normal with the 95% interval of the line's Student-t prediction.
                        (rss / dof as f64).sqrt() * t95(dof) / Z95
                    }
                };
                (line.at(c.log10()), scatter * lever(&x, c.log10()))
            }
            None => (
                y.iter().sum::<f64>() / y.len().max(1) as f64,
                self.offset_spread,
            ),
        }
    }

    /// Predictive mean and SD of a run's loss; `None` when nothing predicts its budget yet.
    fn predict(&self, c: &Candidate) -> Option<(f64, f64)> {
        let u = c.n.log10();
        let (offset, offset_sd) = self.offset(c.vocab, c.budget);
        if let Some(p) = self.budget_at(c.budget).and_then(|b| b.convex()) {
            return Some((p.at(u) + offset, self.sigma.hypot(offset_sd)));
        }
        let s = self.surrogate.as_ref()?;
        let x = c.budget.log10();
        let mean = s.loss.at(x) + s.curvature * (u - s.vertex.at(x)).powi(2) + offset;
        Some((mean, s.sd.hypot(offset_sd)))
    }

    fn noise(&self, rng: &mut SplitMix64) -> f64 {
        match self.pool.len() {
            0 => self.floor * rng.normal(),
            len => self.pool[rng.index(len)],
        }
    }

    /// One bootstrap draw of the target at log10 C* = `x_star` (the loss by `form`); `None`
    /// without a law.
    fn draw(&self, target: Target, form: Form, x_star: f64, rng: &mut SplitMix64) -> Option<f64> {
        let mut points: Vec<(f64, f64)> = Vec::new();
        for b in &self.budgets {
            let Some(p) = &b.parabola else { continue };
            let y: Vec<f64> = b.lx.iter().map(|&u| p.at(u) + self.noise(rng)).collect();
            let refit = BudgetFit {
                x: b.x,
                lx: b.lx.clone(),
                parabola: Parabola::fit(&b.lx, &y),
            };
            if let Some(q) = refit.interior() {
                points.push((b.x, target.of_vertex(q)));
            }
        }
        if points.len() < 3 {
            return None;
        }
        let (x, y): (Vec<f64>, Vec<f64>) = points.into_iter().unzip();
        if target == Target::Loss && form != Form::Log {
            return form_draw(form, &x, &y, x_star, rng);
        }
        let line = Line::fit(&x, &y)?;
        let dof = line.ols.dof;
        let s = (line.ols.residuals.iter().map(|r| r * r).sum::<f64>() / dof as f64).sqrt();
        Some(line.at(x_star) + s * lever(&x, x_star) * student_t(rng, dof))
    }
}

/// How much a new point at `x_star` of a line fitted at `x` scatters, in residual SDs:
/// √(1 + 1/k + (x* − x̄)²/Sxx), the line's own uncertainty there beside the point's.
fn lever(x: &[f64], x_star: f64) -> f64 {
    let k = x.len() as f64;
    let mean = x.iter().sum::<f64>() / k;
    let sxx: f64 = x.iter().map(|v| (v - mean).powi(2)).sum();
    (1.0 + 1.0 / k + (x_star - mean).powi(2) / sxx).sqrt()
}

/// One draw of the loss at `x_star` from `form` fitted on the vertices (`x`, `y`), with the
/// form's own scatter there by the delta method, s·t_dof·√(1 + gᵀ(JᵀJ)⁻¹g) (J: the gradients at
/// the vertices, g: at `x_star`; for the line this is the line's formula). `None` without a
/// vertex to spare beyond the form's parameters.
fn form_draw(form: Form, x: &[f64], y: &[f64], x_star: f64, rng: &mut SplitMix64) -> Option<f64> {
    let (p, centre) = form.fit(x, y)?;
    let dof = x.len().checked_sub(form.params()).filter(|&d| d > 0)?;
    let rss: f64 = x
        .iter()
        .zip(y)
        .map(|(&u, &v)| (v - form.at(&p, centre, u)).powi(2))
        .sum();
    let rows: Vec<Vec<f64>> = x.iter().map(|&u| form.gradient(&p, centre, u)).collect();
    let jac = DMatrix::from_fn(x.len(), form.params(), |i, j| rows[i][j]);
    let g = DVector::from_vec(form.gradient(&p, centre, x_star));
    let lever = 1.0 + g.dot(&((jac.transpose() * &jac).try_inverse()? * &g));
    let s = (rss / dof as f64).sqrt();
    Some(form.at(&p, centre, x_star) + s * lever.max(1.0).sqrt() * student_t(rng, dof))
}

/// A Student-t draw with `dof` degrees of freedom (z / √(χ²/dof)).
fn student_t(rng: &mut SplitMix64, dof: usize) -> f64 {
    let chi2: f64 = (0..dof).map(|_| rng.normal().powi(2)).sum();
    rng.normal() / (chi2 / dof as f64).sqrt()
}

/// The `q` quantile (linear interpolation) of sorted `v`.
fn quantile(v: &[f64], q: f64) -> f64 {
    let at = q * (v.len() - 1) as f64;
    let (i, f) = (at.floor() as usize, at.fract());
    match v.get(i + 1) {
        Some(&next) if f > 0.0 && next != v[i] => v[i] + f * (next - v[i]),
        _ => v[i],
    }
}

/// The posterior of `target` at budget `c_star` given `obs`.
pub fn posterior(obs: &[Observation], target: Target, c_star: f64, s: &Settings) -> Posterior {
    posterior_of(&Model::new(obs, s.misfit_floor), target, c_star, s)
}

fn posterior_of(model: &Model, target: Target, c_star: f64, s: &Settings) -> Posterior {
    let x_star = c_star.log10();
    let mut values = Vec::with_capacity(s.draws);
    let mut missing = 0;
    for i in 0..s.draws {
        let mut rng = SplitMix64::stream(s.seed, i as u64);
        match model.draw(target, s.loss_form, x_star, &mut rng) {
            Some(v) if v.is_finite() => values.push(v),
            _ => missing += 1,
        }
    }
    let valid = values.len();
    // A draw without a law could be anywhere: half below every value, half above.
    values.extend((0..missing).map(|i| match i % 2 {
        0 => f64::NEG_INFINITY,
        _ => f64::INFINITY,
    }));
    values.sort_by(f64::total_cmp);
    if values.is_empty() {
        values.push(f64::NAN);
    }
    let (low, high) = (quantile(&values, 0.025), quantile(&values, 0.975));
    Posterior {
        median: quantile(&values, 0.5),
        low,
        high,
        width: high - low,
        valid,
        draws: s.draws,
    }
}

/// One proposal: runs trained together, what they cost and what they are expected to buy.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Proposal {
    /// Indices into the candidates.
    pub runs: Vec<usize>,
    /// FLOPs.
    pub cost: f64,
    /// The interval's spread before it ([`Posterior::spread`]).
    pub width_before: f64,
    /// Expected spread after it.
    pub expected_width: f64,
    /// Why it was chosen.
    pub why: String,
}

/// Sizes further than this from a budget's vertex (in decades; its own interior minimum, else
/// the law's vertex there) are not proposed there: a parabola describes the loss near its
/// minimum only, and far out its prediction — and so the value it assigns a run — is not to be
/// trusted.
pub const SIZE_WINDOW_DEX: f64 = 0.75;

/// Gauss–Hermite nodes (in predictive SDs) and weights for the expectation over outcomes.
const NODES: [(f64, f64); 3] = [
    (-1.732_050_807_568_877_2, 1.0 / 6.0),
    (0.0, 2.0 / 3.0),
    (1.732_050_807_568_877_2, 1.0 / 6.0),
];

/// The runs that, trained in order, most reduce the target's interval per FLOP: up to `k`
/// proposals from `candidates` within `max_compute` FLOPs, each chosen after the earlier ones
/// are imagined trained at their predicted loss; fewer when no run is expected to narrow it.
pub fn propose(
    obs: &[Observation],
    candidates: &[Candidate],
    target: Target,
    c_star: f64,
    k: usize,
    max_compute: f64,
    s: &Settings,
) -> Vec<Proposal> {
    let q = Question { target, c_star, s };
    let mut known = obs.to_vec();
    let mut open: Vec<usize> = (0..candidates.len()).collect();
    let mut spent = 0.0;
    let mut out = Vec::new();
    while out.len() < k {
        let model = Model::new(&known, s.misfit_floor);
        let Some(best) = best_action(&model, &known, candidates, &open, max_compute - spent, &q)
        else {
            break;
        };
        for &i in &best.runs {
            let (mean, _) = model
                .predict(&candidates[i])
                .expect("scored actions are predictable");
            known.push(observed(&candidates[i], mean));
        }
        open.retain(|i| !best.runs.contains(i));
        spent += best.cost;
        out.push(best);
    }
    out
}

/// What the planner expects of each candidate under the model of `obs`: the predictive mean
/// and SD of its loss by which `propose` scores it; `None` where nothing predicts its budget.
pub fn predictive(
    obs: &[Observation],
    candidates: &[Candidate],
    floor: f64,
) -> Vec<Option<(f64, f64)>> {
    let model = Model::new(obs, floor);
    candidates.iter().map(|c| model.predict(c)).collect()
}

/// The observation a candidate gives with `loss`.
pub fn observed(c: &Candidate, loss: f64) -> Observation {
    Observation {
        budget: c.budget,
        n: c.n,
        vocab: c.vocab,
        loss,
    }
}

/// What the planner narrows: `target` at budget `c_star`, under `s`.
struct Question<'a> {
    target: Target,
    c_star: f64,
    s: &'a Settings,
}

impl Question<'_> {
    /// The target's spread ([`Posterior::spread`]) under `model`.
    fn spread(&self, model: &Model) -> f64 {
        posterior_of(model, self.target, self.c_star, self.s).spread()
    }
}

/// The best next action among the `open` candidates costing at most `room` FLOPs.
fn best_action(
    model: &Model,
    known: &[Observation],
    candidates: &[Candidate],
    open: &[usize],
    room: f64,
    q: &Question,
) -> Option<Proposal> {
    let before = q.spread(model);
    let actions: Vec<(Vec<usize>, String)> = actions(model, known, candidates, open, q.s)
        .into_iter()
        .filter(|(runs, _)| runs.iter().map(|&i| candidates[i].cost).sum::<f64>() <= room)
        .collect();
    let scored: Vec<Proposal> = actions
        .into_par_iter()
        .filter_map(|(runs, what)| {
            let after = expected_width(model, known, candidates, &runs, q, before)?;
            let cost: f64 = runs.iter().map(|&i| candidates[i].cost).sum();
            let why = format!(
                "{what}: spread (capped width + 10 × share of draws without a law) {before:.3} → {after:.3} {} expected ({:+.3} per 10^12 FLOPs)",
                q.target.unit(),
                (after - before) / cost * 1e12
            );
            Some(Proposal {
                runs,
                cost,
                width_before: before,
                expected_width: after,
                why,
            })
        })
        .collect();
    // Nothing that narrows the target is worth its cost: the planner stops there.
    let rate = |p: &Proposal| (p.width_before - p.expected_width) / p.cost;
    scored
        .into_iter()
        .filter(|p| rate(p) > 0.0)
        .max_by(|a, b| rate(a).total_cmp(&rate(b)))
}

/// Expected spread (the capped width and the share of draws without a law) after training
/// `runs`, over their predictive outcomes: `before` plus the expected change, so that runs
/// which change no draw in any outcome come out at exactly `before` (summed as spreads, the
/// weights' rounding made them look a hair narrower, and the planner bought them).
fn expected_width(
    model: &Model,
    known: &[Observation],
    candidates: &[Candidate],
    runs: &[usize],
    q: &Question,
    before: f64,
) -> Option<f64> {
    let predicted: Vec<(f64, f64)> = runs
        .iter()
        .map(|&i| model.predict(&candidates[i]))
        .collect::<Option<_>>()?;
    let mut with = known.to_vec();
    let mut change = 0.0;
    for (z, w) in NODES {
        with.truncate(known.len());
        for (&i, (mean, sd)) in runs.iter().zip(&predicted) {
            with.push(observed(&candidates[i], mean + z * sd));
        }
        change += w * (posterior(&with, q.target, q.c_star, q.s).spread() - before);
    }
    Some(before + change)
}

/// The actions open: single runs at budgets with a parabola; elsewhere the sizes that give the
/// budget its first parabola, nearest the predicted vertex (with why each is considered).
fn actions(
    model: &Model,
    known: &[Observation],
    candidates: &[Candidate],
    open: &[usize],
    s: &Settings,
) -> Vec<(Vec<usize>, String)> {
    let mut out = Vec::new();
    let budgets: Vec<f64> = open.iter().map(|&i| candidates[i].budget).collect();
    for group in group_rows(&budgets, None, GROUP_TOL_DEX) {
        let here: Vec<usize> = group.iter().map(|&g| open[g]).collect();
        let c = candidates[here[0]].budget;
        if let Some(b) = model.budget_at(c).filter(|b| b.parabola.is_some()) {
            // Where the budget has no minimum of its own, the law's vertex stands in: a run
            // far from it would only bend an ill-posed parabola.
            let vertex = b.interior().map(|p| p.vertex()).or_else(|| {
                let law = model.surrogate.as_ref().map(|s| s.vertex.at(c.log10()));
                law.or_else(|| b.convex().map(|p| p.vertex()))
            });
            let near = |i: &&usize| {
                vertex.is_none_or(|v| (candidates[**i].n.log10() - v).abs() <= SIZE_WINDOW_DEX)
            };
            out.extend(here.iter().filter(near).map(|&i| {
                let what = format!("{} on the parabola at {c:.3e}", candidates[i].id);
                (vec![i], what)
            }));
            continue;
        }
        out.extend(entry_sizes(model, known, candidates, &here, s));
    }
    out
}

/// The sizes that give budget `here` (open candidates of one budget without a parabola) its
/// first parabola. With no size there yet, they straddle the predicted vertex's 95% interval
/// at that budget (its 2.5%, 50% and 97.5% points, at most `SIZE_WINDOW_DEX` from the median):
/// three sizes around the median alone did not bracket the vertex when the prediction was off.
/// Otherwise, and while the interval is unbounded, the sizes nearest the law's vertex.
fn entry_sizes(
    model: &Model,
    known: &[Observation],
    candidates: &[Candidate],
    here: &[usize],
    s: &Settings,
) -> Option<(Vec<usize>, String)> {
    let c = candidates[here[0]].budget;
    let seen: Vec<f64> = known
        .iter()
        .filter(|o| (o.budget.log10() - c.log10()).abs() <= GROUP_TOL_DEX)
        .map(|o| o.n)
        .collect();
    let need = 3usize.saturating_sub(distinct(&seen));
    if need == 0 {
        return None;
    }
    let centre = match &model.surrogate {
        Some(law) => law.vertex.at(c.log10()),
        None => {
            let mut lx: Vec<f64> = here.iter().map(|&i| candidates[i].n.log10()).collect();
            lx.sort_by(f64::total_cmp);
            lx[lx.len() / 2]
        }
    };
    // The vertex's posterior (a bootstrap) only where it can place all three sizes.
    let vertex = (need == 3 && model.surrogate.is_some())
        .then(|| posterior_of(model, Target::NOpt, c, s))
        .filter(|v| v.low.is_finite() && v.high.is_finite());
    let (aims, around) = match vertex {
        Some(vertex) => {
            let near = |v: f64| {
                v.clamp(
                    vertex.median - SIZE_WINDOW_DEX,
                    vertex.median + SIZE_WINDOW_DEX,
                )
            };
            let aims = vec![vertex.median, near(vertex.low), near(vertex.high)];
            let around = format!(
                "straddling the predicted vertex N = {:.3e} [{:.3e}, {:.3e}]",
                10f64.powf(vertex.median),
                10f64.powf(vertex.low),
                10f64.powf(vertex.high)
            );
            (aims, around)
        }
        None => (
            vec![centre],
            format!("around the predicted vertex N = {:.3e}", 10f64.powf(centre)),
        ),
    };
    // The vocabulary excess of each open run here, once (it is a line fit).
    let excess: Vec<f64> = here
        .iter()
        .map(|&i| model.offset(candidates[i].vocab, c).0)
        .collect();
    let mut pick: Vec<usize> = Vec::new();
    for k in 0..need {
        let aim = aims[k.min(aims.len() - 1)];
        // The nearest size not taken; among its vocabularies, the lowest expected excess.
        let key = |h: usize| ((candidates[here[h]].n.log10() - aim).abs(), excess[h]);
        let next = (0..here.len())
            .filter(|&h| {
                let n = candidates[here[h]].n;
                !seen.contains(&n) && !pick.iter().any(|&j| candidates[j].n == n)
            })
            .min_by(|&a, &b| {
                let (ka, kb) = (key(a), key(b));
                ka.0.total_cmp(&kb.0)
                    .then(ka.1.total_cmp(&kb.1))
                    .then(here[a].cmp(&here[b]))
            })?;
        pick.push(here[next]);
    }
    let what = format!("{need} sizes at {c:.3e} (no parabola there yet) {around}");
    Some((pick, what))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{isoflop_runs, CHINCHILLA};

    fn runs(budgets: &[f64]) -> Vec<(Candidate, f64)> {
        isoflop_runs(&CHINCHILLA, budgets, 7, 0.01, 0.0, 3)
            .iter()
            .enumerate()
            .map(|(i, r)| {
                let c = Candidate {
                    id: format!("r{i}"),
                    budget: r.c,
                    n: r.n,
                    vocab: None,
                    cost: r.c,
                };
                (c, r.loss)
            })
            .collect()
    }

    #[test]
    fn a_vocabulary_whose_excess_scatters_is_predicted_with_that_scatter() {
        // Two vocabularies at three budgets: K = 1 on the law, K = 2 above it by 0.05, 0.15 and
        // 0.05 (not a line in log C). A K = 2 run's predictive SD holds that scatter; a K = 1
        // run's only the parabolas' misfit.
        let mut obs = Vec::new();
        for ((c, l), k) in runs(&[1e18, 1e19, 1e20]).iter().zip(0..) {
            let mut o = observed(c, *l);
            o.vocab = Some(1.0);
            obs.push(o.clone());
            o.vocab = Some(2.0);
            o.loss += [0.05, 0.15, 0.05][k / 7];
            obs.push(o);
        }
        let model = Model::new(&obs, Settings::default().misfit_floor);
        let at = |vocab: f64| {
            let c = Candidate {
                id: "x".into(),
                budget: 1e19,
                n: CHINCHILLA.n_opt(1e19),
                vocab: Some(vocab),
                cost: 1e19,
            };
            model.predict(&c).unwrap()
        };
        let ((m1, sd1), (m2, sd2)) = (at(1.0), at(2.0));
        assert!(m2 > m1, "K = 2 lies above the envelope: {m1} vs {m2}");
        assert!(
            sd2 > sd1 + 0.05,
            "the offset's scatter widens K = 2: {sd1} vs {sd2}"
        );
    }

    #[test]
    fn a_run_that_joins_no_envelope_in_any_outcome_is_not_proposed() {
        // K = 2 lies 0.5 above K = 1 at every budget, at sizes K = 1 already has: whatever a
        // K = 2 run gives within its predictive spread, every envelope stays as it is, so the
        // expected spread equals today's and the planner has nothing to propose (under any
        // posterior seed: the spread's value decides whether the sum over outcomes rounds).
        let all = runs(&[1e18, 3e18, 1e19, 3e19]);
        let obs: Vec<Observation> = all
            .iter()
            .flat_map(|(c, l)| {
                let on = Observation {
                    vocab: Some(1.0),
                    ..observed(c, *l)
                };
                let above = Observation {
                    vocab: Some(2.0),
                    loss: l + 0.5,
                    ..on.clone()
                };
                [on, above]
            })
            .filter(|o| o.vocab == Some(1.0) || o.budget < 3e19)
            .collect();
        let open: Vec<Candidate> = all[21..]
            .iter()
            .map(|(c, _)| Candidate {
                vocab: Some(2.0),
                ..c.clone()
            })
            .collect();
        for seed in 0..16 {
            let s = Settings {
                draws: 64,
                seed,
                ..Settings::default()
            };
            let p = propose(&obs, &open, Target::NOpt, 1e21, 1, f64::INFINITY, &s);
            assert!(p.is_empty(), "seed {seed}: {p:?}");
        }
    }

    #[test]
    fn a_vocabulary_read_past_its_budgets_is_as_uncertain_as_its_lines_prediction_interval() {
        let mut obs = Vec::new();
        for ((c, l), k) in runs(&[1e18, 1e19, 1e20]).iter().zip(0..) {
            obs.push(Observation {
                vocab: Some(2.0),
                loss: l + [0.05, 0.15, 0.05][k / 7],
                ..observed(c, *l)
            });
            obs.push(Observation {
                vocab: Some(1.0),
                ..observed(c, *l)
            });
        }
        let model = Model::new(&obs, Settings::default().misfit_floor);
        let (_, inside) = model.offset(Some(2.0), 1e19);
        let (_, far) = model.offset(Some(2.0), 1e22);
        // Excess 0.05, 0.15, 0.05 at x = 18, 19, 20: a flat line, residual SD √(0.02/3) on one
        // degree of freedom, leverage √(1 + 1/3 + (x − 19)²/2); the normal with the 95%
        // interval of the Student-t prediction has SD s·lever·t95(1)/1.96.
        let lever = |x: f64| (1.0 + 1.0 / 3.0 + (x - 19.0_f64).powi(2) / 2.0).sqrt();
        let s = (0.02_f64 / 3.0).sqrt();
        let sd = |x: f64| s * lever(x) * t95(1) / Z95;
        assert!((inside - sd(19.0)).abs() < 1e-9, "{inside} vs {}", sd(19.0));
        assert!((far - sd(22.0)).abs() < 1e-9, "{far} vs {}", sd(22.0));
    }

    #[test]
    fn more_budgets_narrow_the_posterior_around_the_law() {
        let s = Settings::default();
        let all = runs(&[1e18, 3e18, 1e19, 3e19, 1e20, 3e20]);
        let obs = |k: usize| -> Vec<Observation> {
            all[..7 * k].iter().map(|(c, l)| observed(c, *l)).collect()
        };
        let few = posterior(&obs(3), Target::NOpt, 1e21, &s);
        let many = posterior(&obs(6), Target::NOpt, 1e21, &s);
        assert!(many.width < few.width, "{few:?} vs {many:?}");
        let truth = CHINCHILLA.n_opt(1e21).log10();
        assert!(many.low < truth && truth < many.high, "{many:?} vs {truth}");
        assert!(posterior(&obs(2), Target::NOpt, 1e21, &s)
            .width
            .is_infinite());
    }

    #[test]
    fn the_loss_target_extrapolates_by_the_chosen_form() {
        // On a Chinchilla-form law the loss at N_opt is E + G·C^(−γ): the floor form in log C.
        let s = |loss_form| Settings {
            loss_form,
            ..Settings::default()
        };
        let obs: Vec<Observation> = runs(&[1e18, 3e18, 1e19, 3e19, 1e20, 3e20])
            .iter()
            .map(|(c, l)| observed(c, *l))
            .collect();
        let n = CHINCHILLA.n_opt(1e23);
        let truth = CHINCHILLA.loss(n, 1e23 / (6.0 * n));
        let floor = posterior(&obs, Target::Loss, 1e23, &s(Form::Floor));
        let line = posterior(&obs, Target::Loss, 1e23, &s(Form::Log));
        assert!(
            floor.low < truth && truth < floor.high,
            "{floor:?} vs {truth}"
        );
        assert!(
            (floor.median - truth).abs() < 0.5 * (line.median - truth).abs(),
            "floor {floor:?}, line {line:?}, truth {truth}"
        );
        assert_eq!(floor.valid, floor.draws);
    }

    #[test]
    fn a_new_budget_is_entered_with_three_sizes_straddling_its_predicted_vertex() {
        let s = Settings {
            draws: 64,
            ..Settings::default()
        };
        let all = runs(&[1e18, 3e18, 1e19, 3e19]);
        let obs: Vec<Observation> = all[..21].iter().map(|(c, l)| observed(c, *l)).collect();
        let open: Vec<Candidate> = all[21..].iter().map(|(c, _)| c.clone()).collect();
        let p = propose(&obs, &open, Target::NOpt, 1e21, 2, f64::INFINITY, &s);
        assert_eq!(p[0].runs.len(), 3, "{p:?}");
        let mut sizes: Vec<usize> = p[0].runs.clone();
        sizes.sort();
        // The grid of seven is centred on the true vertex (size 3): the three sizes straddle
        // it, one at the predicted median and one towards each end of its interval.
        assert!(sizes.contains(&3), "{}", p[0].why);
        assert!(sizes[0] < 3 && 3 < sizes[2], "{}", p[0].why);
        assert!(p[0].why.contains("straddling"), "{}", p[0].why);
        assert!(p[0].expected_width < p[0].width_before);
        assert_eq!(p[1].runs.len(), 1, "then single sizes on the new parabola");
        let cheap = propose(&obs, &open, Target::NOpt, 1e21, 2, 1e19, &s);
        assert!(cheap.is_empty(), "nothing fits in 1e19 FLOPs: {cheap:?}");
    }

    #[test]
    fn a_budget_without_a_minimum_is_offered_sizes_near_the_laws_vertex_only() {
        let all = runs(&[1e18, 3e18, 1e19, 3e19]);
        // 1e18 has three sizes around its vertex, the middle one worst: no minimum there.
        let mut obs: Vec<Observation> = all[7..].iter().map(|(c, l)| observed(c, *l)).collect();
        for (k, bump) in [(2, 0.0), (3, 0.05), (4, 0.0)] {
            obs.push(observed(&all[k].0, all[k].1 + bump));
        }
        let far = Candidate {
            id: "far".into(),
            n: all[3].0.n * 1e3,
            ..all[3].0.clone()
        };
        let open_runs = [all[1].0.clone(), all[5].0.clone(), far];
        let model = Model::new(&obs, Settings::default().misfit_floor);
        assert!(model.budget_at(1e18).unwrap().interior().is_none());
        let offered: Vec<usize> =
            actions(&model, &obs, &open_runs, &[0, 1, 2], &Settings::default())
                .iter()
                .flat_map(|(runs, _)| runs.clone())
                .collect();
        assert_eq!(
            offered,
            [0, 1],
            "three decades off the law's vertex is not offered"
        );
    }
}
