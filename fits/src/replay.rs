//! Replaying a planning policy on a finished table: at each step the policy may only pick a
//! run the table has, and it is given that run's real loss, so a policy is judged on real runs,
//! not on its own model. Every policy starts from the same runs (the cheapest budgets' grids)
//! and stops before its compute would pass the cap.

use crate::isoflop::{envelope_rows, group_rows};
use crate::ols::Z95;
use crate::planner::{self, Candidate, Observation, Posterior, Settings, Target, WIDTH_CAP};
use crate::table::Table;
use crate::FitError;
use motionscale_core::rng::SplitMix64;
use plot::{Chart, Series};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Widths this close are the same interval: the same runs added in another order give the
/// full table's posterior up to the order of summation (about 1e-12 apart).
const SAME_WIDTH: f64 = 1e-9;

/// How the next run is chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Policy {
    /// [`planner::propose`]: the largest expected narrowing per FLOP.
    Active,
    /// The table's own order (budget by budget, as the sweep trained them).
    Grid,
    /// A seeded random order.
    Random,
    /// Knows every outcome: the runs on the full table's envelope (the lowest loss at each N
    /// of a budget), budget by budget from the cheapest, each budget's nearest its best run
    /// first: the cheapest order that reproduces the full table's answer, and what that costs
    /// against the cap.
    Oracle,
}

impl Policy {
    /// Parses `active`, `grid` or `random`.
    pub fn parse(name: &str) -> Result<Self, FitError> {
        match name {
            "active" => Ok(Self::Active),
            "grid" => Ok(Self::Grid),
            "random" => Ok(Self::Random),
            "oracle" => Ok(Self::Oracle),
            other => Err(FitError::UnknownChoice {
                flag: "--policy",
                given: other.into(),
                expected: "active, grid, random or oracle",
            }),
        }
    }

    /// The name `parse` reads.
    pub fn name(self) -> &'static str {
        match self {
            Self::Active => "active",
            Self::Grid => "grid",
            Self::Random => "random",
            Self::Oracle => "oracle",
        }
    }
}

/// A finished table to replay on, and what is scored.
#[derive(Debug, Clone)]
pub struct ReplayTable {
    /// The runs a policy may pick, in the table's order.
    pub pool: Vec<Candidate>,
    /// Each pool run's real loss.
    pub losses: Vec<f64>,
    /// Pool indices every policy starts from.
    pub start: Vec<usize>,
    /// What is extrapolated, and to which budget.
    pub target: Target,
    /// The target budget C*.
    pub c_star: f64,
    /// The target's true value (log10 N_opt or the loss), from the runs at C*.
    pub truth: f64,
    /// The most compute a policy may spend (the start included).
    pub max_compute: f64,
    /// Posterior settings.
    pub settings: Settings,
}

/// One point of a policy's curve.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReplayStep {
    /// `active`, `grid`, `random` or `oracle`.
    pub policy: String,
    /// Which random order (0 for the others).
    pub order: usize,
    /// Step (0: the start).
    pub step: usize,
    /// Runs chosen so far.
    pub runs: usize,
    /// FLOPs spent so far.
    pub compute: f64,
    /// The target's posterior after this step.
    #[serde(flatten)]
    pub posterior: Posterior,
    /// |median − truth|.
    pub error: f64,
    /// Run ids added at this step, `;`-separated.
    pub added: String,
}

impl ReplayStep {
    /// The error, at most [`WIDTH_CAP`]; a step without a law (no median yet) counts as the cap,
    /// as an unbounded width does.
    pub fn capped_error(&self) -> f64 {
        match self.error.is_nan() {
            true => WIDTH_CAP,
            false => self.error.min(WIDTH_CAP),
        }
    }
}

impl ReplayTable {
    /// The posterior from every pool run (the full table's answer).
    pub fn full(&self) -> Posterior {
        let all: Vec<usize> = (0..self.pool.len()).collect();
        planner::posterior(
            &self.observed(&all),
            self.target,
            self.c_star,
            &self.settings,
        )
    }

