//! Generation metrics in the evaluator's embedding space, computed as the T2M / T2M-GPT
//! evaluation scripts do: FID, R-precision over pools of 32, matching score, diversity,
//! multimodality, plus weighted F1 and accuracy of the evaluator's classifiers, and the
//! mean ± 1.96·σ/√n interval those scripts report over repeats.

use motionscale_core::rng::SplitMix64;
use nalgebra::{DMatrix, DVector};
use serde::{Deserialize, Serialize};

fn distance(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
        .sum::<f64>()
        .sqrt()
}

fn mean_and_covariance(rows: &[Vec<f32>]) -> (DVector<f64>, DMatrix<f64>) {
    let (n, dim) = (rows.len(), rows[0].len());
    let x = DMatrix::from_fn(n, dim, |i, j| f64::from(rows[i][j]));
    let mean = DVector::from_fn(dim, |j, _| x.column(j).mean());
    let centred = DMatrix::from_fn(n, dim, |i, j| x[(i, j)] - mean[j]);
    let covariance = centred.transpose() * &centred / (n as f64 - 1.0).max(1.0);
    (mean, covariance)
}

/// Symmetric square root of a positive semi-definite matrix (negative eigenvalues from
/// rounding are clamped to zero).
fn sqrt_psd(m: DMatrix<f64>) -> DMatrix<f64> {
    let eigen = m.symmetric_eigen();
    let roots = eigen.eigenvalues.map(|l| l.max(0.0).sqrt());
    &eigen.eigenvectors * DMatrix::from_diagonal(&roots) * eigen.eigenvectors.transpose()
}

/// Fréchet distance between Gaussians fitted to two sets of embeddings:
/// ‖μa − μb‖² + tr(Σa + Σb − 2(Σa Σb)^½). The trace of (Σa Σb)^½ is taken as the trace of
/// the symmetric (Σa^½ Σb Σa^½)^½, which has the same eigenvalues and stays real.
pub fn fid(a: &[Vec<f32>], b: &[Vec<f32>]) -> f64 {
    let (mean_a, cov_a) = mean_and_covariance(a);
    let (mean_b, cov_b) = mean_and_covariance(b);
    let root_a = sqrt_psd(cov_a.clone());
    let middle = &root_a * &cov_b * &root_a;
    let cross = middle
        .symmetric_eigen()
        .eigenvalues
        .iter()
        .map(|l| l.max(0.0).sqrt())
        .sum::<f64>();
    // Rounding leaves about −1e-7 for identical sets; a distance is never negative.
    ((mean_a - mean_b).norm_squared() + cov_a.trace() + cov_b.trace() - 2.0 * cross).max(0.0)
}

/// Top-1…top-`K` R-precision and matching score over consecutive pools of `pool` pairs
/// (text i belongs with motion i; an incomplete last pool is dropped, as the T2M script
/// does): the share of texts whose own motion is among the k nearest motions of the pool.
pub fn r_precision<const K: usize>(
    text: &[Vec<f32>],
    motion: &[Vec<f32>],
    pool: usize,
) -> [f64; K] {
    let mut hits = [0usize; K];
    let pools = text.len() / pool;
    for p in 0..pools {
        let range = p * pool..(p + 1) * pool;
        for i in range.clone() {
            let own = distance(&text[i], &motion[i]);
            let closer = range
                .clone()
                .filter(|&j| j != i && distance(&text[i], &motion[j]) < own)
                .count();
            for (k, hit) in hits.iter_mut().enumerate() {
                *hit += usize::from(closer <= k);
            }
        }
    }
    let total = (pools * pool).max(1) as f64;
    hits.map(|h| h as f64 / total)
}

/// Mean distance between each text and its own motion.
pub fn matching_score(text: &[Vec<f32>], motion: &[Vec<f32>]) -> f64 {
    let sum: f64 = text.iter().zip(motion).map(|(t, m)| distance(t, m)).sum();
    sum / text.len().max(1) as f64
}

/// `k` distinct indices of 0..n (partial Fisher–Yates).
fn choose(n: usize, k: usize, rng: &mut SplitMix64) -> Vec<usize> {
    let mut all: Vec<usize> = (0..n).collect();
    for i in 0..k.min(n) {
        let j = i + rng.index(n - i);
        all.swap(i, j);
    }
    all.truncate(k.min(n));
    all
}

