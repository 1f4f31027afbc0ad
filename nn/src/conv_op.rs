//! Channels-last 1-D convolution as one fused CPU op: (optional ReLU and nearest ×2
//! up-sampling of the input) → im2col → one AVX-512 gemm with the bias as its initial value,
//! and a backward pass of two gemms and a col2im scatter.
//!
//! Why not candle's `conv1d`: on the CPU its backward goes through a transposed convolution
//! and a convolution over the batch axis, 6× slower than PyTorch/oneDNN at the T2M-GPT shape;
//! here every FLOP of forward and backward is a large gemm (M = batch·frames rows,
//! K = kernel·channels, N = channels). Fusing the ReLU that precedes almost every conv of
//! T2M-GPT and the nearest up-sampling into the im2col copy saves whole passes over the
//! activations. On other devices [`conv1d`] composes candle ops to the same result
//! ([`conv1d_reference`], which avoids candle's `conv1d` backward).
//!
//! Layouts: input `(batch, frames, in)`, weight `(out, in, kernel)` (PyTorch's), bias `(out)`,
//! output `(batch, out_frames, out)`. The im2col matrix has one row per output frame and
//! columns `k·in + c` (tap-major, so each tap is one contiguous copy of a frame).
//!
//! [`ConvCpu`] is the same computation on plain values, for networks that run their own
//! backward pass (the tokenizer's); it can keep its im2col matrix for the backward pass. Over
//! whole sequences, a stride-1 convolution runs one product per tap over the time-major input
//! (no im2col, no multiply-adds with padding), a k3 "same" convolution as Winograd's F(2,3)
//! where that takes fewer products (a third fewer at dilation 1), and an up-sampling k3
//! convolution as two k2 convolutions of the input itself (polyphase: a third fewer
//! multiply-adds).
//!
//! [`conv1d_fused`] can also compute only each sequence's first output frames ([`ConvOutput`]):
//! the rest are zero, as the mask after a padded batch's convolution makes them, but cost
//! nothing, which for a batch padded to its longest clip (the evaluator's) is ~40% of the
//! FLOPs. It can apply a leaky ReLU to the output in the same pass.

use crate::cpu_f32::{contiguous_f32, F32Values};
use crate::matmul::{gemm_new, gemm_strided, gemm_with, transpose, Strided, TransposedLhs};
use crate::par::{new_written, par_new, SharedMut};
use candle_core::{CpuStorage, CustomOp3, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;
use std::borrow::Cow;
use std::mem::MaybeUninit;
use winograd::Winograd;

mod winograd;

/// Geometry of a convolution and the pre-ops fused into its input read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConvGeometry {
    /// Kernel taps.
    pub kernel: usize,
    /// Stride.
    pub stride: usize,
    /// Dilation.
    pub dilation: usize,
    /// Zero padding on both sides (in frames of the possibly up-sampled input).
    pub padding: usize,
    /// Apply ReLU to the input first.
    pub relu_input: bool,
    /// Up-sample the input ×2 (nearest) first.
    pub upsample_input: bool,
}

impl ConvGeometry {
    /// A convolution without pre-ops (PyTorch's `Conv1d(…, kernel, stride, padding, dilation)`).
    pub fn plain(kernel: usize, stride: usize, dilation: usize, padding: usize) -> Self {
        Self {
            kernel,
            stride,
            dilation,
            padding,
            relu_input: false,
            upsample_input: false,
        }
    }

    /// Frames of the input as the convolution sees it (doubled when up-sampling).
    fn virtual_len(&self, frames: usize) -> usize {
        if self.upsample_input {
            2 * frames
        } else {
            frames
        }
    }

    /// Output frames for `frames` input frames (PyTorch's formula); 0 when too short.
    pub fn out_len(&self, frames: usize) -> usize {
        let span = self.dilation * (self.kernel - 1) + 1;
        let padded = self.virtual_len(frames) + 2 * self.padding;
        if padded < span {
            0
        } else {
            (padded - span) / self.stride + 1
        }
    }

    /// Input frame read by output frame `t` at tap `k`, if inside the input.
    fn source(&self, t: usize, k: usize, frames: usize) -> Option<usize> {
        let pos = (t * self.stride + k * self.dilation).checked_sub(self.padding)?;
        (pos < self.virtual_len(frames)).then_some(if self.upsample_input { pos / 2 } else { pos })
    }

    /// The output frames whose tap `k` reads input frame `s` (the inverse of [`Self::source`];
    /// frames past the output's length included, for the caller to drop).
    fn readers(&self, s: usize, k: usize) -> impl Iterator<Item = usize> + '_ {
        let positions = if self.upsample_input {
            2 * s..2 * s + 2
        } else {
            s..s + 1
        };
        positions.filter_map(move |pos| {
            let shifted = (pos + self.padding).checked_sub(k * self.dilation)?;
            (shifted % self.stride == 0).then_some(shifted / self.stride)
        })
    }

    /// Whether the input is read as is (a plain `k1` conv): no im2col copy is needed.
    fn is_pointwise(&self) -> bool {
        self.kernel == 1
            && self.stride == 1
            && self.padding == 0
            && !self.relu_input
            && !self.upsample_input
    }
}

/// Which output frames the fused op computes, and the activation it applies to them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ConvOutput {
    /// Output frames computed for each sequence, from the first; the others are zero and
    /// pass no gradient (`None`: every frame).
    pub valid: Option<Vec<usize>>,
    /// Negative slope of a leaky ReLU applied to the output (`Some(0.0)` is a ReLU).
    pub leaky_slope: Option<f32>,
}

/// Rows per parallel task of the copies (large enough to amortise scheduling).
const ROWS_PER_TASK: usize = 64;

/// The rows an op computes (a convolution's output frames, a GRU's steps): all `batch × out`
/// of them in order, or each sequence's first `valid[b]`, packed one after another.
#[derive(Clone)]
pub(crate) struct Rows {
    batch: usize,
    out: usize,
    /// Packed row of each sequence's first frame, and the total at the end; `None`: all rows.
    starts: Option<Vec<usize>>,
}

impl Rows {
    /// The rows of `batch` sequences of `out` frames, each computed at its first `valid[b]`
    /// (`None`: all of them).
    pub(crate) fn new(batch: usize, out: usize, valid: Option<&[usize]>) -> Self {
        // Every sequence whole (BI-CTVAE's decoder): the rows are already packed.
        let valid = valid.filter(|v| v.iter().any(|&n| n < out));
        let starts = valid.map(|v| {
            let mut starts = vec![0];
            for &n in v {
                starts.push(starts[starts.len() - 1] + n.min(out));
            }
            starts
        });
        Self { batch, out, starts }
    }

    /// Rows computed.
    pub(crate) fn count(&self) -> usize {
        self.starts
            .as_ref()
            .map_or(self.batch * self.out, |s| s[self.batch])
    }

    /// Packed row of sequence `b`'s first frame, and how many frames it has.
    pub(crate) fn span(&self, b: usize) -> (usize, usize) {
        match &self.starts {
            Some(s) => (s[b], s[b + 1] - s[b]),
            None => (b * self.out, self.out),
        }
    }

    /// Sequence and frame of packed row `r`.
    fn locate(&self, r: usize) -> (usize, usize) {
        match &self.starts {
            Some(s) => {
                let b = s.partition_point(|&start| start <= r) - 1;
                (b, r - s[b])
            }
            None => (r / self.out, r % self.out),
        }
    }