    fn observed(&self, chosen: &[usize]) -> Vec<Observation> {
        chosen
            .iter()
            .map(|&i| planner::observed(&self.pool[i], self.losses[i]))
            .collect()
    }

    fn step(
        &self,
        policy: Policy,
        order: usize,
        chosen: &[usize],
        added: &[usize],
        step: usize,
    ) -> ReplayStep {
        let posterior = planner::posterior(
            &self.observed(chosen),
            self.target,
            self.c_star,
            &self.settings,
        );
        let ids: Vec<&str> = added.iter().map(|&i| self.pool[i].id.as_str()).collect();
        ReplayStep {
            policy: policy.name().into(),
            order,
            step,
            runs: chosen.len(),
            compute: chosen.iter().map(|&i| self.pool[i].cost).sum(),
            posterior,
            error: (posterior.median - self.truth).abs(),
            added: ids.join(";"),
        }
    }

    /// The pool's envelope runs outside `chosen` in the oracle's order: budget by budget from
    /// the cheapest, each budget's by distance in log N from its lowest-loss run.
    fn envelope_order(&self, chosen: &[usize]) -> Vec<usize> {
        let c: Vec<f64> = self.pool.iter().map(|r| r.budget).collect();
        let mut order = Vec::new();
        for rows in group_rows(&c, None, planner::GROUP_TOL_DEX) {
            let n: Vec<f64> = rows.iter().map(|&i| self.pool[i].n).collect();
            let loss: Vec<f64> = rows.iter().map(|&i| self.losses[i]).collect();
            let mut best_at_n: Vec<usize> = envelope_rows(&n, &loss)
                .into_iter()
                .map(|k| rows[k])
                .collect();
            let Some(&best) = best_at_n
                .iter()
                .min_by(|&&a, &&b| self.losses[a].total_cmp(&self.losses[b]))
            else {
                continue;
            };
            let distance = |i: usize| (self.pool[i].n / self.pool[best].n).log10().abs();
            best_at_n.sort_by(|&a, &b| distance(a).total_cmp(&distance(b)));
            order.extend(best_at_n.into_iter().filter(|i| !chosen.contains(i)));
        }
        order
    }

    /// Replays `policy` (random order `order`) until its next choice would pass the cap.
    pub fn replay(&self, policy: Policy, order: usize) -> Vec<ReplayStep> {
        let mut chosen = self.start.clone();
        let mut spent: f64 = chosen.iter().map(|&i| self.pool[i].cost).sum();
        let mut curve = vec![self.step(policy, order, &chosen, &self.start, 0)];
        let mut queue: Vec<usize> = (0..self.pool.len())
            .filter(|i| !chosen.contains(i))
            .collect();
        match policy {
            Policy::Random => {
                SplitMix64::stream(self.settings.seed, order as u64).shuffle(&mut queue)
            }
            Policy::Oracle => queue = self.envelope_order(&chosen),
            Policy::Active | Policy::Grid => {}
        }
        loop {
            let next: Vec<usize> = match policy {
                Policy::Active => {
                    let open: Vec<Candidate> =
                        queue.iter().map(|&i| self.pool[i].clone()).collect();
                    let obs = self.observed(&chosen);
                    let room = self.max_compute - spent;
                    match planner::propose(
                        &obs,
                        &open,
                        self.target,
                        self.c_star,
                        1,
                        room,
                        &self.settings,
                    )
                    .pop()
                    {
                        Some(p) => p.runs.iter().map(|&j| queue[j]).collect(),
                        None => break,
                    }
                }
                Policy::Grid | Policy::Random | Policy::Oracle => match queue.first() {
                    Some(&i) if spent + self.pool[i].cost <= self.max_compute => vec![i],
                    _ => break,
                },
            };
            queue.retain(|i| !next.contains(i));
            spent += next.iter().map(|&i| self.pool[i].cost).sum::<f64>();
            chosen.extend(&next);
            curve.push(self.step(policy, order, &chosen, &next, curve.len()));
        }
        curve
    }
}

