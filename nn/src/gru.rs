//! Gated recurrent units with PyTorch's parameter layout (`nn.GRU`: gate order r, z, n;
//! `weight_ih_l<k>[_reverse]`, `weight_hh_l<k>…`, `bias_ih_l<k>…`, `bias_hh_l<k>…`), so
//! weights load into `torch.nn.GRU` unchanged: the evaluator's bidirectional layers and
//! BI-CTVAE's stacked encoder and decoder.
//!
//! On the CPU each layer is one fused op ([`crate::gru_kernel`]: the input projection, the
//! recurrence of every direction, and its backward pass); [`gru_reference`] is the same layer
//! as plain candle ops (other devices, and the tests' yardstick).

use crate::conv_op::{conv1d_fused, ConvGeometry, ConvOutput};
use crate::gru_kernel::{fused_gru, scan_reference};
pub use crate::gru_kernel::{Direction, GruOutput};
use candle_core::{DType, Result, Tensor, D};
use candle_nn::{Linear, VarBuilder};

/// One direction of one GRU layer.
pub struct GruLayer {
    w_ih: Tensor,
    b_ih: Tensor,
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
            w_ih: get((3 * hidden, input), &format!("weight_ih_{suffix}"))?,
            b_ih: bias(&format!("bias_ih_{suffix}"))?,
            w_hh: get((3 * hidden, hidden), &format!("weight_hh_{suffix}"))?,
            b_hh: bias(&format!("bias_hh_{suffix}"))?,
        })
    }

    /// This direction, run last step first when `reverse`.
    pub fn direction(&self, reverse: bool) -> Direction<'_> {
        Direction {
            w_ih: &self.w_ih,
            b_ih: &self.b_ih,
            w_hh: &self.w_hh,
            b_hh: &self.b_hh,
            reverse,
        }
    }
}

/// A GRU layer's `output` over `x` `(batch, steps, in)` from a zero state, as `nn.GRU` gives
/// it over a packed batch: its `directions` side by side, sequence b over its first
/// `lengths[b]` steps (backwards in a reversed direction), states zero past them. f32 CPU
/// tensors take the fused op, anything else [`gru_reference`].
pub fn gru(
    x: &Tensor,
    directions: &[Direction],
    lengths: &[usize],
    output: GruOutput,
) -> Result<Tensor> {
    if x.device().is_cpu() && x.dtype() == DType::F32 {
        fused_gru(x, directions, lengths, output)
    } else {
        gru_reference(x, directions, lengths, output)
    }
}