    /// The packed rows of `padded` (`batch·out` rows of `width`), one sequence per task.
    pub(crate) fn gather<'a>(&self, padded: &'a [f32], width: usize) -> Cow<'a, [f32]> {
        if self.starts.is_none() {
            return Cow::Borrowed(padded);
        }
        let copy = |packed: SharedMut| {
            (0..self.batch).into_par_iter().for_each(|b| {
                let (start, n) = self.span(b);
                let rows = &padded[b * self.out * width..][..n * width];
                // SAFETY: sequence b's packed rows are written by this task alone.
                unsafe { packed.put(start * width, rows) };
            })
        };
        // SAFETY: the sequences' packed rows tile the buffer.
        Cow::Owned(unsafe { new_written(self.count() * width, copy) }.0)
    }

    /// `packed` rows put back in their places among `batch·out` rows, zeros elsewhere; one
    /// sequence per task.
    pub(crate) fn scatter(&self, packed: Vec<f32>, width: usize) -> Vec<f32> {
        if self.starts.is_none() {
            return packed;
        }
        let fill = |b: usize, block: &mut [MaybeUninit<f32>]| {
            let (start, n) = self.span(b);
            let (rows, padding) = block.split_at_mut(n * width);
            rows.iter_mut()
                .zip(&packed[start * width..][..n * width])
                .for_each(|(d, &v)| {
                    d.write(v);
                });
            padding.iter_mut().for_each(|d| {
                d.write(0.0);
            });
        };
        // SAFETY: block b is sequence b's `out` rows, each written whole.
        unsafe { par_new(self.batch * self.out * width, self.out * width, fill) }
    }
}

/// The im2col matrix of `x` (batch × frames × channels) at the output rows `rows`:
/// rows.count() × (kernel·channels).
fn im2col(
    x: &[f32],
    (frames, channels): (usize, usize),
    g: &ConvGeometry,
    rows: &Rows,
) -> Vec<f32> {
    let width = g.kernel * channels;
    let len = rows.count() * width;
    // Written once, zeros only where a tap reads padding: no zero-fill of the whole matrix
    // first (it is the largest buffer of a step).
    let fill = |task: usize, chunk: &mut [MaybeUninit<f32>]| {
        for (i, row) in chunk.chunks_exact_mut(width).enumerate() {
            let (b, t) = rows.locate(task * ROWS_PER_TASK + i);
            for (k, dst) in row.chunks_exact_mut(channels).enumerate() {
                let Some(s) = g.source(t, k, frames) else {
                    dst.iter_mut().for_each(|d| {
                        d.write(0.0);
                    });
                    continue;
                };
                let src = &x[(b * frames + s) * channels..][..channels];
                let relu = g.relu_input;
                dst.iter_mut().zip(src).for_each(|(d, &v)| {
                    d.write(if relu { v.max(0.0) } else { v });
                });
            }
        }
    };
    // SAFETY: every row of every task is written whole.
    unsafe { par_new(len, width * ROWS_PER_TASK, fill) }
}

/// The adjoint of [`im2col`]: each input frame gathers the column gradients of every
/// (row, tap) that read it, then takes the ReLU mask of `x` when the op read `relu(x)`.
/// A gather writes each input gradient once (no zero-fill, no read-modify-write per tap).
fn col2im(
    dcols: &[f32],
    x: &[f32],
    (batch, frames, channels): (usize, usize, usize),
    g: &ConvGeometry,
    rows: &Rows,
) -> Vec<f32> {
    let width = g.kernel * channels;
    let len = batch * frames * channels;
    let fill = |b: usize, dxb: &mut [MaybeUninit<f32>]| {
        let (start, n) = rows.span(b);
        let mut sum = vec![0f32; channels];
        for (s, dst) in dxb.chunks_exact_mut(channels).enumerate() {
            sum.fill(0.0);
            // Taps from the last, so the rows add in increasing order as a scatter would.
            for k in (0..g.kernel).rev() {
                for t in g.readers(s, k).filter(|&t| t < n) {
                    let src = &dcols[(start + t) * width + k * channels..][..channels];
                    sum.iter_mut().zip(src).for_each(|(a, v)| *a += v);
                }
            }
            let xs = &x[(b * frames + s) * channels..][..channels];
            let relu = g.relu_input;
            dst.iter_mut().zip(&sum).zip(xs).for_each(|((d, &a), &v)| {
                d.write(if relu && v <= 0.0 { 0.0 } else { a });
            });
        }
    };
    // SAFETY: block b is sequence b's frames, each written whole.
    unsafe { par_new(len, frames * channels, fill) }
}

/// `w (out, in, kernel)` as `(out, kernel·in)`, the tap-major order of the im2col columns;
/// one output channel per task (the reorders of a whole tokenizer are 20 M values a step).
fn taps_major(w: &[f32], (out, inp, kernel): (usize, usize, usize)) -> Vec<f32> {
    assert_eq!(w.len(), out * kernel * inp, "conv weight size");
    let fill = |o: usize, t: &mut [MaybeUninit<f32>]| {
        let w = &w[o * inp * kernel..][..inp * kernel];
        for (k, t) in t.chunks_exact_mut(inp).enumerate() {
            t.iter_mut()
                .zip(w.iter().skip(k).step_by(kernel))
                .for_each(|(t, &w)| {
                    t.write(w);
                });
        }
    };
    // SAFETY: block o is output channel o's taps, each tap's `inp` values written.
    unsafe { par_new(w.len(), kernel * inp, fill) }
}

/// The inverse of [`taps_major`].
fn channels_major(t: &[f32], (out, inp, kernel): (usize, usize, usize)) -> Vec<f32> {
    assert_eq!(t.len(), out * kernel * inp, "conv weight size");
    let fill = |o: usize, w: &mut [MaybeUninit<f32>]| {
        let t = &t[o * kernel * inp..][..kernel * inp];
        for k in 0..kernel {
            for c in 0..inp {
                w[c * kernel + k].write(t[k * inp + c]);
            }
        }
    };
    // SAFETY: block o is output channel o's `inp · kernel` values, each (c, k) written.
    unsafe { par_new(t.len(), inp * kernel, fill) }
}

/// (batch, frames, channels) of an input, or (out, in, kernel) of a weight.
type Dims3 = (usize, usize, usize);

/// A convolution's weight in the layouts its gemms read, `(out, kernel·in)` tap-major and its
/// transpose, with its bias: made once per step, read by the forward and the backward pass.
#[derive(Debug, Clone)]
pub struct ConvWeights {
    /// `(out, kernel·in)`: the right operand of the input gradient's product.
    taps: Vec<f32>,
    /// `(kernel·in, out)`: the right operand of the forward product. gemm reads a right
    /// operand fastest row-major; transposed, the forward products ran 5–20% slower.
    taps_t: Vec<f32>,
    bias: Vec<f32>,
    /// (out, in, kernel).
    dims: Dims3,
}