/// The runs of a results table as the planner reads them, in the sweep's order (its `index`
/// column, else file order): id (`run_id`, else the row number), budget group (`budget`), N
/// (`n_nv`), vocabulary (`vocab`, when present), cost (`flops`, else the budget) and `loss`.
pub fn read_runs(t: &Table, loss: &str) -> Result<(Vec<Candidate>, Vec<f64>), FitError> {
    let budget = t.numbers("budget", "the sweep's `budget` column")?;
    let n = t.numbers("n_nv", "the sweep's `n_nv` column")?;
    let losses = t.numbers(loss, "--loss-col")?;
    let vocab = t
        .has("vocab")
        .then(|| t.numbers("vocab", "the sweep's `vocab` column"))
        .transpose()?;
    let cost = match t.has("flops") {
        true => t.numbers("flops", "the sweep's `flops` column")?,
        false => budget.clone(),
    };
    let ids = t
        .labels("run_id")
        .unwrap_or_else(|| (1..=t.rows()).map(|r| format!("row {r}")).collect());
    // A replay names its choices by run id: two rows of one id would be one run twice.
    for (row, id) in ids.iter().enumerate() {
        if let Some(first) = ids[..row].iter().position(|other| other == id) {
            return Err(FitError::BadCell {
                path: t.path().to_path_buf(),
                column: "run_id".into(),
                row: row + 1,
                problem: format!(
                    "{id:?} is row {}'s id too; each run needs its own",
                    first + 1
                ),
            });
        }
    }
    let mut order: Vec<usize> = (0..t.rows()).collect();
    if t.has("index") {
        let index = t.numbers("index", "the sweep's `index` column")?;
        order.sort_by(|&a, &b| index[a].total_cmp(&index[b]));
    }
    let runs = order
        .iter()
        .map(|&i| Candidate {
            id: ids[i].clone(),
            budget: budget[i],
            n: n[i],
            vocab: vocab.as_ref().map(|v| v[i]),
            cost: cost[i],
        })
        .collect();
    Ok((runs, order.iter().map(|&i| losses[i]).collect()))
}

/// A pool run a policy did not choose, beside what the planner's model expected of it where
/// the policy stopped.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PredictiveCheck {
    /// Run id.
    pub id: String,
    /// Budget C.
    pub budget: f64,
    /// Model size N.
    pub n: f64,
    /// Vocabulary, when runs differ in it.
    pub vocab: Option<f64>,
    /// Predictive mean of its loss.
    pub predicted: f64,
    /// Predictive SD.
    pub sd: f64,
    /// Its real loss.
    pub loss: f64,
    /// (loss − predicted) / sd.
    pub z: f64,
    /// On its budget's envelope in the full table (the lowest loss at its N).
    pub on_envelope: bool,
}

/// The predictive check summarised: how far the runs left fell from the planner's
/// expectation, in its own predictive SDs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckSummary {
    /// Runs checked (those left at budgets the model predicts).
    pub runs: usize,
    /// RMS of z (1 when the predictive SD is right).
    pub rms_z: f64,
    /// Share with |z| > 1.96 (5% when calibrated).
    pub beyond_95: f64,
    /// Runs on the full table's envelopes.
    pub envelope_runs: usize,
    /// Their RMS z.
    pub envelope_rms_z: f64,
    /// Their mean z (negative: lower than expected).
    pub envelope_mean_z: f64,
}

