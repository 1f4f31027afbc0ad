//! `motionscale fit` and `motionscale predict`: scaling-law fits of a sweep's results table and
//! predictions at a compute budget.

use anyhow::{bail, Context, Result};
use fits::data_value::{
    data_bound, predict_data, size_losses, DataBound, DataPrediction, Hours, SizeLoss, SizeLosses,
};
use fits::family::predict::predict_at;
use fits::family::run::LawReport;
use fits::family::Point;
use fits::fit_file::FitFile;
use fits::fitted::RepeatedData;
use fits::fitted::{ColumnChoice, ColumnSpec, ExchangeForm, FitOptions};
use fits::parametric::StartGrid;
use fits::report::{estimate_text, sig};
use fits::{Fits, Laws, PredictOptions, Prediction, Table};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

/// Arguments of `motionscale fit`.
#[derive(clap::Args, Debug)]
#[command(
    long_about = "Fit scaling laws to a results table (CSV with a header row, or Parquet).\n\n\
    Per budget, a parabola of loss in log10 N gives the IsoFLOP minimum (used only when it is \
    convex with its vertex inside the sampled sizes); likewise over log10 V at each fixed N. \
    Log-log OLS then gives N_opt ∝ C^b, D_opt ∝ C^c, N_v,opt ∝ C^a and N_v ∝ N^γ (with SEs, \
    95% t intervals, R²), and L_opt = α·log10 C + β. The parametric L(N, D) = E + A/N^α + B/D^β \
    minimises the summed Huber loss of log residuals with L-BFGS from every start of a grid, \
    and bootstraps runs for 95% percentile intervals.\n\n\
    Approaches 2 and 3 are compared on the N_opt and D_opt exponents (a warning when their \
    intervals do not overlap), and with an N_v column the whole fit is repeated with N counted \
    as every parameter (N + N_v, `total_n` in fits.json).\n\n\
    Writes OUT/fits.json and plots (isoflop_n, isoflop_v, law_*, log_law; .svg and .png).\n\n\
    With --law, the named law families instead, on any table (an IsoFLOP grid or not, a \
    negative loss allowed): each fitted by one engine, ranked by its error on held-out runs, \
    the best adopted, optionally scored on a --test table and replayed under cost caps \
    (--replay); writes OUT/laws.json.\n\n\
    Columns default to the sweep's results table: n_nv, tokens, budget, norm_test_loss, \
    test_loss, vocab, n_v, d_model. A default column that is missing only disables what needs \
    it; a column named with a flag must exist."
)]
pub struct FitArgs {
    /// Results table: .csv (header row) or .parquet.
    #[arg(long, value_name = "FILE")]
    pub results: PathBuf,
    /// Output folder for fits.json and the plots (created if needed).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// Model-size column N [default: n_nv].
    #[arg(long, value_name = "COL")]
    pub n_col: Option<String>,
    /// Training-tokens column D [default: tokens].
    #[arg(long, value_name = "COL")]
    pub d_col: Option<String>,
    /// Compute column C in FLOPs [default: budget; if absent, C = 6·(N + N_v)·D].
    #[arg(long, value_name = "COL")]
    pub c_col: Option<String>,
    /// Loss for the IsoFLOP minima, power laws and log law [default: norm_test_loss].
    #[arg(long, value_name = "COL")]
    pub loss_col: Option<String>,
    /// Loss for the parametric L(N, D), must be > 0 [default: test_loss, else --loss-col].
    #[arg(long, value_name = "COL")]
    pub param_loss_col: Option<String>,
    /// Vocabulary (codebook) size column V [default: vocab].
    #[arg(long, value_name = "COL")]
    pub v_col: Option<String>,
    /// Vocabulary-parameter column N_v [default: n_v].
    #[arg(long, value_name = "COL")]
    pub nv_col: Option<String>,
    /// Model-width column d, for N_v = V·d [default: d_model; else N_v / V].
    #[arg(long, value_name = "COL")]
    pub width_col: Option<String>,
    /// Budget-group column [default: budget; else C values within --group-tol dex form a group].
    #[arg(long, value_name = "COL")]
    pub group_col: Option<String>,
    /// Training-seed column: rows that differ only in it are averaged for the IsoFLOP minima,
    /// and their spread is reported as the run-to-run noise [default: seed].
    #[arg(long, value_name = "COL")]
    pub seed_col: Option<String>,
    /// Epochs-over-unique-tokens column, for --repeated-data [default: epochs].
    #[arg(long, value_name = "COL")]
    pub epochs_col: Option<String>,
    /// Synthetic share of each run's unique data, for --repeated-data's exchange rate (fitted
    /// when the shares differ, e.g. a real-only and a mixed data ladder) [default: synth_share].
    #[arg(long, value_name = "COL")]
    pub synth_share_col: Option<String>,
    /// Fit without the runs of the budget group at C (FLOPs) and score the prediction on
    /// them: predicted vs trained N_opt and loss, inside or outside the 95% interval.
    #[arg(long, value_name = "C")]
    pub holdout_budget: Option<f64>,
    /// Fit only the runs of vocabulary size K (the --v-col column). Cross-entropy is not
    /// comparable between vocabularies, so the parametric L(N, D) of one vocabulary is the one
    /// to set beside its IsoFLOP law.
    #[arg(long, value_name = "K")]
    pub vocab: Option<f64>,
    /// Also fit Muennighoff et al.'s data-constrained L(N', D') (effective data
    /// D' = U + U·R*_D·(1 − e^(−R/R*_D)), R = epochs − 1; effective parameters N' likewise past
    /// U_N, the size the law allots the unique data seen) with R*_D and R*_N fitted, and
    /// compare it with the plain fit by the error on each budget left out in turn. With a synthetic-share column
    /// whose values differ, also the exchange rate ρ: the unique data counts as U·(1 − s + ρ·s).
    #[arg(long)]
    pub repeated_data: bool,
    /// With --repeated-data: effective parameters too, N' = U_N + U_N·R*_N·(1 − e^(−R_N/R*_N))
    /// past U_N = (αA/(βB))^(1/α)·U_D^(β/α), the size the law allots the unique tokens seen
    /// (R_N = N/U_N − 1), with R*_N fitted (Muennighoff et al. 2023).
    #[arg(long, requires = "repeated_data")]
    pub effective_params: bool,
    /// With --repeated-data: early stopping. The law is fitted on the tokens of each run's
    /// validation-selected checkpoint (tokens·best_step/steps, the sweep's columns), beside a
    /// stopping rule ln e* = c₀ + c_N·ln N + c_U·ln U fitted on the runs selected before the
    /// end of their schedule; `predict --hours` then counts min(D, e*·U) tokens of a run.
    #[arg(long, requires = "repeated_data")]
    pub early_stopping: bool,
    /// With --repeated-data: how a synthetic token counts against captured ones.
    /// `token-worth`: each is worth ρ (U and D scale by 1 − s + ρ·s); `effective-pool`:
    /// repetitions count against the pool U_real + ρ·U_synth. Both (comma-separated): each is
    /// fitted and scored on the data subsets left out in turn, the lower error adopted.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "token-worth",
        value_name = "FORM[,FORM]",
        requires = "repeated_data"
    )]
    pub exchange_form: Vec<ExchangeFormArg>,
    /// Grouping tolerance in log10 C, used without a group column.
    #[arg(long, default_value_t = 0.05, value_name = "DEX")]
    pub group_tol: f64,
    /// L-BFGS starts: `epoch` (4,500: alpha, beta in 0..2 step 0.5; e in -1..1 step 0.5;
    /// a, b in 0..25 step 5), `coarse` (243), or e.g. `alpha=0:2:0.25,a=0:30:5,e=-1/0/1`.
    #[arg(long, default_value = "epoch", value_name = "GRID")]
    pub starts_grid: String,
    /// Bootstrap resamples over runs for the parametric intervals (0: none).
    #[arg(long, default_value_t = 500, value_name = "N")]
    pub bootstrap: usize,
    /// Starts per bootstrap refit: K (the K best distinct local optima of the full-data grid,
    /// distinct = objectives more than 1e-6 apart) or `full` (the whole grid for every
    /// resample: slow) [default: 16; 4 with --law].
    #[arg(long, value_name = "K|full")]
    pub bootstrap_starts: Option<String>,
    /// With --law: bootstrap every scored family, not only the adopted one.
    #[arg(long, requires = "law")]
    pub bootstrap_all: bool,
    /// Bootstrap seed (recorded in fits.json).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Huber threshold δ on log-loss residuals.
    #[arg(long, default_value_t = 1e-3)]
    pub huber_delta: f64,
    /// Worker threads (default: all cores).
    #[arg(long)]
    pub workers: Option<usize>,
    /// Fit these law families instead of the IsoFLOP analysis, each by the one fitter (Huber,
    /// L-BFGS from its start grid, bootstrap): chinchilla, data-constrained (and its
    /// exchange-rate forms data-constrained-token-worth and data-constrained-effective-pool,
    /// which read the --synth-share-col), unique-floor, vocab, vocab-effective, farseer, or
    /// `all` (those the table's columns allow). Each is scored on held-out runs (--select),
    /// the lowest error adopted; writes OUT/laws.json. The loss may be negative (then
    /// residuals are taken in loss space instead of log space).
    #[arg(long, value_name = "NAME[,NAME…]", value_delimiter = ',')]
    pub law: Vec<String>,
    /// With --law: unique-tokens column U [default: unique_tokens; else tokens/epochs].
    #[arg(long, value_name = "COL", requires = "law")]
    pub u_col: Option<String>,
    /// With --law: how families are ranked: `top` holds out the --top-share most expensive
    /// runs (6·(N + N_v)·D), `budget` each budget group in turn, `ladder` each data subset
    /// (the `data` column; empty: the whole train split) in turn.
    #[arg(long, value_enum, default_value = "top", requires = "law")]
    pub select: LawSelection,
    /// With --law: resample whole blocks of runs in the bootstrap instead of runs one by one —
    /// `budget` (each budget group) or `ladder` (each data subset) — as runs that share a
    /// budget or nested clips are correlated.
    #[arg(long, value_enum, value_name = "BLOCK", requires = "law")]
    pub block_bootstrap: Option<BootstrapBlock>,
    /// With --law --select top: the share of runs held out.
    #[arg(long, default_value_t = 0.1, value_name = "SHARE", requires = "law")]
    pub top_share: f64,
    /// With --law: a held-out table with the same columns, on which every fitted family is
    /// scored (R² of the loss, clipped to [-1, 1] as ScaleBench reports it; mean |relative
    /// error|).
    #[arg(long, value_name = "FILE", requires = "law")]
    pub test: Option<PathBuf>,
    /// With one --law and --test: replay a design that buys runs of the table (the pool) up to
    /// each cap, a share of the pool's cost 6·(N + N_v)·D, to predict the --test points
    /// (greedy V-optimal from a seeded cheap start); prints the target-region R² per cap
    /// over --replay-seeds and writes OUT/replays.json.
    #[arg(
        long,
        value_name = "SHARE[,SHARE…]",
        value_delimiter = ',',
        requires = "test"
    )]
    pub replay: Vec<f64>,
    /// Seeds of each cap's replays.
    #[arg(long, default_value_t = 10, value_name = "N", requires = "replay")]
    pub replay_seeds: u64,
}

