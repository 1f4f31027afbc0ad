//! The HTML page of `motionscale report`: one file with its style and charts inline (the
//! fit's own charts from `fits::report::charts`, as SVG), no scripts and no external
//! resources, laid out to read at 1280 px.

use crate::commands::CorpusStats;
use anyhow::Result;
use experiments::plan::IsoFlopPlan;
use experiments::results::RunRow;
use experiments::status::{PointState, PointStatus};
use fits::fitted::{Holdout, RepeatedData};
use fits::laws::Estimate;
use fits::report::{estimate_text, sig};
use fits::{Fits, Prediction};
use std::fmt::Write as _;
use std::path::PathBuf;
use tokenizer::evaluate::EvalReport;

const STYLE: &str = "body{font-family:'DejaVu Sans',system-ui,sans-serif;font-size:16px;\
line-height:1.45;color:#1b1b1b;max-width:1200px;margin:0 auto;padding:8px 24px 48px}\
h1{font-size:28px}h2{font-size:22px;border-bottom:2px solid #ccc;margin-top:40px}\
h3{font-size:18px}nav a{margin-right:16px}table{border-collapse:collapse;font-size:14px;\
margin:8px 0}th,td{padding:3px 9px;border-bottom:1px solid #ddd;text-align:right}\
th:first-child,td:first-child{text-align:left}th{background:#f2f2f2}\
.scroll{overflow-x:auto;max-width:100%}.grid{display:flex;flex-wrap:wrap;gap:8px 32px}\
table.kv td{text-align:left}tr.fail td{background:#fde2e2}.absent{color:#666;font-style:italic}.warn{color:#8a3b00}\
figure{margin:16px 0}figcaption{font-size:14px;color:#444}\
svg{max-width:100%;height:auto;display:block}code{font-size:14px}";

/// The section ids and titles, in page order: the answer (the predictions, their verdicts and
/// the law they extrapolate) first, then what it was built from.
const SECTIONS: [(&str, &str); 7] = [
    ("predictions", "Predictions"),
    ("corpus", "Corpus"),
    ("tokenizers", "Tokenizers"),
    ("sweep", "Sweep status"),
    ("isoflop", "IsoFLOP curves"),
    ("laws", "Scaling laws"),
    ("planner", "Sweep planner"),
];

/// The fit's chart that the predictions rest on: the N_opt law they extrapolate to each
/// budget. It is drawn under the predictions, not again under the laws.
const PREDICTION_CHART: &str = "law_n_opt_vs_c";

/// A `sweep replay` folder: its summary and its charts (SVG documents).
pub struct Replay {
    /// The folder.
    pub dir: PathBuf,
    /// Its `summary.json`.
    pub summary: fits::replay::ReplaySummary,
    /// `replay-width.svg` and `replay-error.svg`.
    pub charts: Vec<String>,
}

/// An IsoFLOP sweep as its folder holds it.
pub struct Sweep {
    /// The sweep folder.
    pub dir: PathBuf,
    /// Its plan.
    pub plan: IsoFlopPlan,
    /// Where each point stands, from its run folder.
    pub points: Vec<PointStatus>,
    /// The rows of `results.csv` (empty when the folder has none).
    pub rows: Vec<RunRow>,
}

/// The data-bound verdict at one budget: the sentence a data engineer acts on.
pub struct DataVerdict {
    /// Budget C.
    pub budget: f64,
    /// The hours it was asked on, as given.
    pub hours: String,
    /// predict's verdict ("data-bound above … buy data — doubling …").
    pub sentence: String,
    /// The data-constrained optimum at C on these hours, in one line.
    pub optimum: String,
    /// Whether C is past C_sat on these hours (the IsoFLOP laws, fitted as if every token
    /// were fresh, do not apply there).
    pub bound: bool,
}

