//! GRU layers as one fused CPU op with a hand-written backward pass through time.
//!
//! Why: as candle ops, every time step was a dozen small graph nodes (narrow, matmul,
//! sigmoid, mul…), and building and walking that graph made the evaluator's training step
//! 0.25–0.3× PyTorch's. Here one op takes a layer's input and parameters (one or both
//! directions) and returns its states or only its final states: each direction projects
//! every real step's input in one gemm (the pointwise convolution of [`crate::conv_op`]) and
//! runs the recurrence with one `(running, h) × (h, 3h)` gemm per step into preallocated
//! buffers and the gates in one pass, as PyTorch's packed sequences do: each group's
//! sequences are sorted longest first, so the ones still running are a prefix and padding
//! costs nothing. Sequences are independent, so the batch is dealt into groups of a fixed
//! size that the threads share (both directions' groups at once); the weight gradients are
//! one large gemm each over every (sequence, step) in batch order, so no result depends on
//! the thread count.
//!
//! Why the projection is inside the op: as its own graph node, its output (the gate inputs,
//! 3h wide, the largest tensor of a layer) and that output's gradient were padded to the
//! longest sequence, and candle's autograd zero-filled and added every gradient it
//! accumulated (the gate inputs', the states', the input's once per direction). Inside, they
//! stay packed (real steps only) and are written once. The values are the same: each
//! product has the shape and operands it had as separate nodes.
//!
//! Semantics (PyTorch's `nn.GRU` over a packed batch, gate order r, z, n): with
//! gi = W_ih·x + b_ih, gh = W_hh·h + b_hh, r = σ(gi_r + gh_r), z = σ(gi_z + gh_z),
//! n = tanh(gi_n + r·gh_n), h' = (1 − z)·n + z·h, from h = 0. Sequence b runs over its first
//! `lengths[b]` steps (last to first in a reversed direction) and its states are zero past
//! them.

use crate::conv_op::{ConvCpu, ConvGeometry, ConvOutput, ConvWeights, Rows};
use crate::cpu_f32::{contiguous_f32, F32Values};
use crate::fast_exp::exp;
use crate::kernels::column_sums;
use crate::matmul::{gemm_with, transpose};
use crate::par::{new_written, SharedMut};
use candle_core::{CpuStorage, CustomOp2, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;
use std::borrow::Cow;
use std::sync::Mutex;

/// Batch, steps, input and hidden width, and directions of a layer.
#[derive(Debug, Clone, Copy)]
struct Dims {
    batch: usize,
    steps: usize,
    input: usize,
    hidden: usize,
    directions: usize,
}

impl Dims {
    /// From the input `(batch, steps, in)` and the directions' parameters, one after another
    /// (see [`DirectionWeights::of`]).
    fn of(x: &Shape, params: &Shape, hidden: usize, directions: usize) -> Result<Self> {
        let (batch, steps, input) = x.dims3()?;
        let d = Self {
            batch,
            steps,
            input,
            hidden,
            directions,
        };
        if directions == 0 || hidden == 0 || params.dims() != [directions * d.per_direction()] {
            candle_core::bail!(
                "gru: input {x:?}, parameters {params:?} for {directions} directions of {hidden}"
            );
        }
        Ok(d)
    }

    /// Parameters of one direction: `W_ih`, `W_hh`, `b_ih`, `b_hh`.
    fn per_direction(&self) -> usize {
        3 * self.hidden * (self.input + self.hidden + 2)
    }
}

/// Sequences scanned together on one thread, longest first (the running ones are a prefix).
struct Group {
    rows: Vec<usize>,
    lengths: Vec<usize>,
}

impl Group {
    /// Sequences still running at step `s`.
    fn active(&self, s: usize) -> usize {
        self.lengths.partition_point(|&l| l > s)
    }
}

/// Sequences per group: enough rows for an efficient gemm, and few enough that a batch of 32
/// keeps two threads busy. Fixed, so every product sees the same rows whatever the thread
/// count (`gemm` may add in another order for another row count).
const GROUP_ROWS: usize = 16;

/// The batch dealt round-robin, longest first, into groups of at most [`GROUP_ROWS`].
fn groups(lengths: &[usize]) -> Vec<Group> {
    let n = lengths.len().div_ceil(GROUP_ROWS).max(1);
    let mut order: Vec<usize> = (0..lengths.len()).collect();
    order.sort_by_key(|&b| (std::cmp::Reverse(lengths[b]), b));
    let mut groups: Vec<Group> = (0..n)
        .map(|_| Group {
            rows: Vec::new(),
            lengths: Vec::new(),
        })
        .collect();
    for (k, &b) in order.iter().enumerate() {
        groups[k % n].rows.push(b);
        groups[k % n].lengths.push(lengths[b]);
    }
    groups
}

#[inline(always)]
fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + exp(-x))
}

