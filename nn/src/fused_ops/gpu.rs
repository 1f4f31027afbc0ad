//! The GPU side of the fused ops: launches of the kernels in `kernels/fused_ops.cu`, whose PTX
//! `build.rs` compiles; the module is loaded once per device by candle.

use super::{rows_cols, PrefixMask, QkvDims};
use candle_core::cuda::cudarc::driver::{CudaSlice, CudaView, LaunchConfig, PushKernelArg};
use candle_core::cuda::{CudaDType, WrapErr};
use candle_core::{CudaDevice, CudaStorage, Layout, Result};

const PTX: &str = include_str!(concat!(env!("OUT_DIR"), "/fused_ops.ptx"));
const MODULE: &str = "motionscale_fused_ops";
/// Threads per block of the row and element-wise kernels.
const THREADS: u32 = 256;

/// Launch kernel `$name` of the module with `$cfg` and the argument references in order.
macro_rules! launch {
    ($dev:expr, $name:expr, $cfg:expr; $($arg:expr),* $(,)?) => {{
        let func = $dev.get_or_load_custom_func($name, MODULE, PTX)?;
        let mut builder = func.builder();
        $(builder.arg($arg);)*
        // SAFETY: the arguments are those of the kernel's signature in fused_ops.cu, in order,
        // and every buffer holds the elements the kernel indexes.
        unsafe { builder.launch($cfg) }.w()?;
    }};
}

fn view<'a, T: CudaDType>(s: &'a CudaStorage, l: &Layout, what: &str) -> Result<CudaView<'a, T>> {
    let (start, end) = l
        .contiguous_offsets()
        .ok_or_else(|| candle_core::Error::Msg(format!("fused op: {what} must be contiguous")))?;
    Ok(s.as_cuda_slice::<T>()?.slice(start..end))
}

fn zeros(dev: &CudaDevice, n: usize) -> Result<CudaSlice<f32>> {
    dev.alloc_zeros::<f32>(n)
}

fn storage(slice: CudaSlice<f32>, dev: &CudaDevice) -> CudaStorage {
    CudaStorage::wrap_cuda_slice(slice, dev.clone())
}

/// One block of [`THREADS`] per row.
fn per_row(rows: usize) -> LaunchConfig {
    LaunchConfig {
        grid_dim: (rows as u32, 1, 1),
        block_dim: (THREADS, 1, 1),
        shared_mem_bytes: 0,
    }
}

/// One thread per element.
fn per_element(n: usize) -> LaunchConfig {
    LaunchConfig::for_num_elems(n as u32)
}

pub(super) fn rms_norm(
    x: &CudaStorage,
    lx: &Layout,
    w: &CudaStorage,
    lw: &Layout,
    eps: f32,
) -> Result<CudaStorage> {
    let dev = &x.device;
    let (rows, d) = rows_cols(lx);
    let (xv, wv) = (view::<f32>(x, lx, "x")?, view::<f32>(w, lw, "w")?);
    let mut y = zeros(dev, rows * d)?;
    let d32 = d as i32;
    launch!(dev, "rms_norm_fwd", per_row(rows); &xv, &wv, &mut y, &d32, &eps);
    Ok(storage(y, dev))
}

/// `(rows + 1) × d`: the gradient of `x`, then that of `w` as deterministic column sums
/// (row chunks of [`SUM_CHUNK`], then the chunks).
pub(super) fn rms_norm_grad(
    s: [&CudaStorage; 3],
    l: [&Layout; 3],
    eps: f32,
) -> Result<CudaStorage> {
    const SUM_CHUNK: usize = 64;
    let dev = &s[0].device;
    let (rows, d) = rows_cols(l[0]);
    let (x, w) = (view::<f32>(s[0], l[0], "x")?, view::<f32>(s[1], l[1], "w")?);
    let g = view::<f32>(s[2], l[2], "gradient")?;
    let mut out = zeros(dev, (rows + 1) * d)?;
    let mut per_row_gw = zeros(dev, rows * d)?;
    let chunks = rows.div_ceil(SUM_CHUNK).max(1);
    let mut partial = zeros(dev, chunks * d)?;
    let (d32, rows32, chunk32, chunks32) = (d as i32, rows as i32, SUM_CHUNK as i32, chunks as i32);
    {
        let mut dx = out.slice_mut(0..rows * d);
        launch!(dev, "rms_norm_bwd", per_row(rows); &x, &w, &g, &mut dx, &mut per_row_gw, &d32, &eps);
    }
    let columns = |y: usize| LaunchConfig {
        grid_dim: (d.div_ceil(THREADS as usize) as u32, y as u32, 1),
        block_dim: (THREADS, 1, 1),
        shared_mem_bytes: 0,
    };
    launch!(dev, "column_sums", columns(chunks); &per_row_gw, &mut partial, &rows32, &d32, &chunk32);
    let mut gw = out.slice_mut(rows * d..);
    launch!(dev, "column_sums", columns(1); &partial, &mut gw, &chunks32, &d32, &chunks32);
    Ok(storage(out, dev))
}