/// Diversity: mean distance between two independent draws of `pairs` distinct embeddings
/// (`None` when there are fewer than `pairs`).
pub fn diversity(embeddings: &[Vec<f32>], pairs: usize, rng: &mut SplitMix64) -> Option<f64> {
    if embeddings.len() < pairs || pairs == 0 {
        return None;
    }
    let first = choose(embeddings.len(), pairs, rng);
    let second = choose(embeddings.len(), pairs, rng);
    let sum: f64 = first
        .iter()
        .zip(&second)
        .map(|(&i, &j)| distance(&embeddings[i], &embeddings[j]))
        .sum();
    Some(sum / pairs as f64)
}

/// Multimodality: for each group (the samples generated from one text), the mean distance
/// between two independent draws of `pairs` of its samples, averaged over groups. Groups
/// with fewer than `pairs` samples are skipped; `None` when none is left.
pub fn multimodality(groups: &[Vec<Vec<f32>>], pairs: usize, rng: &mut SplitMix64) -> Option<f64> {
    let scores: Vec<f64> = groups
        .iter()
        .filter_map(|g| diversity(g, pairs, rng))
        .collect();
    (!scores.is_empty()).then(|| scores.iter().sum::<f64>() / scores.len() as f64)
}

/// Support-weighted mean of the per-class F1 scores over the classes present in `truth`
/// (scikit-learn's `f1_score(average="weighted")`).
pub fn weighted_f1(predicted: &[usize], truth: &[usize]) -> f64 {
    let classes = truth.iter().copied().max().map_or(0, |m| m + 1);
    let mut score = 0.0;
    for c in 0..classes {
        let support = truth.iter().filter(|&&t| t == c).count();
        if support == 0 {
            continue;
        }
        let pairs = || predicted.iter().zip(truth);
        let tp = pairs().filter(|(&p, &t)| p == c && t == c).count() as f64;
        let fp = pairs().filter(|(&p, &t)| p == c && t != c).count() as f64;
        let fn_ = pairs().filter(|(&p, &t)| p != c && t == c).count() as f64;
        let f1 = if tp == 0.0 {
            0.0
        } else {
            2.0 * tp / (2.0 * tp + fp + fn_)
        };
        score += f1 * support as f64;
    }
    score / truth.len().max(1) as f64
}

/// Share of `predicted` equal to `truth`.
pub fn accuracy(predicted: &[usize], truth: &[usize]) -> f64 {
    let right = predicted.iter().zip(truth).filter(|(p, t)| p == t).count();
    right as f64 / truth.len().max(1) as f64
}

/// A metric over repeats: mean and the 95% interval mean ± 1.96·σ/√n (σ the population
/// standard deviation, as the T2M evaluation scripts report it), and every repeat's value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Interval {
    /// Mean over repeats.
    pub mean: f64,
    /// Lower end of the 95% interval.
    pub low: f64,
    /// Upper end of the 95% interval.
    pub high: f64,
    /// Each repeat's value.
    pub values: Vec<f64>,
}