#[inline(always)]
fn tanh(x: f32) -> f32 {
    1.0 - 2.0 / (1.0 + exp(2.0 * x))
}

crate::vectorised!(
    /// One step of one sequence: updates `h` in place from its gate inputs `x` and `gh`
    /// (both `3h`: r, z, n) and keeps r, z, n and gh_n in `saved` for the backward pass.
    fn gate_step / gate_step_at(x: &[f32], gh: &[f32], h: &mut [f32], saved: &mut [f32])
        = gate_step_body;
);

#[inline(always)]
fn gate_step_body(x: &[f32], gh: &[f32], h: &mut [f32], saved: &mut [f32]) {
    let hd = h.len();
    assert!(x.len() == 3 * hd && gh.len() == 3 * hd && saved.len() == 4 * hd);
    let (xr, xz, xn) = (&x[..hd], &x[hd..2 * hd], &x[2 * hd..]);
    let (gr, gz, gn) = (&gh[..hd], &gh[hd..2 * hd], &gh[2 * hd..]);
    let (sr, rest) = saved.split_at_mut(hd);
    let (sz, rest) = rest.split_at_mut(hd);
    let (sn, sg) = rest.split_at_mut(hd);
    for j in 0..hd {
        let r = sigmoid(xr[j] + gr[j]);
        let z = sigmoid(xz[j] + gz[j]);
        let n = tanh(xn[j] + r * gn[j]);
        h[j] = n + z * (h[j] - n);
        (sr[j], sz[j], sn[j], sg[j]) = (r, z, n, gn[j]);
    }
}

/// The backward of [`gate_step`]: from the state's gradient `dh` (replaced by the part that
/// flows directly to the previous state, z·dh) and the previous state `prev`, the gradients
/// of the gate inputs (`dgi`) and of gh (`dgh`).
fn gate_step_backward(
    saved: &[f32],
    prev: &[f32],
    dh: &mut [f32],
    dgi: &mut [f32],
    dgh: &mut [f32],
) {
    let hd = dh.len();
    assert!(
        saved.len() == 4 * hd && prev.len() == hd && dgi.len() == 3 * hd && dgh.len() == 3 * hd
    );
    let (r, z, n, gn) = (
        &saved[..hd],
        &saved[hd..2 * hd],
        &saved[2 * hd..3 * hd],
        &saved[3 * hd..],
    );
    for j in 0..hd {
        let g = dh[j];
        let dn = g * (1.0 - z[j]) * (1.0 - n[j] * n[j]);
        let dz = g * (prev[j] - n[j]) * z[j] * (1.0 - z[j]);
        let dr = dn * gn[j] * r[j] * (1.0 - r[j]);
        (dgi[j], dgi[hd + j], dgi[2 * hd + j]) = (dr, dz, dn);
        (dgh[j], dgh[hd + j], dgh[2 * hd + j]) = (dr, dz, dn * r[j]);
        dh[j] = g * z[j];
    }
}

