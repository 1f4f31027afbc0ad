//! Seeded K-means (k-means++ seeding, then Lloyd iterations): ES-MoE's global dictionary is
//! the centroids of the training set's text features.

use motionscale_core::rng::SplitMix64;

/// Squared Euclidean distance.
fn distance2(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// The index and squared distance of the centroid nearest to `row`.
fn nearest(row: &[f32], centroids: &[Vec<f32>]) -> (usize, f32) {
    centroids
        .iter()
        .map(|c| distance2(row, c))
        .enumerate()
        .fold(
            (0, f32::INFINITY),
            |best, (i, d)| {
                if d < best.1 {
                    (i, d)
                } else {
                    best
                }
            },
        )
}

/// `k` centroids of `rows` (each `dim` wide): k-means++ seeding drawn from `seed`, then
/// `iterations` Lloyd steps (an emptied cluster keeps its centroid). Fewer rows than `k`
/// give one centroid per row.
pub fn kmeans(rows: &[f32], dim: usize, k: usize, iterations: usize, seed: u64) -> Vec<Vec<f32>> {
    let points: Vec<&[f32]> = rows.chunks_exact(dim).collect();
    if points.is_empty() || k == 0 {
        return Vec::new();
    }
    let mut rng = SplitMix64::stream(seed, 0x6b6d);
    let mut centroids = vec![points[rng.index(points.len())].to_vec()];
    let mut d2: Vec<f32> = points.iter().map(|p| distance2(p, &centroids[0])).collect();
    while centroids.len() < k.min(points.len()) {
        let total: f64 = d2.iter().map(|&d| f64::from(d)).sum();
        if total <= 0.0 {
            break;
        }
        let mut u = rng.unit() * total;
        let pick = d2
            .iter()
            .position(|&d| {
                u -= f64::from(d);
                u < 0.0
            })
            .unwrap_or(points.len() - 1);
        centroids.push(points[pick].to_vec());
        for (d, p) in d2.iter_mut().zip(&points) {
            *d = d.min(distance2(p, &centroids[centroids.len() - 1]));
        }
    }
    for _ in 0..iterations {
        let mut sums = vec![vec![0f64; dim]; centroids.len()];
        let mut counts = vec![0usize; centroids.len()];
        for p in &points {
            let (c, _) = nearest(p, &centroids);
            counts[c] += 1;
            sums[c]
                .iter_mut()
                .zip(*p)
                .for_each(|(s, &v)| *s += f64::from(v));
        }
        for ((centroid, sum), n) in centroids.iter_mut().zip(sums).zip(counts) {
            if n > 0 {
                *centroid = sum.iter().map(|s| (s / n as f64) as f32).collect();
            }
        }
    }
    centroids
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_separated_clusters_give_their_means() {
        // Points around (0, 0) and (10, 10): the centroids are the two means.
        let rows = [
            0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 10.0, 10.0, 11.0, 10.0, 10.0, 11.0,
        ];
        let mut c = kmeans(&rows, 2, 2, 10, 3);
        c.sort_by(|a, b| a[0].total_cmp(&b[0]));
        let third = 1.0 / 3.0;
        assert!((c[0][0] - third).abs() < 1e-6 && (c[0][1] - third).abs() < 1e-6);
        assert!((c[1][0] - (10.0 + third)).abs() < 1e-5);
        assert_eq!(kmeans(&rows, 2, 2, 10, 3), kmeans(&rows, 2, 2, 10, 3));
        assert_eq!(kmeans(&rows[..4], 2, 5, 10, 3).len(), 2, "one per row");
    }
}
