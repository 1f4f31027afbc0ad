//! Predictions at a compute budget from fitted (or published) laws, with intervals, an FSQ
//! codebook choice, and explicit consistency checks between the laws.

use crate::fitted::{Fits, Parametric};
use crate::laws::{Estimate, LogLaw, PowerLaw};
use crate::loss_shape::LossShape;
use crate::parametric::with_draws;
use crate::FitError;
use serde::Serialize;
use std::path::Path;

/// FSQ level sets (Mentzer et al.): nominal log2 size and levels; the real size is their product.
pub const FSQ_LEVELS: [(u32, &[u32]); 5] = [
    (8, &[8, 6, 5]),
    (10, &[8, 5, 5, 5]),
    (12, &[7, 5, 5, 5, 5]),
    (14, &[8, 8, 8, 6, 5]),
    (16, &[8, 8, 8, 5, 5, 5]),
];

/// ScaMo's model table (name, layers, width), for a width when none is given.
pub const SCAMO_MODELS: [(&str, u32, u32); 6] = [
    ("ScaMo-44M", 8, 512),
    ("ScaMo-111M", 12, 768),
    ("ScaMo-343M", 24, 1024),
    ("ScaMo-775M", 36, 1280),
    ("ScaMo-1.4B", 48, 1536),
    ("ScaMo-3B", 24, 3200),
];

/// Relative disagreement beyond which a consistency check of two quantities fails (25%).
const TOLERANCE: f64 = 0.25;

/// Absolute disagreement beyond which a consistency check of two exponents fails.
const EXPONENT_TOLERANCE: f64 = 0.05;

/// The laws a prediction uses.
#[derive(Debug, Clone, PartialEq)]
pub struct Laws {
    /// Where they come from (`preset scamo` or a fits file).
    pub source: String,
    /// N_nv,opt = k·C^b.
    pub n: Option<PowerLaw>,
    /// N_v,opt = k·C^a.
    pub nv: Option<PowerLaw>,
    /// V_opt = k·C^v (from the minima over V; fitted laws only).
    pub v: Option<PowerLaw>,
    /// D_opt = k·C^c.
    pub d: Option<PowerLaw>,
    /// N_v = k·N_nv^γ.
    pub nv_vs_n: Option<PowerLaw>,
    /// L = α·log10 C + β.
    pub loss: Option<LogLaw>,
    /// The parametric L(N, D) with its bootstrap draws.
    pub parametric: Option<Parametric>,
    /// The loss law's forms over the minima and the one chosen by leave-one-budget-out error.
    pub loss_shape: Option<LossShape>,
    /// True for ScaMo's published coefficients (enables the comparison with the paper's 1e18 run).
    pub is_scamo: bool,
}

impl Laws {
    /// ScaMo's published fits (Eqs. 10–14).
    pub fn scamo() -> Self {
        Self {
            source: "preset scamo (ScaMo Eqs. 10-14, published coefficients without uncertainty)"
                .into(),
            n: Some(PowerLaw::exact("C", "N_nv", -0.52, 0.57)),
            nv: Some(PowerLaw::exact("C", "N_v", -5.29, 0.75)),
            v: None,
            d: Some(PowerLaw::exact("C", "D", -0.05, 0.43)),
            nv_vs_n: Some(PowerLaw::exact("N_nv", "N_v", -5.604, 1.467)),
            loss: Some(LogLaw::exact(-1.062, 13.839)),
            parametric: None,
            loss_shape: None,
            is_scamo: true,
        }
    }

    /// The laws in a fit.
    pub fn from_fits(f: &Fits, source: &str) -> Self {
        let law = |k: &str| f.power_laws.get(k).cloned();
        Self {
            source: source.into(),
            n: law("n_opt_vs_c"),
            nv: law("nv_opt_vs_c"),
            v: law("v_opt_vs_c"),
            d: law("d_opt_vs_c"),
            nv_vs_n: law("nv_vs_n"),
            loss: f.log_law.clone(),
            parametric: f.parametric.clone(),
            loss_shape: f.loss_shape.clone(),
            is_scamo: false,
        }
    }