impl ConvWeights {
    /// From PyTorch's `weight (out, in, kernel)` and `bias (out)`.
    pub fn new(weight: &[f32], bias: &[f32], dims: Dims3) -> Self {
        let (out, inp, kernel) = dims;
        assert_eq!(weight.len(), out * inp * kernel, "conv weight size");
        assert_eq!(bias.len(), out, "conv bias size");
        let taps = taps_major(weight, dims);
        Self {
            taps_t: transpose(&taps, out, kernel * inp),
            taps,
            bias: bias.to_vec(),
            dims,
        }
    }
}

/// The gradients of one convolution, weight in PyTorch's `(out, in, kernel)` layout.
#[derive(Debug, Clone)]
pub struct ConvGrads {
    /// Gradient of the input (`None` when not asked for).
    pub input: Option<Vec<f32>>,
    /// Gradient of the weight.
    pub weight: Vec<f32>,
    /// Gradient of the bias.
    pub bias: Vec<f32>,
}

/// One convolution on CPU values: its geometry, which output rows it computes and how.
#[derive(Debug, Clone, PartialEq)]
pub struct ConvCpu {
    /// Geometry and input pre-ops.
    pub geometry: ConvGeometry,
    /// Output rows and activation.
    pub output: ConvOutput,
}

impl ConvCpu {
    fn rows(&self, batch: usize, frames: usize) -> Rows {
        Rows::new(
            batch,
            self.geometry.out_len(frames),
            self.output.valid.as_deref(),
        )
    }

    /// The geometry whose im2col matrix the gemms read: for a [polyphase](Polyphase)
    /// convolution the k3 conv on the input before up-sampling (one row per input frame).
    fn columns_geometry(&self) -> ConvGeometry {
        match self.polyphase() {
            true => ConvGeometry {
                upsample_input: false,
                ..self.geometry
            },
            false => self.geometry,
        }
    }

    /// Whether this is nearest ×2 up-sampling then a k3 stride-1 same-length conv over every
    /// output row, which runs as two k2 convs on the input (see [`Polyphase`]).
    fn polyphase(&self) -> bool {
        let g = &self.geometry;
        g.upsample_input
            && (g.kernel, g.stride, g.dilation, g.padding) == (3, 1, 1, 1)
            && self.output.valid.is_none()
    }

    /// Whether this stride-1 conv runs one product per tap over the time-major input
    /// ([`PerTap`]) instead of one over its im2col matrix.
    fn per_tap(&self) -> bool {
        let g = &self.geometry;
        g.kernel > 1 && g.stride == 1 && !g.upsample_input && self.output.valid.is_none()
    }

    /// The [`Winograd`] F(2,3) form of this conv over `frames`-frame sequences, when it is a
    /// k3 "same" conv that [`PerTap`] would run and F(2,3) takes fewer products.
    fn winograd<'a>(
        &self,
        w: &'a ConvWeights,
        (batch, frames): (usize, usize),
    ) -> Option<Winograd<'a>> {
        let g = &self.geometry;
        let same_k3 = g.kernel == 3 && g.padding == g.dilation;
        (self.per_tap() && same_k3 && Winograd::pays_off(frames, g.dilation))
            .then(|| Winograd::new(w, (g.dilation, g.relu_input), (batch, frames)))
    }

    /// The matrix the products read: the im2col matrix of `x` (`x` itself, packed, when
    /// pointwise), one row per output row in `rows`, or per input frame when polyphase; the
    /// time-major input for [`PerTap`] convs, the transformed input for [`Winograd`] ones.
    fn lhs<'a>(&self, x: &'a [f32], frames: usize, rows: &Rows, w: &ConvWeights) -> Cow<'a, [f32]> {
        let inp = w.dims.1;
        assert_eq!(x.len(), rows.batch * frames * inp, "conv input size");
        if let Some(winograd) = self.winograd(w, (rows.batch, frames)) {
            return Cow::Owned(winograd.transform_input(x));
        }
        if self.per_tap() {
            let relu = self.geometry.relu_input;
            return Cow::Owned(time_major(x, (rows.batch, frames, inp), relu));
        }
        if self.polyphase() {
            let input_rows = Rows::new(rows.batch, frames, None);
            return Cow::Owned(im2col(
                x,
                (frames, inp),
                &self.columns_geometry(),
                &input_rows,
            ));
        }
        if self.geometry.is_pointwise() {
            rows.gather(x, inp)
        } else {
            Cow::Owned(im2col(x, (frames, inp), &self.geometry, rows))
        }
    }

    /// The output `(batch, out_frames, out)` of `x` `(batch, frames, in)`.
    pub fn forward(&self, x: &[f32], (batch, frames): (usize, usize), w: &ConvWeights) -> Vec<f32> {
        let rows = self.rows(batch, frames);
        self.product(&self.lhs(x, frames, &rows, w), (&rows, frames), w)
    }

    /// [`Self::forward`], also returning the im2col matrix it multiplied (`None` when that
    /// was `x` itself) for [`Self::backward`] to reuse instead of building it again.
    pub fn forward_keeping_columns(
        &self,
        x: &[f32],
        (batch, frames): (usize, usize),
        w: &ConvWeights,
    ) -> (Vec<f32>, Option<Vec<f32>>) {
        let rows = self.rows(batch, frames);
        match self.lhs(x, frames, &rows, w) {
            Cow::Borrowed(lhs) => (self.product(lhs, (&rows, frames), w), None),
            Cow::Owned(cols) => (self.product(&cols, (&rows, frames), w), Some(cols)),
        }
    }

    /// The output of the gemm operand `lhs` (see [`Self::lhs`]).
    fn product(&self, lhs: &[f32], (rows, frames): (&Rows, usize), w: &ConvWeights) -> Vec<f32> {
        let (out_ch, inp, kernel) = w.dims;
        if let Some(winograd) = self.winograd(w, (rows.batch, frames)) {
            return self.activate(winograd.forward(lhs), rows, out_ch);
        }
        if self.per_tap() {
            let y = PerTap::new(self, w, (rows.batch, frames)).forward(lhs);
            return self.activate(y, rows, out_ch);
        }
        // Every row starts as the bias (written once, no zero-fill first); gemm adds to it.
        let len = rows.count() * out_ch;
        let fill = |_, chunk: &mut [MaybeUninit<f32>]| {
            for row in chunk.chunks_exact_mut(out_ch) {
                row.iter_mut().zip(&w.bias).for_each(|(d, &b)| {
                    d.write(b);
                });
            }
        };
        // SAFETY: every row is written whole.
        let mut y = unsafe { par_new(len, out_ch * ROWS_PER_TASK, fill) };
        if self.polyphase() {
            Polyphase::new(w).forward(&mut y, lhs);
        } else {
            gemm_with(
                &mut y,
                (lhs, false),
                (&w.taps_t, false),
                (rows.count(), out_ch, kernel * inp),
                (true, 1.0, true),
            );
        }
        self.activate(y, rows, out_ch)
    }

    /// The output activation applied to the computed rows `y`, which are then put in place.
    fn activate(&self, mut y: Vec<f32>, rows: &Rows, out_ch: usize) -> Vec<f32> {
        if let Some(slope) = self.output.leaky_slope {
            leaky_relu(&mut y, slope);
        }
        rows.scatter(y, out_ch)
    }

    /// The gradients for the output gradient `dy` of [`Self::forward`] on `x`; `y` is that
    /// output (read only when there is a leaky ReLU), `columns` what
    /// [`Self::forward_keeping_columns`] kept (built again when `None`); the input's
    /// gradient only when `input_grad`.
    pub fn backward(
        &self,
        (x, y, columns): (&[f32], Option<&[f32]>, Option<&[f32]>),
        (batch, frames): (usize, usize),
        w: &ConvWeights,
        dy: &[f32],
        input_grad: bool,
    ) -> ConvGrads {
        let (out_ch, inp, kernel) = w.dims;
        let rows = self.rows(batch, frames);
        let mut dy = rows.gather(dy, out_ch);
        if let Some(slope) = self.output.leaky_slope {
            let y = y.expect("the conv output, to differentiate its leaky ReLU");
            leaky_relu_backward(dy.to_mut(), &rows.gather(y, out_ch), slope);
        }
        let lhs = match columns {
            Some(cols) => Cow::Borrowed(cols),
            None => self.lhs(x, frames, &rows, w),
        };
        if let Some(winograd) = self.winograd(w, (batch, frames)) {
            let (weight, input) = winograd.backward((x, &lhs), &dy, input_grad);
            return ConvGrads {
                input,
                weight: channels_major(&weight, (out_ch, inp, kernel)),
                bias: bias_gradient(&dy, out_ch),
            };
        }
        if self.per_tap() {
            let per_tap = PerTap::new(self, w, (batch, frames));
            let dy_t = time_major(&dy, (batch, rows.out, out_ch), false);
            let input = input_grad.then(|| per_tap.input_grad(&dy_t, x));
            return ConvGrads {
                input,
                weight: channels_major(
                    &per_tap.weight_grad(&dy_t, &lhs, TransposedLhs::chosen()),
                    (out_ch, inp, kernel),
                ),
                bias: bias_gradient(&dy, out_ch),
            };
        }
        let (dwt, dcols) = if self.polyphase() {
            let phases = Polyphase::new(w);
            (
                phases.weight_grad(&dy, &lhs),
                input_grad.then(|| phases.columns_grad(&dy)),
            )
        } else {
            self.gemm_grads(&dy, &lhs, rows.count(), w, input_grad)
        };
        let input = dcols.map(|dcols| {
            if self.geometry.is_pointwise() {
                rows.scatter(dcols, inp)
            } else {
                let col_rows = match self.polyphase() {
                    true => Rows::new(batch, frames, None),
                    false => rows.clone(),
                };
                let g = self.columns_geometry();
                col2im(&dcols, x, (batch, frames, inp), &g, &col_rows)
            }
        });
        ConvGrads {
            input,
            weight: channels_major(&dwt, (out_ch, inp, kernel)),
            bias: bias_gradient(&dy, out_ch),
        }
    }

    /// dW (taps-major) = dYᵀ · cols, and dcols = dY · W when `input_grad`.
    fn gemm_grads(
        &self,
        dy: &[f32],
        cols: &[f32],
        rows: usize,
        w: &ConvWeights,
        input_grad: bool,
    ) -> (Vec<f32>, Option<Vec<f32>>) {
        let (out_ch, inp, kernel) = w.dims;
        let width = kernel * inp;
        let dwt = TransposedLhs::chosen().product(dy, cols, (out_ch, width, rows));
        let dcols =
            input_grad.then(|| gemm_new((dy, false), (&w.taps, false), (rows, width, out_ch)));
        (dwt, dcols)
    }
}

