//! Runs repeated with other training seeds. Their losses are averaged before the IsoFLOP
//! minima are taken, because the lowest of several seeds is biased low. Their spread is the
//! run-to-run noise that the minima must be judged against.

use crate::fitted::SeedNoise;
use crate::isoflop::{self, BudgetMinimum};
use crate::runs::Runs;
use std::collections::BTreeMap;

/// `runs` with the rows that share a budget group, N, V and data subset ([`Runs::data_subsets`])
/// but not the seed averaged into one (the loss columns; the rest from the first such row),
/// and the spread of each such set.
pub fn average(runs: &Runs, groups: &[Vec<usize>]) -> (Runs, Vec<SeedNoise>) {
    let Some(seed) = &runs.seed else {
        return (runs.clone(), Vec::new());
    };
    let mut subset = vec![0; runs.n.len()];
    for (k, rows) in runs.data_subsets().unwrap_or_default().iter().enumerate() {
        rows.iter().for_each(|&i| subset[i] = k);
    }
    let mut sets: BTreeMap<(usize, u64, u64, usize), Vec<usize>> = BTreeMap::new();
    for (g, rows) in groups.iter().enumerate() {
        for &i in rows {
            let v = runs.v.as_ref().map_or(0, |v| v[i].to_bits());
            let key = (g, runs.n[i].to_bits(), v, subset[i]);
            sets.entry(key).or_default().push(i);
        }
    }
    if sets.values().all(|rows| rows.len() == 1) {
        return (runs.clone(), Vec::new());
    }
    // (first row, mean loss, mean parametric loss) per set, in table order.
    let mut kept: Vec<(usize, f64, f64)> = Vec::new();
    let mut noise = Vec::new();
    for ((g, ..), rows) in &sets {
        let mean = |col: &[f64]| rows.iter().map(|&i| col[i]).sum::<f64>() / rows.len() as f64;
        kept.push((rows[0], mean(&runs.loss), mean(&runs.param_loss.1)));
        if rows.len() > 1 {
            let sd = |col: &[f64]| {
                let m = mean(col);
                let ss: f64 = rows.iter().map(|&i| (col[i] - m).powi(2)).sum();
                (ss / (rows.len() - 1) as f64).sqrt()
            };
            noise.push(SeedNoise {
                budget: isoflop::group_budget(&runs.c, &groups[*g]),
                n: runs.n[rows[0]],
                v: runs.v.as_ref().map(|v| v[rows[0]]),
                seeds: rows.iter().map(|&i| seed[i]).collect(),
                mean: mean(&runs.loss),
                sd: sd(&runs.loss),
                param_sd: Some(sd(&runs.param_loss.1)),
                resolved_gap: None,
            });
        }
    }
    kept.sort_by_key(|k| k.0);
    let mut averaged = runs.select(&kept.iter().map(|k| k.0).collect::<Vec<_>>());
    averaged.loss = kept.iter().map(|k| k.1).collect();
    averaged.param_loss.1 = kept.iter().map(|k| k.2).collect();
    (averaged, noise)
}

/// Fills each set's `resolved_gap` from its budget's parabola.
pub fn resolve_gaps(noise: &mut [SeedNoise], budgets: &[BudgetMinimum]) {
    for s in noise {
        let Some(b) = budgets.iter().find(|b| b.min.budget == s.budget) else {
            continue;
        };
        let (Some(c2), true) = (b.min.curvature, b.min.points.len() > 1) else {
            continue;
        };
        let mut steps: Vec<f64> = b
            .min
            .points
            .windows(2)
            .map(|w| w[1][0].log10() - w[0][0].log10())
            .collect();
        steps.sort_by(f64::total_cmp);
        let step = steps[steps.len() / 2];
        s.resolved_gap = Some(c2 * step * step);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    #[test]
    fn seeds_at_one_point_are_averaged_and_their_spread_kept() {
        let runs = Runs {
            n: vec![1e5, 1e5, 1e5, 2e5],
            loss: vec![2.0, 2.2, 2.4, 1.9],
            param_loss: ("test_loss".into(), vec![2.0, 2.2, 2.4, 1.9]),
            c: vec![1e12; 4],
            d: None,
            v: None,
            nv: None,
            width: None,
            group: None,
            epochs: None,
            synth_share: None,
            seed: Some(vec![0.0, 1.0, 2.0, 0.0]),
            hours: None,
            selected: None,
            columns: BTreeMap::new(),
            notes: Vec::new(),
        };
        let groups = vec![vec![0, 1, 2, 3]];
        let (avg, noise) = average(&runs, &groups);
        assert_eq!(avg.n, vec![1e5, 2e5]);
        assert!((avg.loss[0] - 2.2).abs() < 1e-12 && avg.loss[1] == 1.9);
        assert_eq!(noise.len(), 1);
        assert_eq!(noise[0].seeds, vec![0.0, 1.0, 2.0]);
        assert!((noise[0].sd - 0.2).abs() < 1e-12, "{noise:?}");
        let mut no_seed = runs.clone();
        no_seed.seed = None;
        assert_eq!(average(&no_seed, &groups).0, no_seed);
        // The same point on two data subsets (U = D/epochs differs) is not a seed repeat.
        let mut subsets = runs.clone();
        subsets.d = Some(vec![1e6; 4]);
        subsets.epochs = Some(vec![2.0, 2.0, 4.0, 2.0]);
        let (avg, noise) = average(&subsets, &groups);
        assert_eq!(avg.n, vec![1e5, 1e5, 2e5]);
        assert_eq!(noise[0].seeds, vec![0.0, 1.0]);
        assert_eq!(noise[0].param_sd, Some(noise[0].sd));
    }
}
