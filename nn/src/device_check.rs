//! The device's self check: every fused op of [`crate::fused_ops`], forward and backward,
//! and the AdamW step of [`crate::optim`] on a device against the same on the CPU
//! (`motionscale model executors` reports it beside the executors).

use crate::fused_ops::{
    masked_softmax, qkv_heads, rms_norm, sum_of_squares, swiglu_rows, weighted_cross_entropy,
    PrefixMask,
};
use crate::optim::device_agreement;
use candle_core::{Result, Tensor};

/// Each fused op, forward and backward, on `device` against the same op on the CPU from the
/// same seeded inputs: `(output, largest |Δ| over the largest |value|)`, the AdamW update last.
pub fn self_check(device: &candle_core::Device) -> Result<Vec<(String, f32)>> {
    use candle_core::{DType, Device, Var};
    let cpu = Device::Cpu;
    let (batch, slots, heads, hd, vocab) = (3usize, 7usize, 2usize, 8usize, 37usize);
    let (rows, d) = (batch * slots, heads * hd);
    let mask = PrefixMask {
        prefix_slots: 3,
        first_query: 0,
        scale: 0.35,
    };
    let lens = Tensor::new(&[3u32, 1, 2], &cpu)?;
    let targets: Vec<u32> = (0..rows as u32).map(|r| (r * 7) % vocab as u32).collect();
    let weight: Vec<f32> = (0..rows).map(|r| (r % 4) as f32 / 3.0).collect();
    let seeded = |shape: (usize, usize), seed: u64| -> Result<Tensor> {
        let n = shape.0 * shape.1;
        let v: Vec<f32> = (0..n as u64)
            .map(|i| (((i * 2654435761 + seed * 97) % 1000) as f32 / 500.0) - 1.0)
            .collect();
        Tensor::from_vec(v, shape, &cpu)
    };
    let inputs = [
        seeded((rows, 3 * d), 1)?,
        seeded((rows, hd / 2), 2)?,
        seeded((rows, hd / 2), 3)?,
        seeded((d, 1), 4)?,
        seeded((rows, vocab), 5)?,
    ];
    // Every op chained into one scalar, so one backward reaches every op's backward.
    let run = |on: &Device| -> Result<Vec<(String, Tensor)>> {
        let vars: Vec<Var> = inputs
            .iter()
            .map(|t| Var::from_tensor(&t.to_device(on)?))
            .collect::<Result<_>>()?;
        let [qkv, cos, sin, w, logits] = [0, 1, 2, 3, 4].map(|i| vars[i].as_tensor());
        // The rotary tables are constants of the op: no gradient, not reported.
        let (cos, sin) = (cos.detach(), sin.detach());
        let grid = qkv_heads(qkv, &cos, &sin, batch, heads)?;
        let (q, k) = (grid.get(0)?, grid.get(1)?);
        let probs = masked_softmax(&q.matmul(&k.t()?)?, &lens.to_device(on)?, mask)?;
        let attended = probs
            .matmul(&grid.get(2)?)?
            .transpose(1, 2)?
            .reshape((rows, d))?;
        let normed = rms_norm(&attended, &w.flatten_all()?, 1e-5)?;
        let act = swiglu_rows(&normed)?;
        // A per-row factor on the logits: a per-row shift would carry no gradient (the
        // cross-entropy's gradient sums to 0 over each row) and leave only rounding noise.
        let factor = (logits.narrow(1, 0, d / 2)?.mul(&act)?.sum_keepdim(1)? + 1.0)?;
        let tail = logits.broadcast_mul(&factor)?;
        let ce = weighted_cross_entropy(
            &tail,
            &Tensor::new(targets.as_slice(), on)?,
            &Tensor::new(weight.as_slice(), on)?,
        )?;
        let grads = ce.sum_all()?.backward()?;
        let mut out = vec![("forward".to_string(), ce)];
        for (name, i) in [("qkv", 0), ("w", 3), ("logits", 4)] {
            let missing = || candle_core::Error::Msg(format!("self check: no gradient of {name}"));
            let g = grads.get(vars[i].as_tensor()).ok_or_else(missing)?;
            out.push((format!("gradient of {name}"), g.clone()));
        }
        Ok(out)
    };
    let (here, there) = (run(&cpu)?, run(device)?);
    let mut report = here
        .into_iter()
        .zip(there)
        .map(|((name, a), (_, b))| {
            let (a, b) = (
                a.flatten_all()?.to_dtype(DType::F32)?,
                b.to_device(&cpu)?.flatten_all()?,
            );
            let scale = a.abs()?.max(0)?.to_scalar::<f32>()?.max(f32::MIN_POSITIVE);
            let diff = (a - b)?.abs()?.max(0)?.to_scalar::<f32>()?;
            Ok((name, diff / scale))
        })
        .collect::<Result<Vec<_>>>()?;
    let squares = |t: &Tensor| sum_of_squares(t)?.to_device(&cpu)?.to_vec1::<f32>();
    let (a, b) = (
        squares(&inputs[4])?[0],
        squares(&inputs[4].to_device(device)?)?[0],
    );
    report.push(("sum of squares".to_string(), (a - b).abs() / a));
    let adamw =
        device_agreement(device).map_err(|e| candle_core::Error::Msg(format!("adamw: {e}")))?;
    report.push(("adamw, 3 steps".to_string(), adamw));
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn the_self_check_chains_every_op_and_agrees_with_itself_on_the_cpu() {
        let report = self_check(&Device::Cpu).unwrap();
        let names: Vec<&str> = report.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names[0], "forward");
        assert_eq!(report.len(), 6);
        assert!(report.iter().all(|(_, e)| *e == 0.0), "{report:?}");
    }
}