/// Everything the page shows, each part present when an input provided it.
pub struct Study {
    /// The inputs as given.
    pub inputs: Vec<PathBuf>,
    /// A corpus folder and its statistics.
    pub corpus: Option<(PathBuf, CorpusStats)>,
    /// Tokenizer evaluations, each with the file it came from.
    pub tokenizers: Vec<(PathBuf, EvalReport)>,
    /// A sweep folder.
    pub sweep: Option<Sweep>,
    /// A fit and its `fits.json`.
    pub fits: Option<(PathBuf, Fits)>,
    /// A prediction (or why there is none) at each budget.
    pub predictions: Vec<(f64, Result<Prediction, String>)>,
    /// predict's data-bound verdict at each budget (given the corpus's hours).
    pub data_verdicts: Vec<DataVerdict>,
    /// A replay of the sweep planner.
    pub replay: Option<Replay>,
}

/// The sections on the page: the planner's only when a replay was given.
fn shown(study: &Study) -> impl Iterator<Item = (&'static str, &'static str)> + '_ {
    SECTIONS
        .into_iter()
        .filter(|(id, _)| *id != "planner" || study.replay.is_some())
}

/// The whole page.
pub fn page(study: &Study) -> Result<String> {
    let mut body = String::new();
    for (id, title) in shown(study) {
        let inner = match id {
            "corpus" => corpus(study),
            "tokenizers" => tokenizers(study),
            "sweep" => study
                .sweep
                .as_ref()
                .map_or_else(|| absent("sweep folder"), sweep),
            "isoflop" => match &study.fits {
                Some((_, f)) => isoflop(f)?,
                None => absent("fit"),
            },
            "laws" => match &study.fits {
                Some((path, f)) => laws(&path.display().to_string(), f)?,
                None => absent("fit"),
            },
            "predictions" => predictions(study)?,
            _ => study.replay.as_ref().map_or_else(String::new, planner),
        };
        let _ = writeln!(
            body,
            "<section id=\"{id}\"><h2>{title}</h2>{inner}</section>"
        );
    }
    let inputs: Vec<String> = study
        .inputs
        .iter()
        .map(|p| format!("<code>{}</code>", esc(&p.display().to_string())))
        .collect();
    let nav: String = shown(study)
        .map(|(id, title)| format!("<a href=\"#{id}\">{title}</a>"))
        .collect();
    Ok(format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
         <title>motionscale report</title><style>{STYLE}</style></head><body>\n\
         <h1>motionscale report</h1><p>From {} (motionscale {}).</p><nav>{nav}</nav>\n{body}\
         </body></html>\n",
        inputs.join(", "),
        env!("CARGO_PKG_VERSION")
    ))
}

/// The titles of the sections that have content, in page order.
pub fn contents(study: &Study) -> Vec<&'static str> {
    SECTIONS
        .iter()
        .filter(|(id, _)| has_content(study, id))
        .map(|(_, title)| *title)
        .collect()
}

/// Whether the inputs gave section `id` something to show.
fn has_content(study: &Study, id: &str) -> bool {
    match id {
        "predictions" => !study.predictions.is_empty(),
        "corpus" => study.corpus.is_some(),
        "tokenizers" => !study.tokenizers.is_empty(),
        "sweep" => study.sweep.is_some(),
        "isoflop" | "laws" => study.fits.is_some(),
        _ => study.replay.is_some(),
    }
}

/// The planner's replay: each policy's summary against the full table, and its curves.
fn planner(r: &Replay) -> String {
    let s = &r.summary;
    let opt = |v: Option<f64>| v.map_or("never".to_string(), |v| format!("{v:.3}"));
    let rows = s.policies.iter().map(|p| {
        let cells = vec![
            p.policy.clone(),
            p.orders.to_string(),
            format!("{:.3}", p.final_share),
            format!("{:.3}", p.final_width),
            format!("{:.3}", p.final_error),
            format!(
                "{} ({}/{})",
                opt(p.share_to_full_width),
                p.orders_reaching_full_width,
                p.orders
            ),
            format!("{:.3}", p.mean_width),
            format!("{:.3}", p.mean_error),
        ];
        (None, cells)
    });
    let head = [
        "policy",
        "orders",
        "compute at end (share)",
        "width at end",
        "error at end",
        "share to the full table's width",
        "mean width",
        "mean error",
    ];
    format!(
        "<p>Replay of <code>{}</code> from <code>{}</code>: target {} at C* = {} (truth {:.4}); the full table's 95% interval is {:.4} wide; every policy starts from {} runs ({:.1}% of the compute) and stops at {:.0}%.</p>{}{}{}",
        esc(&r.dir.display().to_string()),
        esc(&s.results),
        esc(&s.target),
        sig(s.target_budget),
        s.truth,
        s.full_table.width,
        s.start_runs,
        100.0 * s.start_share,
        100.0 * s.max_compute_share,
        table("", &head, rows),
        s.active_predictive_check.as_ref().map_or_else(String::new, |c| format!(
            "<p>Active's model where it stopped, against the {} runs it left: RMS z {:.2}, |z| &gt; 1.96 at {:.0}% (1 and 5% if its predictive SD is right).</p>",
            c.runs,
            c.rms_z,
            100.0 * c.beyond_95
        )),
        r.charts.iter().map(|c| format!("<figure>{c}</figure>")).collect::<String>()
    )
}