    /// Reads a `fits.json`.
    pub fn read(path: &Path) -> Result<Self, FitError> {
        Ok(Self::from_fits(
            &Fits::read(path)?,
            &path.display().to_string(),
        ))
    }
}

/// The model width used to turn N_v into V.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Width {
    /// d.
    pub value: f64,
    /// Given, or which ScaMo configuration it was taken from.
    pub source: String,
}

/// The codebook implied by N_v and d, rounded to an FSQ level set.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Vocab {
    /// N_v / d (with the interval of N_v).
    pub exact: Estimate,
    /// Nearest nominal size 2^k in log2.
    pub nominal: u64,
    /// k.
    pub nominal_log2: u32,
    /// The level set's real codebook size Π L_i.
    pub real: u64,
    /// The FSQ levels.
    pub levels: Vec<u32>,
    /// Set when the exact size is outside the available level sets.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

/// Compute-optimal allocation from the parametric L(N, D) under C = 6·N·D.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ParametricPrediction {
    /// N_opt (the fit's N column) with bootstrap interval.
    pub n_opt: Estimate,
    /// D_opt = C / (6·N_opt).
    pub d_opt: Estimate,
    /// L(N_opt, D_opt).
    pub loss: Estimate,
}

/// One consistency check: two numbers that should agree.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Check {
    /// What is compared.
    pub name: String,
    /// The predicted quantity.
    pub value: f64,
    /// What it should match.
    pub reference: f64,
    /// value / reference.
    pub ratio: f64,
    /// The agreement required.
    pub rule: String,
    /// True when the rule holds.
    pub ok: bool,
    /// How the numbers were obtained.
    pub note: String,
}

impl Check {
    fn with(name: &str, value: f64, reference: f64, rule: String, ok: bool, note: String) -> Self {
        Self {
            name: name.into(),
            value,
            reference,
            ratio: value / reference,
            rule,
            ok,
            note,
        }
    }

    /// Quantities that should agree within ±25%.
    fn ratio(name: &str, value: f64, reference: f64, note: String) -> Self {
        let r = value / reference;
        let ok = r.is_finite() && (r - 1.0).abs() <= TOLERANCE;
        let rule = format!("ratio within 1 ± {TOLERANCE}");
        Self::with(name, value, reference, rule, ok, note)
    }

    /// Exponents that should agree within ±0.05.
    fn exponent(name: &str, value: f64, reference: f64, note: String) -> Self {
        let ok = (value - reference).abs() <= EXPONENT_TOLERANCE;
        let rule = format!("difference within ± {EXPONENT_TOLERANCE}");
        Self::with(name, value, reference, rule, ok, note)
    }

    /// A codebook size that should round to the FSQ level set of `reference`, inside the
    /// available sizes (2^8..2^16, one octave of slack at either end).
    fn codebook(name: &str, value: f64, reference: f64, note: String) -> Self {
        let ok = fsq_for(value).0 == fsq_for(reference).0
            && (2f64.powi(7)..=2f64.powi(17)).contains(&value);
        let rule = "rounds to the same FSQ level set".to_string();
        Self::with(name, value, reference, rule, ok, note)
    }
}

/// What to predict.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PredictOptions {
    /// Compute budget C in FLOPs.
    pub budget: f64,
    /// Model width d (default: from the ScaMo model table nearest to N_nv).
    pub width: Option<f64>,
    /// Fixed codebook size V (then N_v = V·d instead of the N_v law).
    pub vocab: Option<f64>,
}