impl Interval {
    /// The interval of `values` (at least one).
    pub fn of(values: Vec<f64>) -> Self {
        let n = values.len() as f64;
        let mean = values.iter().sum::<f64>() / n;
        let sd = (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
        let half = 1.96 * sd / n.sqrt();
        Self {
            mean,
            low: mean - half,
            high: mean + half,
            values,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gaussian(n: usize, dim: usize, mean: f64, sd: f64, seed: u64) -> Vec<Vec<f32>> {
        let mut rng = SplitMix64::stream(seed, 0);
        (0..n)
            .map(|_| {
                (0..dim)
                    .map(|_| (mean + sd * rng.normal()) as f32)
                    .collect()
            })
            .collect()
    }

    #[test]
    fn fid_is_zero_for_one_set_and_matches_the_closed_form() {
        let a = gaussian(500, 3, 0.0, 1.0, 1);
        assert!(fid(&a, &a).abs() < 1e-9);
        // Hand case, 1-d: (μa − μb)² + σa² + σb² − 2σaσb = (1 − 3)² + (2 − 1)² = 5 for
        // samples whose sample moments are exactly μ = 1, σ = 2 and μ = 3, σ = 1.
        let exact = |mu: f32, sd: f32| vec![vec![mu - sd], vec![mu + sd]];
        let (a, b) = (exact(1.0, 2.0 / 2f32.sqrt()), exact(3.0, 1.0 / 2f32.sqrt()));
        assert!((fid(&a, &b) - 5.0).abs() < 1e-5, "{}", fid(&a, &b));
        // Diagonal 2-d case: the sum of the per-axis 1-d distances.
        let two = |m: [f32; 2], s: [f32; 2]| {
            vec![
                vec![m[0] - s[0], m[1] - s[1]],
                vec![m[0] + s[0], m[1] + s[1]],
                vec![m[0] - s[0], m[1] + s[1]],
                vec![m[0] + s[0], m[1] - s[1]],
            ]
        };
        // Sample variance with n − 1 = 3 over 4 points at ±s: 4s²/3.
        let k = (3f32 / 4.0).sqrt();
        let f = fid(
            &two([0.0, 0.0], [k, 2.0 * k]),
            &two([1.0, 0.0], [3.0 * k, 2.0 * k]),
        );
        assert!((f - (1.0 + 4.0)).abs() < 1e-6, "{f}");
    }

    #[test]
    fn fid_grows_with_a_shift() {
        let a = gaussian(400, 4, 0.0, 1.0, 2);
        let near = gaussian(400, 4, 0.2, 1.0, 3);
        let far = gaussian(400, 4, 1.0, 1.0, 4);
        assert!(fid(&a, &near) < fid(&a, &far));
    }

    #[test]
    fn r_precision_is_one_for_matched_pairs_and_counts_ranks() {
        let text: Vec<Vec<f32>> = (0..64).map(|i| vec![i as f32, 0.0]).collect();
        assert_eq!(r_precision::<3>(&text, &text, 32), [1.0, 1.0, 1.0]);
        // Every motion moved 0.6 towards the next text: its own text is second-closest
        // for all but the last of each pool (whose neighbour is outside the pool).
        let motion: Vec<Vec<f32>> = (0..64).map(|i| vec![i as f32 - 0.6, 0.0]).collect();
        let [top1, top2, top3] = r_precision::<3>(&text, &motion, 32);
        assert!((top1 - 2.0 / 64.0).abs() < 1e-12, "{top1}");
        assert_eq!((top2, top3), (1.0, 1.0));
        assert!((matching_score(&text, &motion) - 0.6).abs() < 1e-6);
    }

    #[test]
    fn diversity_and_multimodality_measure_spread() {
        let mut rng = SplitMix64::stream(0, 0);
        let same = vec![vec![1.0f32, 1.0]; 400];
        assert_eq!(diversity(&same, 300, &mut rng), Some(0.0));
        assert_eq!(diversity(&same[..10], 300, &mut rng), None);
        let spread = gaussian(400, 2, 0.0, 1.0, 5);
        // E‖x − y‖ for independent 2-d standard normals is √π ≈ 1.77.
        let d = diversity(&spread, 300, &mut rng).unwrap();
        assert!((d - std::f64::consts::PI.sqrt()).abs() < 0.2, "{d}");
        let groups = vec![vec![vec![0.0f32], vec![2.0]]; 3];
        assert!(multimodality(&groups, 2, &mut rng).unwrap() <= 2.0);
        assert_eq!(multimodality(&groups, 10, &mut rng), None);
    }

    #[test]
    fn weighted_f1_matches_a_hand_case() {
        // Class 0: tp 2, fp 1, fn 0 → F1 0.8 (support 2); class 1: tp 1, fp 0, fn 1 → 2/3
        // (support 2). Weighted: (0.8·2 + 2/3·2)/4.
        let f1 = weighted_f1(&[0, 0, 1, 0], &[0, 0, 1, 1]);
        assert!((f1 - (0.8 * 2.0 + 2.0 / 3.0 * 2.0) / 4.0).abs() < 1e-12);
        assert_eq!(accuracy(&[0, 0, 1, 0], &[0, 0, 1, 1]), 0.75);
    }

    #[test]
    fn interval_is_mean_plus_minus_1_96_sigma_over_root_n() {
        let i = Interval::of(vec![1.0, 3.0]);
        assert_eq!(i.mean, 2.0);
        assert!((i.high - (2.0 + 1.96 / 2f64.sqrt())).abs() < 1e-12);
        assert!((i.low - (2.0 - 1.96 / 2f64.sqrt())).abs() < 1e-12);
    }
}
