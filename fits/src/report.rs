//! Writing a fit: `fits.json`, the plots (SVG + PNG) and a short text summary.

use crate::fitted::{DataFrontierPoint, Fits, InSampleCoverage, RepeatedData, StoppingRule};
use crate::laws::{Estimate, PowerLaw};
use crate::FitError;
use plot::ticks::format_tick;
use plot::{Chart, Series};
use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};

/// Palette index for the markers of interior minima (black).
const MINIMA_COLOR: usize = 7;

/// Palette index of the i-th curve, skipping the minima's black.
fn curve_color(i: usize) -> usize {
    let i = i % (plot::PALETTE_LEN - 1);
    if i >= MINIMA_COLOR {
        i + 1
    } else {
        i
    }
}

/// The column the fit used for `role` (empty when none).
fn column(f: &Fits, role: &str) -> String {
    f.input
        .columns
        .get(role)
        .cloned()
        .flatten()
        .unwrap_or_default()
}

/// The charts of a fit, each with its file stem.
pub fn charts(f: &Fits) -> Vec<(String, Chart)> {
    let mut out = Vec::new();
    let n_name = column(f, "N");
    let loss_name = column(f, "loss");
    let mut iso = Chart::new(
        "IsoFLOP curves: loss vs N per budget, fitted parabolas in log10 N",
        format!("N ({n_name})"),
        format!("loss ({loss_name})"),
    );
    iso.log_x = true;
    for (i, b) in f.budgets.iter().enumerate() {
        let pts = b.min.points.iter().map(|p| (p[0], p[1])).collect();
        iso.series.push(
            Series::points(format!("C = {}", format_tick(b.min.budget)), pts)
                .with_color(curve_color(i)),
        );
        if let Some(curve) = parabola_curve(&b.min.points, b.min.parabola) {
            iso.series
                .push(Series::line("", curve).with_color(curve_color(i)));
        }
    }
    let minima: Vec<(f64, f64)> = f
        .budgets
        .iter()
        .filter(|b| b.min.interior)
        .filter_map(|b| Some((b.min.opt?, b.min.loss_opt?)))
        .collect();
    if !minima.is_empty() {
        iso.series
            .push(Series::points("interior minimum", minima).with_color(MINIMA_COLOR));
    }
    out.push(("isoflop_n".to_string(), iso));

    // One chart of vocabulary curves per budget (one curve per N).
    let mut budgets: Vec<f64> = f.vocab_minima.iter().map(|m| m.budget).collect();
    budgets.dedup();
    for (k, &c) in budgets.iter().enumerate() {
        let mut v = Chart::new(
            format!(
                "IsoFLOP curves over V at C = {}, parabolas in log10 V",
                format_tick(c)
            ),
            "vocabulary size V",
            format!("loss ({loss_name})"),
        );
        v.log_x = true;
        let at_c = f.vocab_minima.iter().filter(|m| m.budget == c);
        for (i, m) in at_c.enumerate() {
            let name = format!("N = {}", format_tick(m.fixed_n.unwrap_or(f64::NAN)));
            let pts = m.points.iter().map(|p| (p[0], p[1])).collect();
            v.series
                .push(Series::points(name, pts).with_color(curve_color(i)));
            if let Some(curve) = parabola_curve(&m.points, m.parabola) {
                v.series
                    .push(Series::line("", curve).with_color(curve_color(i)));
            }
        }
        let minima: Vec<(f64, f64)> = f
            .vocab_minima
            .iter()
            .filter(|m| m.budget == c && m.interior)
            .filter_map(|m| Some((m.opt?, m.loss_opt?)))
            .collect();
        if !minima.is_empty() {
            v.series
                .push(Series::points("interior minimum", minima).with_color(MINIMA_COLOR));
        }
        out.push((format!("isoflop_v_{}", k + 1), v));
    }

    // The held-out budget's own minimum, marked on the laws that predicted it.
    let held = f
        .holdout
        .as_ref()
        .filter(|h| h.trained.interior)
        .and_then(|h| Some((h.budget, h.trained.opt?, h.trained.loss_opt?)));
    for (key, law) in &f.power_laws {
        let held_point = held.filter(|_| key == "n_opt_vs_c").map(|(c, n, _)| (c, n));
        out.push((format!("law_{key}"), power_law_chart(law, held_point)));
    }
    if let Some(law) = &f.log_law {
        let pts: Vec<(f64, f64)> = law
            .fit
            .points
            .iter()
            .map(|p| (10f64.powf(p[0]), p[1]))
            .collect();
        let held_point = held.map(|(c, _, l)| (c, l));
        let (lo, hi) = x_range(&pts, held_point);
        let mut chart = Chart::new(
            format!(
                "Log law: {}  (R² = {})",
                law.equation(),
                r2_text(law.fit.r2)
            ),
            "compute C (FLOPs)",
            format!("loss at the IsoFLOP minimum ({loss_name})"),
        );
        chart.log_x = true;
        chart.series.push(Series::points("IsoFLOP minima", pts));
        push_fit(&mut chart, lo, hi, |c| law.at(c), held_point);
        out.push(("log_law".to_string(), chart));
    }
    out.extend(data_charts(f));
    out
}