/// A prediction at one budget.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Prediction {
    /// The laws' source.
    pub source: String,
    /// C.
    pub budget: f64,
    /// The laws used, as equations.
    pub equations: Vec<String>,
    /// N_nv from its C-law.
    pub n_nv: Option<Estimate>,
    /// N_v: from its C-law, or V·d with `--vocab`.
    pub n_v: Option<Estimate>,
    /// How N_v was obtained.
    pub n_v_source: Option<String>,
    /// N_v from the N_nv-law at the predicted N_nv.
    pub n_v_from_n_nv_law: Option<Estimate>,
    /// D from its C-law.
    pub d: Option<Estimate>,
    /// D that spends the budget exactly: C / (6·(N_nv + N_v)).
    pub d_from_budget: Option<f64>,
    /// Width used for V.
    pub width: Option<Width>,
    /// Codebook.
    pub vocab: Option<Vocab>,
    /// V from its own C-law (the minima over V), when the fit has one.
    pub v_opt: Option<Estimate>,
    /// Loss from the log law (95% interval of the fitted mean).
    pub loss: Option<Estimate>,
    /// Loss from each form of the loss law (log, curved, floor), the chosen one marked.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub loss_by_form: Vec<FormLoss>,
    /// From the parametric fit, when the fits have one.
    pub parametric: Option<ParametricPrediction>,
    /// Checks between the laws (and with the paper for the scamo preset at 1e18).
    pub consistency: Vec<Check>,
    /// Plain statements of the failed checks and other caveats.
    pub warnings: Vec<String>,
}

/// The loss one form of the loss law predicts at the budget.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FormLoss {
    /// `log`, `curved` or `floor`.
    pub form: String,
    /// Its loss at C.
    pub loss: f64,
    /// Its leave-one-budget-out RMS error over the minima (none: too few to score).
    pub lobo_rms: Option<f64>,
    /// Whether leave-one-budget-out error chose it.
    pub chosen: bool,
}

/// Each form's loss at `c`, and a warning when the chosen form is not the log law that
/// `loss` reports.
fn losses_by_form(shape: &LossShape, c: f64, warnings: &mut Vec<String>) -> Vec<FormLoss> {
    let chosen = shape.chosen.as_deref();
    let by_form: Vec<FormLoss> = shape
        .forms
        .iter()
        .map(|f| FormLoss {
            form: f.form.clone(),
            loss: f.at(c.log10()),
            lobo_rms: f.lobo_rms,
            chosen: chosen == Some(f.form.as_str()),
        })
        .collect();
    let log = by_form.iter().find(|f| f.form == "log");
    if let (Some(best), Some(log)) = (by_form.iter().find(|f| f.chosen), log) {
        if best.form != "log" {
            warnings.push(format!(
                "the loss law's form chosen by leave-one-budget-out error is {} (RMS {}): loss {} at this budget; the log law's {} above extrapolates worse (RMS {})",
                best.form,
                best.lobo_rms.map_or("n/a".into(), |r| format!("{r:.3}")),
                crate::report::sig(best.loss),
                crate::report::sig(log.loss),
                log.lobo_rms.map_or("n/a".into(), |r| format!("{r:.3}")),
            ));
        }
    }
    by_form
}

/// Nearest FSQ level set to a codebook size (in log2).
pub fn fsq_for(v: f64) -> (u32, &'static [u32]) {
    let l = v.log2();
    *FSQ_LEVELS
        .iter()
        .min_by(|a, b| (a.0 as f64 - l).abs().total_cmp(&(b.0 as f64 - l).abs()))
        .expect("non-empty table")
}

/// The ScaMo configuration whose non-vocabulary parameters (≈ 12·layers·d²) are nearest to `n_nv`.
fn scamo_width(n_nv: f64) -> Width {
    let params = |l: u32, d: u32| 12.0 * l as f64 * (d as f64).powi(2);
    let (name, layers, d) = *SCAMO_MODELS
        .iter()
        .min_by(|a, b| {
            let da = (params(a.1, a.2).log10() - n_nv.log10()).abs();
            let db = (params(b.1, b.2).log10() - n_nv.log10()).abs();
            da.total_cmp(&db)
        })
        .expect("non-empty table");
    Width {
        value: d as f64,
        source: format!(
            "{name} ({layers} layers x {d}, about {:.3e} non-vocabulary parameters by 12·layers·d²): the ScaMo configuration nearest to N_nv; pass --width to choose",
            params(layers, d)
        ),
    }
}

fn scale(e: &Estimate, k: f64) -> Estimate {
    Estimate {
        value: e.value * k,
        se: e.se.map(|s| s * k),
        ci_low: e.ci_low.map(|v| v * k),
        ci_high: e.ci_high.map(|v| v * k),
    }
}

