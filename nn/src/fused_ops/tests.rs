//! Each fused op against the same function composed of candle's differentiable ops (the
//! graph executor's former definition): value and gradient of every input.

use super::*;
use candle_core::{Device, Var, D};

fn seeded(shape: &[usize], seed: u64) -> Var {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n as u64)
        .map(|i| ((i * 2654435761 + seed * 7919) % 2001) as f32 / 1000.0 - 1.0)
        .collect();
    Var::from_vec(v, shape, &Device::Cpu).unwrap()
}

/// Largest |a − b| over the largest |a|.
fn rel(a: &Tensor, b: &Tensor) -> f32 {
    let a = a.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let b = b.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    assert_eq!(a.len(), b.len());
    let scale = a.iter().fold(f32::MIN_POSITIVE, |m, v| m.max(v.abs()));
    a.iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
        / scale
}

/// `fused` and `composed` of the same inputs agree in value and in the gradient of a
/// seeded weighting of the output with respect to every input in `vars`.
fn agree(vars: &[&Var], fused: impl Fn() -> Tensor, composed: impl Fn() -> Tensor, what: &str) {
    let (f, c) = (fused(), composed());
    let err = rel(&c, &f);
    assert!(err < 1e-5, "{what}: values differ by {err}");
    let weights = seeded(f.dims(), 99).as_tensor().clone();
    let (gf, gc) = (
        (f * &weights)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap(),
        (c * &weights)
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap(),
    );
    for (i, v) in vars.iter().enumerate() {
        let (a, b) = (
            gc.get(v.as_tensor()).unwrap(),
            gf.get(v.as_tensor()).unwrap(),
        );
        let err = rel(a, b);
        assert!(err < 1e-5, "{what}: gradient of input {i} differs by {err}");
    }
}

#[test]
fn rms_norm_matches_the_composed_norm() {
    let (x, w) = (seeded(&[9, 24], 1), seeded(&[24], 2));
    agree(
        &[&x, &w],
        || rms_norm(&x, &w, 1e-5).unwrap(),
        || candle_nn::ops::rms_norm_slow(&x, &w, 1e-5).unwrap(),
        "rms_norm",
    );
}

#[test]
fn swiglu_matches_silu_times_the_gate() {
    let ab = seeded(&[7, 2 * 10], 3);
    agree(
        &[&ab],
        || swiglu_rows(&ab).unwrap(),
        || {
            (candle_nn::ops::silu(&ab.narrow(1, 0, 10).unwrap()).unwrap()
                * ab.narrow(1, 10, 10).unwrap())
            .unwrap()
        },
        "swiglu",
    );
}

#[test]
fn qkv_heads_rotates_queries_and_keys_and_moves_values_into_the_grid() {
    let (batch, slots, heads, hd) = (2, 5, 3, 4);
    let rows = batch * slots;
    let qkv = seeded(&[rows, 3 * heads * hd], 4);
    let angles = seeded(&[rows, 1, hd / 2], 5).as_tensor().clone();
    let (cos, sin) = (angles.cos().unwrap(), angles.sin().unwrap());
    let composed = || {
        let parts: Vec<Tensor> = (0..3)
            .map(|p| {
                let x = qkv
                    .narrow(1, p * heads * hd, heads * hd)
                    .unwrap()
                    .reshape((rows, heads, hd))
                    .unwrap();
                let x = match p {
                    2 => x,
                    _ => {
                        let (x1, x2) = (
                            x.narrow(2, 0, hd / 2).unwrap(),
                            x.narrow(2, hd / 2, hd / 2).unwrap(),
                        );
                        let r1 = (x1.broadcast_mul(&cos).unwrap()
                            - x2.broadcast_mul(&sin).unwrap())
                        .unwrap();
                        let r2 = (x2.broadcast_mul(&cos).unwrap()
                            + x1.broadcast_mul(&sin).unwrap())
                        .unwrap();
                        Tensor::cat(&[&r1, &r2], 2).unwrap()
                    }
                };
                x.reshape((batch, slots, heads, hd))
                    .unwrap()
                    .transpose(1, 2)
                    .unwrap()
            })
            .collect();
        Tensor::stack(&parts, 0).unwrap()
    };
    let (c2, s2) = (
        cos.squeeze(1).unwrap().detach(),
        sin.squeeze(1).unwrap().detach(),
    );
    agree(
        &[&qkv],
        || qkv_heads(&qkv, &c2, &s2, batch, heads).unwrap(),
        composed,
        "qkv_heads",
    );
}

#[test]
fn masked_softmax_matches_the_additive_mask_and_softmax() {
    let (batch, heads, queries, keys) = (2, 2, 4, 6);
    let mask = PrefixMask {
        prefix_slots: 2,
        first_query: 2,
        scale: 0.5,
    };
    let lens = [2u32, 1];
    let scores = seeded(&[batch, heads, queries, keys], 6);
    let additive: Vec<f32> = (0..batch)
        .flat_map(|b| {
            (0..queries).flat_map(move |q| {
                (0..keys).map(move |j| {
                    if mask.allowed(lens[b] as usize, 2 + q, j) {
                        0.0
                    } else {
                        MASKED
                    }
                })
            })
        })
        .collect();
    let additive = Tensor::from_vec(additive, (batch, 1, queries, keys), &Device::Cpu).unwrap();
    let lens_t = Tensor::new(&lens, &Device::Cpu).unwrap();
    agree(
        &[&scores],
        || masked_softmax(&scores, &lens_t, mask).unwrap(),
        || {
            let s = (scores.as_tensor() * 0.5)
                .unwrap()
                .broadcast_add(&additive)
                .unwrap();
            candle_nn::ops::softmax(&s, D::Minus1).unwrap()
        },
        "masked_softmax",
    );
}

#[test]
fn weighted_cross_entropy_matches_log_softmax_at_the_targets() {
    let logits = seeded(&[6, 11], 7);
    let targets = Tensor::new(&[0u32, 3, 10, 5, 5, 1], &Device::Cpu).unwrap();
    let weight = Tensor::new(&[1f32, 0.0, 0.5, 2.0, 1.0, 0.0], &Device::Cpu).unwrap();
    agree(
        &[&logits],
        || weighted_cross_entropy(&logits, &targets, &weight).unwrap(),
        || {
            let lp = candle_nn::ops::log_softmax(&logits, D::Minus1).unwrap();
            let picked = lp
                .gather(&targets.unsqueeze(1).unwrap(), 1)
                .unwrap()
                .squeeze(1)
                .unwrap();
            (picked.neg().unwrap() * &weight).unwrap()
        },
        "cross_entropy",
    );
}

#[test]
fn sum_of_squares_matches_the_composed_sum() {
    let x = seeded(&[13, 17], 8);
    let fused = sum_of_squares(&x).unwrap().to_vec1::<f32>().unwrap()[0];
    let composed = x
        .sqr()
        .unwrap()
        .sum_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap();
    assert!(
        (fused - composed).abs() <= 1e-6 * composed,
        "{fused} vs {composed}"
    );
}