/// Synthetic shares below this are captured-only corpora, above 1 − this synthetic-only.
const ONE_SOURCE_SHARE: f64 = 0.05;

/// The data-constrained fit's charts: the lowest loss at each budget against the unique data
/// (`data_loss_vs_hours`), and, with an exchange rate ρ, the same against the captured-
/// equivalent data U·(1 − s + ρ·s) (`data_exchange_rate`), where corpora of any mix fall on
/// one curve per budget if ρ is right.
fn data_charts(f: &Fits) -> Vec<(String, Chart)> {
    let Some(r) = f.repeated_data.as_ref().filter(|r| !r.frontier.is_empty()) else {
        return Vec::new();
    };
    let by_hours = r.frontier.iter().all(|p| p.hours.is_some());
    let unit = if by_hours { "hours" } else { "tokens" };
    let size = |p: &DataFrontierPoint| match by_hours {
        true => p.hours.unwrap_or(f64::NAN),
        false => p.unique_tokens,
    };
    let loss_name = column(f, "parametric_loss");
    let mut out = vec![(
        "data_loss_vs_hours".to_string(),
        data_chart(
            &r.frontier,
            "Lowest loss vs unique data, per budget (lines: mixed; dots: one source)",
            format!("unique data ({unit})"),
            &loss_name,
            size,
        ),
    )];
    if let Some(rho) = &r.exchange {
        let k = |p: &DataFrontierPoint| 1.0 - p.synth_share + rho.value * p.synth_share;
        out.push((
            "data_exchange_rate".to_string(),
            data_chart(
                &r.frontier,
                &format!(
                    "Captured-equivalent data U·(1 − s + ρ·s), ρ = {:.2} [{:.2}, {:.2}]",
                    rho.value,
                    rho.ci_low.unwrap_or(f64::NAN),
                    rho.ci_high.unwrap_or(f64::NAN)
                ),
                format!("captured-equivalent unique data ({unit})"),
                &loss_name,
                |p| size(p) * k(p),
            ),
        ));
    }
    out
}

/// `captured only`, `synthetic only` or `mixed`, by a corpus's synthetic share.
fn source_kind(synth_share: f64) -> &'static str {
    match synth_share {
        s if s < ONE_SOURCE_SHARE => "captured only",
        s if s > 1.0 - ONE_SOURCE_SHARE => "synthetic only",
        _ => "mixed",
    }
}

/// One chart of `frontier` at x = `x(point)`: per budget, a line through its mixed corpora
/// and markers for its captured-only and synthetic-only ones.
fn data_chart(
    frontier: &[DataFrontierPoint],
    title: &str,
    x_label: String,
    loss_name: &str,
    x: impl Fn(&DataFrontierPoint) -> f64,
) -> Chart {
    let mut chart = Chart::new(title, x_label, format!("lowest loss ({loss_name})"));
    chart.log_x = true;
    let mut budgets: Vec<f64> = frontier.iter().map(|p| p.budget).collect();
    budgets.dedup();
    for (i, &c) in budgets.iter().enumerate() {
        for kind in ["mixed", "captured only", "synthetic only"] {
            let mut pts: Vec<(f64, f64)> = frontier
                .iter()
                .filter(|p| p.budget == c && source_kind(p.synth_share) == kind)
                .map(|p| (x(p), p.loss))
                .collect();
            if pts.is_empty() {
                continue;
            }
            pts.sort_by(|a, b| a.0.total_cmp(&b.0));
            let name = format!("C = {}, {kind}", format_tick(c));
            if kind == "mixed" {
                chart
                    .series
                    .push(Series::line(name, pts.clone()).with_color(curve_color(i)));
                chart
                    .series
                    .push(Series::points("", pts).with_color(curve_color(i)));
            } else {
                chart
                    .series
                    .push(Series::points(name, pts).with_color(curve_color(i)));
            }
        }
    }
    chart
}