/// `fit --exchange-form`'s values.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq)]
pub enum ExchangeFormArg {
    /// Each synthetic token is worth ρ captured ones.
    TokenWorth,
    /// Repetitions count against U_real + ρ·U_synth.
    EffectivePool,
}

impl From<ExchangeFormArg> for ExchangeForm {
    fn from(a: ExchangeFormArg) -> Self {
        match a {
            ExchangeFormArg::TokenWorth => ExchangeForm::TokenWorth,
            ExchangeFormArg::EffectivePool => ExchangeForm::EffectivePool,
        }
    }
}

/// How `fit --law` ranks the families.
#[derive(clap::ValueEnum, Clone, Copy, Debug)]
pub enum LawSelection {
    /// Leave the most expensive runs out.
    Top,
    /// Leave each budget group out in turn.
    Budget,
    /// Leave each data subset (ladder) out in turn.
    Ladder,
}

/// `fit --block-bootstrap`'s blocks.
#[derive(clap::ValueEnum, Clone, Copy, Debug)]
pub enum BootstrapBlock {
    /// The runs of one budget group.
    Budget,
    /// The runs of one data subset (the `data` column).
    Ladder,
}

impl FitArgs {
    /// The fit's options from the arguments (columns, grid, bootstrap).
    pub(crate) fn options(&self) -> Result<FitOptions> {
        let col = |given: &Option<String>, default: &str| {
            ColumnChoice::or_default(given.clone(), default)
        };
        let d = ColumnSpec::default();
        let bootstrap_starts = match self.bootstrap_starts.as_deref().unwrap_or("16") {
            "full" => None,
            k => Some(
                k.parse::<usize>()
                    .ok()
                    .filter(|&k| k > 0)
                    .with_context(|| {
                        format!("--bootstrap-starts {k:?}: want a positive count or `full`")
                    })?,
            ),
        };
        if self.huber_delta.is_nan() || self.huber_delta <= 0.0 {
            bail!("--huber-delta {}: must be > 0", self.huber_delta);
        }
        Ok(FitOptions {
            columns: ColumnSpec {
                n: col(&self.n_col, &d.n.name),
                d: col(&self.d_col, &d.d.name),
                c: col(&self.c_col, &d.c.name),
                loss: col(&self.loss_col, &d.loss.name),
                param_loss: col(&self.param_loss_col, &d.param_loss.name),
                v: col(&self.v_col, &d.v.name),
                nv: col(&self.nv_col, &d.nv.name),
                width: col(&self.width_col, &d.width.name),
                group: col(&self.group_col, &d.group.name),
                epochs: col(&self.epochs_col, &d.epochs.name),
                synth_share: col(&self.synth_share_col, &d.synth_share.name),
                seed: col(&self.seed_col, &d.seed.name),
            },
            group_tol_dex: self.group_tol,
            grid: StartGrid::parse(&self.starts_grid)?,
            grid_name: self.starts_grid.clone(),
            bootstrap: self.bootstrap,
            bootstrap_starts,
            seed: self.seed,
            huber_delta: self.huber_delta,
            holdout_budget: self.holdout_budget,
            vocab: self.vocab,
            repeated_data: self.repeated_data,
            effective_params: self.effective_params,
            early_stopping: self.early_stopping,
            exchange_forms: dedup_forms(&self.exchange_form),
            ..FitOptions::default()
        })
    }
}