/// `(sequences, steps, width)` values whose cells past each sequence's length are zero and
/// whose real cells `fill` writes through the pointer it gets (`fill`'s result is passed
/// on): a layer's padded states are not zero-filled first (that fill was a pass over as much
/// memory as the scan writes).
///
/// # Safety
/// `fill` writes every value of every real cell (step < `lengths[b]` ≤ `steps`).
unsafe fn cells_new<R>(
    lengths: &[usize],
    steps: usize,
    width: usize,
    fill: impl FnOnce(SharedMut) -> R,
) -> (Vec<f32>, R) {
    let write = |values: SharedMut| {
        for (b, &n) in lengths.iter().enumerate() {
            assert!(n <= steps);
            // SAFETY: sequence b's padding cells lie inside the buffer.
            unsafe {
                std::ptr::write_bytes(values.at((b * steps + n) * width), 0, (steps - n) * width)
            };
        }
        fill(values)
    };
    // SAFETY: the padding is zeroed above and `fill` writes every real cell.
    unsafe { new_written(lengths.len() * steps * width, write) }
}

/// What [`fused_gru`] returns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GruOutput {
    /// The state after every step, `(batch, steps, directions·h)`, zero past each length
    /// (`nn.GRU`'s output).
    States,
    /// Each direction's state after its last step, `(batch, directions·h)` (`nn.GRU`'s
    /// `h_n`, the directions side by side).
    Final,
}

/// One direction of a GRU layer: PyTorch's parameters and the way it runs.
#[derive(Clone, Copy)]
pub struct Direction<'a> {
    /// `weight_ih (3h, in)`.
    pub w_ih: &'a Tensor,
    /// `bias_ih (3h)`.
    pub b_ih: &'a Tensor,
    /// `weight_hh (3h, h)`.
    pub w_hh: &'a Tensor,
    /// `bias_hh (3h)`.
    pub b_hh: &'a Tensor,
    /// Last step first (the `_reverse` direction of a bidirectional layer).
    pub reverse: bool,
}

/// A direction's input projection: a pointwise convolution over one sequence of every
/// packed step.
fn projection() -> ConvCpu {
    ConvCpu {
        geometry: ConvGeometry::plain(1, 1, 1, 0),
        output: ConvOutput::default(),
    }
}

/// One direction's parameters in the layouts its products read.
struct DirectionWeights<'a> {
    /// `W_ih` and `b_ih`, as the projection's.
    input: ConvWeights,
    /// `W_hh` (3h × h): the right operand of the state gradient's product.
    w_hh: &'a [f32],
    /// `W_hhᵀ` (h × 3h): each step's few-row product reads it as it lies (see `transpose`).
    w_hh_t: Vec<f32>,
    b_hh: &'a [f32],
}

impl<'a> DirectionWeights<'a> {
    /// Direction `k`'s, from the directions' parameters one after another, each direction's
    /// `W_ih (3h, in)`, `W_hh (3h, h)`, `b_ih (3h)`, `b_hh (3h)` flattened in that order.
    fn of(params: &'a [f32], d: Dims, k: usize) -> Self {
        let (h3, inp) = (3 * d.hidden, d.input);
        let own = &params[k * d.per_direction()..][..d.per_direction()];
        let (w_ih, rest) = own.split_at(h3 * inp);
        let (w_hh, rest) = rest.split_at(h3 * d.hidden);
        let (b_ih, b_hh) = rest.split_at(h3);
        Self {
            input: ConvWeights::new(w_ih, b_ih, (h3, inp, 1)),
            w_hh,
            w_hh_t: transpose(w_hh, h3, d.hidden),
            b_hh,
        }
    }
}

/// What the forward pass keeps for the backward: every direction's gates (r, z, n, gh_n)
/// and state at every packed step, direction by direction, and the packed input (`None`
/// when every sequence is whole: the input itself).
struct Saved {
    gates: Vec<f32>,
    states: Vec<f32>,
    packed_input: Option<Vec<f32>>,
}

