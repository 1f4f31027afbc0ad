//! The runs a fit reads: the results table's columns, checked and row-aligned, with the
//! derived ones (C without a compute column, width without a width column).

use crate::fitted::{ColumnChoice, FitOptions};
use crate::isoflop;
use crate::table::Table;
use crate::FitError;
use std::collections::BTreeMap;

/// One results table as the fit sees it; every vector has one value per run.
#[derive(Debug, Clone, PartialEq)]
pub struct Runs {
    /// Model size N (the N column; `N_nv + N_v` in the total-parameter convention).
    pub n: Vec<f64>,
    /// Loss for the minima, power laws and log law.
    pub loss: Vec<f64>,
    /// Loss for the parametric fit, and its column's name.
    pub param_loss: (String, Vec<f64>),
    /// Compute C.
    pub c: Vec<f64>,
    /// Training tokens D.
    pub d: Option<Vec<f64>>,
    /// Vocabulary size V.
    pub v: Option<Vec<f64>>,
    /// Vocabulary parameters N_v.
    pub nv: Option<Vec<f64>>,
    /// Model width.
    pub width: Option<Vec<f64>>,
    /// Budget-group key.
    pub group: Option<Vec<f64>>,
    /// Epochs over the unique training tokens (the data-constrained fit's input).
    pub epochs: Option<Vec<f64>>,
    /// Synthetic share of each run's unique data, in [0, 1] (the exchange rate's input).
    pub synth_share: Option<Vec<f64>>,
    /// Training seed (runs repeated with other seeds are averaged for the minima).
    pub seed: Option<Vec<f64>>,
    /// Hours of motion in each run's unique data (the sweep's `hours` column; `None` unless
    /// recorded on every row): the data-constrained fit's tokens per hour.
    pub hours: Option<Vec<f64>>,
    /// The share of each run's steps at its validation-selected checkpoint, best_step / steps
    /// (read for `--early-stopping` only).
    pub selected: Option<Vec<f64>>,
    /// Role → column used (`None`: not used).
    pub columns: BTreeMap<String, Option<String>>,
    /// Defaults substituted or computed.
    pub notes: Vec<String>,
}

/// Reads a column the user may or may not have named; `Ok(None)` for a missing default.
fn optional(t: &Table, col: &ColumnChoice, flag: &str) -> Result<Option<Vec<f64>>, FitError> {
    if t.has(&col.name) || col.explicit {
        t.numbers(&col.name, flag).map(Some)
    } else {
        Ok(None)
    }
}

/// Every value must be > 0 (the column goes on a log axis).
fn positive(t: &Table, name: &str, values: &[f64]) -> Result<(), FitError> {
    match values.iter().position(|&v| v <= 0.0) {
        None => Ok(()),
        Some(row) => Err(FitError::BadCell {
            path: t.path().to_path_buf(),
            column: name.into(),
            row: row + 1,
            problem: format!("{} must be > 0 (it goes on a log scale)", values[row]),
        }),
    }
}

/// The synthetic-share column: `None` when absent or not recorded on every row (NaN, with a
/// note); a value outside [0, 1] is an error.
fn shares(
    t: &Table,
    col: &ColumnChoice,
    notes: &mut Vec<String>,
) -> Result<Option<Vec<f64>>, FitError> {
    if !(t.has(&col.name) || col.explicit) {
        return Ok(None);
    }
    let values = t.numbers_or_nan(&col.name, "--synth-share-col")?;
    if let Some(row) = values.iter().position(|v| v.is_nan()) {
        notes.push(format!(
            "{:?} is not recorded at row {} (a run on the whole train split): no exchange rate",
            col.name,
            row + 1
        ));
        return Ok(None);
    }
    match values.iter().position(|v| !(0.0..=1.0).contains(v)) {
        None => Ok(Some(values)),
        Some(row) => Err(FitError::BadCell {
            path: t.path().to_path_buf(),
            column: col.name.clone(),
            row: row + 1,
            problem: format!("{} is not a share in [0, 1]", values[row]),
        }),
    }
}

