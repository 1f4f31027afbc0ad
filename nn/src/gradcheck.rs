//! The references of the gradient tests of every model: finite differences, and the
//! largest element-wise difference their tolerances are checked on.

use candle_core::{Device, Tensor, Var};

/// The central difference (L(x + ε) − L(x − ε)) / 2ε of `loss` in element `k` of `var`
/// (ε = 0.01), which is left as it was.
pub fn numeric_gradient(var: &Var, k: usize, loss: impl Fn() -> f64) -> f64 {
    let eps = 1e-2f32;
    let start: Vec<f32> = var.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
    let set = |values: Vec<f32>| {
        var.set(&Tensor::from_vec(values, var.dims(), &Device::Cpu).unwrap())
            .unwrap();
    };
    let at = |delta: f32| {
        let mut v = start.clone();
        v[k] += delta;
        set(v);
        loss()
    };
    let numeric = (at(eps) - at(-eps)) / (2.0 * f64::from(eps));
    set(start.clone());
    numeric
}

/// The largest `|a[i] − b[i]|` (the slices must have the same length).
pub fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}