/// `x` (batch × frames × channels) as frames × batch × channels, through a ReLU when `relu`.
fn time_major(x: &[f32], (batch, frames, channels): Dims3, relu: bool) -> Vec<f32> {
    let fill = |f: usize, block: &mut [MaybeUninit<f32>]| {
        for (b, dst) in block.chunks_exact_mut(channels).enumerate() {
            let src = &x[(b * frames + f) * channels..][..channels];
            for (d, &v) in dst.iter_mut().zip(src) {
                d.write(if relu { v.max(0.0) } else { v });
            }
        }
    };
    // SAFETY: block f is frame f's `batch` rows of `channels`, each written whole.
    unsafe { par_new(x.len(), batch * channels, fill) }
}

/// The time-major `v_t` (frames × batch × width) back to batch-major: `write(b, f, row, src)`
/// writes the row of sequence `b`, frame `f` from its time-major row `src`.
///
/// # Safety
/// `write` writes every value of the row it is given.
unsafe fn batch_major(
    v_t: &[f32],
    (batch, frames, width): Dims3,
    write: impl Fn(usize, usize, &mut [MaybeUninit<f32>], &[f32]) + Sync,
) -> Vec<f32> {
    let fill = |b: usize, vb: &mut [MaybeUninit<f32>]| {
        for (f, row) in vb.chunks_exact_mut(width).enumerate() {
            write(b, f, row, &v_t[(f * batch + b) * width..][..width]);
        }
    };
    // SAFETY: block b is sequence b's frames, each row written whole (the caller's contract).
    unsafe { par_new(v_t.len(), frames * width, fill) }
}

/// A stride-1 convolution as one product per tap over the time-major input: with frames
/// outermost, the output frames whose tap `k` reads inside the input are one contiguous block
/// of rows for the whole batch, and so are the input frames they read. So no im2col copy, and
/// no multiply-adds with padding: at 16 frames a dilation-9 tap reads padding for 9 of them
/// (the residual stacks' dilated convs spend 5% of a tokenizer step's FLOPs on zeros).
struct PerTap<'a> {
    w: &'a ConvWeights,
    geometry: ConvGeometry,
    batch: usize,
    /// Input frames.
    frames: usize,
    /// Output frames.
    out_frames: usize,
}

impl<'a> PerTap<'a> {
    fn new(op: &ConvCpu, w: &'a ConvWeights, (batch, frames): (usize, usize)) -> Self {
        Self {
            w,
            geometry: op.geometry,
            batch,
            frames,
            out_frames: op.geometry.out_len(frames),
        }
    }

    /// Per tap: the first output frame, the first input frame it reads and how many frames.
    fn spans(&self) -> Vec<(usize, usize, usize, usize)> {
        let g = &self.geometry;
        (0..g.kernel)
            .filter_map(|k| {
                let shift = (k * g.dilation) as isize - g.padding as isize;
                let t0 = (-shift).max(0) as usize;
                let t1 = (self.frames as isize - shift).clamp(0, self.out_frames as isize) as usize;
                (t1 > t0).then(|| (k, t0, (t0 as isize + shift) as usize, t1 - t0))
            })
            .collect()
    }

    /// The output (batch-major, with the bias) of the time-major input `x_t`.
    fn forward(&self, x_t: &[f32]) -> Vec<f32> {
        let (out, inp, _) = self.w.dims;
        let b = self.batch;
        let mut y_t = vec![0f32; self.out_frames * b * out];
        for (k, t0, s0, n) in self.spans() {
            gemm_strided(
                &mut y_t,
                (t0 * b * out, out),
                Strided::rows(x_t, s0 * b * inp, inp),
                Strided::rows(&self.w.taps_t, k * inp * out, out),
                (n * b, out, inp),
                true,
            );
        }
        // Back to batch-major, adding the bias on the way (as bias + product, the order of
        // the other paths' single add).
        let add_bias = |_, _, row: &mut [MaybeUninit<f32>], src: &[f32]| {
            row.iter_mut()
                .zip(src)
                .zip(&self.w.bias)
                .for_each(|((d, v), bias)| {
                    d.write(bias + v);
                });
        };
        // SAFETY: `out` values of the bias and of `src` for each of the row's `out` values.
        unsafe { batch_major(&y_t, (b, self.out_frames, out), add_bias) }
    }

