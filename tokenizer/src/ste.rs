//! The straight-through estimator shared by both quantizers.

use candle_core::{Result, Tensor};

/// `x + (target - x).detach()`: the value of `target`, the gradient of `x` (identity).
pub fn straight_through(x: &Tensor, target: &Tensor) -> Result<Tensor> {
    x + (target - x)?.detach()
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    #[test]
    fn rounding_passes_the_identity_gradient() {
        let x = Var::new(&[0.2f32, 1.7, -2.4, 3.5], &Device::Cpu).unwrap();
        let y = straight_through(x.as_tensor(), &x.as_tensor().round().unwrap()).unwrap();
        assert_eq!(y.to_vec1::<f32>().unwrap(), vec![0.0, 2.0, -2.0, 4.0]);
        let grads = (y.sqr().unwrap().sum_all().unwrap()).backward().unwrap();
        // d(y²)/dx = 2y · dy/dx, and dy/dx must be exactly 1.
        let g = grads.get(&x).unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(g, vec![0.0, 4.0, -4.0, 8.0]);
    }
}