/// Predicts at `opts.budget`.
pub fn predict(laws: &Laws, opts: &PredictOptions) -> Result<Prediction, FitError> {
    let c = opts.budget;
    if !(c.is_finite() && c > 0.0) {
        return Err(FitError::Invalid(format!(
            "--budget {c}: must be a positive number of FLOPs"
        )));
    }
    if laws.n.is_none() && laws.loss.is_none() && laws.parametric.is_none() {
        return Err(FitError::Invalid(format!(
            "{}: no N_opt law, log law or parametric fit to predict from",
            laws.source
        )));
    }
    let mut warnings = Vec::new();
    let equations = equations(laws);
    let n_nv = laws.n.as_ref().map(|l| l.at(c));
    let width = opts
        .width
        .map(|w| Width {
            value: w,
            source: "given (--width)".into(),
        })
        .or_else(|| n_nv.map(|n| scamo_width(n.value)));
    let (n_v, n_v_source) = match (opts.vocab, &width, &laws.nv) {
        (Some(v), Some(w), _) => (
            Some(Estimate::exact(v * w.value)),
            Some(format!("fixed: --vocab {v} x width {}", w.value)),
        ),
        (Some(_), None, _) => {
            warnings.push("--vocab needs a width (--width, or an N_nv law to pick one)".into());
            (None, None)
        }
        (None, _, Some(law)) => (Some(law.at(c)), Some(format!("C-law: {}", law.equation()))),
        (None, _, None) => (None, None),
    };
    let n_v_from_n_nv_law = match (&laws.nv_vs_n, &n_nv) {
        (Some(law), Some(n)) => Some(law.at(n.value)),
        _ => None,
    };
    let d = laws.d.as_ref().map(|l| l.at(c));
    let total = n_nv.map(|n| n.value + n_v.map_or(0.0, |v| v.value));
    let d_from_budget = total.map(|t| c / (6.0 * t));

    let vocab = vocab_at(n_v.as_ref(), width.as_ref(), &mut warnings);
    let loss_by_form = laws
        .loss_shape
        .as_ref()
        .map_or_else(Vec::new, |s| losses_by_form(s, c, &mut warnings));
    let parametric = laws
        .parametric
        .as_ref()
        .and_then(|p| parametric_if_finite(p, c, &mut warnings));
    let mut prediction = Prediction {
        source: laws.source.clone(),
        budget: c,
        equations,
        n_nv,
        n_v,
        n_v_source,
        n_v_from_n_nv_law,
        d,
        d_from_budget,
        width,
        vocab,
        v_opt: laws.v.as_ref().map(|l| l.at(c)),
        loss: laws.loss.as_ref().map(|l| l.at(c)),
        loss_by_form,
        parametric,
        consistency: Vec::new(),
        warnings,
    };
    let mut checks = law_checks(laws, &prediction);
    if laws.is_scamo {
        let mut warnings = std::mem::take(&mut prediction.warnings);
        let p = &prediction;
        let (n_nv, n_v, from_law, d) = (&p.n_nv, &p.n_v, &p.n_v_from_n_nv_law, &p.d);
        paper_checks(c, n_nv, n_v, from_law, d, &mut checks, &mut warnings);
        prediction.warnings = warnings;
    }
    for ch in checks.iter().filter(|ch| !ch.ok) {
        prediction.warnings.push(format!(
            "inconsistent: {}: {} vs {} (ratio {:.3}; needs {}); {}",
            ch.name,
            crate::report::sig(ch.value),
            crate::report::sig(ch.reference),
            ch.ratio,
            ch.rule,
            ch.note
        ));
    }
    if laws.loss.as_ref().is_some_and(|l| l.fit.slope.se.is_none()) {
        prediction
            .warnings
            .push("the loss law carries no standard errors: no interval".into());
    }
    let wide = wide_intervals(&prediction);
    prediction.warnings.extend(wide);
    prediction.consistency = checks;
    Ok(prediction)
}

/// The equations of every law the prediction reads, the loss law's last.
fn equations(laws: &Laws) -> Vec<String> {
    [&laws.n, &laws.nv, &laws.v, &laws.d, &laws.nv_vs_n]
        .into_iter()
        .flatten()
        .map(|law| law.equation())
        .chain(laws.loss.as_ref().map(|l| l.equation()))
        .collect()
}