/// The fused GRU layer (see the module docs).
struct GruOp {
    lengths: Vec<usize>,
    hidden: usize,
    /// Per direction, whether it runs last step first.
    reverse: Vec<bool>,
    output: GruOutput,
    saved: Mutex<Option<Saved>>,
}

impl GruOp {
    /// Each sequence's real steps, packed in batch then step order.
    fn rows(&self, d: Dims) -> Rows {
        Rows::new(d.batch, d.steps, Some(&self.lengths))
    }

    /// Position in its sequence (of `len` steps) of direction `k`'s `s`-th step.
    fn position(&self, k: usize, len: usize, s: usize) -> usize {
        if self.reverse[k] {
            len - 1 - s
        } else {
            s
        }
    }

    /// Where direction `k`'s state at step `s` (position `t`) of sequence `b` (of `len`
    /// steps) lies in the output, if it is there.
    fn output_at(
        &self,
        d: Dims,
        k: usize,
        (b, len): (usize, usize),
        (s, t): Step,
    ) -> Option<usize> {
        let width = d.directions * d.hidden;
        match self.output {
            GruOutput::States => Some((b * d.steps + t) * width + k * d.hidden),
            GruOutput::Final => (s + 1 == len).then_some(b * width + k * d.hidden),
        }
    }