impl ReplayTable {
    /// The planner's predictive check where `curve` ends: every pool run the curve did not
    /// choose, at a budget the model predicts, against the model of the runs it chose.
    pub fn predictive_check(&self, curve: &[ReplayStep]) -> Vec<PredictiveCheck> {
        let added: Vec<&str> = curve.iter().flat_map(|s| s.added.split(';')).collect();
        let (chosen, left): (Vec<usize>, Vec<usize>) =
            (0..self.pool.len()).partition(|&i| added.contains(&self.pool[i].id.as_str()));
        let envelope = self.envelope_order(&[]);
        let runs: Vec<Candidate> = left.iter().map(|&i| self.pool[i].clone()).collect();
        let floor = self.settings.misfit_floor;
        planner::predictive(&self.observed(&chosen), &runs, floor)
            .into_iter()
            .zip(left)
            .filter_map(|(p, i)| {
                let (predicted, sd) = p?;
                let run = &self.pool[i];
                Some(PredictiveCheck {
                    id: run.id.clone(),
                    budget: run.budget,
                    n: run.n,
                    vocab: run.vocab,
                    predicted,
                    sd,
                    loss: self.losses[i],
                    z: (self.losses[i] - predicted) / sd,
                    on_envelope: envelope.contains(&i),
                })
            })
            .collect()
    }
}

/// `checks` summarised.
pub fn summarise_check(checks: &[PredictiveCheck]) -> CheckSummary {
    let rms = |z: &[f64]| (z.iter().map(|v| v * v).sum::<f64>() / z.len().max(1) as f64).sqrt();
    let z: Vec<f64> = checks.iter().map(|c| c.z).collect();
    let on: Vec<f64> = checks
        .iter()
        .filter(|c| c.on_envelope)
        .map(|c| c.z)
        .collect();
    CheckSummary {
        runs: z.len(),
        rms_z: rms(&z),
        beyond_95: z.iter().filter(|v| v.abs() > Z95).count() as f64 / z.len().max(1) as f64,
        envelope_runs: on.len(),
        envelope_rms_z: rms(&on),
        envelope_mean_z: on.iter().sum::<f64>() / on.len().max(1) as f64,
    }
}

/// The last step of `curve` within `compute` FLOPs.
fn at_compute(curve: &[ReplayStep], compute: f64) -> Option<&ReplayStep> {
    curve.iter().take_while(|s| s.compute <= compute).last()
}

/// The median over `curves` of `value` at `compute` (each curve's last step within it).
pub fn median_at(curves: &[Vec<ReplayStep>], compute: f64, value: fn(&ReplayStep) -> f64) -> f64 {
    let mut v: Vec<f64> = curves
        .iter()
        .filter_map(|c| at_compute(c, compute).map(value))
        .collect();
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        k if k % 2 == 1 => v[k / 2],
        k => 0.5 * (v[k / 2 - 1] + v[k / 2]),
    }
}

/// A policy's curve summarised (random orders by their median).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PolicySummary {
    /// Policy name.
    pub policy: String,
    /// Curves summarised (random orders; 1 otherwise).
    pub orders: usize,
    /// Compute spent at the end, as a share of the pool's.
    pub final_share: f64,
    /// Interval width at the end.
    #[serde(deserialize_with = "planner::infinite_if_null")]
    pub final_width: f64,
    /// |median − truth| at the end.
    pub final_error: f64,
    /// The first compute share at which the width is no wider than the full table's
    /// (median over orders that reach it; `None` if none does).
    pub share_to_full_width: Option<f64>,
    /// Orders that reach the full table's width.
    pub orders_reaching_full_width: usize,
    /// Mean capped width over 100 compute levels from the start to the cap (lower is better).
    pub mean_width: f64,
    /// Mean capped error over the same levels.
    pub mean_error: f64,
}

/// The active curve against another policy's: the shares of compute levels at which its
/// capped width and its error are at or below the other's (median) curve.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AtOrBelow {
    /// The other policy.
    pub policy: String,
    /// Share of levels where the active width is at or below.
    pub width: f64,
    /// Share of levels where the active (capped) error is at or below.
    pub error: f64,
}