/// A warning for each predicted quantity whose 95% interval spans more than a decade.
fn wide_intervals(p: &Prediction) -> Vec<String> {
    let param = p.parametric.as_ref();
    [
        ("N_nv", p.n_nv.as_ref()),
        ("N_v", p.n_v.as_ref()),
        ("D", p.d.as_ref()),
        ("the parametric N_opt", param.map(|q| &q.n_opt)),
        ("the parametric D_opt", param.map(|q| &q.d_opt)),
    ]
    .into_iter()
    .filter_map(|(name, e)| too_wide(name, e?))
    .collect()
}

/// The parametric law's compute-optimal point at `c`, or None with a warning when its fit
/// diverged (a scale A or B at ∞, an exponent at 0): then it has no finite allocation, and an
/// N_opt of 0 with a NaN loss is not a prediction.
fn parametric_if_finite(
    p: &Parametric,
    c: f64,
    warnings: &mut Vec<String>,
) -> Option<ParametricPrediction> {
    let q = parametric_at(p, c);
    let finite = [q.n_opt.value, q.d_opt.value, q.loss.value]
        .iter()
        .all(|v| v.is_finite() && *v > 0.0);
    if !finite {
        warnings.push(format!(
            "the parametric law has no compute-optimal allocation (A {}, B {}, α {:.3}, β {:.3}: a term diverged in the fit); not predicted",
            crate::report::sig(p.law.a.value),
            crate::report::sig(p.law.b.value),
            p.law.alpha.value,
            p.law.beta.value
        ));
    }
    finite.then_some(q)
}

/// A plain statement when `e`'s 95% interval spans more than a decade: a prediction that
/// cannot be acted on should say so.
fn too_wide(name: &str, e: &Estimate) -> Option<String> {
    let (lo, hi) = (e.ci_low?, e.ci_high?);
    let decades = if lo > 0.0 {
        (hi / lo).log10()
    } else {
        f64::INFINITY
    };
    (decades > 1.0).then(|| {
        format!("{name}'s 95% interval spans {decades:.1} decades ([{lo:.3e}, {hi:.3e}]): too wide to act on")
    })
}

/// The FSQ vocabulary of the vocabulary parameters `n_v` at `width` (V = N_v / d, rounded to
/// the nearest level set); a V outside 2^8..2^16 adds a warning.
fn vocab_at(
    n_v: Option<&Estimate>,
    width: Option<&Width>,
    warnings: &mut Vec<String>,
) -> Option<Vocab> {
    let (nv, w) = (n_v?, width?);
    let exact = scale(nv, 1.0 / w.value);
    let (k, levels) = fsq_for(exact.value);
    let note = (exact.value < 2f64.powi(7) || exact.value > 2f64.powi(17)).then(|| {
        format!(
            "V = {:.0} is outside the FSQ level sets (2^8..2^16); the nearest end is shown",
            exact.value
        )
    });
    if let Some(n) = &note {
        warnings.push(n.clone());
    }
    Some(Vocab {
        exact,
        nominal: 1u64 << k,
        nominal_log2: k,
        real: levels.iter().map(|&l| l as u64).product(),
        levels: levels.to_vec(),
        note,
    })
}