/// The forms asked for, each once, in the order given.
fn dedup_forms(given: &[ExchangeFormArg]) -> Vec<ExchangeForm> {
    let mut out: Vec<ExchangeForm> = Vec::new();
    for &f in given {
        if !out.contains(&f.into()) {
            out.push(f.into());
        }
    }
    out
}

/// `motionscale fit`: fits, fits.json, plots and a summary on stdout.
pub fn fit(args: FitArgs) -> Result<ExitCode> {
    let t0 = Instant::now();
    let opts = args.options()?;
    let pool = crate::commands::thread_pool(args.workers)?;
    let table = Table::read(&args.results)?;
    let mut result = pool.install(|| fits::fit_table(&table, &opts))?;
    let written = fits::report::write_outputs(&mut result, &args.out)?;
    print!("{}", fits::report::summary(&result));
    println!(
        "wrote {} ({} files: fits.json and {} plots as SVG + PNG) in {:.2} s on {} threads",
        args.out.display(),
        written.len(),
        result.plots.len(),
        t0.elapsed().as_secs_f64(),
        pool.current_num_threads()
    );
    Ok(ExitCode::SUCCESS)
}

/// Built-in sets of published coefficients.
#[derive(clap::ValueEnum, Clone, Copy, Debug)]
pub enum Preset {
    /// ScaMo Eqs. 10-14: N_v = 10^-5.29·C^0.75, N_nv = 10^-0.52·C^0.57, D = 10^-0.05·C^0.43,
    /// N_v = 10^-5.604·N_nv^1.467, L_u = -1.062·log10 C + 13.839.
    Scamo,
}