/// The sweep's `best_step` / `steps` per run, each in (0, 1]: where the validation-selected
/// checkpoint lies in the run's schedule.
fn selected_share(t: &Table) -> Result<Vec<f64>, FitError> {
    if let Some(missing) = ["best_step", "steps"].into_iter().find(|c| !t.has(c)) {
        return Err(FitError::MissingColumn {
            path: t.path().to_path_buf(),
            column: missing.into(),
            available: t.names().join(", "),
            hint: "--early-stopping reads the sweep's `best_step` and `steps` columns".into(),
        });
    }
    let best = t.numbers("best_step", "--early-stopping")?;
    let steps = t.numbers("steps", "--early-stopping")?;
    let share: Vec<f64> = best.iter().zip(&steps).map(|(b, s)| b / s).collect();
    match share.iter().position(|v| !(*v > 0.0 && *v <= 1.0)) {
        None => Ok(share),
        Some(row) => Err(FitError::BadCell {
            path: t.path().to_path_buf(),
            column: "best_step".into(),
            row: row + 1,
            problem: format!(
                "best_step {} of {} steps: the selected step must lie in (0, steps]",
                best[row], steps[row]
            ),
        }),
    }
}

impl Runs {
    /// Reads and checks the columns `opts` names from `t`.
    pub fn read(t: &Table, opts: &FitOptions) -> Result<Self, FitError> {
        let cs = &opts.columns;
        let mut notes = Vec::new();
        let mut columns: BTreeMap<String, Option<String>> = BTreeMap::new();
        let n = t.numbers(&cs.n.name, "--n-col")?;
        positive(t, &cs.n.name, &n)?;
        let loss = t.numbers(&cs.loss.name, "--loss-col")?;
        columns.insert("N".into(), Some(cs.n.name.clone()));
        columns.insert("loss".into(), Some(cs.loss.name.clone()));
        let mut read = |role: &str, col: &ColumnChoice, flag: &str| {
            let values = optional(t, col, flag)?;
            if let Some(vals) = &values {
                positive(t, &col.name, vals)?;
            }
            columns.insert(role.into(), values.as_ref().map(|_| col.name.clone()));
            Ok::<_, FitError>(values)
        };
        let d = read("D", &cs.d, "--d-col")?;
        let v = read("V", &cs.v, "--v-col")?;
        let nv = read("N_v", &cs.nv, "--nv-col")?;
        let width_col = read("width", &cs.width, "--width-col")?;
        let epochs = read("epochs", &cs.epochs, "--epochs-col")?;
        let c = match optional(t, &cs.c, "--c-col")? {
            Some(c) => {
                positive(t, &cs.c.name, &c)?;
                columns.insert("C".into(), Some(cs.c.name.clone()));
                c
            }
            None => {
                let Some(d) = &d else {
                    return Err(FitError::MissingColumn {
                        path: t.path().to_path_buf(),
                        column: cs.c.name.clone(),
                        available: t.names().join(", "),
                        hint: "pick the compute column with --c-col (or give --d-col so C = 6·N·D)"
                            .into(),
                    });
                };
                let extra = nv.as_deref();
                notes.push(format!(
                    "no column {:?}: C computed as 6·({}{})·{}",
                    cs.c.name,
                    cs.n.name,
                    extra.map_or(String::new(), |_| format!(" + {}", cs.nv.name)),
                    cs.d.name
                ));
                columns.insert("C".into(), None);
                (0..n.len())
                    .map(|i| 6.0 * (n[i] + extra.map_or(0.0, |x| x[i])) * d[i])
                    .collect()
            }
        };
        let width = match (&width_col, &v, &nv) {
            (Some(w), _, _) => Some(w.clone()),
            (None, Some(v), Some(nv)) => {
                notes.push(format!(
                    "no column {:?}: width = {} / {}",
                    cs.width.name, cs.nv.name, cs.v.name
                ));
                Some(nv.iter().zip(v).map(|(a, b)| a / b).collect())
            }
            _ => None,
        };
        let group = optional(t, &cs.group, "--group-col")?;
        let seed = optional(t, &cs.seed, "--seed-col")?;
        let synth_share = shares(t, &cs.synth_share, &mut notes)?;
        let hours = match t.has("hours") {
            true => Some(t.numbers_or_nan("hours", "the sweep's `hours` column")?)
                .filter(|h| h.iter().all(|v| v.is_finite() && *v > 0.0)),
            false => None,
        };
        columns.insert("hours".into(), hours.as_ref().map(|_| "hours".into()));
        columns.insert(
            "synth_share".into(),
            synth_share.as_ref().map(|_| cs.synth_share.name.clone()),
        );
        columns.insert("seed".into(), seed.as_ref().map(|_| cs.seed.name.clone()));
        columns.insert(
            "group".into(),
            group.as_ref().map(|_| cs.group.name.clone()),
        );
        let param_loss = match optional(t, &cs.param_loss, "--param-loss-col")? {
            Some(l) => (cs.param_loss.name.clone(), l),
            None => {
                notes.push(format!(
                    "no column {:?}: the parametric fit uses {:?}",
                    cs.param_loss.name, cs.loss.name
                ));
                (cs.loss.name.clone(), loss.clone())
            }
        };
        columns.insert("parametric_loss".into(), Some(param_loss.0.clone()));
        let selected = match opts.early_stopping {
            true => Some(selected_share(t)?),
            false => None,
        };
        Ok(Self {
            n,
            loss,
            param_loss,
            c,
            d,
            v,
            nv,
            width,
            group,
            epochs,
            synth_share,
            seed,
            hours,
            selected,
            columns,
            notes,
        })
    }

