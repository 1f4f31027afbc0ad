//! Gated recurrent units with PyTorch's parameter layout (`nn.GRU`: gate order r, z, n;
//! `weight_ih_l<k>[_reverse]`, `weight_hh_l<k>…`, `bias_ih_l<k>…`, `bias_hh_l<k>…`), so
//! weights load into `torch.nn.GRU` unchanged: the evaluator's bidirectional layers and
//! BI-CTVAE's stacked encoder and decoder.
//!
//! Each layer projects every step's input in one matmul and runs the recurrence through the
//! fused scan of [`crate::gru_kernel`]; [`crate::gru_kernel::scan_reference`] is the same recurrence as plain
//! candle ops (other devices, and the tests' yardstick).

use crate::conv_op::{conv1d_fused, ConvGeometry, ConvOutput};
use crate::gru_kernel::gru_scan;
use candle_core::{Result, Tensor};
use candle_nn::{Linear, VarBuilder};

/// One direction of one GRU layer.
pub struct GruLayer {
    w_ih: Linear,
    w_hh: Tensor,
    b_hh: Tensor,
}

impl GruLayer {
    /// The layer whose parameters end in `suffix` (`l0`, `l0_reverse`, `l3`…).
    pub fn new(input: usize, hidden: usize, suffix: &str, vb: &VarBuilder) -> Result<Self> {
        let bound = 1.0 / (hidden as f64).sqrt();
        let init = candle_nn::Init::Uniform {
            lo: -bound,
            up: bound,
        };
        let get = |shape: (usize, usize), name: &str| vb.get_with_hints(shape, name, init);
        let bias = |name: &str| vb.get_with_hints(3 * hidden, name, init);
        Ok(Self {
            w_ih: Linear::new(
                get((3 * hidden, input), &format!("weight_ih_{suffix}"))?,
                Some(bias(&format!("bias_ih_{suffix}"))?),
            ),
            w_hh: get((3 * hidden, hidden), &format!("weight_hh_{suffix}"))?,
            b_hh: bias(&format!("bias_hh_{suffix}"))?,
        })
    }

    /// The state after every step, `(batch, steps, hidden)`, from a zero state, as a packed
    /// `nn.GRU` gives it: sequence b runs over its first `lengths[b]` steps of `x`
    /// (`(batch, steps, in)`), last to first when `reverse`, and is zero past them.
    pub fn states(&self, x: &Tensor, lengths: &[usize], reverse: bool) -> Result<Tensor> {
        gru_scan(
            &per_step(&self.w_ih, x, lengths)?,
            &self.w_hh,
            &self.b_hh,
            lengths,
            reverse,
        )
    }
}

/// `linear` applied to each sequence's first `lengths[b]` steps of `x` `(batch, steps, in)`,
/// zero past them: a pointwise convolution through the fused conv op (one gemm over the real
/// steps only, with the bias as its initial value, and a hand-written backward that skips the
/// input's gradient when nothing needs it).
///
/// Why not `Linear::forward` on the 3-D tensor: candle broadcasts the weight over the batch,
/// and its backward then runs one small product per sequence and sums them.
pub fn per_step(linear: &Linear, x: &Tensor, lengths: &[usize]) -> Result<Tensor> {
    let w = linear.weight();
    let (out, inp) = w.dims2()?;
    let bias = linear
        .bias()
        .ok_or_else(|| candle_core::Error::Msg("per-step linear without a bias".into()))?;
    let output = ConvOutput {
        valid: Some(lengths.to_vec()),
        leaky_slope: None,
    };
    conv1d_fused(
        x,
        &w.reshape((out, inp, 1))?,
        bias,
        ConvGeometry::plain(1, 1, 1, 0),
        &output,
    )
}

/// Of `(batch, steps, width)` states, each sequence's at its last real step.
pub fn last_states(states: &Tensor, lengths: &[usize]) -> Result<Tensor> {
    let (batch, steps, width) = states.dims3()?;
    let last: Vec<u32> = lengths
        .iter()
        .enumerate()
        .map(|(b, &len)| (b * steps + len - 1) as u32)
        .collect();
    states
        .reshape((batch * steps, width))?
        .index_select(&Tensor::new(last, states.device())?, 0)
}

