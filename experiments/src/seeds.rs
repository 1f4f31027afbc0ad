//! Repeats of one experiment over training seeds, as `continual compare` and `cl2gen compare`
//! tabulate them: runs whose configurations differ only in their seed and output folder form
//! one group, reported as the mean and the 95% Student-t interval over seeds; runs scored by
//! different evaluators are never silently put in one table.

use crate::error::SweepError;
use motionscale_core::read_json;
use serde::de::DeserializeOwned;
use serde::Serialize;
use std::path::PathBuf;

/// A finished run: its folder, its summary and the evaluator that scored it.
pub struct ScoredRun<R> {
    /// The run folder.
    pub dir: PathBuf,
    /// Its summary.
    pub report: R,
    /// Content id of its evaluator (empty for runs from before ids were recorded).
    pub evaluator_id: String,
}

/// Read `DIR/summary.json` of every run folder, with the evaluator id `evaluator_id` finds in it.
pub fn read_runs<R: DeserializeOwned>(
    runs: &[PathBuf],
    evaluator_id: fn(&R) -> &str,
) -> Result<Vec<ScoredRun<R>>, SweepError> {
    runs.iter()
        .map(|dir| {
            let report: R = read_json(&dir.join("summary.json"))?;
            Ok(ScoredRun {
                dir: dir.clone(),
                evaluator_id: evaluator_id(&report).to_string(),
                report,
            })
        })
        .collect()
}

/// Group `runs` by `seedless` (the configuration with seed and output folder blanked), in the
/// order their first members were given; refuse runs of different evaluators unless
/// `mixed_evaluators`.
pub fn group<R, C: Serialize>(
    runs: Vec<ScoredRun<R>>,
    seedless: impl Fn(&R) -> C,
    mixed_evaluators: bool,
) -> Result<Vec<Vec<ScoredRun<R>>>, SweepError> {
    if !mixed_evaluators && runs.iter().any(|r| r.evaluator_id != runs[0].evaluator_id) {
        let listed: Vec<String> = runs
            .iter()
            .map(|r| format!("{} ({})", r.dir.display(), evaluator_label(&r.evaluator_id)))
            .collect();
        return Err(SweepError::Argument(format!(
            "the runs were scored by different evaluators, so their numbers are not comparable: \
             {}; re-run them with one evaluator or pass --mixed-evaluators",
            listed.join(", ")
        )));
    }
    let mut groups: Vec<(String, Vec<ScoredRun<R>>)> = Vec::new();
    for run in runs {
        let key = serde_json::to_string(&seedless(&run.report))
            .map_err(|e| SweepError::invalid(&run.dir, e))?;
        match groups.iter_mut().find(|(k, _)| *k == key) {
            Some((_, members)) => members.push(run),
            None => groups.push((key, vec![run])),
        }
    }
    Ok(groups.into_iter().map(|(_, members)| members).collect())
}

/// The run column of a group: its first folder, and how many more seeds it holds.
pub fn run_label<R>(members: &[ScoredRun<R>]) -> String {
    match members.len() {
        1 => members[0].dir.display().to_string(),
        n => format!("{} (+{} seeds)", members[0].dir.display(), n - 1),
    }
}

/// One metric over a group's seeds: the value, `mean ± half-width` with two or more seeds,
/// or `–` when some run lacks it.
pub fn cell(values: Option<Vec<f64>>, digits: usize) -> String {
    match values {
        Some(v) if v.len() > 1 => {
            let (mean, half) = fits::ols::mean_interval(&v);
            format!("{mean:.digits$} ± {half:.digits$}")
        }
        Some(v) if v.len() == 1 => format!("{:.digits$}", v[0]),
        _ => "–".to_string(),
    }
}

/// The evaluator id, or a word saying a run from before ids were recorded has none.
pub fn evaluator_label(id: &str) -> &str {
    if id.is_empty() {
        "unrecorded"
    } else {
        id
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(dir: &str, seed: u64, lr: f64, evaluator: &str) -> ScoredRun<(u64, f64)> {
        ScoredRun {
            dir: dir.into(),
            report: (seed, lr),
            evaluator_id: evaluator.into(),
        }
    }

    #[test]
    fn seeds_share_a_group_and_other_settings_do_not() {
        let runs = vec![
            run("a", 0, 1e-3, "e1"),
            run("b", 0, 1e-4, "e1"),
            run("a1", 1, 1e-3, "e1"),
            run("a2", 2, 1e-3, "e1"),
        ];
        let groups = group(runs, |&(_, lr)| lr, false).unwrap();
        let dirs: Vec<Vec<String>> = groups
            .iter()
            .map(|g| g.iter().map(|r| r.dir.display().to_string()).collect())
            .collect();
        assert_eq!(dirs, vec![vec!["a", "a1", "a2"], vec!["b"]]);
        assert_eq!(run_label(&groups[0]), "a (+2 seeds)");
        assert_eq!(cell(Some(vec![1.0, 2.0, 3.0]), 3), "2.000 ± 2.484");
        assert_eq!(cell(Some(vec![0.25]), 2), "0.25");
        assert_eq!(cell(None, 2), "–");
    }

    #[test]
    fn different_evaluators_are_refused_unless_allowed() {
        let runs = || vec![run("a", 0, 1e-3, "e1"), run("b", 1, 1e-3, "")];
        let err = group(runs(), |&(_, lr)| lr, false)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("a (e1), b (unrecorded)"), "{err}");
        assert_eq!(group(runs(), |&(_, lr)| lr, true).unwrap().len(), 1);
    }
}