    /// Number of runs.
    pub fn len(&self) -> usize {
        self.n.len()
    }

    /// True without runs.
    pub fn is_empty(&self) -> bool {
        self.n.is_empty()
    }

    /// The runs at `rows`, in that order.
    pub fn select(&self, rows: &[usize]) -> Self {
        let pick = |v: &[f64]| rows.iter().map(|&i| v[i]).collect::<Vec<f64>>();
        let pick_opt = |v: &Option<Vec<f64>>| v.as_deref().map(pick);
        Self {
            n: pick(&self.n),
            loss: pick(&self.loss),
            param_loss: (self.param_loss.0.clone(), pick(&self.param_loss.1)),
            c: pick(&self.c),
            d: pick_opt(&self.d),
            v: pick_opt(&self.v),
            nv: pick_opt(&self.nv),
            width: pick_opt(&self.width),
            group: pick_opt(&self.group),
            epochs: pick_opt(&self.epochs),
            synth_share: pick_opt(&self.synth_share),
            hours: pick_opt(&self.hours),
            seed: pick_opt(&self.seed),
            selected: pick_opt(&self.selected),
            columns: self.columns.clone(),
            notes: self.notes.clone(),
        }
    }

    /// The same runs with N counted as every parameter, N + N_v (embedding and output head
    /// included, as Pearce & Song 2024 recommend at small scale); `None` without an N_v column.
    /// Where several vocabularies were trained at one budget and N, only the one with the
    /// lowest mean loss is kept (every seed of it): each IsoFLOP curve is then the N
    /// convention's envelope over vocabularies, each point at its own run's total N. Pooling
    /// them instead mixes curves of different vocabularies, which no parabola fits.
    pub fn total_parameters(&self, tol_dex: f64) -> Option<Self> {
        self.nv.as_ref()?;
        let mut out = match &self.v {
            Some(v) => self.select(&self.best_vocabulary_rows(v, tol_dex)),
            None => self.clone(),
        };
        let nv = out.nv.as_deref().unwrap_or_default();
        out.n = out.n.iter().zip(nv).map(|(a, b)| a + b).collect();
        let name = |c: &Option<String>| c.clone().unwrap_or_default();
        let total = format!(
            "{} + {}",
            name(&self.columns["N"]),
            name(&self.columns["N_v"])
        );
        out.columns.insert("N".into(), Some(total));
        Some(out)
    }

    /// The runs of vocabulary size `k`; an error without a V column or without such runs.
    pub fn of_vocabulary(&self, k: f64) -> Result<Self, FitError> {
        let bad = |problem: String| FitError::BadOption {
            flag: format!("--vocab {k}"),
            problem,
        };
        let v = self
            .v
            .as_ref()
            .ok_or_else(|| bad("the table has no vocabulary column".into()))?;
        let rows: Vec<usize> = (0..v.len()).filter(|&i| v[i] == k).collect();
        if rows.is_empty() {
            let mut sizes: Vec<f64> = v.clone();
            sizes.sort_by(f64::total_cmp);
            sizes.dedup();
            return Err(bad(format!(
                "no runs of this vocabulary; the table has {sizes:?}"
            )));
        }
        let mut out = self.select(&rows);
        out.notes
            .push(format!("only the {} runs of vocabulary {k}", rows.len()));
        Ok(out)
    }