    /// Every direction's groups of sequences: the tasks the threads share.
    fn tasks<'g>(&self, groups: &'g [Group]) -> Vec<(usize, &'g Group)> {
        (0..self.reverse.len())
            .flat_map(|k| groups.iter().map(move |g| (k, g)))
            .collect()
    }

    /// The output, and what the backward pass needs.
    fn forward(&self, x: &[f32], weights: &[DirectionWeights], d: Dims) -> (Vec<f32>, Saved) {
        let (hd, h3) = (d.hidden, 3 * d.hidden);
        let rows = self.rows(d);
        let cells = rows.count();
        let xs = rows.gather(x, d.input);
        let gi: Vec<Vec<f32>> = weights
            .iter()
            .map(|w| projection().forward(&xs, (1, cells), &w.input))
            .collect();
        let groups = groups(&self.lengths);
        let scan = |out: SharedMut, gates: SharedMut, states: SharedMut| {
            self.tasks(&groups).par_iter().for_each(|&(k, g)| {
                let w = &weights[k];
                let mut h = vec![0f32; g.rows.len() * hd];
                let mut gh = vec![0f32; g.rows.len() * h3];
                let mut saved = vec![0f32; 4 * hd];
                for s in 0..g.lengths[0] {
                    let a = g.active(s);
                    gh[..a * h3]
                        .chunks_exact_mut(h3)
                        .for_each(|row| row.copy_from_slice(w.b_hh));
                    gemm_with(
                        &mut gh[..a * h3],
                        (&h[..a * hd], false),
                        (&w.w_hh_t, false),
                        (a, h3, hd),
                        (true, 1.0, false),
                    );
                    for i in 0..a {
                        let (b, len) = (g.rows[i], g.lengths[i]);
                        let t = self.position(k, len, s);
                        let packed = rows.span(b).0 + t;
                        let cell = k * cells + packed;
                        let hi = &mut h[i * hd..][..hd];
                        gate_step(
                            &gi[k][packed * h3..][..h3],
                            &gh[i * h3..][..h3],
                            hi,
                            &mut saved,
                        );
                        // SAFETY: each (direction, sequence, step) cell and each output
                        // state belongs to one task and one step.
                        unsafe {
                            gates.put(cell * 4 * hd, &saved);
                            states.put(cell * hd, hi);
                            if let Some(at) = self.output_at(d, k, (b, len), (s, t)) {
                                out.put(at, hi);
                            }
                        }
                    }
                }
            })
        };
        let per_cell = |width: usize| d.directions * cells * width;
        let fill = |out| {
            // SAFETY: the scan writes every cell of both buffers.
            unsafe {
                new_written(per_cell(4 * hd), |gates| {
                    new_written(per_cell(hd), |states| scan(out, gates, states))
                })
            }
        };
        let width = d.directions * hd;
        // SAFETY: the scan writes every real step's states (States) or every sequence's
        // final states (Final).
        let (out, (gates, (states, ()))) = unsafe {
            match self.output {
                GruOutput::States => cells_new(&self.lengths, d.steps, width, fill),
                GruOutput::Final => new_written(d.batch * width, fill),
            }
        };
        let packed_input = match xs {
            Cow::Owned(packed) => Some(packed),
            Cow::Borrowed(_) => None,
        };
        let saved = Saved {
            gates,
            states,
            packed_input,
        };
        (out, saved)
    }

    /// Gradients of the input (when `input_grad`) and of the parameters (laid out as they
    /// are), from the output's gradient `dout`.
    fn backward(
        &self,
        (x, input_grad): (&[f32], bool),
        weights: &[DirectionWeights],
        saved: &Saved,
        dout: &[f32],
        d: Dims,
    ) -> (Option<Vec<f32>>, Vec<f32>) {
        let (hd, h3) = (d.hidden, 3 * d.hidden);
        let rows = self.rows(d);
        let cells = rows.count();
        let zero = vec![0f32; hd];
        let groups = groups(&self.lengths);
        // Per (direction, packed step): the gate inputs' gradient, gh's, and the previous
        // state, for the projection's backward and the one recurrent weight-gradient product.
        let scan = |dgi: SharedMut, dgh: SharedMut, prev: SharedMut| {
            self.tasks(&groups).par_iter().for_each(|&(k, g)| {
                let w = &weights[k];
                let mut dh = vec![0f32; g.rows.len() * hd];
                let mut dgh_step = vec![0f32; g.rows.len() * h3];
                let mut dgi_cell = vec![0f32; h3];
                for s in (0..g.lengths[0]).rev() {
                    let a = g.active(s);
                    for i in 0..a {
                        let (b, len) = (g.rows[i], g.lengths[i]);
                        let (first, t) = (k * cells + rows.span(b).0, self.position(k, len, s));
                        let cell = first + t;
                        let hp = match s {
                            0 => &zero[..],
                            _ => {
                                let before = first + self.position(k, len, s - 1);
                                &saved.states[before * hd..][..hd]
                            }
                        };
                        let dhi = &mut dh[i * hd..][..hd];
                        if let Some(at) = self.output_at(d, k, (b, len), (s, t)) {
                            dhi.iter_mut()
                                .zip(&dout[at..][..hd])
                                .for_each(|(a, b)| *a += b);
                        }
                        let dghi = &mut dgh_step[i * h3..][..h3];
                        let gates = &saved.gates[cell * 4 * hd..][..4 * hd];
                        gate_step_backward(gates, hp, dhi, &mut dgi_cell, dghi);
                        // SAFETY: each (direction, sequence, step) cell belongs to one task
                        // and one step.
                        unsafe {
                            dgi.put(cell * h3, &dgi_cell);
                            dgh.put(cell * h3, dghi);
                            prev.put(cell * hd, hp);
                        }
                    }
                    if s > 0 {
                        gemm_with(
                            &mut dh[..a * hd],
                            (&dgh_step[..a * h3], false),
                            (w.w_hh, false),
                            (a, hd, h3),
                            (true, 1.0, false),
                        );
                    }
                }
            })
        };
        let per_cell = |width: usize| d.directions * cells * width;
        // SAFETY: the scan writes every cell of the three buffers.
        let (dgi, (dgh, (prev, ()))) = unsafe {
            new_written(per_cell(h3), |dgi| {
                new_written(per_cell(h3), |dgh| {
                    new_written(per_cell(hd), |prev| scan(dgi, dgh, prev))
                })
            })
        };
        let xs = saved.packed_input.as_deref().unwrap_or(x);
        let mut dx = None::<Vec<f32>>;
        let mut grads = Vec::with_capacity(d.directions * d.per_direction());
        for (k, w) in weights.iter().enumerate() {
            let part = |width: usize| k * cells * width..(k + 1) * cells * width;
            let (dgi, dgh, prev) = (&dgi[part(h3)], &dgh[part(h3)], &prev[part(hd)]);
            let input =
                projection().backward((xs, None, None), (1, cells), &w.input, dgi, input_grad);
            let mut dw_hh = vec![0f32; h3 * hd];
            gemm_with(
                &mut dw_hh,
                (dgh, true),
                (prev, false),
                (h3, hd, cells),
                (false, 1.0, true),
            );
            grads.extend_from_slice(&input.weight);
            grads.extend_from_slice(&dw_hh);
            grads.extend_from_slice(&input.bias);
            grads.extend_from_slice(&column_sums(dgh, h3));
            dx = match (dx, input.input) {
                (Some(mut sum), Some(more)) => {
                    sum.iter_mut().zip(&more).for_each(|(a, b)| *a += b);
                    Some(sum)
                }
                (sum, more) => sum.or(more),
            };
        }
        (dx.map(|dx| rows.scatter(dx, d.input)), grads)
    }

    fn weights<'a>(&self, params: &'a [f32], d: Dims) -> Vec<DirectionWeights<'a>> {
        (0..d.directions)
            .map(|k| DirectionWeights::of(params, d, k))
            .collect()
    }
}