fn r2_text(r2: Option<f64>) -> String {
    r2.map_or("n/a".into(), |v| format!("{v:.4}"))
}

/// The x range of `pts` and of the held-out point, if any.
fn x_range(pts: &[(f64, f64)], held: Option<(f64, f64)>) -> (f64, f64) {
    pts.iter()
        .chain(held.as_ref())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
            (a.min(p.0), b.max(p.0))
        })
}

/// The fitted line over [lo, hi] (log-spaced), its 95% interval band as two thin lines, and
/// the held-out budget's own minimum.
fn push_fit(
    chart: &mut Chart,
    lo: f64,
    hi: f64,
    at: impl Fn(f64) -> Estimate,
    held: Option<(f64, f64)>,
) {
    let xs: Vec<f64> = (0..60)
        .map(|k| 10f64.powf(lo.log10() + (hi.log10() - lo.log10()) * k as f64 / 59.0))
        .collect();
    let curve = |f: &dyn Fn(&Estimate) -> Option<f64>| -> Vec<(f64, f64)> {
        xs.iter().filter_map(|&x| Some((x, f(&at(x))?))).collect()
    };
    chart
        .series
        .push(Series::line("fit", curve(&|e| Some(e.value))).with_color(0));
    let low = curve(&|e| e.ci_low);
    if !low.is_empty() {
        chart
            .series
            .push(Series::line("95% interval", low).with_color(1));
        chart
            .series
            .push(Series::line("", curve(&|e| e.ci_high)).with_color(1));
    }
    if let Some(p) = held {
        chart
            .series
            .push(Series::points("held-out budget (trained)", vec![p]).with_color(3));
    }
}

/// 60 points of a fitted parabola across the sampled x range.
fn parabola_curve(points: &[[f64; 2]], parabola: Option<[f64; 4]>) -> Option<Vec<(f64, f64)>> {
    let [centre, c0, c1, c2] = parabola?;
    let lo = points.first()?[0].log10();
    let hi = points.last()?[0].log10();
    Some(
        (0..60)
            .map(|k| {
                let x = lo + (hi - lo) * k as f64 / 59.0;
                let u = x - centre;
                (10f64.powf(x), c0 + c1 * u + c2 * u * u)
            })
            .collect(),
    )
}

fn power_law_chart(law: &PowerLaw, held: Option<(f64, f64)>) -> Chart {
    let pts: Vec<(f64, f64)> = law
        .fit
        .points
        .iter()
        .map(|p| (10f64.powf(p[0]), 10f64.powf(p[1])))
        .collect();
    let (lo, hi) = x_range(&pts, held);
    let mut chart = Chart::new(
        format!("{}  (R² = {})", law.equation(), r2_text(law.fit.r2)),
        law.x.clone(),
        law.y.clone(),
    );
    chart.log_x = true;
    chart.log_y = true;
    chart.series.push(Series::points("IsoFLOP minima", pts));
    push_fit(&mut chart, lo, hi, |x| law.at(x), held);
    chart
}