    /// The rows of the vocabulary with the lowest mean loss at each (budget group, N), in
    /// row order.
    fn best_vocabulary_rows(&self, v: &[f64], tol_dex: f64) -> Vec<usize> {
        let mut keep = Vec::new();
        for group in isoflop::group_rows(&self.c, self.group.as_deref(), tol_dex) {
            // (N, V) → (loss sum, runs) of this budget.
            let mut cells: BTreeMap<(u64, u64), (f64, usize)> = BTreeMap::new();
            for &i in &group {
                let cell = cells
                    .entry((self.n[i].to_bits(), v[i].to_bits()))
                    .or_default();
                *cell = (cell.0 + self.loss[i], cell.1 + 1);
            }
            let mut best: BTreeMap<u64, (f64, u64)> = BTreeMap::new();
            for ((n, vocab), (sum, count)) in cells {
                let mean = sum / count as f64;
                let entry = best.entry(n).or_insert((mean, vocab));
                if mean < entry.0 {
                    *entry = (mean, vocab);
                }
            }
            keep.extend(
                group
                    .iter()
                    .filter(|&&i| best[&self.n[i].to_bits()].1 == v[i].to_bits()),
            );
        }
        keep.sort_unstable();
        keep
    }

    /// Unique training tokens per run, D / epochs (needs both columns).
    pub fn unique_tokens(&self) -> Option<Vec<f64>> {
        let (d, e) = (self.d.as_ref()?, self.epochs.as_ref()?);
        Some(d.iter().zip(e).map(|(d, e)| d / e).collect())
    }