/// A direction's step: how many it has run before (`s`) and its position in the sequence.
type Step = (usize, usize);

impl CustomOp2 for GruOp {
    fn name(&self) -> &'static str {
        "gru"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        ps: &CpuStorage,
        pl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let d = Dims::of(xl.shape(), pl.shape(), self.hidden, self.reverse.len())?;
        let x = contiguous_f32(xs, xl, "input")?;
        let params = contiguous_f32(ps, pl, "parameters")?;
        let (out, saved) = self.forward(x, &self.weights(params, d), d);
        *self.saved.lock().expect("gru lock") = Some(saved);
        let width = d.directions * d.hidden;
        let shape = match self.output {
            GruOutput::States => Shape::from((d.batch, d.steps, width)),
            GruOutput::Final => Shape::from((d.batch, width)),
        };
        Ok((CpuStorage::F32(out), shape))
    }

    fn bwd(
        &self,
        x: &Tensor,
        params: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let d = Dims::of(x.shape(), params.shape(), self.hidden, self.reverse.len())?;
        let saved = self.saved.lock().expect("gru lock");
        let saved = saved
            .as_ref()
            .ok_or_else(|| candle_core::Error::Msg("gru: backward before forward".into()))?;
        let values = F32Values::of(params)?;
        let (xv, dout) = (F32Values::of(x)?, F32Values::of(grad)?);
        let weights = self.weights(&values, d);
        // An input that no gradient reaches (the data under the first layer) gets none.
        let (dx, dp) = self.backward((&xv, x.track_op()), &weights, saved, &dout, d);
        let device = x.device();
        Ok((
            dx.map(|dx| Tensor::from_vec(dx, x.shape(), device))
                .transpose()?,
            Some(Tensor::from_vec(dp, params.shape(), device)?),
        ))
    }
}