/// Writes the plots and `fits.json` into `dir` (created if needed); records the plot stems in
/// `fits.plots`. Returns the paths written.
pub fn write_outputs(fits: &mut Fits, dir: &Path) -> Result<Vec<PathBuf>, FitError> {
    std::fs::create_dir_all(dir).map_err(|source| FitError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut written = Vec::new();
    fits.plots.clear();
    for (stem, chart) in charts(fits) {
        written.extend(chart.write(&dir.join(&stem))?);
        fits.plots.push(stem);
    }
    let path = dir.join("fits.json");
    let json = serde_json::to_vec_pretty(fits).map_err(|e| FitError::Invalid(e.to_string()))?;
    let io = |source| FitError::Io {
        path: path.clone(),
        source,
    };
    let mut tmp = tempfile::NamedTempFile::new_in(dir).map_err(io)?;
    tmp.write_all(&json).map_err(io)?;
    tmp.as_file().sync_all().map_err(io)?;
    tmp.persist(&path).map_err(|e| io(e.error))?;
    written.push(path);
    Ok(written)
}

/// `value [ci_low, ci_high]` with a given number of significant digits.
pub fn estimate_text(e: &Estimate) -> String {
    match (e.ci_low, e.ci_high) {
        (Some(lo), Some(hi)) => format!("{} [{}, {}]", sig(e.value), sig(lo), sig(hi)),
        _ => sig(e.value),
    }
}

/// Four significant digits, scientific for very large or small magnitudes.
pub fn sig(v: f64) -> String {
    if v != 0.0 && (v.abs() >= 1e5 || v.abs() < 1e-3) {
        format!("{v:.3e}")
    } else {
        format!("{v:.4}")
    }
}

/// The loss-shape forms and the one chosen, a line each.
fn loss_shape_lines(shape: &crate::loss_shape::LossShape, s: &mut String) {
    for form in &shape.forms {
        let lobo = form
            .lobo_rms
            .map_or("not scored (too few minima)".into(), |v| format!("{v:.4}"));
        let params: Vec<String> = form.params.iter().map(|v| format!("{v:.4}")).collect();
        let _ = writeln!(
            s,
            "loss shape {}: [{}] (x̄ = {:.3}), RMS {:.4}, leave-one-budget-out RMS {lobo}",
            form.form,
            params.join(", "),
            form.centre,
            form.rms
        );
    }
    if let Some(c) = &shape.chosen {
        let _ = writeln!(s, "loss shape chosen by leave-one-budget-out error: {c}");
    }
}

/// A short human summary of a fit.
pub fn summary(f: &Fits) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "input: {} ({} rows, {} budget groups by {})",
        f.input.file, f.input.rows, f.input.groups, f.input.grouping
    );
    for note in &f.input.notes {
        let _ = writeln!(s, "  note: {note}");
    }
    let interior = f.budgets.iter().filter(|b| b.min.interior).count();
    let _ = writeln!(
        s,
        "IsoFLOP minima over N: {interior} of {} interior",
        f.budgets.len()
    );
    for b in &f.budgets {
        match (b.min.interior, b.min.opt, b.min.loss_opt) {
            (true, Some(n), Some(l)) => {
                let _ = writeln!(
                    s,
                    "  C = {:.3e}: N_opt = {:.3e}, loss = {}",
                    b.min.budget,
                    n,
                    sig(l)
                );
            }
            _ => {
                let _ = writeln!(
                    s,
                    "  C = {:.3e}: not interior: {}",
                    b.min.budget,
                    b.min.reason.as_deref().unwrap_or("?")
                );
            }
        }
    }
    if !f.vocab_minima.is_empty() {
        let ok = f.vocab_minima.iter().filter(|m| m.interior).count();
        let _ = writeln!(
            s,
            "minima over V at fixed N: {ok} of {} interior",
            f.vocab_minima.len()
        );
    }
    for (key, law) in &f.power_laws {
        let _ = writeln!(
            s,
            "{key}: {}; exponent {}, R² {}, {} points, scatter around the law {} decades (RMS)",
            law.equation(),
            estimate_text(&law.fit.slope),
            r2_text(law.fit.r2),
            law.fit.n_points,
            law.fit.scatter().map_or("n/a".into(), sig)
        );
    }
    if let Some(law) = &f.log_law {
        let _ = writeln!(
            s,
            "log law: {}; slope {}, R² {}",
            law.equation(),
            estimate_text(&law.fit.slope),
            r2_text(law.fit.r2)
        );
    }
    if let Some(shape) = &f.loss_shape {
        loss_shape_lines(shape, &mut s);
    }
    if let Some(p) = &f.parametric {
        let _ = writeln!(
            s,
            "parametric L(N, D) = E + A/N^alpha + B/D^beta on {:?} ({} runs; {} starts, {} at the optimum; {} of {} bootstrap refits, 95% percentile intervals):",
            p.loss_column,
            p.n_runs,
            p.starts,
            p.starts_at_optimum,
            p.bootstrap.succeeded,
            p.bootstrap.resamples
        );
        for (name, e) in [
            ("E", &p.law.e),
            ("A", &p.law.a),
            ("B", &p.law.b),
            ("alpha", &p.law.alpha),
            ("beta", &p.law.beta),
        ] {
            let _ = writeln!(s, "  {name:<5} = {}", estimate_text(e));
        }
        let _ = writeln!(s, "  N_opt ∝ C^{}", estimate_text(&p.n_opt_exponent));
        let _ = writeln!(s, "  D_opt ∝ C^{}", estimate_text(&p.d_opt_exponent));
    }
    for a in &f.agreement {
        let _ = writeln!(
            s,
            "{} exponent: IsoFLOP (approach 2) {} vs parametric (approach 3) {}{}",
            a.quantity,
            estimate_text(&a.isoflop),
            estimate_text(&a.parametric),
            match a.overlap {
                Some(true) => ": intervals overlap",
                Some(false) => ": intervals DO NOT overlap",
                None => "",
            }
        );
    }
    extras(f, &mut s);
    for k in &f.skipped {
        let _ = writeln!(s, "skipped: {k}");
    }
    for w in &f.warnings {
        let _ = writeln!(s, "warning: {w}");
    }
    s
}