/// The consistency checks between the laws at the prediction `p`'s budget.
fn law_checks(laws: &Laws, p: &Prediction) -> Vec<Check> {
    let c = p.budget;
    let mut checks = Vec::new();
    let total = p.n_nv.map(|n| n.value + p.n_v.map_or(0.0, |v| v.value));
    if let (Some(t), Some(dd)) = (total, p.d) {
        checks.push(Check::ratio(
            "compute: 6·(N_nv + N_v)·D vs C",
            6.0 * t * dd.value,
            c,
            "N_nv, N_v and D each from their own law; C ≈ 6·N·D should hold".into(),
        ));
    }
    if let (Some(a), Some(b)) = (&p.n_v, &p.n_v_from_n_nv_law) {
        checks.push(Check::ratio(
            "N_v: C-law vs N_nv-law",
            a.value,
            b.value,
            "N_v at C, against N_v from the N_v–N_nv law at the predicted N_nv".into(),
        ));
    }
    if let (Some(n), Some(dl)) = (&laws.n, &laws.d) {
        checks.push(Check::exponent(
            "exponents: b + c (N_nv·D ∝ C^(b+c)) vs 1",
            n.exponent() + dl.exponent(),
            1.0,
            "C = 6·N·D needs the N and D exponents to add to 1".into(),
        ));
    }
    if let (Some(nv), Some(dl)) = (&laws.nv, &laws.d) {
        checks.push(Check::exponent(
            "exponents: a + c (N_v·D ∝ C^(a+c)) vs 1",
            nv.exponent() + dl.exponent(),
            1.0,
            "above 1, N_v·D alone eventually exceeds C".into(),
        ));
    }
    if let (Some(n), Some(nv), Some(g)) = (&laws.n, &laws.nv, &laws.nv_vs_n) {
        checks.push(Check::exponent(
            "exponents: a / b (N_v ∝ N_nv^(a/b) from the C-laws) vs γ",
            nv.exponent() / n.exponent(),
            g.exponent(),
            "the C-laws imply an N_v–N_nv exponent; the direct fit should agree".into(),
        ));
    }
    if let (Some(v), Some(from_nv)) = (&p.v_opt, &p.vocab) {
        checks.push(Check::codebook(
            "V: V-law vs N_v / d",
            v.value,
            from_nv.exact.value,
            "V_opt from its own C-law, against N_v (its C-law) over the width".into(),
        ));
    }
    if let (Some(n), Some(pp)) = (&p.n_nv, &p.parametric) {
        checks.push(Check::ratio(
            "N_opt: IsoFLOP law (approach 2) vs parametric (approach 3)",
            n.value,
            pp.n_opt.value,
            "the two ways of fitting the same runs should place the optimum alike".into(),
        ));
    }
    checks
}

/// The paper's own 1e18 run (ScaMo §5.5): a 3B model (24 layers × 3200), vocabulary 2^16,
/// about 10^7.5 tokens; and its text's exponent claims.
fn paper_checks(
    c: f64,
    n_nv: &Option<Estimate>,
    n_v: &Option<Estimate>,
    n_v_from_n_nv: &Option<Estimate>,
    d: &Option<Estimate>,
    checks: &mut Vec<Check>,
    warnings: &mut Vec<String>,
) {
    let paper_n = 12.0 * 24.0 * 3200f64.powi(2);
    let paper_v = 65536.0;
    let paper_d = 10f64.powf(7.5);
    checks.push(Check::exponent(
        "paper: N_v/N_nv exponent (text says C^1.315)",
        0.75 - 0.57,
        1.315,
        "N_v/N_nv ∝ C^(0.75−0.57) = C^0.18; 1.315 is the ratio 0.75/0.57, not an exponent".into(),
    ));
    checks.push(Check::exponent(
        "paper: N_nv/D exponent (text says C^1.325)",
        0.57 - 0.43,
        1.325,
        "N_nv/D ∝ C^(0.57−0.43) = C^0.14; 1.325 is the ratio 0.57/0.43, not an exponent".into(),
    ));
    if (c.log10() - 18.0).abs() > 0.01 {
        warnings.push(
            "the paper's trained configuration is for C = 1e18 only; pass --budget 1e18 to compare with it"
                .into(),
        );
        return;
    }
    if let Some(n) = n_nv {
        checks.push(Check::ratio(
            "paper at 1e18: N_nv vs the 3B model trained",
            n.value,
            paper_n,
            "ScaMo-3B: 24 layers x 3200 ≈ 2.95e9 non-vocabulary parameters (12·L·d²)".into(),
        ));
    }
    if let Some(nv) = n_v {
        checks.push(Check::codebook(
            "paper at 1e18: V = N_v / 3200 (C-law) vs 2^16",
            nv.value / 3200.0,
            paper_v,
            "N_v from its C-law at the paper's 3B width".into(),
        ));
    }
    if let Some(nv) = n_v_from_n_nv {
        checks.push(Check::codebook(
            "paper at 1e18: V = N_v / 3200 (N_nv-law) vs 2^16",
            nv.value / 3200.0,
            paper_v,
            "N_v from the N_v–N_nv law at the predicted N_nv, at the paper's 3B width".into(),
        ));
    }
    if let Some(dd) = d {
        checks.push(Check::ratio(
            "paper at 1e18: D vs 10^7.5 tokens",
            dd.value,
            paper_d,
            "the paper states about 10^7.5 tokens".into(),
        ));
    }
    checks.push(Check::ratio(
        "paper at 1e18: 6·(N_nv + N_v)·D of the run trained vs C",
        6.0 * (paper_n + paper_v * 3200.0) * paper_d,
        c,
        "3B (2.95e9) + 2^16·3200 vocabulary parameters on 10^7.5 tokens".into(),
    ));
}

