//! Gated recurrent units with PyTorch's parameter layout (`nn.GRU`: gate order r, z, n;
//! `weight_ih_l<k>[_reverse]`, `weight_hh_l<k>…`, `bias_ih_l<k>…`, `bias_hh_l<k>…`), so
//! weights load into `torch.nn.GRU` unchanged: the evaluator's bidirectional layers and
//! BI-CTVAE's stacked encoder and decoder.

use candle_core::{Module, Result, Tensor};
use candle_nn::{Linear, VarBuilder};

/// One direction of one GRU layer.
pub struct GruLayer {
    w_ih: Linear,
    w_hh: Linear,
    hidden: usize,
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
            w_hh: Linear::new(
                get((3 * hidden, hidden), &format!("weight_hh_{suffix}"))?,
                Some(bias(&format!("bias_hh_{suffix}"))?),
            ),
            hidden,
        })
    }

    /// The hidden state after every step, `(batch, steps, hidden)`, from a zero state. `x` is
    /// `(batch, steps, in)`; the input projection of every step is one matmul, only the
    /// recurrence loops.
    pub fn states(&self, x: &Tensor) -> Result<Tensor> {
        let (batch, steps, _) = x.dims3()?;
        let projected = self.w_ih.forward(x)?;
        let mut h = Tensor::zeros((batch, self.hidden), x.dtype(), x.device())?;
        let mut states = Vec::with_capacity(steps);
        for t in 0..steps {
            let gi = projected.narrow(1, t, 1)?.squeeze(1)?;
            let gh = self.w_hh.forward(&h)?;
            let (ir, iz, inn) = (
                gi.narrow(1, 0, self.hidden)?,
                gi.narrow(1, self.hidden, self.hidden)?,
                gi.narrow(1, 2 * self.hidden, self.hidden)?,
            );
            let (hr, hz, hn) = (
                gh.narrow(1, 0, self.hidden)?,
                gh.narrow(1, self.hidden, self.hidden)?,
                gh.narrow(1, 2 * self.hidden, self.hidden)?,
            );
            let r = candle_nn::ops::sigmoid(&(ir + hr)?)?;
            let z = candle_nn::ops::sigmoid(&(iz + hz)?)?;
            let n = (inn + (r * hn)?)?.tanh()?;
            // h' = (1 − z)·n + z·h
            h = ((&z * &h)? + ((1.0 - &z)? * n)?)?;
            states.push(h.clone());
        }
        Tensor::stack(&states, 1)
    }

    /// The hidden state after each sequence's last real step, `(batch, hidden)`.
    pub fn last_state(&self, x: &Tensor, lengths: &[usize]) -> Result<Tensor> {
        last_states(&self.states(x)?, lengths)
    }
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

    /// The top layer's state after every step, `(batch, steps, hidden)`.
    pub fn states(&self, x: &Tensor) -> Result<Tensor> {
        let mut x = x.clone();
        for layer in &self.layers {
            x = layer.states(&x)?;
        }
        Ok(x)
    }
}

/// Each sequence of `x` reversed within its own length (padding stays in place).
pub fn reverse_within(x: &Tensor, lengths: &[usize]) -> Result<Tensor> {
    let (batch, steps, width) = x.dims3()?;
    let order: Vec<u32> = lengths
        .iter()
        .enumerate()
        .flat_map(|(b, &len)| {
            (0..steps).map(move |t| (b * steps + if t < len { len - 1 - t } else { t }) as u32)
        })
        .collect();
    x.reshape((batch * steps, width))?
        .index_select(&Tensor::new(order, x.device())?, 0)?
        .reshape((batch, steps, width))
}