/// The in-sample coverage of the law's prediction intervals, and the cells they miss.
fn coverage_lines(c: &InSampleCoverage, s: &mut String) {
    let _ = writeln!(
        s,
        "  in sample: the 95% prediction interval (refits + a run's scatter, log SD {}) holds the best loss of {} of {} (budget, data subset) cells",
        sig(c.scatter),
        c.covered,
        c.cells
    );
    for m in &c.misses {
        let _ = writeln!(
            s,
            "    outside: C {} U {} synth {:.2}: best {} vs {}",
            sig(m.budget),
            sig(m.unique_tokens),
            m.synth_share,
            sig(m.loss),
            estimate_text(&m.predicted)
        );
    }
}

/// The exchange forms fitted, each with its held-out error (the adopted one first).
fn form_lines(r: &RepeatedData, s: &mut String) {
    for (k, f) in r.exchange_forms.iter().enumerate() {
        let rho = f.exchange.map_or("-".to_string(), sig);
        let error = f.held_out.as_ref().map_or("not scored".to_string(), |h| {
            format!(
                "RMS log error {} over {} {} left out",
                sig(h.rms),
                h.folds,
                h.clusters
            )
        });
        let adopted = if k == 0 { " (adopted)" } else { "" };
        let _ = writeln!(s, "  form {}{adopted}: rho {rho}, {error}", f.form.name());
    }
}

/// The block-bootstrap intervals of R*_D and ρ, a line per clustering.
fn block_lines(r: &RepeatedData, s: &mut String) {
    for b in &r.block_intervals {
        let _ = writeln!(
            s,
            "  block bootstrap, {} {} resampled whole ({} refits): R*_D [{}, {}]{}",
            b.count,
            b.clusters,
            b.refits,
            sig(b.r_star[0]),
            sig(b.r_star[1]),
            b.exchange.map_or(String::new(), |[lo, hi]| format!(
                ", ρ [{}, {}]",
                sig(lo),
                sig(hi)
            ))
        );
    }
}