/// A bidirectional single-layer GRU (`nn.GRU(bidirectional=True)`), summarised by its two
/// final states (`h_n` of both directions side by side, `2 × hidden`).
pub struct BiGru {
    forward: GruLayer,
    backward: GruLayer,
}

impl BiGru {
    /// The layer under `vb` (`weight_ih_l0`, `weight_ih_l0_reverse`…).
    pub fn new(input: usize, hidden: usize, vb: &VarBuilder) -> Result<Self> {
        Ok(Self {
            forward: GruLayer::new(input, hidden, "l0", vb)?,
            backward: GruLayer::new(input, hidden, "l0_reverse", vb)?,
        })
    }

    /// `(batch, 2·hidden)`: the forward direction's state after each sequence's last step,
    /// then the backward direction's after its first.
    pub fn summary(&self, x: &Tensor, lengths: &[usize]) -> Result<Tensor> {
        let fwd = last_states(&self.forward.states(x, lengths, false)?, lengths)?;
        let bwd = self
            .backward
            .states(x, lengths, true)?
            .narrow(1, 0, 1)?
            .squeeze(1)?;
        Tensor::cat(&[fwd, bwd], 1)
    }
}

/// A stack of unidirectional GRU layers (`nn.GRU(num_layers=n)`), each reading the states of
/// the one below.
pub struct StackedGru {
    layers: Vec<GruLayer>,
}

impl StackedGru {
    /// `layers` layers of width `hidden` over `input`-wide steps.
    pub fn new(input: usize, hidden: usize, layers: usize, vb: &VarBuilder) -> Result<Self> {
        let layers = (0..layers)
            .map(|k| {
                GruLayer::new(
                    if k == 0 { input } else { hidden },
                    hidden,
                    &format!("l{k}"),
                    vb,
                )
            })
            .collect::<Result<_>>()?;
        Ok(Self { layers })
    }