/// Arguments of `motionscale predict`.
#[derive(clap::Args, Debug)]
#[command(
    long_about = "Predict N_nv, N_v, the codebook V (rounded to an FSQ level set: nominal \
    2^8..2^16, real 240, 1000, 4375, 15360, 64000), D and the loss at a compute budget, with \
    95% intervals where the laws carry uncertainty (OLS standard errors, parametric bootstrap). \
    Consistency checks between the laws (6·N·D vs C, the two N_v laws, the exponents, and for \
    the scamo preset the paper's own 1e18 run) are printed; failed ones become warnings.\n\n\
    With a laws.json of `fit --law`: the adopted law's compute-optimal N and D at the budget \
    and the loss there, 95% intervals over its bootstrap refits (the loss's a prediction \
    interval, holding the runs' scatter); a law of unique tokens or vocabulary parameters \
    needs --unique-tokens or --vocab-params."
)]
pub struct PredictArgs {
    /// A fits.json written by `motionscale fit`, or a laws.json of `fit --law`.
    #[arg(
        long,
        value_name = "FILE",
        required_unless_present = "preset",
        conflicts_with = "preset"
    )]
    pub fits: Option<PathBuf>,
    /// Built-in published coefficients instead of a fits file.
    #[arg(long, value_enum)]
    pub preset: Option<Preset>,
    /// Compute budget C in FLOPs, e.g. 1e18.
    #[arg(long)]
    pub budget: f64,
    /// Model width d, to turn N_v into V [default: the ScaMo configuration nearest to N_nv].
    #[arg(long)]
    pub width: Option<f64>,
    /// Fixed codebook size V (N_v = V·d instead of the N_v law).
    #[arg(long)]
    pub vocab: Option<f64>,
    /// The data question (--hours, --noise, --mirrored).
    #[command(flatten)]
    pub data: HoursArgs,
    /// Unique tokens U held at the budget (a laws.json whose law reads U).
    #[arg(long, value_name = "U")]
    pub unique_tokens: Option<f64>,
    /// Vocabulary parameters N_v held at the budget (a laws.json whose law reads N_v).
    #[arg(long, value_name = "N_V")]
    pub vocab_params: Option<f64>,
    /// Synthetic share s of the unique data held at the budget (a laws.json whose law reads
    /// it: the data-constrained exchange-rate laws).
    #[arg(long, value_name = "S")]
    pub synth_share: Option<f64>,
    /// With --hours: the model sizes N (the fit's N column) that can be trained, comma-separated:
    /// the loss the law gives each at this budget and these hours (with early stopping, on the
    /// tokens it trains before it stops), and the best of them — a cell's best run.
    #[arg(
        long,
        value_name = "N[,N...]",
        value_delimiter = ',',
        requires = "hours"
    )]
    pub sizes: Vec<f64>,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// The corpus's hours, read by `predict` and `report` with a fit of the data-constrained law.