    /// The weight gradient, taps-major, from the time-major output gradient `dy_t`, which the
    /// products read `way` (a copy transposed once for every tap, or in place).
    fn weight_grad(&self, dy_t: &[f32], x_t: &[f32], way: TransposedLhs) -> Vec<f32> {
        let (out, inp, kernel) = self.w.dims;
        let b = self.batch;
        // dW_k = dYᵀ · X over the tap's rows.
        let rows = self.out_frames * b;
        let dy_tt = match way {
            TransposedLhs::Copied => Some(transpose(dy_t, rows, out)),
            TransposedLhs::InPlace => None,
        };
        let dy_rows = |t0: usize| match &dy_tt {
            Some(dy_tt) => Strided::rows(dy_tt, t0 * b, rows),
            None => Strided::rows(dy_t, t0 * b * out, out).t(),
        };
        let mut dwt = vec![0f32; out * kernel * inp];
        for (k, t0, s0, n) in self.spans() {
            gemm_strided(
                &mut dwt,
                (k * inp, kernel * inp),
                dy_rows(t0),
                Strided::rows(x_t, s0 * b * inp, inp),
                (out, inp, n * b),
                false,
            );
        }
        dwt
    }

    /// The input gradient (batch-major, through the input ReLU's mask) from `dy_t`.
    fn input_grad(&self, dy_t: &[f32], x: &[f32]) -> Vec<f32> {
        let (out, inp, kernel) = self.w.dims;
        let b = self.batch;
        let mut dx_t = vec![0f32; self.frames * b * inp];
        for (k, t0, s0, n) in self.spans() {
            gemm_strided(
                &mut dx_t,
                (s0 * b * inp, inp),
                Strided::rows(dy_t, t0 * b * out, out),
                Strided::rows(&self.w.taps, k * inp, kernel * inp),
                (n * b, inp, out),
                true,
            );
        }
        let relu = self.geometry.relu_input;
        let mask = |bi: usize, f: usize, row: &mut [MaybeUninit<f32>], src: &[f32]| {
            let xs = &x[(bi * self.frames + f) * inp..][..inp];
            row.iter_mut().zip(src).zip(xs).for_each(|((d, &g), &v)| {
                d.write(if relu && v <= 0.0 { 0.0 } else { g });
            });
        };
        // SAFETY: `inp` values of `src` and of `x` for each of the row's `inp` values.
        unsafe { batch_major(&dx_t, (b, self.frames, inp), mask) }
    }
}

/// Nearest ×2 up-sampling then a k3 conv (stride 1, padding 1), T2M-GPT's decoder stage.
/// Output frame 2s reads input frames (s−1, s, s) through taps (0, 1, 2) and frame 2s+1 reads
/// (s, s, s+1): each phase is a k2 conv of the input itself, with the taps that read the same
/// frame summed into one, (W0, W1+W2) for even outputs and (W0+W1, W2) for odd ones. That is a
/// third fewer multiply-adds, and an im2col matrix of the input's length instead of twice it.
/// Both phases read the k3 im2col matrix of the input (taps s−1, s, s+1): the even phase its
/// first two taps, the odd phase its last two; their outputs interleave row by row.
struct Polyphase<'a> {
    w: &'a ConvWeights,
}

/// Per phase, the taps that read the same frame summed: (B0, B1+B2) for even outputs and
/// (B0+B1, B2) for odd ones, for every unit of three consecutive blocks of `block` values
/// (a tap-major weight row: blocks of `in`; its transpose: blocks of `in·out`).
fn phase_blocks(taps: &[f32], block: usize) -> [Vec<f32>; 2] {
    let mut even = Vec::with_capacity(taps.len() / 3 * 2);
    let mut odd = Vec::with_capacity(taps.len() / 3 * 2);
    for unit in taps.chunks_exact(3 * block) {
        let (b0, rest) = unit.split_at(block);
        let (b1, b2) = rest.split_at(block);
        even.extend_from_slice(b0);
        even.extend(b1.iter().zip(b2).map(|(a, b)| a + b));
        odd.extend(b0.iter().zip(b1).map(|(a, b)| a + b));
        odd.extend_from_slice(b2);
    }
    [even, odd]
}

impl<'a> Polyphase<'a> {
    fn new(w: &'a ConvWeights) -> Self {
        Self { w }
    }

    fn dims(&self) -> (usize, usize) {
        (self.w.dims.0, self.w.dims.1)
    }

    /// Input rows of the im2col matrix `cols` (`rows × 3·in`).
    fn rows(&self, cols: &[f32]) -> usize {
        cols.len() / (3 * self.dims().1)
    }

    /// `y` (2·rows × out, holding the bias) += both phases' products.
    fn forward(&self, y: &mut [f32], cols: &[f32]) {
        let (out, inp) = self.dims();
        let rows = self.rows(cols);
        let phases = phase_blocks(&self.w.taps_t, inp * out);
        for (phase, weights) in phases.iter().enumerate() {
            gemm_strided(
                y,
                (phase * out, 2 * out),
                Strided::rows(cols, phase * inp, 3 * inp),
                Strided::rows(weights, 0, out),
                (rows, out, 2 * inp),
                true,
            );
        }
    }

    /// The weight gradient (taps-major `out × 3·in`) for output gradient `dy`.
    fn weight_grad(&self, dy: &[f32], cols: &[f32]) -> Vec<f32> {
        let (out, inp) = self.dims();
        let rows = self.rows(cols);
        let grads = [0, 1].map(|phase| {
            let mut g = vec![0f32; out * 2 * inp];
            gemm_strided(
                &mut g,
                (0, 2 * inp),
                Strided::rows(dy, phase * out, 2 * out).t(),
                Strided::rows(cols, phase * inp, 3 * inp),
                (out, 2 * inp, rows),
                false,
            );
            g
        });
        let mut dwt = vec![0f32; out * 3 * inp];
        for (o, d) in dwt.chunks_exact_mut(3 * inp).enumerate() {
            let (even, odd) = (&grads[0][o * 2 * inp..], &grads[1][o * 2 * inp..]);
            for c in 0..inp {
                d[c] = even[c] + odd[c];
                d[inp + c] = even[inp + c] + odd[c];
                d[2 * inp + c] = even[inp + c] + odd[inp + c];
            }
        }
        dwt
    }

    /// The gradient of the im2col matrix (`rows × 3·in`) for output gradient `dy`.
    fn columns_grad(&self, dy: &[f32]) -> Vec<f32> {
        let (out, inp) = self.dims();
        let rows = dy.len() / (2 * out);
        let mut dcols = vec![0f32; rows * 3 * inp];
        let phases = phase_blocks(&self.w.taps, inp);
        for (phase, weights) in phases.iter().enumerate() {
            gemm_strided(
                &mut dcols,
                (phase * inp, 3 * inp),
                Strided::rows(dy, phase * out, 2 * out),
                Strided::rows(weights, 0, 2 * inp),
                (rows, 2 * inp, out),
                phase == 1,
            );
        }
        dcols
    }
}

/// The fused convolution as a candle op (see the module docs).
struct ConvOp(ConvCpu);