    /// The runs grouped into data subsets: equal synthetic share (to 0.01) and unique tokens
    /// U within 1% of their neighbour's (U = D/epochs carries the epochs column's rounding);
    /// `None` without D and epochs.
    pub fn data_subsets(&self) -> Option<Vec<Vec<usize>>> {
        let u = self.unique_tokens()?;
        let share = self.synth_share.as_deref();
        let key = |i: usize| share.map_or(0, |s| (100.0 * s[i]).round() as i64);
        let mut order: Vec<usize> = (0..u.len()).collect();
        order.sort_by(|&a, &b| key(a).cmp(&key(b)).then(u[a].total_cmp(&u[b])));
        let mut out: Vec<Vec<usize>> = Vec::new();
        for (j, &i) in order.iter().enumerate() {
            let same = j > 0 && {
                let p = order[j - 1];
                key(p) == key(i) && (u[i] / u[p]).ln() < 0.01
            };
            match (same, out.last_mut()) {
                (true, Some(last)) => last.push(i),
                _ => out.push(vec![i]),
            }
        }
        Some(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn runs() -> Runs {
        let mut columns = BTreeMap::new();
        columns.insert("N".to_string(), Some("n_nv".to_string()));
        columns.insert("N_v".to_string(), Some("n_v".to_string()));
        Runs {
            n: vec![74_048.0, 24_672.0],
            loss: vec![-3.1, -3.3],
            param_loss: ("test_loss".into(), vec![1.84, 1.71]),
            c: vec![3e11, 3e11],
            d: Some(vec![476_163.0, 1_243_403.0]),
            v: Some(vec![240.0, 240.0]),
            nv: Some(vec![31_104.0, 15_552.0]),
            width: Some(vec![64.0, 32.0]),
            group: None,
            epochs: Some(vec![2.0, 4.0]),
            synth_share: None,
            seed: None,
            hours: None,
            selected: None,
            columns,
            notes: Vec::new(),
        }
    }

    #[test]
    fn total_parameters_add_the_vocabulary_parameters_by_hand() {
        // The sweep's c3e11 rows: N_v = (240 codes + 3 specials)·d for the embedding and
        // again for the head: 243·64·2 = 31,104 and 243·32·2 = 15,552.
        let r = runs();
        assert_eq!(r.nv.as_ref().unwrap()[0], 243.0 * 64.0 * 2.0);
        assert_eq!(r.nv.as_ref().unwrap()[1], 243.0 * 32.0 * 2.0);
        let t = r.total_parameters(0.05).unwrap();
        assert_eq!(t.n, vec![74_048.0 + 31_104.0, 24_672.0 + 15_552.0]);
        assert_eq!(t.columns["N"].as_deref(), Some("n_nv + n_v"));
        assert_eq!(t.loss, r.loss);
        let mut no_nv = r.clone();
        no_nv.nv = None;
        assert!(no_nv.total_parameters(0.05).is_none());
    }

    #[test]
    fn total_parameters_keep_the_best_vocabulary_of_each_budget_and_size() {
        // Row 2: the 24,672 model at K = 1,000 (N_v = 1,003·32·2 = 64,192) beats K = 240,
        // so it replaces row 1; at 74,048 only K = 240 was trained.
        let mut r = runs().select(&[0, 1, 1]);
        r.v.as_mut().unwrap()[2] = 1000.0;
        r.nv.as_mut().unwrap()[2] = 64_192.0;
        r.loss[2] = -3.4;
        let t = r.total_parameters(0.05).unwrap();
        assert_eq!(t.n, vec![74_048.0 + 31_104.0, 24_672.0 + 64_192.0]);
        assert_eq!(t.loss, vec![-3.1, -3.4]);
        assert_eq!(t.v, Some(vec![240.0, 1000.0]));
    }

    #[test]
    fn one_vocabulary_is_selected_or_the_sizes_are_listed() {
        let mut r = runs();
        r.v.as_mut().unwrap()[1] = 1000.0;
        let k = r.of_vocabulary(1000.0).unwrap();
        assert_eq!((k.n.clone(), k.loss.clone()), (vec![24_672.0], vec![-3.3]));
        let err = r.of_vocabulary(4375.0).unwrap_err().to_string();
        assert!(err.contains("[240.0, 1000.0]"), "{err}");
    }

    #[test]
    fn synthetic_shares_read_when_every_run_records_one() {
        let dir = tempfile::tempdir().unwrap();
        let read = |shares: [&str; 2]| {
            let path = dir.path().join("results.csv");
            let csv = format!(
                "budget,n_nv,tokens,norm_test_loss,synth_share\n1e12,1e5,1e6,-2,{}\n1e12,2e5,5e5,-2.1,{}\n",
                shares[0], shares[1]
            );
            std::fs::write(&path, csv).unwrap();
            Runs::read(&Table::read(&path).unwrap(), &FitOptions::default())
        };
        assert_eq!(
            read(["0.5", "0"]).unwrap().synth_share,
            Some(vec![0.5, 0.0])
        );
        let unrecorded = read(["NaN", "0.5"]).unwrap();
        assert_eq!(unrecorded.synth_share, None);
        assert!(unrecorded
            .notes
            .iter()
            .any(|n| n.contains("not recorded at row 1")));
        let e = read(["0.5", "1.5"]).unwrap_err().to_string();
        assert!(e.contains("synth_share") && e.contains("[0, 1]"), "{e}");
    }

    #[test]
    fn early_stopping_reads_the_selected_share_or_says_which_column_is_wrong() {
        let dir = tempfile::tempdir().unwrap();
        let opts = FitOptions {
            early_stopping: true,
            ..FitOptions::default()
        };
        let read = |header: &str, row: &str| {
            let path = dir.path().join("results.csv");
            let csv = format!("budget,n_nv,tokens,norm_test_loss{header}\n1e12,1e5,1e6,-2{row}\n");
            std::fs::write(&path, csv).unwrap();
            Runs::read(&Table::read(&path).unwrap(), &opts)
        };
        let ok = read(",best_step,steps", ",250,1000").unwrap();
        assert_eq!(ok.selected, Some(vec![0.25]));
        let e = read(",steps", ",1000").unwrap_err().to_string();
        assert!(
            e.contains("best_step") && e.contains("--early-stopping"),
            "{e}"
        );
        let e = read(",best_step,steps", ",1200,1000")
            .unwrap_err()
            .to_string();
        assert!(e.contains("row 1") && e.contains("(0, steps]"), "{e}");
    }

    #[test]
    fn select_and_unique_tokens() {
        let r = runs();
        let s = r.select(&[1]);
        assert_eq!(s.n, vec![24_672.0]);
        assert_eq!(s.param_loss.1, vec![1.71]);
        assert_eq!(
            r.unique_tokens().unwrap(),
            vec![476_163.0 / 2.0, 1_243_403.0 / 4.0]
        );
    }
}