/// The summary lines of the total-parameter convention, the data-constrained fit and the
/// held-out budget.
fn extras(f: &Fits, s: &mut String) {
    for n in &f.seed_noise {
        let _ = writeln!(
            s,
            "seed noise at C = {:.3e}, N = {:.3e}{}: loss {} ± sd {} over {} seeds; the parabola resolves {} (one size step from its vertex)",
            n.budget,
            n.n,
            n.v.map_or(String::new(), |v| format!(", V = {v}")),
            sig(n.mean),
            sig(n.sd),
            n.seeds.len(),
            n.resolved_gap.map_or("n/a".into(), sig)
        );
    }
    if let Some(t) = &f.total_n {
        let n = column(t, "N");
        let law = |k: &str, y: &str| {
            t.power_laws
                .get(k)
                .map_or(format!("{y} law not fitted"), |l| {
                    let scatter = l.fit.scatter().map_or("n/a".into(), sig);
                    format!(
                        "{y} ∝ C^{} (scatter {scatter} decades)",
                        estimate_text(&l.fit.slope)
                    )
                })
        };
        let _ = writeln!(
            s,
            "total parameters (N = {n}): {}, {}{}",
            law("n_opt_vs_c", "N_opt"),
            law("d_opt_vs_c", "D_opt"),
            t.parametric.as_ref().map_or(String::new(), |p| format!(
                "; parametric alpha {}, beta {}, N_opt ∝ C^{}",
                estimate_text(&p.law.alpha),
                estimate_text(&p.law.beta),
                estimate_text(&p.n_opt_exponent)
            ))
        );
    }
    if let Some(r) = &f.repeated_data {
        repeated_lines(r, s);
    }
    if let Some(h) = &f.holdout {
        let _ = writeln!(
            s,
            "held-out budget {:.3e} ({} runs; lowest loss {} at N = {:.3e}):",
            h.budget,
            h.runs,
            sig(h.best_run[1]),
            h.best_run[0]
        );
        for c in &h.checks {
            let _ = writeln!(
                s,
                "  {}: predicted {} vs trained {} (ratio {:.3}){}",
                c.quantity,
                estimate_text(&c.predicted),
                sig(c.trained),
                c.ratio,
                match c.inside {
                    Some(true) => ": inside the interval",
                    Some(false) => ": OUTSIDE the interval",
                    None => "",
                }
            );
        }
        for m in &h.missing {
            let _ = writeln!(s, "  not predicted: {m}");
        }
    }
}

/// The summary lines of the data-constrained fit.
fn repeated_lines(r: &RepeatedData, s: &mut String) {
    let _ = writeln!(
        s,
        "data-constrained L({}, D'): R*_D = {}, alpha {}, beta {}, E {} ({} of {} runs repeat data, up to {:.1} epochs)",
        if r.r_star_n.is_some() { "N'" } else { "N" },
        estimate_text(&r.r_star),
        estimate_text(&r.law.alpha),
        estimate_text(&r.law.beta),
        estimate_text(&r.law.e),
        r.repeated_runs,
        r.n_runs,
        r.max_epochs
    );
    if let Some(rn) = &r.r_star_n {
        let _ = writeln!(
            s,
            "  effective parameters N': R*_N = {} ({} of {} runs larger than U_N, the size the law allots their unique data)",
            estimate_text(rn),
            r.past_base_size,
            r.n_runs
        );
    }
    if let Some(rho) = &r.exchange {
        let _ = writeln!(
            s,
            "  exchange rate ({}): a synthetic token is worth {} captured tokens",
            r.exchange_form.name(),
            estimate_text(rho)
        );
    }
    form_lines(r, s);
    block_lines(r, s);
    if let Some(c) = &r.in_sample {
        coverage_lines(c, s);
    }
    if let Some(rule) = &r.stopping {
        let _ = writeln!(s, "  {}", stopping_text(rule));
    }
    for note in r.note.iter().chain(&r.note_n) {
        let _ = writeln!(s, "  note: {note}");
    }
    if let Some(h) = &r.held_out {
        let _ = writeln!(
            s,
            "  leave-one-budget-out RMS log error over {} budgets: plain {}, data-constrained {} ({} is better)",
            h.folds,
            sig(h.plain_rms),
            sig(h.repeated_rms),
            h.better
        );
    }
}

/// The stopping rule of an early-stopping fit, in one line.
fn stopping_text(rule: &StoppingRule) -> String {
    let [c0, cn, cu] = rule.coef;
    let [s0, sn, su] = rule.se;
    format!(
        "early stopping: ln e* = {c0:.3} (±{s0:.3}) + {cn:.3} (±{sn:.3})·ln N + {cu:.3} (±{su:.3})·ln U over the {} runs selected before the end of their schedule (residual s.d. {:.3}); the law is fitted on the selected checkpoints' tokens",
        rule.runs, rule.residual_sd
    )
}