/// What `sweep replay` writes to `summary.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReplaySummary {
    /// The results table replayed.
    pub results: String,
    /// `n_opt` or `loss`.
    pub target: String,
    /// The loss law of the `loss` target (`log`, `curved` or `floor`); none for `n_opt`.
    #[serde(default)]
    pub loss_form: Option<String>,
    /// C*.
    pub target_budget: f64,
    /// The target's true value.
    pub truth: f64,
    /// The loss column.
    pub loss_col: String,
    /// Runs below C*.
    pub pool_runs: usize,
    /// Their FLOPs.
    pub pool_compute: f64,
    /// Runs every policy starts from.
    pub start_runs: usize,
    /// Their share of the pool's compute.
    pub start_share: f64,
    /// The cap, as a share of the pool's compute.
    pub max_compute_share: f64,
    /// Bootstrap draws per posterior.
    pub draws: usize,
    /// Seed of the draws and orders.
    pub seed: u64,
    /// The posterior from every pool run.
    pub full_table: Posterior,
    /// Each policy's summary.
    pub policies: Vec<PolicySummary>,
    /// The active curve against each other policy.
    pub active_at_or_below: Vec<AtOrBelow>,
    /// The planner's predictive check where the active policy stopped (`predictive-check.csv`).
    #[serde(default)]
    pub active_predictive_check: Option<CheckSummary>,
}

/// The active curve against each other policy's, over `levels` of compute.
pub fn at_or_below(curves: &[(&str, Vec<Vec<ReplayStep>>)], levels: &[f64]) -> Vec<AtOrBelow> {
    let Some((_, active)) = curves.iter().find(|(n, _)| *n == "active") else {
        return Vec::new();
    };
    let share = |other: &[Vec<ReplayStep>], value: fn(&ReplayStep) -> f64| {
        let hits = levels
            .iter()
            .filter(|&&x| median_at(active, x, value) <= median_at(other, x, value))
            .count();
        hits as f64 / levels.len() as f64
    };
    curves
        .iter()
        .filter(|(n, _)| *n != "active")
        .map(|(name, c)| AtOrBelow {
            policy: name.to_string(),
            width: share(c, |s| s.posterior.capped_width()),
            error: share(c, ReplayStep::capped_error),
        })
        .collect()
}

/// Summarises the curves of one policy against the full table's width.
pub fn summarise(
    policy: &str,
    curves: &[Vec<ReplayStep>],
    pool_compute: f64,
    levels: &[f64],
    full_width: f64,
) -> PolicySummary {
    let ends: Vec<Vec<ReplayStep>> = curves
        .iter()
        .map(|c| c.last().into_iter().cloned().collect())
        .collect();
    let end = |value: fn(&ReplayStep) -> f64| median_at(&ends, f64::INFINITY, value);
    let mut reach: Vec<f64> = curves
        .iter()
        .filter_map(|c| {
            c.iter()
                .find(|s| s.posterior.width <= full_width + SAME_WIDTH)
        })
        .map(|s| s.compute / pool_compute)
        .collect();
    reach.sort_by(f64::total_cmp);
    let mean = |value: fn(&ReplayStep) -> f64| {
        levels
            .iter()
            .map(|&x| median_at(curves, x, value))
            .sum::<f64>()
            / levels.len() as f64
    };
    PolicySummary {
        policy: policy.into(),
        orders: curves.len(),
        final_share: end(|s| s.compute) / pool_compute,
        final_width: end(|s| s.posterior.width),
        final_error: end(|s| s.error),
        share_to_full_width: (!reach.is_empty()).then(|| reach[reach.len() / 2]),
        orders_reaching_full_width: reach.len(),
        mean_width: mean(|s| s.posterior.capped_width()),
        mean_error: mean(ReplayStep::capped_error),
    }
}

/// Writes every step as CSV (one row per step of every curve).
pub fn write_csv(path: &Path, curves: &[Vec<ReplayStep>]) -> Result<(), FitError> {
    let mut out = String::from(
        "policy,order,step,runs,compute,median,low,high,width,valid,draws,error,added\n",
    );
    for s in curves.iter().flatten() {
        let p = &s.posterior;
        out.push_str(&format!(
            "{},{},{},{},{:e},{},{},{},{},{},{},{},{}\n",
            s.policy,
            s.order,
            s.step,
            s.runs,
            s.compute,
            p.median,
            p.low,
            p.high,
            p.width,
            p.valid,
            p.draws,
            s.error,
            s.added
        ));
    }
    write_text(path, &out)
}