/// A GRU layer's [`GruOutput`] over `x` `(batch, steps, in)`, its `directions` side by side
/// (one, or a bidirectional layer's two); sequence b runs over its first `lengths[b]` steps.
/// f32 CPU tensors only ([`crate::gru::gru`] composes candle ops for the others).
pub fn fused_gru(
    x: &Tensor,
    directions: &[Direction],
    lengths: &[usize],
    output: GruOutput,
) -> Result<Tensor> {
    let (batch, steps, _) = x.dims3()?;
    if lengths.len() != batch || lengths.iter().any(|&l| l == 0 || l > steps) {
        candle_core::bail!("gru: lengths {lengths:?} for {batch} sequences of {steps} steps");
    }
    if !(x.device().is_cpu() && x.dtype() == DType::F32) {
        candle_core::bail!("fused gru: f32 CPU tensors only, not {:?}", x.dtype());
    }
    // One tensor for the op: every parameter flattened, one after another (see
    // `DirectionWeights::of`): one copy forward, views of its gradient backward.
    let params = directions
        .iter()
        .flat_map(|d| [d.w_ih, d.w_hh, d.b_ih, d.b_hh])
        .map(|p| p.flatten_all())
        .collect::<Result<Vec<_>>>()?;
    let op = GruOp {
        lengths: lengths.to_vec(),
        hidden: directions.first().map_or(Ok(0), |d| d.w_hh.dim(1))?,
        reverse: directions.iter().map(|d| d.reverse).collect(),
        output,
        saved: Mutex::new(None),
    };
    x.contiguous()?.apply_op2(&Tensor::cat(&params, 0)?, op)
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

/// The recurrence of [`gru_scan`] as candle ops, one step at a time over
/// the whole batch (a reversed direction runs on each sequence reversed within its length),
/// states zeroed past each length.
pub fn scan_reference(
    gi: &Tensor,
    w_hh: &Tensor,
    b_hh: &Tensor,
    lengths: &[usize],
    reverse: bool,
) -> Result<Tensor> {
    let (batch, steps, h3) = gi.dims3()?;
    let hidden = h3 / 3;
    let gi = if reverse {
        reverse_within(gi, lengths)?
    } else {
        gi.clone()
    };
    let mut h = Tensor::zeros((batch, hidden), gi.dtype(), gi.device())?;
    let mut states = Vec::with_capacity(steps);
    for t in 0..steps {
        let gi = gi.narrow(1, t, 1)?.squeeze(1)?;
        let gh = h.matmul(&w_hh.t()?)?.broadcast_add(b_hh)?;
        let part = |g: &Tensor, k: usize| g.narrow(1, k * hidden, hidden);
        let r = candle_nn::ops::sigmoid(&(part(&gi, 0)? + part(&gh, 0)?)?)?;
        let z = candle_nn::ops::sigmoid(&(part(&gi, 1)? + part(&gh, 1)?)?)?;
        let n = (part(&gi, 2)? + (r * part(&gh, 2)?)?)?.tanh()?;
        // h' = (1 − z)·n + z·h
        h = ((&z * &h)? + ((1.0 - &z)? * n)?)?;
        states.push(h.clone());
    }
    let mask: Vec<f32> = lengths
        .iter()
        .flat_map(|&l| (0..steps).map(move |t| if t < l { 1.0 } else { 0.0 }))
        .collect();
    let mask = Tensor::from_vec(mask, (batch, steps, 1), gi.device())?;
    let states = Tensor::stack(&states, 1)?.broadcast_mul(&mask)?;
    if reverse {
        reverse_within(&states, lengths)
    } else {
        Ok(states)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One GRU gate step gives the same bits at every vector level.
    #[test]
    fn gate_step_agrees_at_every_vector_level() {
        let hd = 67;
        let mut rng = motionscale_core::rng::SplitMix64(9);
        let mut draw =
            |n: usize| -> Vec<f32> { (0..n).map(|_| rng.range(-4.0, 4.0) as f32).collect() };
        let (x, gh, h) = (draw(3 * hd), draw(3 * hd), draw(hd));
        crate::simd::assert_levels_agree(|isa| {
            let (mut h, mut saved) = (h.clone(), vec![0f32; 4 * hd]);
            gate_step_at(isa, &x, &gh, &mut h, &mut saved);
            crate::simd::bits(&[h, saved].concat())
        });
    }
}