#[derive(clap::Args, Debug, Clone)]
pub struct HoursArgs {
    /// The corpus's hours per source, `real=H,synth=H`: the data question, answered by the
    /// fit's data-constrained law (`fit --repeated-data`) — the optimum at this budget and
    /// these hours, what +1 h and +10 h of each source are worth, and whether the budget is
    /// data-bound.
    #[arg(long, value_name = "real=H,synth=H", value_parser = parse_hours)]
    pub hours: Option<Hours>,
    /// With --hours: the seed SD of the loss, below which more compute is not worth buying
    /// [default: the fit's seed SD of its parametric loss at its largest budget with repeats].
    #[arg(long, value_name = "NATS", requires = "hours")]
    pub noise: Option<f64>,
    /// With --hours: the hours given are distinct capture and the fit's hours count mirrored
    /// copies, so each is doubled.
    #[arg(long, requires = "hours")]
    pub mirrored: bool,
}

/// What the data question gets: the data-constrained law's prediction at a budget and, given
/// a seed SD, its data-bound verdict.
pub(crate) struct DataAnswer {
    /// The optimum, the loss and the value of more hours.
    pub prediction: DataPrediction,
    /// Whether compute past C_sat is worth buying (absent without a seed SD).
    pub bound: Option<DataBound>,
}

impl HoursArgs {
    /// The answer at `budget` from `fits` (read from `path`), or None without --hours; a fit
    /// without the data-constrained law is an error naming the file.
    pub(crate) fn answer(
        &self,
        fits: &Fits,
        path: &Path,
        budget: f64,
    ) -> Result<Option<DataAnswer>> {
        let Some(hours) = self.hours else {
            return Ok(None);
        };
        let Some(rd) = &fits.repeated_data else {
            bail!(
                "{}: no data-constrained law (fit with --repeated-data on a table with an epochs column)",
                path.display()
            );
        };
        let fit_hours = self.fit_hours(hours);
        let in_file = |e: String| anyhow::anyhow!("{}: {e}", path.display());
        let prediction = predict_data(rd, budget, fit_hours).map_err(in_file)?;
        let bound = self
            .noise
            .or_else(|| fits.param_seed_sd())
            .map(|sd| data_bound(rd, budget, fit_hours, sd))
            .transpose()
            .map_err(in_file)?;
        Ok(Some(DataAnswer { prediction, bound }))
    }

    /// `hours` as the fit counts them: doubled when --mirrored.
    pub(crate) fn fit_hours(&self, hours: Hours) -> Hours {
        let scale = if self.mirrored { 2.0 } else { 1.0 };
        Hours {
            real: scale * hours.real,
            synth: scale * hours.synth,
        }
    }

    /// Hours as given, with their mirrored count when --mirrored.
    pub(crate) fn hours_text(&self, h: f64) -> String {
        match self.mirrored {
            true => format!("{h} h distinct = {} h with mirrors", 2.0 * h),
            false => format!("{h} h"),
        }
    }