impl ConvOp {
    fn dims(x: &Layout, w: &Layout) -> Result<(Dims3, Dims3)> {
        let (b, t, c) = x.shape().dims3()?;
        let (o, i, k) = w.shape().dims3()?;
        if i != c {
            candle_core::bail!("conv op: input has {c} channels, weight expects {i}");
        }
        Ok(((b, t, c), (o, i, k)))
    }
}

/// Leaky ReLU in place.
fn leaky_relu(y: &mut [f32], slope: f32) {
    y.par_chunks_mut(4096).for_each(|chunk| {
        chunk
            .iter_mut()
            .for_each(|v| *v = if *v > 0.0 { *v } else { *v * slope })
    });
}

/// `dy` through the leaky ReLU whose outputs were `y` (same sign as its inputs).
fn leaky_relu_backward(dy: &mut [f32], y: &[f32], slope: f32) {
    dy.par_chunks_mut(4096)
        .zip(y.par_chunks(4096))
        .for_each(|(d, y)| {
            d.iter_mut()
                .zip(y)
                .for_each(|(d, &y)| *d = if y > 0.0 { *d } else { *d * slope })
        });
}

/// The bias gradient, column sums of `dy` (rows × width): per fixed chunk of rows in
/// parallel, then summed in order (a rayon `reduce` would add in a scheduling-dependent order).
fn bias_gradient(dy: &[f32], width: usize) -> Vec<f32> {
    let partial: Vec<Vec<f32>> = dy
        .par_chunks(width * ROWS_PER_TASK)
        .map(|chunk| {
            let mut s = vec![0f32; width];
            chunk
                .chunks_exact(width)
                .for_each(|r| s.iter_mut().zip(r).for_each(|(a, v)| *a += v));
            s
        })
        .collect();
    let mut sums = vec![0f32; width];
    for s in &partial {
        sums.iter_mut().zip(s).for_each(|(a, v)| *a += v);
    }
    sums
}

impl CustomOp3 for ConvOp {
    fn name(&self) -> &'static str {
        "conv1d-channels-last"
    }

    fn cpu_fwd(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        ws: &CpuStorage,
        wl: &Layout,
        bs: &CpuStorage,
        bl: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let g = &self.0.geometry;
        let ((batch, frames, _), dims) = Self::dims(xl, wl)?;
        if dims.2 != g.kernel {
            candle_core::bail!("conv op: weight has {} taps, geometry {}", dims.2, g.kernel);
        }
        let x = contiguous_f32(xs, xl, "input")?;
        let w = contiguous_f32(ws, wl, "weight")?;
        let bias = contiguous_f32(bs, bl, "bias")?;
        let y = self
            .0
            .forward(x, (batch, frames), &ConvWeights::new(w, bias, dims));
        let shape = Shape::from((batch, g.out_len(frames), dims.0));
        Ok((CpuStorage::F32(y), shape))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        bias: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let ((batch, frames, inp), dims) = Self::dims(x.layout(), w.layout())?;
        let weights = ConvWeights::new(&F32Values::of(w)?, &F32Values::of(bias)?, dims);
        let (xv, y, dy) = (F32Values::of(x)?, F32Values::of(res)?, F32Values::of(grad)?);
        // An input that no gradient reaches (the data under the first layer) gets none.
        let grads = self.0.backward(
            (&xv, Some(&y), None),
            (batch, frames),
            &weights,
            &dy,
            x.track_op(),
        );
        let device = x.device();
        let dx = grads
            .input
            .map(|dx| Tensor::from_vec(dx, (batch, frames, inp), device))
            .transpose()?;
        Ok((
            dx,
            Some(Tensor::from_vec(grads.weight, dims, device)?),
            Some(Tensor::from_vec(grads.bias, dims.0, device)?),
        ))
    }
}

/// Convolve `x` (batch, frames, in) with `weight` (out, in, kernel) and `bias` (out) under
/// geometry `g` → (batch, out_frames, out). f32 CPU tensors take the fused op; anything else
/// [`conv1d_reference`].
pub fn conv1d(x: &Tensor, weight: &Tensor, bias: &Tensor, g: ConvGeometry) -> Result<Tensor> {
    conv1d_fused(x, weight, bias, g, &ConvOutput::default())
}

/// [`conv1d`] computing only the output rows and activation `output` names; other devices
/// compose it of [`conv1d_reference`], candle's leaky ReLU and a mask.
pub fn conv1d_fused(
    x: &Tensor,
    weight: &Tensor,
    bias: &Tensor,
    geometry: ConvGeometry,
    output: &ConvOutput,
) -> Result<Tensor> {
    if x.device().is_cpu() && x.dtype() == DType::F32 {
        let op = ConvOp(ConvCpu {
            geometry,
            output: output.clone(),
        });
        return x.contiguous()?.apply_op3(weight, bias, op);
    }
    let mut y = conv1d_reference(x, weight, bias, geometry)?;
    if let Some(slope) = output.leaky_slope {
        y = candle_nn::ops::leaky_relu(&y, slope as f64)?;
    }
    match &output.valid {
        Some(valid) => y.broadcast_mul(&valid_mask(valid, y.dim(1)?, y.device())?),
        None => Ok(y),
    }
}

/// `(batch, frames, 1)`: ones at each sequence's first `valid[b]` frames, zeros after.
pub fn valid_mask(valid: &[usize], frames: usize, device: &candle_core::Device) -> Result<Tensor> {
    let values: Vec<f32> = valid
        .iter()
        .flat_map(|&n| (0..frames).map(move |t| if t < n { 1.0 } else { 0.0 }))
        .collect();
    Tensor::from_vec(values, (valid.len(), frames, 1), device)
}

