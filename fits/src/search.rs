//! One-dimensional searches shared by the laws' allocations: the lowest point of a function on
//! an interval (a grid, then golden section between the best grid point's neighbours), and the
//! crossing of a predicate that holds left of it (bisection).

/// The argument in `[lo, hi]` where `f` is lowest: `steps + 1` evenly spaced points, then
/// `iters` golden-section steps between the best one's neighbours; `None` when `f` is nowhere
/// finite. Ties go to the leftmost grid point; each grid point is evaluated once.
pub fn grid_golden_min(
    f: impl Fn(f64) -> f64,
    (lo, hi): (f64, f64),
    steps: usize,
    iters: usize,
) -> Option<f64> {
    let at = |i: usize| lo + (hi - lo) * i as f64 / steps as f64;
    let values: Vec<f64> = (0..=steps).map(|i| f(at(i))).collect();
    let best = (0..=steps)
        .filter(|&i| values[i].is_finite())
        .min_by(|&i, &j| values[i].total_cmp(&values[j]))?;
    let (mut a, mut b) = (at(best.saturating_sub(1)), at((best + 1).min(steps)));
    let g = (5f64.sqrt() - 1.0) / 2.0;
    for _ in 0..iters {
        let (x1, x2) = (b - g * (b - a), a + g * (b - a));
        if f(x1) < f(x2) {
            b = x2;
        } else {
            a = x1;
        }
    }
    Some(0.5 * (a + b))
}

/// The point of `[lo, hi]` where `left` stops holding, to `iters` halvings (`left(lo)` is
/// assumed true and `left(hi)` false).
pub fn bisect(left: impl Fn(f64) -> bool, (mut lo, mut hi): (f64, f64), iters: usize) -> f64 {
    for _ in 0..iters {
        let mid = 0.5 * (lo + hi);
        match left(mid) {
            true => lo = mid,
            false => hi = mid,
        }
    }
    0.5 * (lo + hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_a_minimum_and_a_crossing() {
        let x = grid_golden_min(|x| (x - 0.3).powi(2), (-1.0, 2.0), 30, 60).unwrap();
        assert!((x - 0.3).abs() < 1e-8, "{x}");
        assert_eq!(grid_golden_min(|_| f64::NAN, (0.0, 1.0), 10, 10), None);
        let c = bisect(|x| x * x < 2.0, (0.0, 2.0), 60);
        assert!((c - 2f64.sqrt()).abs() < 1e-12, "{c}");
    }
}