    /// The verdict sentence at `budget` (or why there is none), for the page and the terminal.
    pub(crate) fn verdict_text(&self, answer: &DataAnswer) -> String {
        let p = &answer.prediction;
        match &answer.bound {
            Some(b) => bound_text(b, p.budget, p.stop_epochs.as_ref()),
            None => "no seed SD (no repeated runs in the fit; give --noise): no data-bound verdict"
                .into(),
        }
    }
}

/// `real=H,synth=H` (either may be left out: 0 hours).
pub(crate) fn parse_hours(text: &str) -> Result<Hours, String> {
    let mut h = Hours {
        real: 0.0,
        synth: 0.0,
    };
    for part in text.split(',') {
        let (source, value) = part
            .split_once('=')
            .ok_or_else(|| format!("{part:?}: want real=H or synth=H"))?;
        let value: f64 = value
            .parse()
            .map_err(|_| format!("{part:?}: {value:?} is not a number of hours"))?;
        match source {
            "real" => h.real = value,
            "synth" => h.synth = value,
            other => return Err(format!("{other:?}: the sources are real and synth")),
        }
    }
    Ok(h)
}

/// What an hour buys in compute: C'/C with its interval, or "more than any compute", with the
/// share of refits at which no budget reaches the loss.
fn worth_text(v: &fits::data_value::HourValue, data_bound: bool) -> String {
    let e = &v.compute_equivalent;
    let share = 100.0 * v.unbuyable;
    let end = |x: Option<f64>| x.map_or("∞".into(), sig);
    let interval = format!(
        "{} [{}, {}]× compute",
        sig(e.value),
        end(e.ci_low),
        end(e.ci_high)
    );
    let why = match v.unbuyable > 0.0 {
        true => format!("no budget reaches that loss at {share:.0}% of refits"),
        false => "the loss change's sign is not resolved".into(),
    };
    match (e.value.is_infinite(), data_bound, v.resolved()) {
        (true, ..) => format!(
            "worth more than any compute: no budget reaches that loss with today's hours (nor at {share:.0}% of refits)"
        ),
        (false, true, _) => {
            "no compute equivalent: past C_sat compute buys less than the seed SD".into()
        }
        (false, false, true) => format!("worth {interval}"),
        (false, false, false) => format!("no compute equivalent to act on ({interval}: {why})"),
    }
}