/// SwiGLU of `[a | b]` rows, or (with the output gradient) its backward.
pub(super) fn swiglu(
    ab: &CudaStorage,
    l: &Layout,
    grad: Option<(&CudaStorage, &Layout)>,
) -> Result<CudaStorage> {
    let dev = &ab.device;
    let (rows, cols) = rows_cols(l);
    let (n, f) = (rows * cols / 2, (cols / 2) as i32);
    let abv = view::<f32>(ab, l, "ab")?;
    match grad {
        None => {
            let mut y = zeros(dev, n)?;
            launch!(dev, "swiglu_fwd", per_element(n); &abv, &mut y, &n, &f);
            Ok(storage(y, dev))
        }
        Some((g, lg)) => {
            let gv = view::<f32>(g, lg, "gradient")?;
            let mut dab = zeros(dev, 2 * n)?;
            launch!(dev, "swiglu_bwd", per_element(n); &abv, &gv, &mut dab, &n, &f);
            Ok(storage(dab, dev))
        }
    }
}

pub(super) fn qkv_heads(
    s: [&CudaStorage; 3],
    l: [&Layout; 3],
    q: &QkvDims,
    backward: bool,
) -> Result<CudaStorage> {
    let dev = &s[0].device;
    let src = view::<f32>(s[0], l[0], "qkv")?;
    let (cos, sin) = (
        view::<f32>(s[1], l[1], "cos")?,
        view::<f32>(s[2], l[2], "sin")?,
    );
    let n = 3 * q.batch * q.slots * q.heads * q.half;
    let mut dst = zeros(dev, 2 * n)?;
    let (batch, slots, heads, half) = (
        q.batch as i32,
        q.slots as i32,
        q.heads as i32,
        q.half as i32,
    );
    let (sign, back) = if backward {
        (-1f32, 1i32)
    } else {
        (1f32, 0i32)
    };
    launch!(dev, "qkv_heads", per_element(n); &src, &cos, &sin, &mut dst, &batch, &slots, &heads, &half, &sign, &back);
    Ok(storage(dst, dev))
}

pub(super) fn masked_softmax(
    scores: &CudaStorage,
    l: &Layout,
    lens: &CudaStorage,
    ll: &Layout,
    mask: PrefixMask,
) -> Result<CudaStorage> {
    let dev = &scores.device;
    let (_, heads, queries, keys) = l.shape().dims4()?;
    let rows = l.shape().elem_count() / keys;
    let (sv, lv) = (
        view::<f32>(scores, l, "scores")?,
        view::<u32>(lens, ll, "prefix lengths")?,
    );
    let mut probs = zeros(dev, rows * keys)?;
    let dims = [
        rows,
        heads,
        queries,
        keys,
        mask.prefix_slots,
        mask.first_query,
    ]
    .map(|v| v as i32);
    let [rows32, heads32, queries32, keys32, prefix32, first32] = dims;
    launch!(dev, "masked_softmax_fwd", per_warp(rows);
        &sv, &lv, &mut probs, &rows32, &heads32, &queries32, &keys32, &prefix32, &first32, &mask.scale);
    Ok(storage(probs, dev))
}

/// One warp per row, [`THREADS`] / 32 rows a block.
fn per_warp(rows: usize) -> LaunchConfig {
    let per_block = (THREADS / 32) as usize;
    LaunchConfig {
        grid_dim: (rows.div_ceil(per_block) as u32, 1, 1),
        block_dim: (THREADS, 1, 1),
        shared_mem_bytes: 0,
    }
}