/// `s` with the HTML special characters escaped.
fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

fn absent(what: &str) -> String {
    format!("<p class=\"absent\">No {what} among the inputs.</p>")
}

/// A table of escaped text cells with a class (`kv`: left-aligned values); a row with a class
/// gets it (`fail` highlights it).
fn table(
    class: &str,
    head: &[&str],
    rows: impl IntoIterator<Item = (Option<&'static str>, Vec<String>)>,
) -> String {
    let mut s = format!("<div class=\"scroll\"><table class=\"{class}\"><tr>");
    for h in head {
        let _ = write!(s, "<th>{}</th>", esc(h));
    }
    s.push_str("</tr>");
    for (class, cells) in rows {
        match class {
            Some(c) => {
                let _ = write!(s, "<tr class=\"{c}\">");
            }
            None => s.push_str("<tr>"),
        }
        for c in cells {
            let _ = write!(s, "<td>{}</td>", esc(&c));
        }
        s.push_str("</tr>");
    }
    s.push_str("</table></div>");
    s
}

/// A list of escaped items with a class (e.g. warnings), or nothing when empty.
fn list(title: &str, class: &str, items: &[String]) -> String {
    if items.is_empty() {
        return String::new();
    }
    let items: String = items
        .iter()
        .map(|i| format!("<li>{}</li>", esc(i)))
        .collect();
    format!("<p>{}</p><ul class=\"{class}\">{items}</ul>", esc(title))
}

fn corpus(study: &Study) -> String {
    let Some((dir, stats)) = &study.corpus else {
        return absent("corpus");
    };
    let mut s = format!(
        "<p><code>{}</code>: {} clips, {:.2} hours of motion, {} rejected inputs.</p><div class=\"grid\">",
        esc(&dir.display().to_string()),
        stats.clips,
        stats.hours,
        stats.rejects
    );
    for (key, groups) in &stats.by {
        let rows = groups.iter().map(|(k, b)| {
            (
                None,
                vec![k.clone(), b.clips.to_string(), format!("{:.3}", b.hours)],
            )
        });
        s.push_str(&table("", &[key, "clips", "hours"], rows));
    }
    s.push_str("</div>");
    s
}

fn tokenizers(study: &Study) -> String {
    if study.tokenizers.is_empty() {
        return absent("tokenizer evaluation");
    }
    let rows = study.tokenizers.iter().map(|(path, e)| {
        let per_code = e.tokens as f64 / e.codebook_size as f64;
        let name = path
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let cells = vec![
            name,
            e.quantizer.clone(),
            format!("{} → {}", e.nominal_codebook, e.codebook_size),
            e.split.clone(),
            e.clips.to_string(),
            e.tokens.to_string(),
            format!("{per_code:.2}"),
            format!("{:.4}", e.recon_l1),
            format!("{:.1}", e.mpjpe_mm),
            format!("{} ({:.1}%)", e.used_codes, 100.0 * e.utilization),
            format!("{:.1}%", 100.0 * (1.0 - (-per_code).exp())),
            format!("{:.1}", e.perplexity),
        ];
        (None, cells)
    });
    let head = [
        "evaluation",
        "quantizer",
        "codebook K",
        "split",
        "clips",
        "tokens N",
        "N/K",
        "recon L1",
        "MPJPE mm",
        "codes used",
        "uniform coverage",
        "perplexity",
    ];
    format!(
        "{}<p>Codebook use is only meaningful where N ≫ K: the uniform coverage \
         1 − e<sup>−N/K</sup> is what a perfectly uniform tokenizer would reach on the same tokens.</p>",
        table("", &head, rows)
    )
}

/// A point's state, counting a row of the results table as done when its run folder is absent
/// (a sweep whose results were kept without its run folders).
fn state(sweep: &Sweep, i: usize) -> (&'static str, Option<&experiments::results::RunRow>) {
    let point = &sweep.points[i];
    let row = sweep.rows.iter().find(|r| r.run_id == point.run_id);
    match (point.state, row) {
        (PointState::Pending, Some(row)) => ("done (results table)", Some(row)),
        (state, row) => (state.as_str(), row),
    }
}

fn sweep(sweep: &Sweep) -> String {
    let states: Vec<_> = (0..sweep.points.len()).map(|i| state(sweep, i)).collect();
    let mut counts: Vec<(&str, usize)> = Vec::new();
    for (s, _) in &states {
        match counts.iter_mut().find(|(k, _)| k == s) {
            Some((_, n)) => *n += 1,
            None => counts.push((s, 1)),
        }
    }
    let counts: Vec<String> = counts.iter().map(|(s, n)| format!("{n} {s}")).collect();
    let plan = &sweep.plan;
    let mut s = format!(
        "<p><code>{}</code>: {} points ({}); corpus <code>{}</code>, text encoder <code>{}</code>; \
         vocabularies {}; results table: {} rows.</p>",
        esc(&sweep.dir.display().to_string()),
        sweep.points.len(),
        counts.join(", "),
        esc(&plan.corpus.display().to_string()),
        esc(&plan.text_encoder),
        plan.vocabularies
            .iter()
            .map(|v| format!("{} ({} codes)", v.codebook, v.codebook_size))
            .collect::<Vec<_>>()
            .join(", "),
        sweep.rows.len()
    );
    let rows = plan.points.iter().zip(&states).map(|(p, (state, row))| {
        let loss = |f: fn(&experiments::results::RunRow) -> f64| {
            row.map_or(String::new(), |r| format!("{:.4}", f(r)))
        };
        let cells = vec![
            p.run_id.clone(),
            sig(p.budget),
            p.model.clone(),
            p.codebook.to_string(),
            count(p.n_nv),
            count(p.n_v),
            count(p.tokens),
            format!("{:.2}", p.epochs),
            state.to_string(),
            loss(|r| r.test_loss),
            loss(|r| r.norm_test_loss),
        ];
        (matches!(*state, "failed").then_some("fail"), cells)
    });
    let head = [
        "run",
        "C (FLOPs)",
        "model",
        "V",
        "N_nv",
        "N_v",
        "D",
        "epochs",
        "state",
        "test CE",
        "L_u",
    ];
    s.push_str(&table("", &head, rows));
    s
}

/// Inline SVG of the fit's charts whose file stem passes `keep`.
fn charts(f: &Fits, keep: impl Fn(&str) -> bool) -> Result<String> {
    let mut s = String::new();
    for (_, chart) in fits::report::charts(f).into_iter().filter(|(k, _)| keep(k)) {
        let _ = write!(
            s,
            "<figure>{}<figcaption>{}</figcaption></figure>",
            chart.svg()?,
            esc(&chart.title)
        );
    }
    Ok(s)
}

fn isoflop(f: &Fits) -> Result<String> {
    let rows = f.budgets.iter().map(|b| {
        let opt = |v: Option<f64>| v.map_or("–".to_string(), sig);
        let verdict = if b.min.interior {
            "interior".to_string()
        } else {
            format!(
                "not used: {}",
                b.min.reason.as_deref().unwrap_or("not interior")
            )
        };
        let cells = vec![
            sig(b.min.budget),
            b.runs.to_string(),
            opt(b.min.opt),
            opt(b.min.loss_opt),
            opt(b.d_opt),
            opt(b.nv_opt),
            verdict,
        ];
        ((!b.min.interior).then_some("fail"), cells)
    });
    let head = [
        "C (FLOPs)",
        "runs",
        "N_opt",
        "loss at N_opt",
        "D_opt",
        "N_v,opt",
        "minimum",
    ];
    Ok(format!(
        "<p>{} rows of <code>{}</code> in {} budget groups ({}).</p>{}{}",
        f.input.rows,
        esc(&f.input.file),
        f.input.groups,
        esc(&f.input.grouping),
        table("", &head, rows),
        charts(f, |k| k.starts_with("isoflop"))?
    ))
}

fn laws(path: &str, f: &Fits) -> Result<String> {
    let mut rows: Vec<(Option<&'static str>, Vec<String>)> = f
        .power_laws
        .iter()
        .map(|(key, law)| {
            let cells = vec![
                key.clone(),
                law.equation(),
                estimate_text(&law.fit.slope),
                r2(law.fit.r2),
                law.fit.n_points.to_string(),
            ];
            (None, cells)
        })
        .collect();
    if let Some(law) = &f.log_law {
        let cells = vec![
            "log law".into(),
            law.equation(),
            estimate_text(&law.fit.slope),
            r2(law.fit.r2),
            law.fit.n_points.to_string(),
        ];
        rows.push((None, cells));
    }
    let mut s = format!(
        "<p>From <code>{}</code>; 95% intervals in brackets (t intervals of the OLS fits, \
         bootstrap percentiles of the parametric fit).</p>{}",
        esc(path),
        table(
            "",
            &["law", "equation", "exponent / slope", "R²", "points"],
            rows
        )
    );
    if let Some(p) = &f.parametric {
        let _ = write!(
            s,
            "<h3>Parametric L(N, D) = E + A/N<sup>α</sup> + B/D<sup>β</sup></h3><p>On {} ({} runs; \
             {} starts, {} at the optimum; {} of {} bootstrap refits).</p>",
            esc(&p.loss_column),
            p.n_runs,
            p.starts,
            p.starts_at_optimum,
            p.bootstrap.succeeded,
            p.bootstrap.resamples
        );
        let rows: [(&str, &Estimate); 7] = [
            ("E", &p.law.e),
            ("A", &p.law.a),
            ("B", &p.law.b),
            ("α", &p.law.alpha),
            ("β", &p.law.beta),
            ("N_opt ∝ C^", &p.n_opt_exponent),
            ("D_opt ∝ C^", &p.d_opt_exponent),
        ];
        let rows = rows.map(|(k, e)| (None, vec![k.to_string(), estimate_text(e)]));
        s.push_str(&table(
            "kv",
            &["parameter", "estimate [95% interval]"],
            rows,
        ));
    }
    s.push_str(&checks_of_the_law(f));
    s.push_str(&list("Input notes:", "", &f.input.notes));
    s.push_str(&list("Fits not done:", "warn", &f.skipped));
    s.push_str(&list("Warnings:", "warn", &f.warnings));
    s.push_str(&charts(f, |k| {
        !k.starts_with("isoflop") && k != PREDICTION_CHART
    })?);
    Ok(s)
}

/// Approaches 2 and 3 side by side, the total-parameter convention, the data-constrained fit
/// and the held-out budget, as far as the fit has them.
fn checks_of_the_law(f: &Fits) -> String {
    let mut s = String::new();
    if !f.agreement.is_empty() {
        s.push_str(&approaches(f));
    }
    if let Some(t) = &f.total_n {
        s.push_str(&conventions(f, t));
    }
    if let Some(r) = &f.repeated_data {
        s.push_str(&repeated_data(r));
    }
    if let Some(h) = &f.holdout {
        s.push_str(&holdout(h));
    }
    s
}

/// The exponents of approach 2 (IsoFLOP minima) against approach 3 (parametric).
fn approaches(f: &Fits) -> String {
    let rows = f.agreement.iter().map(|a| {
        let overlap = match a.overlap {
            Some(true) => "yes",
            Some(false) => "no",
            None => "n/a",
        };
        let class = (a.overlap == Some(false)).then_some("fail");
        let cells = vec![
            format!("{} ∝ C^", a.quantity),
            estimate_text(&a.isoflop),
            estimate_text(&a.parametric),
            overlap.to_string(),
        ];
        (class, cells)
    });
    let head = ["exponent", "approach 2", "approach 3", "intervals overlap"];
    format!(
        "<h3>Approach 2 (IsoFLOP minima) vs approach 3 (parametric)</h3>{}",
        table("", &head, rows)
    )
}

/// The exponents of the fit `f` (N counts non-vocabulary parameters) beside those of `total`
/// (N counts every parameter).
fn conventions(f: &Fits, total: &Fits) -> String {
    let exponent = |g: &Fits, k: &str| {
        g.power_laws
            .get(k)
            .map_or("–".into(), |l| estimate_text(&l.fit.slope))
    };
    let row = |name: &str, g: &Fits| {
        let p = g.parametric.as_ref();
        let cells = vec![
            name.to_string(),
            exponent(g, "n_opt_vs_c"),
            exponent(g, "d_opt_vs_c"),
            p.map_or("–".into(), |p| estimate_text(&p.n_opt_exponent)),
        ];
        (None, cells)
    };
    let head = [
        "N counts",
        "N_opt ∝ C^ (approach 2)",
        "D_opt ∝ C^",
        "N_opt ∝ C^ (approach 3)",
    ];
    let rows = [
        row("non-vocabulary (N_nv)", f),
        row("every parameter (N_nv + N_v)", total),
    ];
    format!("<h3>Parameter conventions</h3>{}", table("", &head, rows))
}

/// The data-constrained law L(N, D'): its constants, the exchange rate of synthetic tokens and
/// its leave-one-budget-out error against the plain law.
fn repeated_data(r: &RepeatedData) -> String {
    format!(
        "<h3>Data-constrained L({}, D')</h3><p>R*_D = {}{}, α = {}, β = {} ({} of {} runs repeat data, up to {:.1} epochs).{}{}</p>",
        if r.r_star_n.is_some() { "N'" } else { "N" },
        esc(&estimate_text(&r.r_star)),
        r.r_star_n.as_ref().map_or(String::new(), |rn| format!(
            ", R*_N = {} ({} runs larger than U_N)",
            esc(&estimate_text(rn)),
            r.past_base_size
        )),
        esc(&estimate_text(&r.law.alpha)),
        esc(&estimate_text(&r.law.beta)),
        r.repeated_runs,
        r.n_runs,
        r.max_epochs,
        r.exchange.as_ref().map_or(String::new(), |rho| format!(
            " A synthetic token is worth {} captured tokens.",
            esc(&estimate_text(rho))
        )),
        r.held_out.as_ref().map_or(String::new(), |h| format!(
            " Leave-one-budget-out RMS log error: plain {}, data-constrained {}.",
            sig(h.plain_rms),
            sig(h.repeated_rms)
        ))
    )
}

/// The held-out budget's trained optimum against what the laws predicted for it.
fn holdout(h: &Holdout) -> String {
    let rows = h.checks.iter().map(|c| {
        let inside = c
            .inside
            .map_or("n/a", |i| if i { "inside" } else { "outside" });
        let class = (c.inside == Some(false)).then_some("fail");
        let cells = vec![
            c.quantity.clone(),
            estimate_text(&c.predicted),
            sig(c.trained),
            format!("{:.3}", c.ratio),
            inside.to_string(),
        ];
        (class, cells)
    });
    let head = [
        "quantity",
        "predicted [95% prediction interval]",
        "trained",
        "ratio",
        "",
    ];
    format!(
        "<h3>Held-out budget C = {} ({} runs, not fitted)</h3>{}{}",
        sig(h.budget),
        h.runs,
        table("", &head, rows),
        list("Not predicted:", "warn", &h.missing)
    )
}

/// An integer in full below 10^5, else in scientific notation like [`sig`].
fn count(n: u64) -> String {
    if n < 100_000 {
        n.to_string()
    } else {
        sig(n as f64)
    }
}

fn r2(r2: Option<f64>) -> String {
    r2.map_or("n/a".into(), |v| format!("{v:.4}"))
}

/// The predictions at each budget with predict's verdict on them, the chart of the law they
/// extrapolate, and the consistency checks between the laws.
fn predictions(study: &Study) -> Result<String> {
    if study.predictions.is_empty() {
        return Ok(absent("fit to predict from"));
    }
    let mut s = data_verdicts(study);
    for (budget, p) in &study.predictions {
        let _ = write!(s, "<h3>C = {} FLOPs</h3>", sig(*budget));
        if let Some(v) = study
            .data_verdicts
            .iter()
            .find(|v| v.budget == *budget && v.bound)
        {
            let _ = write!(
                s,
                "<p class=\"warn\">Past C_sat on {}: the IsoFLOP laws below extrapolate as if every token were fresh and do not apply here; the data-constrained optimum above does.</p>",
                esc(&v.hours)
            );
        }
        match p {
            Ok(p) => s.push_str(&prediction(p)),
            Err(e) => {
                let _ = write!(s, "<p class=\"warn\">No prediction: {}</p>", esc(e));
            }
        }
    }
    if let Some((_, f)) = &study.fits {
        s.push_str(&charts(f, |k| k == PREDICTION_CHART)?);
    }
    for (budget, p) in &study.predictions {
        if let Ok(p) = p {
            let _ = write!(
                s,
                "<p>Consistency checks between the laws at C = {} FLOPs:</p>{}",
                sig(*budget),
                consistency(p)
            );
        }
    }
    Ok(s)
}

/// The data-bound verdicts first, each budget's in one line; or, for a fit of the
/// data-constrained law asked without hours, how to get them.
fn data_verdicts(study: &Study) -> String {
    let has_data_law = study
        .fits
        .as_ref()
        .is_some_and(|(_, f)| f.repeated_data.is_some());
    if study.data_verdicts.is_empty() {
        return match has_data_law {
            true => "<p class=\"warn\">The fit has a data-constrained law: give --hours real=H,synth=H for its data-bound verdict.</p>".into(),
            false => String::new(),
        };
    }
    let lines = study.data_verdicts.iter().map(|v| {
        format!(
            "<p><b>C = {} FLOPs on {}:</b> {} <br>The data-constrained optimum: {}.</p>",
            sig(v.budget),
            esc(&v.hours),
            esc(&v.sentence),
            esc(&v.optimum)
        )
    });
    format!(
        "<div class=\"verdict data\">{}</div>",
        lines.collect::<String>()
    )
}

/// The predicted quantities with their 95% intervals, then predict's verdict on them.
fn prediction(p: &Prediction) -> String {
    let rows = crate::fit::prediction_rows(p)
        .into_iter()
        .map(|(name, value)| (None, vec![name.to_string(), value]));
    format!(
        "{}{}",
        table("kv", &["quantity", "prediction [95% interval]"], rows),
        verdict(p)
    )
}

/// predict's verdict on `p`: its warnings (intervals too wide to act on, laws that disagree),
/// or that it has none.
fn verdict(p: &Prediction) -> String {
    if p.warnings.is_empty() {
        return "<p class=\"verdict\">Verdict: no warnings from predict.</p>".into();
    }
    format!(
        "<div class=\"verdict\">{}</div>",
        list("Verdict:", "warn", &p.warnings)
    )
}

/// The consistency checks between the laws at `p`'s budget, failed ones highlighted.
fn consistency(p: &Prediction) -> String {
    let checks = p.consistency.iter().map(|c| {
        let cells = vec![
            c.name.clone(),
            sig(c.value),
            sig(c.reference),
            format!("{:.3}", c.ratio),
            c.rule.clone(),
            if c.ok { "ok" } else { "FAILED" }.to_string(),
        ];
        ((!c.ok).then_some("fail"), cells)
    });
    table(
        "",
        &["check", "value", "reference", "ratio", "rule", "result"],
        checks,
    )
}