/// `predict --hours`: the data question.
fn predict_hours(path: &Path, args: &PredictArgs) -> Result<ExitCode> {
    let fits = Fits::read(path)?;
    let (Some(hours), Some(answer)) =
        (args.data.hours, args.data.answer(&fits, path, args.budget)?)
    else {
        bail!("--hours is required for the data question");
    };
    let (p, bound) = (&answer.prediction, &answer.bound);
    let sizes = match (&fits.repeated_data, args.sizes.is_empty()) {
        (Some(rd), false) => Some(
            size_losses(rd, args.budget, args.data.fit_hours(hours), &args.sizes)
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?,
        ),
        _ => None,
    };
    if args.json {
        let both = serde_json::json!({ "prediction": p, "data_bound": bound, "sizes": sizes });
        println!("{}", serde_json::to_string_pretty(&both)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "C = {} with {} real + {} synthetic ({} unique tokens, vocabulary {}):",
        sig(p.budget),
        args.data.hours_text(hours.real),
        args.data.hours_text(hours.synth),
        sig(p.unique_tokens),
        p.vocab.map_or("mixed".into(), |v| format!("{v:.0}"))
    );
    for (name, e) in [
        ("N_opt", Some(&p.n_opt)),
        ("D", Some(&p.d)),
        ("epochs", Some(&p.epochs)),
        ("stops at", p.stop_epochs.as_ref()),
        ("loss", Some(&p.loss)),
        ("a run", p.loss_prediction.as_ref()),
    ] {
        if let Some(e) = e {
            println!("  {name:<8} {}", estimate_text(e));
        }
    }
    if p.loss_prediction.is_some() {
        println!("  (loss: the law's 95% interval; a run: the 95% prediction interval of one run's loss, the runs' scatter about the law added)");
    }
    println!("  N_v {} ; 6·(N + N_v)·D / C = {:.4}", sig(p.n_v), p.spends);
    for v in &p.hour_values {
        println!(
            "  +{} h {:<5}: loss {} ; {}",
            v.hours,
            v.source,
            estimate_text(&v.loss_change),
            worth_text(v, bound.as_ref().is_some_and(|b| b.bound))
        );
    }
    for v in &p.verdicts {
        println!("  {v}");
    }
    if let Some(rd) = &fits.repeated_data {
        baseline_lines(rd, p);
    }
    if let Some(s) = &sizes {
        size_lines(s);
    }
    println!("  {}", args.data.verdict_text(&answer));
    Ok(ExitCode::SUCCESS)
}

/// "; a run [interval]": one run's 95% prediction interval where the fit has one.
pub(crate) fn run_text(e: Option<&fits::laws::Estimate>) -> String {
    e.map_or(String::new(), |e| format!("; a run {}", estimate_text(e)))
}

/// `predict --sizes`: each size's loss at the budget, then the best of them.
fn size_lines(s: &SizeLosses) {
    println!("  the sizes asked about (--sizes):");
    let line = |label: String, z: &SizeLoss| {
        let stops = z
            .stop_epochs
            .map_or(String::new(), |e| format!(", stops at {e:.1}"));
        let run = run_text(z.loss_prediction.as_ref());
        println!(
            "    {label:<16} {:.1} epochs{stops}: loss {}{run}",
            z.epochs,
            estimate_text(&z.loss)
        );
    };
    for z in &s.sizes {
        line(format!("N {}", sig(z.n)), z);
    }
    line(format!("best, N {}", sig(s.best.n)), &s.best);
}

/// The two naive baselines beside N_opt and the loss, from the fit's frontier on the unique
/// set nearest these hours: no growth (its last budget carried forward) and N ∝ C from its
/// last best run (that run's tokens).
fn baseline_lines(rd: &RepeatedData, p: &DataPrediction) {
    let distance = |u: f64| (u / p.unique_tokens).ln().abs();
    let Some(set) = rd
        .frontier
        .iter()
        .min_by(|a, b| distance(a.unique_tokens).total_cmp(&distance(b.unique_tokens)))
    else {
        return;
    };
    let same_set = |u: f64| (u / set.unique_tokens).ln().abs() < 0.01;
    let Some(last) = rd
        .frontier
        .iter()
        .filter(|f| same_set(f.unique_tokens) && f.budget <= p.budget)
        .max_by(|a, b| a.budget.total_cmp(&b.budget))
    else {
        return;
    };
    println!(
        "  baselines from the best run at C = {} on {} unique tokens: no growth N {} loss {}; N ∝ C N {}",
        sig(last.budget),
        sig(last.unique_tokens),
        sig(last.n),
        sig(last.loss),
        sig(last.n * p.budget / last.budget)
    );
}

/// The data-bound verdict: whether compute past C_sat is worth buying on these hours, and
/// what doubling the captured hours buys.
fn bound_text(b: &DataBound, budget: f64, stop: Option<&fits::laws::Estimate>) -> String {
    let doubling = format!(
        "doubling the captured hours changes the loss by {}",
        estimate_text(&b.doubling)
    );
    match b.bound {
        true => format!(
            "data-bound above {} FLOPs (past it all further compute lowers the loss by less than the seed SD {}; floor {}): {}buy data — {doubling}",
            sig(b.saturation.value),
            sig(b.noise),
            sig(b.floor.value),
            stop.map_or(String::new(), |e| format!(
                "train {:.1} epochs with the schedule ending there (a checkpoint selected early in a longer schedule keeps its higher learning rate); ",
                e.value
            )),
        ),
        false => format!(
            "compute-bound at {}: compute keeps paying up to {} FLOPs [{}]; {doubling}",
            sig(budget),
            sig(b.saturation.value),
            estimate_text(&b.saturation)
        ),
    }
}

/// `motionscale predict`.
pub fn predict(args: PredictArgs) -> Result<ExitCode> {
    if args.data.hours.is_some() {
        let Some(path) = &args.fits else {
            bail!("--hours needs --fits: the data question is answered by a fit's data-constrained law");
        };
        return predict_hours(path, &args);
    }
    let laws = match (&args.fits, args.preset) {
        (Some(path), _) => match FitFile::read(path)? {
            FitFile::IsoFlop(fits) => Laws::from_fits(&fits, &path.display().to_string()),
            FitFile::Families(report) => return predict_family(&report, &args),
        },
        (None, Some(Preset::Scamo)) => Laws::scamo(),
        (None, None) => bail!("give --fits FILE or --preset scamo"),
    };
    let p = fits::predict(
        &laws,
        &PredictOptions {
            budget: args.budget,
            width: args.width,
            vocab: args.vocab,
        },
    )?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&p)?);
    } else {
        print!("{}", prediction_text(&p));
    }
    Ok(ExitCode::SUCCESS)
}