/// Writes `text` to `path` atomically.
fn write_text(path: &Path, text: &str) -> Result<(), FitError> {
    motionscale_core::files::write_atomic(path, text.as_bytes()).map_err(|source| FitError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Writes the predictive check as CSV.
pub fn write_check_csv(path: &Path, checks: &[PredictiveCheck]) -> Result<(), FitError> {
    let mut out = String::from("id,budget,n,vocab,predicted,sd,loss,z,on_envelope\n");
    for c in checks {
        let vocab = c.vocab.map(|v| v.to_string()).unwrap_or_default();
        out.push_str(&format!(
            "{},{:e},{:e},{vocab},{},{},{},{},{}\n",
            c.id, c.budget, c.n, c.predicted, c.sd, c.loss, c.z, c.on_envelope
        ));
    }
    write_text(path, &out)
}

/// The width and error charts: active, grid and the random orders' median against the
/// compute share, with the full table's width.
pub fn charts(
    curves: &[(&str, Vec<Vec<ReplayStep>>)],
    pool_compute: f64,
    levels: &[f64],
    full: &Posterior,
    unit: &str,
) -> [Chart; 2] {
    let series = |value: fn(&ReplayStep) -> f64| -> Vec<Series> {
        curves
            .iter()
            .enumerate()
            .map(|(k, (name, c))| {
                let label = match c.len() {
                    1 => name.to_string(),
                    n => format!("{name} (median of {n} orders)"),
                };
                let pts = levels
                    .iter()
                    .map(|&x| (x / pool_compute, median_at(c, x, value)))
                    .collect();
                Series::line(label, pts).with_color(k)
            })
            .collect()
    };
    let span = (
        levels[0] / pool_compute,
        levels[levels.len() - 1] / pool_compute,
    );
    let mut width = Chart::new(
        "Interval width against compute spent (replay on real runs)",
        "compute spent (share of the table's)",
        format!("95% interval width ({unit}, capped at {WIDTH_CAP})"),
    );
    width.series = series(|s| s.posterior.capped_width());
    width.series.push(
        Series::line(
            format!("full table ({:.3})", full.width),
            vec![(span.0, full.width), (span.1, full.width)],
        )
        .with_color(curves.len()),
    );
    let mut error = Chart::new(
        "Error of the posterior median against compute spent",
        "compute spent (share of the table's)",
        format!("|median − truth| ({unit})"),
    );
    error.series = series(|s| s.error);
    [width, error]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::{isoflop_runs, CHINCHILLA};

    /// A Chinchilla-form table with 1% loss noise and a misfit the parabolas cannot follow
    /// (a budget-dependent ripple in log N), six budgets below the target 10^21.
    fn synthetic_table() -> ReplayTable {
        let budgets = [1e18, 3e18, 1e19, 3e19, 1e20, 3e20];
        let runs = isoflop_runs(&CHINCHILLA, &budgets, 7, 0.01, 0.0, 7);
        let pool: Vec<Candidate> = runs
            .iter()
            .enumerate()
            .map(|(i, r)| Candidate {
                id: format!("r{i}"),
                budget: r.c,
                n: r.n,
                vocab: None,
                cost: r.c,
            })
            .collect();
        let losses = runs
            .iter()
            .map(|r| r.loss + 0.02 * (4.0 * r.n.log10() + r.c.log10()).sin())
            .collect();
        let total: f64 = pool.iter().map(|c| c.cost).sum();
        ReplayTable {
            start: (0..21).collect(),
            pool,
            losses,
            target: Target::NOpt,
            c_star: 1e21,
            truth: CHINCHILLA.n_opt(1e21).log10(),
            max_compute: 0.3 * total,
            settings: Settings {
                draws: 64,
                ..Settings::default()
            },
        }
    }

    #[test]
    fn active_policy_ends_closer_to_the_truth_than_the_median_random_order() {
        let table = synthetic_table();
        let last = |curve: Vec<ReplayStep>| curve.last().expect("the start is a step").clone();
        let active = last(table.replay(Policy::Active, 0));
        let mut random: Vec<f64> = (0..9)
            .map(|order| last(table.replay(Policy::Random, order)).error)
            .collect();
        random.sort_by(f64::total_cmp);
        assert!(active.compute <= table.max_compute);
        assert!(
            active.error < random[4],
            "active error {} vs random median {} ({random:?})",
            active.error,
            random[4]
        );
    }

    #[test]
    fn the_predictive_check_scores_every_run_left_in_the_models_own_sds() {
        let table = synthetic_table();
        let curve = table.replay(Policy::Active, 0);
        let checks = table.predictive_check(&curve);
        let chosen: usize = curve.iter().map(|s| s.added.split(';').count()).sum();
        assert_eq!(
            chosen + checks.len(),
            table.pool.len(),
            "every run is chosen or checked"
        );
        for c in &checks {
            let i = table.pool.iter().position(|r| r.id == c.id).unwrap();
            assert_eq!(c.loss, table.losses[i]);
            assert!((c.z - (c.loss - c.predicted) / c.sd).abs() < 1e-12);
        }
        // The table is the model's own family (a parabola per budget, misfit from the noise
        // and a ripple the pooled residuals carry): its SDs should fit the runs left.
        let summary = summarise_check(&checks);
        assert!(
            (0.5..2.0).contains(&summary.rms_z),
            "RMS z {}",
            summary.rms_z
        );
    }

    #[test]
    fn every_policy_starts_from_the_same_runs_and_keeps_to_the_cap() {
        let table = synthetic_table();
        for policy in [Policy::Active, Policy::Grid, Policy::Random] {
            let curve = table.replay(policy, 1);
            assert_eq!(curve[0].runs, 21, "{policy:?}");
            assert!(curve.iter().all(|s| s.compute <= table.max_compute));
            assert!(curve.windows(2).all(|w| w[1].compute > w[0].compute));
        }
    }

    #[test]
    fn oracle_takes_each_budget_envelope_nearest_its_best_run_first() {
        let mut table = synthetic_table();
        let n = table.pool.len();
        for i in 0..n {
            let worse = Candidate {
                id: format!("{}-worse", table.pool[i].id),
                vocab: Some(2.0),
                ..table.pool[i].clone()
            };
            table.pool.push(worse);
            table.losses.push(table.losses[i] + 0.05);
        }
        table.max_compute = f64::INFINITY;
        let curve = table.replay(Policy::Oracle, 0);
        let added: Vec<usize> = curve[1..]
            .iter()
            .map(|s| table.pool.iter().position(|c| c.id == s.added).unwrap())
            .collect();
        assert_eq!(added.len(), n - table.start.len(), "each envelope run once");
        assert!(added.iter().all(|&i| i < n), "never a run off the envelope");
        for pair in added.windows(2) {
            let (a, b) = (&table.pool[pair[0]], &table.pool[pair[1]]);
            assert!(a.budget <= b.budget, "budget by budget from the cheapest");
            if a.budget == b.budget {
                let best = (0..n)
                    .filter(|&i| table.pool[i].budget == a.budget)
                    .min_by(|&i, &j| table.losses[i].total_cmp(&table.losses[j]))
                    .unwrap();
                let d = |c: &Candidate| (c.n / table.pool[best].n).log10().abs();
                assert!(d(a) <= d(b), "nearest the budget's best run first");
            }
        }
        let (end, full) = (curve.last().unwrap().posterior, table.full());
        for (a, b) in [
            (end.low, full.low),
            (end.median, full.median),
            (end.high, full.high),
        ] {
            assert!(
                (a - b).abs() < 1e-9,
                "the envelope is all the posterior reads"
            );
        }
        let spent = curve.last().unwrap().compute;
        let summary = summarise("oracle", &[curve], spent, &[spent], full.width);
        assert_eq!(summary.orders_reaching_full_width, 1);
    }
}