/// [`gru`] as candle ops: each direction's projection as one matmul over every step, its
/// recurrence one step at a time ([`scan_reference`]).
pub fn gru_reference(
    x: &Tensor,
    directions: &[Direction],
    lengths: &[usize],
    output: GruOutput,
) -> Result<Tensor> {
    let (batch, steps, input) = x.dims3()?;
    let rows = x.reshape((batch * steps, input))?;
    let parts = directions
        .iter()
        .map(|d| {
            let gi =
                rows.matmul(&d.w_ih.t()?)?
                    .broadcast_add(d.b_ih)?
                    .reshape((batch, steps, ()))?;
            let states = scan_reference(&gi, d.w_hh, d.b_hh, lengths, d.reverse)?;
            match (output, d.reverse) {
                (GruOutput::States, _) => Ok(states),
                (GruOutput::Final, false) => last_states(&states, lengths),
                (GruOutput::Final, true) => states.narrow(1, 0, 1)?.squeeze(1),
            }
        })
        .collect::<Result<Vec<_>>>()?;
    Tensor::cat(&parts, D::Minus1)
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
fn last_states(states: &Tensor, lengths: &[usize]) -> Result<Tensor> {
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
        let directions = [self.forward.direction(false), self.backward.direction(true)];
        gru(x, &directions, lengths, GruOutput::Final)
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

    /// The top layer's `output` ([`GruOutput::States`]: its state after every step,
    /// `(batch, steps, hidden)`; [`GruOutput::Final`]: after each sequence's last step,
    /// `(batch, hidden)`), each sequence over its first `lengths[b]` steps.
    pub fn run(&self, x: &Tensor, lengths: &[usize], output: GruOutput) -> Result<Tensor> {
        let mut x = x.clone();
        for (k, layer) in self.layers.iter().enumerate() {
            let top = k + 1 == self.layers.len();
            let layer_output = if top { output } else { GruOutput::States };
            x = gru(&x, &[layer.direction(false)], lengths, layer_output)?;
        }
        Ok(x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gradcheck::{max_abs_diff, numeric_gradient};
    use crate::gru_kernel::reverse_within;
    use candle_core::{Device, Var};
    use motionscale_core::rng::SplitMix64;

    fn random(shape: &[usize], scale: f64, rng: &mut SplitMix64) -> Var {
        let n: usize = shape.iter().product();
        let values: Vec<f32> = (0..n).map(|_| (rng.normal() * scale) as f32).collect();
        Var::from_tensor(&Tensor::from_vec(values, shape, &Device::Cpu).unwrap()).unwrap()
    }

    /// A random input, the parameters of two directions (the second reversed), and a random
    /// projection of each output (so the loss reaches every output value).
    struct Case {
        x: Var,
        /// Per direction: w_ih, b_ih, w_hh, b_hh.
        params: [[Var; 4]; 2],
        lengths: Vec<usize>,
        seed: u64,
    }

    impl Case {
        fn new(
            lengths: &[usize],
            steps: usize,
            (input, hidden): (usize, usize),
            seed: u64,
        ) -> Self {
            let mut rng = SplitMix64::stream(seed, 0);
            let mut direction = || {
                [
                    random(&[3 * hidden, input], 0.5, &mut rng),
                    random(&[3 * hidden], 0.5, &mut rng),
                    random(&[3 * hidden, hidden], 0.5, &mut rng),
                    random(&[3 * hidden], 0.5, &mut rng),
                ]
            };
            let params = [direction(), direction()];
            Self {
                x: random(&[lengths.len(), steps, input], 1.0, &mut rng),
                params,
                lengths: lengths.to_vec(),
                seed,
            }
        }

        fn directions(&self, count: usize) -> Vec<Direction<'_>> {
            self.params[..count]
                .iter()
                .enumerate()
                .map(|(k, [w_ih, b_ih, w_hh, b_hh])| Direction {
                    w_ih: w_ih.as_tensor(),
                    b_ih: b_ih.as_tensor(),
                    w_hh: w_hh.as_tensor(),
                    b_hh: b_hh.as_tensor(),
                    reverse: k == 1,
                })
                .collect()
        }

        /// The output of `count` directions and a loss that reaches all of it.
        fn run(&self, fused: bool, count: usize, output: GruOutput) -> (Tensor, Tensor) {
            let layer = if fused { fused_gru } else { gru_reference };
            let out = layer(
                self.x.as_tensor(),
                &self.directions(count),
                &self.lengths,
                output,
            )
            .unwrap();
            let mut rng = SplitMix64::stream(self.seed, 1);
            let probe = random(out.dims(), 1.0, &mut rng);
            let loss = (&out * probe.as_tensor()).unwrap().sum_all().unwrap();
            (out, loss)
        }

        /// The variables `count` directions read: the input, then each direction's four.
        fn vars(&self, count: usize) -> Vec<&Var> {
            std::iter::once(&self.x)
                .chain(self.params[..count].iter().flatten())
                .collect()
        }

        /// The output and every variable's gradient, flattened.
        fn outputs(&self, fused: bool, count: usize, output: GruOutput) -> Vec<Vec<f32>> {
            let (out, loss) = self.run(fused, count, output);
            let grads = loss.backward().unwrap();
            std::iter::once(flat(&out))
                .chain(
                    self.vars(count)
                        .into_iter()
                        .map(|v| flat(grads.get(v.as_tensor()).unwrap())),
                )
                .collect()
        }
    }

    fn flat(t: &Tensor) -> Vec<f32> {
        t.flatten_all().unwrap().to_vec1().unwrap()
    }

    /// Mixed lengths (with 1 and the full length), equal lengths, a batch of one, more
    /// sequences than a group holds.
    const SHAPES: [(&[usize], usize, (usize, usize)); 5] = [
        (&[5, 1, 7, 3, 7, 2], 7, (4, 6)),
        (&[4, 4, 4], 4, (3, 5)),
        (&[1], 1, (2, 3)),
        (&[9, 2, 6, 1, 8], 9, (5, 16)),
        (
            &[3, 6, 1, 6, 2, 5, 4, 6, 1, 3, 2, 6, 5, 4, 3, 2, 1, 6, 4],
            6,
            (3, 4),
        ),
    ];

    const WHAT: [&str; 10] = [
        "output",
        "d x",
        "d w_ih",
        "d b_ih",
        "d w_hh",
        "d b_hh",
        "d w_ih reverse",
        "d b_ih reverse",
        "d w_hh reverse",
        "d b_hh reverse",
    ];

    #[test]
    fn fused_layer_matches_the_op_by_op_gru_with_its_gradients() {
        for (k, &(lengths, steps, widths)) in SHAPES.iter().enumerate() {
            let case = Case::new(lengths, steps, widths, k as u64);
            for count in [1, 2] {
                for output in [GruOutput::States, GruOutput::Final] {
                    let fused = case.outputs(true, count, output);
                    let reference = case.outputs(false, count, output);
                    assert_eq!(fused.len(), 2 + 4 * count);
                    for (what, (a, b)) in WHAT.iter().zip(fused.iter().zip(&reference)) {
                        let diff = max_abs_diff(a, b);
                        assert!(
                            diff < 2e-5 * (1.0 + b.iter().fold(0f32, |m, v| m.max(v.abs()))),
                            "{lengths:?}, {count} directions, {output:?}: {what} differ by {diff}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn fused_layer_is_zero_past_each_length_and_its_final_states_are_its_last() {
        let case = Case::new(&[3, 1, 2], 3, (2, 4), 7);
        let (states, _) = case.run(true, 2, GruOutput::States);
        let (last, _) = case.run(true, 2, GruOutput::Final);
        let states: Vec<Vec<Vec<f32>>> = states.to_vec3().unwrap();
        let last: Vec<Vec<f32>> = last.to_vec2().unwrap();
        for (b, len) in [3, 1, 2].into_iter().enumerate() {
            for past in &states[b][len..] {
                assert_eq!(past, &vec![0.0; 8]);
            }
            // Forward: after the last step; reversed: after the first position.
            assert_eq!(last[b][..4], states[b][len - 1][..4]);
            assert_eq!(last[b][4..], states[b][0][4..]);
        }
    }

    #[test]
    fn fused_layer_gradients_match_central_differences() {
        let case = Case::new(&[4, 1, 3], 4, (3, 3), 11);
        for output in [GruOutput::States, GruOutput::Final] {
            let (_, loss) = case.run(true, 2, output);
            let grads = loss.backward().unwrap();
            for var in case.vars(2) {
                let analytic = flat(grads.get(var.as_tensor()).unwrap());
                for k in (0..analytic.len()).step_by(5) {
                    let numeric = numeric_gradient(var, k, || {
                        f64::from(case.run(true, 2, output).1.to_scalar::<f32>().unwrap())
                    });
                    let err = (numeric - f64::from(analytic[k])).abs();
                    assert!(
                        err < 2e-3 * (1.0 + numeric.abs()),
                        "{output:?}, element {k}: analytic {} vs numeric {numeric}",
                        analytic[k]
                    );
                }
            }
        }
    }

    #[test]
    fn input_gradient_is_skipped_only_for_data() {
        let case = Case::new(&[3, 2], 3, (2, 3), 5);
        let data = case.x.as_tensor().detach();
        let out = fused_gru(&data, &case.directions(2), &case.lengths, GruOutput::Final).unwrap();
        let grads = out.sum_all().unwrap().backward().unwrap();
        assert!(grads.get(&data).is_none());
        assert!(grads.get(case.params[1][0].as_tensor()).is_some());
    }

    #[test]
    fn fused_layer_does_not_depend_on_the_thread_count() {
        let lengths: Vec<usize> = (0..40).map(|b| 1 + (b * 7) % 9).collect();
        let case = Case::new(&lengths, 9, (5, 16), 3);
        let on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                [GruOutput::States, GruOutput::Final].map(|output| case.outputs(true, 2, output))
            })
        };
        assert_eq!(on(1), on(3));
    }

    #[test]
    fn stacked_layers_end_in_the_top_layers_states_or_final_states() {
        let device = Device::Cpu;
        let varmap = candle_nn::VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &device);
        let stack = StackedGru::new(3, 4, 2, &vb).unwrap();
        let lengths = [3, 1];
        let x = Tensor::randn(0f32, 1.0, (2, 3, 3), &device).unwrap();
        let states: Vec<Vec<Vec<f32>>> = stack
            .run(&x, &lengths, GruOutput::States)
            .unwrap()
            .to_vec3()
            .unwrap();
        let last: Vec<Vec<f32>> = stack
            .run(&x, &lengths, GruOutput::Final)
            .unwrap()
            .to_vec2()
            .unwrap();
        assert_eq!(last[0], states[0][2]);
        assert_eq!(last[1], states[1][0]);
        assert_eq!(varmap.all_vars().len(), 8);
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