pub(super) fn softmax_grad(
    p: &CudaStorage,
    lp: &Layout,
    dp: &CudaStorage,
    ldp: &Layout,
    scale: f32,
) -> Result<CudaStorage> {
    let dev = &p.device;
    let (rows, keys) = rows_cols(lp);
    let (pv, dpv) = (
        view::<f32>(p, lp, "probs")?,
        view::<f32>(dp, ldp, "gradient")?,
    );
    let mut ds = zeros(dev, rows * keys)?;
    let (rows32, keys32) = (rows as i32, keys as i32);
    launch!(dev, "masked_softmax_bwd", per_warp(rows); &pv, &dpv, &mut ds, &rows32, &keys32, &scale);
    Ok(storage(ds, dev))
}

/// The weighted cross-entropy per row, or (`backward`, the third operand then the weight
/// times the loss gradient) the gradient of the logits.
pub(super) fn cross_entropy(
    s: [&CudaStorage; 3],
    l: [&Layout; 3],
    backward: bool,
) -> Result<CudaStorage> {
    let dev = &s[0].device;
    let (rows, vocab) = rows_cols(l[0]);
    let logits = view::<f32>(s[0], l[0], "logits")?;
    let (targets, weight) = (
        view::<u32>(s[1], l[1], "targets")?,
        view::<f32>(s[2], l[2], "weight")?,
    );
    let vocab32 = vocab as i32;
    if backward {
        let mut dl = zeros(dev, rows * vocab)?;
        launch!(dev, "cross_entropy_bwd", per_row(rows); &logits, &targets, &weight, &mut dl, &vocab32);
        return Ok(storage(dl, dev));
    }
    let mut loss = zeros(dev, rows)?;
    launch!(dev, "cross_entropy_fwd", per_row(rows); &logits, &targets, &weight, &mut loss, &vocab32);
    Ok(storage(loss, dev))
}

/// One AdamW step in place: parameter `p`, gradient `g`, moments `mv` (`2 × n`: m then v),
/// with `[scale, beta1, beta2, eps, step size, √bias2, decay]` (`optim::StepValues`). `mv` is
/// written through a shared borrow: the optimiser alone holds that tensor.
pub(crate) fn adamw_step(
    p: &mut CudaStorage,
    lp: &Layout,
    (g, lg): (&CudaStorage, &Layout),
    (mv, lmv): (&CudaStorage, &Layout),
    values: [f32; 7],
) -> Result<()> {
    let dev = p.device.clone();
    let n = lp.shape().elem_count();
    let (start, _) = lp
        .contiguous_offsets()
        .ok_or_else(|| candle_core::Error::Msg("adamw: parameter not contiguous".into()))?;
    let gv = view::<f32>(g, lg, "gradient")?;
    let moments = view::<f32>(mv, lmv, "moments")?;
    let (m, v) = (moments.slice(0..n), moments.slice(n..2 * n));
    let mut pv = p.as_cuda_slice_mut::<f32>()?.slice_mut(start..start + n);
    let [scale, b1, b2, eps, step_size, bias2_sqrt, decay] = values;
    launch!(dev, "adamw_step", per_element(n);
        &mut pv, &gv, &m, &v, &n, &scale, &b1, &b2, &eps, &step_size, &bias2_sqrt, &decay);
    Ok(())
}

/// Σ x² of a contiguous f32 tensor: block partials, then their sum (one value).
pub(crate) fn sum_of_squares(x: &CudaStorage, l: &Layout) -> Result<CudaStorage> {
    const BLOCKS: usize = 512;
    let dev = &x.device;
    let n = l.shape().elem_count();
    let xv = view::<f32>(x, l, "x")?;
    let mut partial = zeros(dev, BLOCKS)?;
    let mut total = zeros(dev, 1)?;
    let (square, plain, blocks) = (1i32, 0i32, BLOCKS);
    let grid = |blocks: usize| LaunchConfig {
        grid_dim: (blocks as u32, 1, 1),
        block_dim: (THREADS, 1, 1),
        shared_mem_bytes: 0,
    };
    launch!(dev, "square_sums", grid(BLOCKS); &xv, &mut partial, &n, &square);
    launch!(dev, "square_sums", grid(1); &partial, &mut total, &blocks, &plain);
    Ok(storage(total, dev))
}