/// `predict` on a laws.json: the adopted family at the budget.
fn predict_family(report: &LawReport, args: &PredictArgs) -> Result<ExitCode> {
    let at = Point {
        u: args.unique_tokens,
        nv: args.vocab_params,
        s: args.synth_share,
        ..Point::default()
    };
    let p = predict_at(report, args.budget, at)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&p)?);
        return Ok(ExitCode::SUCCESS);
    }
    let held = [("U", p.unique_tokens), ("N_v", p.vocab_params)]
        .into_iter()
        .filter_map(|(k, v)| v.map(|v| format!(", {k} = {}", sig(v))))
        .collect::<String>();
    println!(
        "{} at C = {}{held} (95% intervals over {} bootstrap refits):",
        p.law,
        sig(p.compute),
        p.draws
    );
    println!("  N_opt    {}", estimate_text(&p.n));
    println!("  D_opt    {}", estimate_text(&p.d));
    println!(
        "  loss     {} (prediction interval: the law's uncertainty and the runs' scatter)",
        estimate_text(&p.loss)
    );
    Ok(ExitCode::SUCCESS)
}

/// The predicted quantities of `p` as (name, value with its 95% interval) rows, for the
/// text of `predict` and the report's table.
pub fn prediction_rows(p: &Prediction) -> Vec<(&'static str, String)> {
    let mut rows = Vec::new();
    let estimates = [
        ("N_nv", &p.n_nv),
        ("N_v", &p.n_v),
        ("N_v (from N_nv law)", &p.n_v_from_n_nv_law),
        ("D", &p.d),
        ("loss", &p.loss),
    ];
    for (name, e) in estimates {
        if let Some(e) = e {
            rows.push((name, estimate_text(e)));
        }
    }
    if !p.loss_by_form.is_empty() {
        let forms: Vec<String> = p
            .loss_by_form
            .iter()
            .map(|f| {
                let lobo = f
                    .lobo_rms
                    .map_or("not scored".into(), |r| format!("{r:.3}"));
                let chosen = if f.chosen { ", chosen" } else { "" };
                format!("{} {} (LOBO RMS {lobo}{chosen})", f.form, sig(f.loss))
            })
            .collect();
        rows.push(("loss by form", forms.join("; ")));
    }
    if let Some(d) = p.d_from_budget {
        rows.push(("D spending C exactly", sig(d)));
    }
    if let Some(w) = &p.width {
        rows.push(("width d", format!("{} ({})", w.value, w.source)));
    }
    if let Some(v) = &p.vocab {
        let text = format!(
            "N_v/d = {} -> FSQ 2^{} (nominal {}, real {} = {:?})",
            estimate_text(&v.exact),
            v.nominal_log2,
            v.nominal,
            v.real,
            v.levels
        );
        rows.push(("vocabulary V", text));
    }
    if let Some(v) = &p.v_opt {
        let (k, _) = fits::predict::fsq_for(v.value);
        rows.push((
            "V (its own C-law)",
            format!("{} -> FSQ 2^{k}", estimate_text(v)),
        ));
    }
    if let Some(pp) = &p.parametric {
        rows.push(("parametric N_opt", estimate_text(&pp.n_opt)));
        rows.push(("parametric D_opt", estimate_text(&pp.d_opt)));
        rows.push(("parametric loss", estimate_text(&pp.loss)));
    }
    rows
}

fn prediction_text(p: &Prediction) -> String {
    let mut lines = vec![
        format!("laws: {}", p.source),
        format!("budget C = {:.3e} FLOPs", p.budget),
    ];
    for e in &p.equations {
        lines.push(format!("  {e}"));
    }
    for (name, value) in prediction_rows(p) {
        lines.push(format!("{name:<22} {value}"));
    }
    lines.push("consistency:".into());
    for c in &p.consistency {
        lines.push(format!(
            "  [{}] {}: {} vs {} (ratio {:.3})",
            if c.ok { "ok" } else { "!!" },
            c.name,
            sig(c.value),
            sig(c.reference),
            c.ratio
        ));
    }
    for w in &p.warnings {
        lines.push(format!("warning: {w}"));
    }
    lines.join("\n") + "\n"
}
