//! Per-dimension feature mean and block-averaged std over the training split
//! (HumanML3D's `Mean.npy`/`Std.npy` convention).

use crate::hml263::BLOCKS;

/// Running sums for the mean and (population) std of 263-d feature rows.
#[derive(Debug, Clone)]
pub struct FeatureStats {
    dim: usize,
    rows: u64,
    sum: Vec<f64>,
    sum_sq: Vec<f64>,
}

impl FeatureStats {
    /// Empty accumulator for `dim`-wide rows.
    pub fn new(dim: usize) -> Self {
        Self {
            dim,
            rows: 0,
            sum: vec![0.0; dim],
            sum_sq: vec![0.0; dim],
        }
    }

    /// Add a block of rows (row-major, `dim` values per row).
    pub fn add(&mut self, rows: &[f32]) {
        for row in rows.chunks_exact(self.dim) {
            for ((s, q), &v) in self.sum.iter_mut().zip(&mut self.sum_sq).zip(row) {
                let v = v as f64;
                *s += v;
                *q += v * v;
            }
        }
        self.rows += (rows.len() / self.dim) as u64;
    }

    /// Number of rows added.
    pub fn rows(&self) -> u64 {
        self.rows
    }

    /// Mean and block-averaged std. Blocks whose std is 0 (a degenerate corpus) get 1 so
    /// normalisation stays finite; the returned list names them.
    pub fn finish(&self) -> (Vec<f32>, Vec<f32>, Vec<(usize, usize)>) {
        let n = self.rows.max(1) as f64;
        let mean: Vec<f64> = self.sum.iter().map(|s| s / n).collect();
        let std: Vec<f64> = self
            .sum_sq
            .iter()
            .zip(&mean)
            .map(|(q, m)| (q / n - m * m).max(0.0).sqrt())
            .collect();
        let mut blocked = std.clone();
        let mut degenerate = Vec::new();
        for &(a, b) in BLOCKS.iter().filter(|(_, b)| *b <= self.dim) {
            let avg = std[a..b].iter().sum::<f64>() / (b - a) as f64;
            let value = if avg > 0.0 {
                avg
            } else {
                degenerate.push((a, b));
                1.0
            };
            blocked[a..b].iter_mut().for_each(|s| *s = value);
        }
        (
            mean.iter().map(|&m| m as f32).collect(),
            blocked.iter().map(|&s| s as f32).collect(),
            degenerate,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn block_average_of_population_std() {
        let mut stats = FeatureStats::new(263);
        let mut rows = vec![0f32; 2 * 263];
        // Dim 1 takes values 1, 3 (std 1); dim 2 takes 0, 0 (std 0): block [1,3) → 0.5.
        rows[1] = 1.0;
        rows[263 + 1] = 3.0;
        // Dim 0 takes values 2, 2: std 0 → degenerate block, std 1.
        rows[0] = 2.0;
        rows[263] = 2.0;
        stats.add(&rows);
        let (mean, std, degenerate) = stats.finish();
        assert_eq!(stats.rows(), 2);
        assert_eq!(mean[1], 2.0);
        assert_eq!(std[1], 0.5);
        assert_eq!(std[2], 0.5);
        assert_eq!(std[0], 1.0);
        assert!(degenerate.contains(&(0, 1)));
    }
}
