//! The GRU recurrence as one fused CPU op with a hand-written backward pass through time.
//!
//! Why: as candle ops, every time step was a dozen small graph nodes (narrow, matmul,
//! sigmoid, mul…), and building and walking that graph made the evaluator's training step
//! 0.25–0.3× PyTorch's. Here the input projection stays one candle matmul over all steps
//! (`gi`) and this op runs the recurrence: one `(running, h) × (h, 3h)` gemm per step into
//! preallocated buffers and the gates in one pass, as PyTorch's packed sequences do: each
//! group's sequences are sorted longest first, so the ones still running are a prefix and
//! padding costs nothing. Sequences are independent, so the batch is dealt into groups of a
//! fixed size that the threads share; the weight gradient is one large gemm over every
//! (sequence, step) in batch order, so no result depends on the thread count.
//!
//! Semantics (PyTorch's `nn.GRU` over a packed batch, gate order r, z, n): with
//! gh = W_hh·h + b_hh, r = σ(gi_r + gh_r), z = σ(gi_z + gh_z), n = tanh(gi_n + r·gh_n),
//! h' = (1 − z)·n + z·h, from h = 0. Sequence b runs over its first `lengths[b]` steps (last
//! to first when `reverse`) and its output is zero past its length.

use crate::cpu_f32::{contiguous_f32, F32Values};
use crate::fast_exp::exp;
use crate::kernels::column_sums;
use crate::matmul::{gemm_with, transpose};
use crate::par::{new_written, SharedMut};
use candle_core::{CpuStorage, CustomOp3, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;
use std::sync::Mutex;

/// Batch, steps and hidden width of a scan.
#[derive(Debug, Clone, Copy)]
struct Dims {
    batch: usize,
    steps: usize,
    hidden: usize,
}

impl Dims {
    fn of(gi: &Shape, w: &Shape, bias: &Shape) -> Result<Self> {
        let (batch, steps, h3) = gi.dims3()?;
        let hidden = h3 / 3;
        if h3 % 3 != 0 || w.dims() != [h3, hidden] || bias.dims() != [h3] {
            candle_core::bail!("gru scan: gate inputs {gi:?}, weight {w:?}, bias {bias:?}");
        }
        Ok(Self {
            batch,
            steps,
            hidden,
        })
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
/// on): the buffers a scan fills are not zero-filled first (for the states, gates and their
/// gradients of a layer, that fill was a pass over as much memory as the scan writes).
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

/// The fused scan of one GRU direction (see the module docs). Keeps the gates of its forward
/// pass for the backward.
struct GruScan {
    lengths: Vec<usize>,
    reverse: bool,
    saved: Mutex<Option<Vec<f32>>>,
}

impl GruScan {
    /// Index of sequence `row`'s `s`-th step in `(batch, steps)` order.
    fn cell(&self, d: Dims, row: usize, len: usize, s: usize) -> usize {
        row * d.steps + if self.reverse { len - 1 - s } else { s }
    }

    /// States `(batch, steps, h)` and saved gates `(batch, steps, 4h)`.
    fn forward(&self, gi: &[f32], w: &[f32], bias: &[f32], d: Dims) -> (Vec<f32>, Vec<f32>) {
        let (hd, h3) = (d.hidden, 3 * d.hidden);
        // Each step's few-row product reads W_hhᵀ as it lies (see `transpose`).
        let wt = transpose(w, h3, hd);
        let scan = |out_ptr: SharedMut, gates_ptr: SharedMut| {
            groups(&self.lengths).par_iter().for_each(|g| {
                let mut h = vec![0f32; g.rows.len() * hd];
                let mut gh = vec![0f32; g.rows.len() * h3];
                let mut saved = vec![0f32; 4 * hd];
                for s in 0..g.lengths[0] {
                    let a = g.active(s);
                    gh[..a * h3]
                        .chunks_exact_mut(h3)
                        .for_each(|row| row.copy_from_slice(bias));
                    gemm_with(
                        &mut gh[..a * h3],
                        (&h[..a * hd], false),
                        (&wt, false),
                        (a, h3, hd),
                        (true, 1.0, false),
                    );
                    for i in 0..a {
                        let at = self.cell(d, g.rows[i], g.lengths[i], s);
                        let hi = &mut h[i * hd..][..hd];
                        gate_step(&gi[at * h3..][..h3], &gh[i * h3..][..h3], hi, &mut saved);
                        // SAFETY: each (sequence, step) cell belongs to one group and one step.
                        unsafe {
                            out_ptr.put(at * hd, hi);
                            gates_ptr.put(at * 4 * hd, &saved);
                        }
                    }
                }
            })
        };
        let lengths = &self.lengths;
        // SAFETY: the scan writes every real cell of both buffers.
        let (out, (gates, ())) = unsafe {
            cells_new(lengths, d.steps, hd, |out_ptr| {
                cells_new(lengths, d.steps, 4 * hd, |gates_ptr| {
                    scan(out_ptr, gates_ptr)
                })
            })
        };
        (out, gates)
    }

    /// Gradients of the gate inputs `(batch, steps, 3h)`, the recurrent weight `(3h, h)` and
    /// its bias `(3h)` from the states' gradient `dout`.
    fn backward(
        &self,
        w: &[f32],
        states: &[f32],
        gates: &[f32],
        dout: &[f32],
        d: Dims,
    ) -> [Vec<f32>; 3] {
        let (hd, h3) = (d.hidden, 3 * d.hidden);
        // gh's gradient and the previous state of every real cell, packed in batch then step
        // order (sequence b's cells from `first[b]`) for the one weight-gradient product.
        let first: Vec<usize> = self
            .lengths
            .iter()
            .scan(0, |acc, &l| {
                let at = *acc;
                *acc += l;
                Some(at)
            })
            .collect();
        let cells: usize = self.lengths.iter().sum();
        let zero = vec![0f32; hd];
        let scan = |ptrs: [SharedMut; 3]| {
            groups(&self.lengths).par_iter().for_each(|g| {
                let mut dh = vec![0f32; g.rows.len() * hd];
                let mut dgh_step = vec![0f32; g.rows.len() * h3];
                let mut dgi_cell = vec![0f32; h3];
                for s in (0..g.lengths[0]).rev() {
                    let a = g.active(s);
                    for i in 0..a {
                        let (row, len) = (g.rows[i], g.lengths[i]);
                        let at = self.cell(d, row, len, s);
                        let packed = first[row] + at - row * d.steps;
                        let hp = match s {
                            0 => &zero[..],
                            _ => &states[self.cell(d, row, len, s - 1) * hd..][..hd],
                        };
                        let dhi = &mut dh[i * hd..][..hd];
                        dhi.iter_mut()
                            .zip(&dout[at * hd..][..hd])
                            .for_each(|(a, b)| *a += b);
                        let dghi = &mut dgh_step[i * h3..][..h3];
                        let saved = &gates[at * 4 * hd..][..4 * hd];
                        gate_step_backward(saved, hp, dhi, &mut dgi_cell, dghi);
                        // SAFETY: each (sequence, step) cell, packed or not, belongs to one
                        // group and one step.
                        unsafe {
                            ptrs[0].put(at * h3, &dgi_cell);
                            ptrs[1].put(packed * h3, dghi);
                            ptrs[2].put(packed * hd, hp);
                        }
                    }
                    if s > 0 {
                        gemm_with(
                            &mut dh[..a * hd],
                            (&dgh_step[..a * h3], false),
                            (w, false),
                            (a, hd, h3),
                            (true, 1.0, false),
                        );
                    }
                }
            })
        };
        // dgi is zero past each length; the packed buffers have real cells only.
        // SAFETY: the scan writes every real cell of the three buffers.
        let (dgi, (dgh, (prev, ()))) = unsafe {
            cells_new(&self.lengths, d.steps, h3, |dgi| {
                cells_new(&[cells], cells, h3, |dgh| {
                    cells_new(&[cells], cells, hd, |prev| scan([dgi, dgh, prev]))
                })
            })
        };
        let mut dw = vec![0f32; h3 * hd];
        gemm_with(
            &mut dw,
            (&dgh, true),
            (&prev, false),
            (h3, hd, cells),
            (false, 1.0, true),
        );
        let db = column_sums(&dgh, h3);
        [dgi, dw, db]
    }
}

impl CustomOp3 for GruScan {
    fn name(&self) -> &'static str {
        "gru-scan"
    }

    fn cpu_fwd(
        &self,
        gs: &CpuStorage,
        gl: &Layout,
        ws: &CpuStorage,
        wl: &Layout,
        bs: &CpuStorage,
        bl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let d = Dims::of(gl.shape(), wl.shape(), bl.shape())?;
        let gi = contiguous_f32(gs, gl, "gate inputs")?;
        let w = contiguous_f32(ws, wl, "recurrent weight")?;
        let bias = contiguous_f32(bs, bl, "recurrent bias")?;
        let (out, gates) = self.forward(gi, w, bias, d);
        *self.saved.lock().expect("gru scan lock") = Some(gates);
        Ok((
            CpuStorage::F32(out),
            Shape::from((d.batch, d.steps, d.hidden)),
        ))
    }

    fn bwd(
        &self,
        gi: &Tensor,
        w: &Tensor,
        bias: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let d = Dims::of(gi.shape(), w.shape(), bias.shape())?;
        let saved = self.saved.lock().expect("gru scan lock");
        let gates = saved
            .as_ref()
            .ok_or_else(|| candle_core::Error::Msg("gru scan: backward before forward".into()))?;
        let (wv, states, dout) = (F32Values::of(w)?, F32Values::of(res)?, F32Values::of(grad)?);
        let [dgi, dw, db] = self.backward(&wv, &states, gates, &dout, d);
        let device = gi.device();
        Ok((
            Some(Tensor::from_vec(dgi, gi.shape(), device)?),
            Some(Tensor::from_vec(dw, w.shape(), device)?),
            Some(Tensor::from_vec(db, bias.shape(), device)?),
        ))
    }
}

/// The states `(batch, steps, h)` of one GRU direction from its gate inputs
/// `gi = x·W_ihᵀ + b_ih` `(batch, steps, 3h)`, recurrent weight `w_hh` `(3h, h)` and bias
/// `b_hh` `(3h)`; sequence b runs over its first `lengths[b]` steps (backwards when
/// `reverse`), zero past them. f32 CPU tensors take the fused op, anything else
/// [`scan_reference`].
pub fn gru_scan(
    gi: &Tensor,
    w_hh: &Tensor,
    b_hh: &Tensor,
    lengths: &[usize],
    reverse: bool,
) -> Result<Tensor> {
    let (batch, steps, _) = gi.dims3()?;
    if lengths.len() != batch || lengths.iter().any(|&l| l == 0 || l > steps) {
        candle_core::bail!("gru scan: lengths {lengths:?} for {batch} sequences of {steps} steps");
    }
    if !(gi.device().is_cpu() && gi.dtype() == DType::F32) {
        return scan_reference(gi, w_hh, b_hh, lengths, reverse);
    }
    let op = GruScan {
        lengths: lengths.to_vec(),
        reverse,
        saved: Mutex::new(None),
    };
    gi.contiguous()?
        .apply_op3(&w_hh.contiguous()?, &b_hh.contiguous()?, op)
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