    /// The top layer's state after every step, `(batch, steps, hidden)`, each sequence over
    /// its first `lengths[b]` steps.
    pub fn states(&self, x: &Tensor, lengths: &[usize]) -> Result<Tensor> {
        let mut x = x.clone();
        for layer in &self.layers {
            x = layer.states(&x, lengths, false)?;
        }
        Ok(x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gradcheck::{max_abs_diff, numeric_gradient};
    use crate::gru_kernel::{reverse_within, scan_reference};
    use candle_core::{Device, Var};
    use motionscale_core::rng::SplitMix64;

    fn random(shape: &[usize], scale: f64, rng: &mut SplitMix64) -> Var {
        let n: usize = shape.iter().product();
        let values: Vec<f32> = (0..n).map(|_| (rng.normal() * scale) as f32).collect();
        Var::from_tensor(&Tensor::from_vec(values, shape, &Device::Cpu).unwrap()).unwrap()
    }

    /// Gate inputs, recurrent weight and bias of a random direction, and a random
    /// projection of its states (so the loss reaches every state).
    struct Case {
        gi: Var,
        w: Var,
        b: Var,
        probe: Tensor,
        lengths: Vec<usize>,
    }

    impl Case {
        fn new(lengths: &[usize], steps: usize, hidden: usize, seed: u64) -> Self {
            let mut rng = SplitMix64::stream(seed, 0);
            let batch = lengths.len();
            Self {
                gi: random(&[batch, steps, 3 * hidden], 1.0, &mut rng),
                w: random(&[3 * hidden, hidden], 0.5, &mut rng),
                b: random(&[3 * hidden], 0.5, &mut rng),
                probe: random(&[batch, steps, hidden], 1.0, &mut rng)
                    .as_tensor()
                    .clone(),
                lengths: lengths.to_vec(),
            }
        }

        fn loss(&self, states: &Tensor) -> Tensor {
            (states * &self.probe).unwrap().sum_all().unwrap()
        }

        fn run(&self, fused: bool, reverse: bool) -> (Tensor, Tensor) {
            let scan = if fused { gru_scan } else { scan_reference };
            let (gi, w, b) = (self.gi.as_tensor(), self.w.as_tensor(), self.b.as_tensor());
            let states = scan(gi, w, b, &self.lengths, reverse).unwrap();
            let loss = self.loss(&states);
            (states, loss)
        }

        /// States and the three gradients, flattened.
        fn outputs(&self, fused: bool, reverse: bool) -> Vec<Vec<f32>> {
            let (states, loss) = self.run(fused, reverse);
            let grads = loss.backward().unwrap();
            let mut out = vec![flat(&states)];
            for v in [&self.gi, &self.w, &self.b] {
                out.push(flat(grads.get(v.as_tensor()).unwrap()));
            }
            out
        }
    }

    fn flat(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1().unwrap()
    }

    /// Mixed lengths (with 1 and the full length), equal lengths, a batch of one.
    const SHAPES: [(&[usize], usize, usize); 4] = [
        (&[5, 1, 7, 3, 7, 2], 7, 6),
        (&[4, 4, 4], 4, 5),
        (&[1], 1, 3),
        (&[9, 2, 6, 1, 8], 9, 16),
    ];

    #[test]
    fn fused_scan_matches_the_op_by_op_gru_with_its_gradients() {
        for (k, &(lengths, steps, hidden)) in SHAPES.iter().enumerate() {
            let case = Case::new(lengths, steps, hidden, k as u64);
            for reverse in [false, true] {
                let fused = case.outputs(true, reverse);
                let reference = case.outputs(false, reverse);
                for (what, (a, b)) in ["states", "d gi", "d w_hh", "d b_hh"]
                    .iter()
                    .zip(fused.iter().zip(&reference))
                {
                    let diff = max_abs_diff(a, b);
                    assert!(
                        diff < 2e-5,
                        "{lengths:?} reverse {reverse}: {what} differ by {diff}"
                    );
                }
            }
        }
    }

    #[test]
    fn fused_scan_is_zero_past_each_length_and_reversed_runs_backwards() {
        let case = Case::new(&[3, 1], 3, 2, 7);
        let (fwd, _) = case.run(true, false);
        let (bwd, _) = case.run(true, true);
        let fwd: Vec<Vec<Vec<f32>>> = fwd.to_vec3().unwrap();
        let bwd: Vec<Vec<Vec<f32>>> = bwd.to_vec3().unwrap();
        for t in 1..3 {
            assert_eq!(fwd[1][t], vec![0.0; 2]);
            assert_eq!(bwd[1][t], vec![0.0; 2]);
        }
        // A sequence of one step is the same step either way.
        assert_eq!(fwd[1][0], bwd[1][0]);
        // The reversed direction's last state (position 0) depends on every step.
        assert_ne!(bwd[0][0], fwd[0][0]);
    }

    #[test]
    fn fused_scan_gradients_match_central_differences() {
        let case = Case::new(&[4, 1, 3], 4, 3, 11);
        for reverse in [false, true] {
            let (_, loss) = case.run(true, reverse);
            let grads = loss.backward().unwrap();
            for var in [&case.gi, &case.w, &case.b] {
                let analytic = flat(grads.get(var.as_tensor()).unwrap());
                for k in (0..analytic.len()).step_by(5) {
                    let numeric = numeric_gradient(var, k, || {
                        f64::from(case.run(true, reverse).1.to_scalar::<f32>().unwrap())
                    });
                    let err = (numeric - f64::from(analytic[k])).abs();
                    assert!(
                        err < 2e-3 * (1.0 + numeric.abs()),
                        "reverse {reverse}, element {k}: analytic {} vs numeric {numeric}",
                        analytic[k]
                    );
                }
            }
        }
    }

    #[test]
    fn fused_scan_does_not_depend_on_the_thread_count() {
        let lengths: Vec<usize> = (0..40).map(|b| 1 + (b * 7) % 9).collect();
        let case = Case::new(&lengths, 9, 16, 3);
        let on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| [false, true].map(|reverse| case.outputs(true, reverse)))
        };
        assert_eq!(on(1), on(3));
    }

    #[test]
    fn reversal_stays_within_each_length() {
        let x = Tensor::arange(0f32, 8.0, &Device::Cpu)
            .unwrap()
            .reshape((2, 4, 1))
            .unwrap();
        let r = reverse_within(&x, &[4, 2]).unwrap();
        let v: Vec<f32> = r.flatten_all().unwrap().to_vec1().unwrap();
        assert_eq!(v, vec![3.0, 2.0, 1.0, 0.0, 5.0, 4.0, 6.0, 7.0]);
    }
}