/// Compute-optimal N, D and loss from the parametric fit (and each bootstrap draw).
pub fn parametric_at(p: &Parametric, c: f64) -> ParametricPrediction {
    let alloc = |s: [f64; 5]| {
        let [e, a, b, alpha, beta] = s;
        let g = (alpha * a / (beta * b)).powf(1.0 / (alpha + beta));
        let n = g * (c / 6.0).powf(beta / (alpha + beta));
        let d = c / (6.0 * n);
        [n, d, e + a / n.powf(alpha) + b / d.powf(beta)]
    };
    let best = alloc([
        p.law.e.value,
        p.law.a.value,
        p.law.b.value,
        p.law.alpha.value,
        p.law.beta.value,
    ]);
    let draws: Vec<[f64; 3]> = p.bootstrap.samples.iter().map(|&s| alloc(s)).collect();
    let est = |k: usize| {
        let v: Vec<f64> = draws.iter().map(|d| d[k]).collect();
        with_draws(best[k], &v)
    };
    ParametricPrediction {
        n_opt: est(0),
        d_opt: est(1),
        loss: est(2),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_interval_wider_than_a_decade_is_called_too_wide_to_act_on() {
        let e = |lo: f64, hi: f64| Estimate {
            value: 1.0,
            se: None,
            ci_low: Some(lo),
            ci_high: Some(hi),
        };
        let wide = too_wide("N_nv", &e(1e4, 1e8)).unwrap();
        assert!(
            wide.contains("4.0 decades") && wide.contains("too wide"),
            "{wide}"
        );
        assert!(too_wide("N_nv", &e(-1.0, 1e8))
            .unwrap()
            .contains("inf decades"));
        assert_eq!(too_wide("N_nv", &e(1e5, 5e5)), None);
        assert_eq!(too_wide("N_nv", &Estimate::exact(3.0)), None);
    }

    #[test]
    fn fsq_sets_round_in_log2() {
        assert_eq!(fsq_for(50_000.0).0, 16);
        assert_eq!(fsq_for(300.0).0, 8);
        assert_eq!(fsq_for(2048.0 * 1.5).0, 12);
        let real: Vec<u64> = FSQ_LEVELS
            .iter()
            .map(|(_, l)| l.iter().map(|&v| v as u64).product())
            .collect();
        assert_eq!(real, vec![240, 1000, 4375, 15360, 64000]);
    }

    #[test]
    fn the_loss_is_also_predicted_by_each_form_and_the_chosen_one_is_said() {
        let law = |x: f64| -5.0 + 3.0 * 10f64.powf(-0.6 * (x - 12.5));
        let minima: Vec<[f64; 2]> = (0..7)
            .map(|i| 11.0 + 0.5 * i as f64)
            .map(|x| [x, law(x)])
            .collect();
        let laws = Laws {
            source: "test".into(),
            n: None,
            nv: None,
            v: None,
            d: None,
            nv_vs_n: None,
            loss: Some(LogLaw::exact(-1.0, 10.0)),
            parametric: None,
            loss_shape: Some(crate::loss_shape::compare(&minima)),
            is_scamo: false,
        };
        let options = PredictOptions {
            budget: 1e14,
            width: None,
            vocab: None,
        };
        let p = predict(&laws, &options).unwrap();
        let forms: Vec<&str> = p.loss_by_form.iter().map(|f| f.form.as_str()).collect();
        assert_eq!(forms, ["log", "curved", "floor"]);
        let chosen = p.loss_by_form.iter().find(|f| f.chosen).unwrap();
        assert_eq!(chosen.form, "floor");
        assert!((chosen.loss - law(14.0)).abs() < 1e-3, "{chosen:?}");
        assert!(
            p.warnings
                .iter()
                .any(|w| w.contains("chosen by leave-one-budget-out error is floor")),
            "{:?}",
            p.warnings
        );
    }

    #[test]
    fn scamo_preset_at_1e18_evaluates_the_equations_and_flags_inconsistencies() {
        let p = predict(
            &Laws::scamo(),
            &PredictOptions {
                budget: 1e18,
                width: None,
                vocab: None,
            },
        )
        .unwrap();
        let n_nv = 10f64.powf(-0.52 + 0.57 * 18.0);
        let n_v = 10f64.powf(-5.29 + 0.75 * 18.0);
        let d = 10f64.powf(-0.05 + 0.43 * 18.0);
        assert!((p.n_nv.unwrap().value / n_nv - 1.0).abs() < 1e-12);
        assert!((p.n_nv.unwrap().value / 5.5e9 - 1.0).abs() < 0.01);
        assert!((p.n_v.unwrap().value / n_v - 1.0).abs() < 1e-12);
        assert!((p.d.unwrap().value / d - 1.0).abs() < 1e-12);
        assert!((p.loss.unwrap().value - (-1.062 * 18.0 + 13.839)).abs() < 1e-12);
        let w = p.width.as_ref().unwrap();
        assert_eq!(w.value, 3200.0, "{w:?}");
        let v = p.vocab.as_ref().unwrap();
        assert_eq!((v.nominal, v.real), (65536, 64000));
        let check = |name: &str| {
            p.consistency
                .iter()
                .find(|c| c.name.starts_with(name))
                .unwrap_or_else(|| panic!("no check {name}"))
        };
        let compute = check("compute");
        assert!((compute.ratio - 6.0 * (n_nv + n_v) * d / 1e18).abs() < 1e-9);
        assert!(!compute.ok, "6ND is {:.2}× C", compute.ratio);
        let laws = check("N_v: C-law");
        let from_n = 10f64.powf(-5.604 + 1.467 * n_nv.log10());
        assert!((laws.ratio - n_v / from_n).abs() < 1e-9 && !laws.ok);
        assert!(!check("paper at 1e18: N_nv").ok);
        assert!(
            check("paper at 1e18: V = N_v / 3200 (C-law)").ok,
            "N_v/3200 rounds to 2^16"
        );
        assert!(
            !check("paper at 1e18: V = N_v / 3200 (N_nv-law)").ok,
            "151k is past 2^17"
        );
        assert!(!check("exponents: a + c").ok, "0.75 + 0.43 = 1.18");
        assert!(check("exponents: b + c").ok, "0.57 + 0.43 = 1");
        assert!(
            !check("exponents: a / b").ok,
            "0.75 / 0.57 = 1.316 vs 1.467"
        );
        assert!(!check("paper at 1e18: D").ok);
        assert!(p
            .warnings
            .iter()
            .any(|w| w.contains("inconsistent: compute")));
    }

    #[test]
    fn fixed_vocab_and_width_are_used() {
        let p = predict(
            &Laws::scamo(),
            &PredictOptions {
                budget: 1e16,
                width: Some(1024.0),
                vocab: Some(4096.0),
            },
        )
        .unwrap();
        assert_eq!(p.n_v.unwrap().value, 4096.0 * 1024.0);
        assert_eq!(p.vocab.as_ref().unwrap().nominal, 4096);
        let t = p.n_nv.unwrap().value + 4096.0 * 1024.0;
        assert!((p.d_from_budget.unwrap() - 1e16 / (6.0 * t)).abs() < 1e-6);
        assert!(p.warnings.iter().any(|w| w.contains("C = 1e18 only")));
    }
}
