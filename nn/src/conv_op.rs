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
//! [`conv1d_fused`] can also compute only each sequence's first output frames ([`ConvOutput`]):
//! the rest are zero, as the mask after a padded batch's convolution makes them, but cost
//! nothing, which for a batch padded to its longest clip (the evaluator's) is ~40% of the
//! FLOPs. It can apply a leaky ReLU to the output in the same pass.

use crate::cpu_f32::{contiguous_f32, F32Values};
use crate::matmul::gemm_with;
use candle_core::{CpuStorage, CustomOp3, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;
use std::borrow::Cow;

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

/// The output rows an op computes: all `batch × out` of them in order, or each sequence's
/// first `valid[b]`, packed one after another.
struct Rows {
    batch: usize,
    out: usize,
    /// Packed row of each sequence's first frame, and the total at the end; `None`: all rows.
    starts: Option<Vec<usize>>,
}

impl Rows {
    fn new(batch: usize, out: usize, valid: Option<&[usize]>) -> Self {
        let starts = valid.map(|v| {
            let mut starts = vec![0];
            for &n in v {
                starts.push(starts[starts.len() - 1] + n.min(out));
            }
            starts
        });
        Self { batch, out, starts }
    }

    fn count(&self) -> usize {
        self.starts
            .as_ref()
            .map_or(self.batch * self.out, |s| s[self.batch])
    }

    /// Packed row of sequence `b`'s first frame, and how many frames it has.
    fn span(&self, b: usize) -> (usize, usize) {
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

    /// The packed rows of `padded` (`batch·out` rows of `width`).
    fn gather<'a>(&self, padded: &'a [f32], width: usize) -> Cow<'a, [f32]> {
        if self.starts.is_none() {
            return Cow::Borrowed(padded);
        }
        let mut packed = vec![0f32; self.count() * width];
        for b in 0..self.batch {
            let (start, n) = self.span(b);
            packed[start * width..][..n * width]
                .copy_from_slice(&padded[b * self.out * width..][..n * width]);
        }
        Cow::Owned(packed)
    }

    /// `packed` rows put back in their places among `batch·out` rows, zeros elsewhere.
    fn scatter(&self, packed: Vec<f32>, width: usize) -> Vec<f32> {
        if self.starts.is_none() {
            return packed;
        }
        let mut padded = vec![0f32; self.batch * self.out * width];
        for b in 0..self.batch {
            let (start, n) = self.span(b);
            padded[b * self.out * width..][..n * width]
                .copy_from_slice(&packed[start * width..][..n * width]);
        }
        padded
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
    let mut cols = vec![0f32; rows.count() * width];
    cols.par_chunks_mut(width * ROWS_PER_TASK)
        .enumerate()
        .for_each(|(task, chunk)| {
            for (i, row) in chunk.chunks_exact_mut(width).enumerate() {
                let (b, t) = rows.locate(task * ROWS_PER_TASK + i);
                for (k, dst) in row.chunks_exact_mut(channels).enumerate() {
                    if let Some(s) = g.source(t, k, frames) {
                        let src = &x[(b * frames + s) * channels..][..channels];
                        if g.relu_input {
                            dst.iter_mut().zip(src).for_each(|(d, &v)| *d = v.max(0.0));
                        } else {
                            dst.copy_from_slice(src);
                        }
                    }
                }
            }
        });
    cols
}

/// The adjoint of [`im2col`]: scatter-add column gradients back onto the input frames, then
/// apply the ReLU mask of `x` when the op read `relu(x)`.
fn col2im(
    dcols: &[f32],
    x: &[f32],
    (batch, frames, channels): (usize, usize, usize),
    g: &ConvGeometry,
    rows: &Rows,
) -> Vec<f32> {
    let width = g.kernel * channels;
    let mut dx = vec![0f32; batch * frames * channels];
    dx.par_chunks_mut(frames * channels)
        .enumerate()
        .for_each(|(b, dxb)| {
            let (start, n) = rows.span(b);
            for t in 0..n {
                let row = &dcols[(start + t) * width..][..width];
                for (k, src) in row.chunks_exact(channels).enumerate() {
                    if let Some(s) = g.source(t, k, frames) {
                        let dst = &mut dxb[s * channels..][..channels];
                        dst.iter_mut().zip(src).for_each(|(d, v)| *d += v);
                    }
                }
            }
            if g.relu_input {
                let xb = &x[b * frames * channels..][..frames * channels];
                dxb.iter_mut()
                    .zip(xb)
                    .for_each(|(d, &v)| *d = if v > 0.0 { *d } else { 0.0 });
            }
        });
    dx
}

/// `w (out, in, kernel)` as `(out, kernel·in)`, the tap-major order of the im2col columns.
fn taps_major(w: &[f32], (out, inp, kernel): (usize, usize, usize)) -> Vec<f32> {
    let mut t = vec![0f32; w.len()];
    for o in 0..out {
        for c in 0..inp {
            for k in 0..kernel {
                t[o * kernel * inp + k * inp + c] = w[(o * inp + c) * kernel + k];
            }
        }
    }
    t
}

/// The inverse of [`taps_major`].
fn channels_major(t: &[f32], (out, inp, kernel): (usize, usize, usize)) -> Vec<f32> {
    let mut w = vec![0f32; t.len()];
    for o in 0..out {
        for k in 0..kernel {
            for c in 0..inp {
                w[(o * inp + c) * kernel + k] = t[o * kernel * inp + k * inp + c];
            }
        }
    }
    w
}

/// (batch, frames, channels) of an input, or (out, in, kernel) of a weight.
type Dims3 = (usize, usize, usize);

/// The fused convolution (see the module docs).
struct ConvOp {
    geometry: ConvGeometry,
    output: ConvOutput,
}

impl ConvOp {
    fn dims(x: &Layout, w: &Layout) -> Result<(Dims3, Dims3)> {
        let (b, t, c) = x.shape().dims3()?;
        let (o, i, k) = w.shape().dims3()?;
        if i != c {
            candle_core::bail!("conv op: input has {c} channels, weight expects {i}");
        }
        Ok(((b, t, c), (o, i, k)))
    }

    fn rows(&self, batch: usize, frames: usize) -> Rows {
        Rows::new(
            batch,
            self.geometry.out_len(frames),
            self.output.valid.as_deref(),
        )
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
        let g = &self.geometry;
        let ((batch, frames, inp), (out_ch, _, kernel)) = Self::dims(xl, wl)?;
        if kernel != g.kernel {
            candle_core::bail!("conv op: weight has {kernel} taps, geometry {}", g.kernel);
        }
        let x = contiguous_f32(xs, xl, "input")?;
        let w = contiguous_f32(ws, wl, "weight")?;
        let bias = contiguous_f32(bs, bl, "bias")?;
        let rows = self.rows(batch, frames);
        let width = kernel * inp;
        let wt = taps_major(w, (out_ch, inp, kernel));
        let lhs = if g.is_pointwise() {
            rows.gather(x, inp)
        } else {
            Cow::Owned(im2col(x, (frames, inp), g, &rows))
        };
        let mut y = vec![0f32; rows.count() * out_ch];
        y.par_chunks_mut(out_ch * ROWS_PER_TASK).for_each(|chunk| {
            chunk
                .chunks_exact_mut(out_ch)
                .for_each(|r| r.copy_from_slice(bias))
        });
        gemm_with(
            &mut y,
            (&lhs, false),
            (&wt, true),
            (rows.count(), out_ch, width),
            (true, 1.0, true),
        );
        if let Some(slope) = self.output.leaky_slope {
            leaky_relu(&mut y, slope);
        }
        let y = rows.scatter(y, out_ch);
        let shape = Shape::from((batch, g.out_len(frames), out_ch));
        Ok((CpuStorage::F32(y), shape))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _bias: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let g = &self.geometry;
        let ((batch, frames, inp), (out_ch, _, kernel)) = Self::dims(x.layout(), w.layout())?;
        let rows = self.rows(batch, frames);
        let width = kernel * inp;
        let xv = F32Values::of(x)?;
        let wt = taps_major(&F32Values::of(w)?, (out_ch, inp, kernel));
        let dy_padded = F32Values::of(grad)?;
        let mut dy = rows.gather(&dy_padded, out_ch);
        if let Some(slope) = self.output.leaky_slope {
            let y = F32Values::of(res)?;
            leaky_relu_backward(dy.to_mut(), &rows.gather(&y, out_ch), slope);
        }
        let lhs = if g.is_pointwise() {
            rows.gather(&xv, inp)
        } else {
            Cow::Owned(im2col(&xv, (frames, inp), g, &rows))
        };
        // dW (out × kernel·in) = dYᵀ · cols.
        let mut dwt = vec![0f32; out_ch * width];
        gemm_with(
            &mut dwt,
            (&dy, true),
            (&lhs, false),
            (out_ch, width, rows.count()),
            (false, 1.0, true),
        );
        let dw = channels_major(&dwt, (out_ch, inp, kernel));
        let db = bias_gradient(&dy, out_ch);
        let device = x.device();
        // An input that no gradient reaches (the data under the first layer) gets none.
        let dx = if x.track_op() {
            // dcols (rows × kernel·in) = dY · Wt, then scattered back onto the input frames.
            let mut dcols = vec![0f32; rows.count() * width];
            gemm_with(
                &mut dcols,
                (&dy, false),
                (&wt, false),
                (rows.count(), width, out_ch),
                (false, 1.0, true),
            );
            let dx = if g.is_pointwise() {
                rows.scatter(dcols, inp)
            } else {
                col2im(&dcols, &xv, (batch, frames, inp), g, &rows)
            };
            Some(Tensor::from_vec(dx, (batch, frames, inp), device)?)
        } else {
            None
        };
        Ok((
            dx,
            Some(Tensor::from_vec(dw, (out_ch, inp, kernel), device)?),
            Some(Tensor::from_vec(db, out_ch, device)?),
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
        let op = ConvOp {
            geometry,
            output: output.clone(),
        };
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