/// The same convolution composed of candle ops with exact gradients on every device: pad,
/// one strided slice of the frames per tap, the taps side by side, one matmul.
///
/// Why not candle's `conv1d`: its backward passes the output gradient, transposed, as the
/// kernel of a convolution, and candle 0.11.1's CPU `conv1d` reads a non-contiguous kernel as
/// if it were contiguous, so its weight gradient is wrong for batches larger than one.
pub fn conv1d_reference(
    x: &Tensor,
    weight: &Tensor,
    bias: &Tensor,
    g: ConvGeometry,
) -> Result<Tensor> {
    let (batch, frames, channels) = x.dims3()?;
    let (out_ch, _, kernel) = weight.dims3()?;
    let mut h = x.clone();
    if g.relu_input {
        h = h.relu()?;
    }
    if g.upsample_input {
        h = h
            .unsqueeze(2)?
            .broadcast_as((batch, frames, 2, channels))?
            .reshape((batch, 2 * frames, channels))?;
    }
    let out = g.out_len(frames);
    // Extra zeros on the right so that every tap's slice of stride·out frames fits.
    let h = h.pad_with_zeros(1, g.padding, g.padding + g.stride - 1)?;
    let taps = (0..kernel)
        .map(|k| {
            let slice = h.narrow(1, k * g.dilation, g.stride * out)?;
            slice
                .reshape((batch, out, g.stride, channels))?
                .narrow(2, 0, 1)?
                .reshape((batch * out, channels))
        })
        .collect::<Result<Vec<_>>>()?;
    let cols = Tensor::cat(&taps, 1)?;
    let taps_major = weight
        .permute((0, 2, 1))?
        .reshape((out_ch, kernel * channels))?;
    cols.matmul(&taps_major.t()?)?
        .broadcast_add(bias)?
        .reshape((batch, out, out_ch))
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    }

    /// Central differences of `loss` at `values[i]` for a spread of indices `i`.
    fn numeric(values: &[f32], loss: &dyn Fn(&[f32]) -> f32) -> Vec<(usize, f32)> {
        let step = (values.len() / 40).max(1);
        (0..values.len())
            .step_by(step)
            .map(|i| {
                let (mut up, mut down) = (values.to_vec(), values.to_vec());
                up[i] += 1e-2;
                down[i] -= 1e-2;
                (i, (loss(&up) - loss(&down)) / 2e-2)
            })
            .collect()
    }

    /// candle's `conv1d` forward (correct for a contiguous kernel; its gradients are not
    /// used, see [`conv1d_reference`]).
    fn candle_conv1d(x: &Tensor, w: &Tensor, b: &Tensor, g: ConvGeometry) -> Tensor {
        let mut h = x.transpose(1, 2).unwrap();
        if g.relu_input {
            h = h.relu().unwrap();
        }
        if g.upsample_input {
            let frames = h.dim(2).unwrap();
            h = h.upsample_nearest1d(2 * frames).unwrap();
        }
        h.contiguous()
            .unwrap()
            .conv1d(w, g.padding, g.stride, g.dilation, 1)
            .unwrap()
            .broadcast_add(&b.reshape((1, (), 1)).unwrap())
            .unwrap()
            .transpose(1, 2)
            .unwrap()
    }

    /// The fused op's and the reference's forward values against candle's `conv1d`, and all
    /// three gradients of both against central differences.
    fn check(g: ConvGeometry, frames: usize, (inp, out): (usize, usize)) {
        check_op(conv1d, g, frames, (inp, out));
        check_op(conv1d_reference, g, frames, (inp, out));
    }

    type Conv = fn(&Tensor, &Tensor, &Tensor, ConvGeometry) -> Result<Tensor>;

    fn check_op(conv: Conv, g: ConvGeometry, frames: usize, (inp, out): (usize, usize)) {
        let dev = Device::Cpu;
        // Inputs kept 0.05 away from the ReLU kink, where differences would straddle it.
        let xv: Vec<f32> = Tensor::randn(0f32, 1.0, 3 * frames * inp, &dev)
            .unwrap()
            .to_vec1::<f32>()
            .unwrap()
            .into_iter()
            .map(|v| {
                if v.abs() < 0.05 {
                    v.signum() * 0.05 + v
                } else {
                    v
                }
            })
            .collect();
        let x = Var::from_vec(xv.clone(), (3, frames, inp), &dev).unwrap();
        let w = Var::randn(0f32, 0.3, (out, inp, g.kernel), &dev).unwrap();
        let b = Var::randn(0f32, 1.0, out, &dev).unwrap();
        let y = conv(&x, &w, &b, g).unwrap();
        let reference = candle_conv1d(&x, &w, &b, g);
        assert_eq!(y.dims(), reference.dims(), "{g:?}");
        assert!(max_diff(&y, &reference) < 1e-4, "{g:?}");
        // A loss that weights every output differently, so every gradient entry matters.
        let probe = Tensor::randn(0f32, 1.0, y.dims(), &dev).unwrap();
        let loss = |x: &Tensor, w: &Tensor, b: &Tensor| {
            (conv(x, w, b, g).unwrap() * &probe)
                .unwrap()
                .sum_all()
                .unwrap()
        };
        let grads = loss(&x, &w, &b).backward().unwrap();
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let scalar = |t: Tensor| t.to_scalar::<f32>().unwrap();
        let rebuild = |v: &[f32], like: &Tensor| Tensor::from_slice(v, like.dims(), &dev).unwrap();
        type Loss<'a> = Box<dyn Fn(&[f32]) -> f32 + 'a>;
        let checks: [(&str, &Var, Loss); 3] = [
            ("x", &x, Box::new(|v| scalar(loss(&rebuild(v, &x), &w, &b)))),
            ("w", &w, Box::new(|v| scalar(loss(&x, &rebuild(v, &w), &b)))),
            ("b", &b, Box::new(|v| scalar(loss(&x, &w, &rebuild(v, &b))))),
        ];
        for (name, var, f) in checks {
            let analytic = flat(grads.get(var).unwrap());
            for (i, expected) in numeric(&flat(var), f.as_ref()) {
                let tolerance = 2e-2 * expected.abs().max(1.0);
                assert!(
                    (analytic[i] - expected).abs() < tolerance,
                    "d/d{name}[{i}]: {} vs {expected} ({g:?})",
                    analytic[i]
                );
            }
        }
    }

    #[test]
    fn matches_candle_conv1d_for_every_t2m_gpt_layer_shape() {
        check(ConvGeometry::plain(3, 1, 1, 1), 16, (7, 5)); // input / output / post convs
        check(ConvGeometry::plain(4, 2, 1, 1), 16, (6, 6)); // stride-2 down-sampling
        check(ConvGeometry::plain(3, 1, 9, 9), 8, (4, 4)); // dilation 9, wider than the sequence
        check(ConvGeometry::plain(3, 1, 3, 3), 8, (4, 4));
        check(ConvGeometry::plain(1, 1, 1, 0), 8, (5, 3)); // pointwise, no im2col
    }

    #[test]
    fn fused_relu_and_upsampling_match_the_unfused_ops() {
        let relu = ConvGeometry {
            relu_input: true,
            ..ConvGeometry::plain(1, 1, 1, 0)
        };
        check(relu, 8, (5, 5));
        check(
            ConvGeometry {
                relu_input: true,
                ..ConvGeometry::plain(3, 1, 3, 3)
            },
            8,
            (4, 6),
        );
        let up = ConvGeometry {
            upsample_input: true,
            ..ConvGeometry::plain(3, 1, 1, 1)
        };
        check(up, 5, (4, 3));
    }

    /// `geometry`'s own path (polyphase, per-tap or Winograd) against the generic path (im2col, one
    /// gemm), which computing every frame as "valid" selects: outputs and all three gradients
    /// agree to rounding, across sequence boundaries.
    fn matches_the_generic_path(
        geometry: ConvGeometry,
        (batch, frames, inp, out): (usize, usize, usize, usize),
    ) {
        let mut rng = motionscale_core::rng::SplitMix64(9);
        let mut draw =
            |n: usize| -> Vec<f32> { (0..n).map(|_| rng.range(-1.0, 1.0) as f32).collect() };
        let k = geometry.kernel;
        let (x, w, b) = (draw(batch * frames * inp), draw(out * inp * k), draw(out));
        let out_frames = geometry.out_len(frames);
        let dy = draw(batch * out_frames * out);
        let weights = ConvWeights::new(&w, &b, (out, inp, k));
        let own = ConvCpu {
            geometry,
            output: ConvOutput::default(),
        };
        let generic = ConvCpu {
            geometry,
            output: ConvOutput {
                valid: Some(vec![out_frames; batch]),
                leaky_slope: None,
            },
        };
        assert!((own.polyphase() || own.per_tap()) && !generic.polyphase() && !generic.per_tap());
        let close = |a: &[f32], b: &[f32], what: &str| {
            assert_eq!(a.len(), b.len(), "{what}");
            let diff = a
                .iter()
                .zip(b)
                .map(|(a, b)| (a - b).abs())
                .fold(0f32, f32::max);
            assert!(diff < 1e-5, "{what} {geometry:?}: {diff}");
        };
        let dims = (batch, frames);
        let (y, cols) = own.forward_keeping_columns(&x, dims, &weights);
        close(&y, &generic.forward(&x, dims, &weights), "output");
        let ours = own.backward((&x, None, cols.as_deref()), dims, &weights, &dy, true);
        let theirs = generic.backward((&x, None, None), dims, &weights, &dy, true);
        close(&ours.weight, &theirs.weight, "weight gradient");
        close(&ours.bias, &theirs.bias, "bias gradient");
        close(
            &ours.input.unwrap(),
            &theirs.input.unwrap(),
            "input gradient",
        );
    }

    #[test]
    fn polyphase_upsampling_matches_the_upsampled_im2col() {
        let up = ConvGeometry {
            relu_input: true,
            upsample_input: true,
            ..ConvGeometry::plain(3, 1, 1, 1)
        };
        matches_the_generic_path(up, (3, 7, 16, 24));
    }

    /// Per-tap products over the time-major input, dilations whose taps read padding for some
    /// frames or (9 at 8 frames) for all of them, with and without the input ReLU.
    #[test]
    fn per_tap_products_match_the_im2col() {
        for (kernel, dilation, frames) in [(3, 1, 7), (3, 3, 16), (3, 9, 16), (3, 9, 8), (4, 1, 6)]
        {
            for relu_input in [false, true] {
                let padding = dilation * (kernel - 1) / 2;
                let g = ConvGeometry {
                    relu_input,
                    ..ConvGeometry::plain(kernel, 1, dilation, padding)
                };
                matches_the_generic_path(g, (3, frames, 16, 24));
            }
        }
    }

    /// The per-tap weight gradient reads the output gradient in place or through a transposed
    /// copy with the same bits (strided views of every tap's window).
    #[test]
    fn per_tap_weight_gradients_do_not_depend_on_how_dy_is_read() {
        let mut rng = motionscale_core::rng::SplitMix64(4);
        let mut draw =
            |n: usize| -> Vec<f32> { (0..n).map(|_| rng.range(-1.0, 1.0) as f32).collect() };
        for (dilation, frames) in [(1, 7), (3, 16), (9, 8)] {
            let g = ConvGeometry::plain(3, 1, dilation, dilation);
            let (batch, inp, out) = (3, 16, 24);
            let weights = ConvWeights::new(&draw(out * inp * 3), &draw(out), (out, inp, 3));
            let op = ConvCpu {
                geometry: g,
                output: ConvOutput::default(),
            };
            let per_tap = PerTap::new(&op, &weights, (batch, frames));
            let x_t = draw(frames * batch * inp);
            let dy_t = draw(g.out_len(frames) * batch * out);
            let [in_place, copied] = [TransposedLhs::InPlace, TransposedLhs::Copied]
                .map(|way| per_tap.weight_grad(&dy_t, &x_t, way));
            assert_eq!(
                crate::simd::bits(&in_place),
                crate::simd::bits(&copied),
                "{g:?}"
            );
        }
    }

    /// Winograd F(2,3) where it takes fewer products than one per tap: dilation 1 with and
    /// without a tile whose second output is past the end (9 and 8 frames), residue classes
    /// of unequal lengths (dilation 2 and 3), with and without the input ReLU; per tap where
    /// many taps read padding (dilation 9 over 16 frames, dilation 3 over 16).
    #[test]
    fn winograd_matches_the_im2col() {
        let weights = ConvWeights::new(&[0.0; 3 * 16 * 24], &[0.0; 24], (24, 16, 3));
        for (dilation, frames) in [(1, 8), (1, 9), (2, 13), (3, 32)] {
            for relu_input in [false, true] {
                let g = ConvGeometry {
                    relu_input,
                    ..ConvGeometry::plain(3, 1, dilation, dilation)
                };
                let op = ConvCpu {
                    geometry: g,
                    output: ConvOutput::default(),
                };
                assert!(op.winograd(&weights, (3, frames)).is_some(), "{g:?}");
                matches_the_generic_path(g, (3, frames, 16, 24));
            }
        }
        assert!(
            !Winograd::pays_off(16, 9) && !Winograd::pays_off(16, 3) && Winograd::pays_off(16, 1)
        );
    }

    /// The fused op computing only the first frames of each sequence, with a leaky ReLU,
    /// against the composed reference (convolution, candle's leaky ReLU, mask): outputs and
    /// all three gradients, in the strided and the pointwise (no im2col) paths.
    #[test]
    fn valid_rows_and_leaky_output_match_the_composed_ops() {
        let dev = Device::Cpu;
        for (g, frames, valid) in [
            (ConvGeometry::plain(4, 2, 1, 1), 12, vec![6, 2, 0, 4]),
            (ConvGeometry::plain(1, 1, 1, 0), 7, vec![7, 1, 3, 5]),
        ] {
            let output = ConvOutput {
                valid: Some(valid.clone()),
                leaky_slope: Some(0.2),
            };
            // Seeded, so no run meets an output within rounding of the ReLU's kink.
            let mut rng = motionscale_core::rng::SplitMix64(frames as u64);
            let mut normal = |shape: &[usize], scale: f64| {
                let n = shape.iter().product();
                let v: Vec<f32> = (0..n).map(|_| (rng.normal() * scale) as f32).collect();
                Var::from_vec(v, shape, &dev).unwrap()
            };
            let x = normal(&[4, frames, 5], 1.0);
            let w = normal(&[6, 5, g.kernel], 0.3);
            let b = normal(&[6], 1.0);
            let composed = |x: &Tensor, w: &Tensor, b: &Tensor| {
                let y = conv1d_reference(x, w, b, g).unwrap();
                let y = candle_nn::ops::leaky_relu(&y, 0.2).unwrap();
                let mask = valid_mask(&valid, y.dim(1).unwrap(), &dev).unwrap();
                y.broadcast_mul(&mask).unwrap()
            };
            let fused = conv1d_fused(&x, &w, &b, g, &output).unwrap();
            let reference = composed(&x, &w, &b);
            assert!(max_diff(&fused, &reference) < 1e-5, "{g:?}");
            let probe = normal(fused.dims(), 1.0).as_tensor().clone();
            let fused_grads = (fused * &probe)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            let reference_grads = (reference * &probe)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            for var in [&x, &w, &b] {
                let (a, e) = (
                    fused_grads.get(var).unwrap(),
                    reference_grads.get(var).unwrap(),
                );
                assert!(max_diff(a, e) < 1e-4, "{g:?}: {}", max_diff(a, e));
            }
        }
    }

    #[test]
    fn output_length_follows_pytorch() {
        assert_eq!(ConvGeometry::plain(4, 2, 1, 1).out_len(64), 32);
        assert_eq!(ConvGeometry::plain(3, 1, 9, 9).out_len(16), 16);
        assert_eq!(ConvGeometry::plain(3, 1, 1, 0).out_len(2), 0);
        let up = ConvGeometry {
            upsample_input: true,
            ..ConvGeometry::plain(3, 1, 1, 1)
        };
        assert_eq!(up.out_len(16), 32);
    }
}
