// The GPU side of `nn::fused_ops`: each kernel computes what its op's CPU side computes (see
// `fused_ops.rs`), in f32. Built to PTX by `build.rs` with --fmad=false, so that no multiply
// and add is contracted that the CPU side rounds twice (AdamW's arithmetic is PyTorch's).

#define FULL_MASK 0xffffffffu

__device__ __forceinline__ float warp_sum(float v) {
  for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(FULL_MASK, v, o);
  return v;
}

__device__ __forceinline__ float warp_max(float v) {
  for (int o = 16; o > 0; o >>= 1) v = fmaxf(v, __shfl_xor_sync(FULL_MASK, v, o));
  return v;
}

// The sum over the block (blockDim.x a multiple of 32), returned to every thread.
__device__ float block_sum(float v, float* shared) {
  v = warp_sum(v);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, warps = blockDim.x >> 5;
  __syncthreads();  // `shared` may still be read by a previous reduction
  if (lane == 0) shared[warp] = v;
  __syncthreads();
  return warp_sum(lane < warps ? shared[lane] : 0.f);
}

// The maximum over the block, returned to every thread.
__device__ float block_max(float v, float* shared) {
  v = warp_max(v);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, warps = blockDim.x >> 5;
  __syncthreads();
  if (lane == 0) shared[warp] = v;
  __syncthreads();
  return warp_max(lane < warps ? shared[lane] : -INFINITY);
}

// ---- RMSNorm: one block per row.

__device__ float row_rstd(const float* x, int d, float eps, float* shared) {
  float s = 0.f;
  for (int i = threadIdx.x; i < d; i += blockDim.x) s += x[i] * x[i];
  return 1.f / sqrtf(block_sum(s, shared) / d + eps);
}

extern "C" __global__ void rms_norm_fwd(const float* x, const float* w, float* y, int d,
                                        float eps) {
  __shared__ float shared[32];
  const float* xr = x + (size_t)blockIdx.x * d;
  float* yr = y + (size_t)blockIdx.x * d;
  const float r = row_rstd(xr, d, eps, shared);
  for (int i = threadIdx.x; i < d; i += blockDim.x) yr[i] = xr[i] * r * w[i];
}

// dx = r·g·w − x·r³·(g·w·x)/d into `dx`; the per-row terms of dw, g·x·r, into `gw`.
extern "C" __global__ void rms_norm_bwd(const float* x, const float* w, const float* g, float* dx,
                                        float* gw, int d, float eps) {
  __shared__ float shared[32];
  const size_t at = (size_t)blockIdx.x * d;
  const float r = row_rstd(x + at, d, eps, shared);
  float t = 0.f;
  for (int i = threadIdx.x; i < d; i += blockDim.x) t += g[at + i] * w[i] * x[at + i];
  const float c = r * r * r * block_sum(t, shared) / d;
  for (int i = threadIdx.x; i < d; i += blockDim.x) {
    dx[at + i] = r * (g[at + i] * w[i]) - c * x[at + i];
    gw[at + i] = g[at + i] * x[at + i] * r;
  }
}

// Column sums of rows [y·chunk, (y+1)·chunk) of a rows × d matrix into row y of `out`, in row
// order (deterministic). Launched twice: row chunks into partial sums, then the partial sums.
extern "C" __global__ void column_sums(const float* x, float* out, int rows, int d, int chunk) {
  const int col = blockIdx.x * blockDim.x + threadIdx.x;
  if (col >= d) return;
  const int from = blockIdx.y * chunk, to = min(rows, from + chunk);
  float s = 0.f;
  for (int r = from; r < to; ++r) s += x[(size_t)r * d + col];
  out[(size_t)blockIdx.y * d + col] = s;
}

// ---- SwiGLU of rows [a | b] (each 2f wide): silu(a)·b, and its backward.

extern "C" __global__ void swiglu_fwd(const float* ab, float* y, size_t n, int f) {
  const size_t at = (size_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (at >= n) return;
  const size_t row = at / f, i = at % f;
  const float a = ab[row * 2 * f + i], b = ab[row * 2 * f + f + i];
  const float s = 1.f / (1.f + expf(-a));
  y[at] = a * s * b;
}

extern "C" __global__ void swiglu_bwd(const float* ab, const float* g, float* dab, size_t n,
                                      int f) {
  const size_t at = (size_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (at >= n) return;
  const size_t row = at / f, i = at % f;
  const float a = ab[row * 2 * f + i], b = ab[row * 2 * f + f + i];
  const float s = 1.f / (1.f + expf(-a));
  dab[row * 2 * f + i] = g[at] * b * s * (1.f + a * (1.f - s));
  dab[row * 2 * f + f + i] = g[at] * a * s;
}

// ---- QKV rows (rows × 3·heads·hd, rows = batch·slots) to rotated queries, rotated keys and
// values in the attention grid (3, batch, heads, slots, hd); rotate-half by each row's cos,
// sin (rows × hd/2). The backward is the inverse map: sign = -1 rotates back.

extern "C" __global__ void qkv_heads(const float* src, const float* cos, const float* sin,
                                     float* dst, int batch, int slots, int heads, int half,
                                     float sign, int backward) {
  const size_t n = (size_t)3 * batch * slots * heads * half;
  const size_t at = (size_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (at >= n) return;
  const int i = at % half;
  size_t rest = at / half;
  const int h = rest % heads;
  rest /= heads;
  const int s = rest % slots;
  rest /= slots;
  const int b = rest % batch, part = rest / batch;
  const int hd = 2 * half, d = heads * hd;
  const size_t row = (size_t)b * slots + s;
  const size_t rows_at = row * 3 * d + (size_t)part * d + (size_t)h * hd + i;
  const size_t grid_at = ((((size_t)part * batch + b) * heads + h) * slots + s) * hd + i;
  const float* x = backward ? src + grid_at : src + rows_at;
  float* y = backward ? dst + rows_at : dst + grid_at;
  const float x1 = x[0], x2 = x[half];
  if (part == 2) {
    y[0] = x1;
    y[half] = x2;
    return;
  }
  const float c = cos[row * half + i], sn = sign * sin[row * half + i];
  y[0] = x1 * c - x2 * sn;
  y[half] = x2 * c + x1 * sn;
}

// ---- Masked softmax of attention scores (batch, heads, queries, keys), one warp per row:
// softmax(scale·s + mask), mask 0 where the prefix-LM layout allows the key, else -1e9 (the
// graph executor's additive mask). Query q sits at slot q_offset + q.

__device__ __forceinline__ bool key_allowed(int prefix_slots, int prefix_len, int i, int j) {
  return j < prefix_slots ? j < prefix_len : (i >= prefix_slots && j <= i);
}

extern "C" __global__ void masked_softmax_fwd(const float* scores, const unsigned* prefix_lens,
                                              float* probs, int rows, int heads, int queries,
                                              int keys, int prefix_slots, int q_offset,
                                              float scale) {
  const int row = blockIdx.x * (blockDim.x >> 5) + (threadIdx.x >> 5), lane = threadIdx.x & 31;
  if (row >= rows) return;
  const int q = row % queries, b = row / (queries * heads);
  const int i = q_offset + q, plen = prefix_lens[b];
  const float* s = scores + (size_t)row * keys;
  float* p = probs + (size_t)row * keys;
  float m = -INFINITY;
  for (int j = lane; j < keys; j += 32) {
    const float v = s[j] * scale + (key_allowed(prefix_slots, plen, i, j) ? 0.f : -1e9f);
    p[j] = v;
    m = fmaxf(m, v);
  }
  m = warp_max(m);
  float sum = 0.f;
  for (int j = lane; j < keys; j += 32) {
    const float e = expf(p[j] - m);
    p[j] = e;
    sum += e;
  }
  const float inv = 1.f / warp_sum(sum);
  for (int j = lane; j < keys; j += 32) p[j] *= inv;
}

// d scores = scale · p ⊙ (dp − Σ p·dp), one warp per row.
extern "C" __global__ void masked_softmax_bwd(const float* probs, const float* dprobs,
                                              float* dscores, int rows, int keys, float scale) {
  const int row = blockIdx.x * (blockDim.x >> 5) + (threadIdx.x >> 5), lane = threadIdx.x & 31;
  if (row >= rows) return;
  const size_t at = (size_t)row * keys;
  float dot = 0.f;
  for (int j = lane; j < keys; j += 32) dot += probs[at + j] * dprobs[at + j];
  dot = warp_sum(dot);
  for (int j = lane; j < keys; j += 32)
    dscores[at + j] = scale * probs[at + j] * (dprobs[at + j] - dot);
}

// ---- Cross-entropy of logit rows (rows × vocab) at their targets, weighted per row: one
// block per row. Forward: weight · (log Σ exp − logit[target]); backward: grad_weight ·
// (softmax − onehot). A row of weight 0 costs nothing and gets a zero gradient.

__device__ float row_log_sum_exp(const float* x, int n, float* shared) {
  float m = -INFINITY;
  for (int j = threadIdx.x; j < n; j += blockDim.x) m = fmaxf(m, x[j]);
  m = block_max(m, shared);
  float s = 0.f;
  for (int j = threadIdx.x; j < n; j += blockDim.x) s += expf(x[j] - m);
  return m + logf(block_sum(s, shared));
}

extern "C" __global__ void cross_entropy_fwd(const float* logits, const unsigned* targets,
                                             const float* weight, float* loss, int vocab) {
  __shared__ float shared[32];
  const int row = blockIdx.x;
  if (weight[row] == 0.f) {
    if (threadIdx.x == 0) loss[row] = 0.f;
    return;
  }
  const float* x = logits + (size_t)row * vocab;
  const float lse = row_log_sum_exp(x, vocab, shared);
  if (threadIdx.x == 0) loss[row] = weight[row] * (lse - x[targets[row]]);
}

extern "C" __global__ void cross_entropy_bwd(const float* logits, const unsigned* targets,
                                             const float* grad_weight, float* dlogits,
                                             int vocab) {
  __shared__ float shared[32];
  const int row = blockIdx.x;
  const float gw = grad_weight[row];
  const float* x = logits + (size_t)row * vocab;
  float* dx = dlogits + (size_t)row * vocab;
  if (gw == 0.f) {
    for (int j = threadIdx.x; j < vocab; j += blockDim.x) dx[j] = 0.f;
    return;
  }
  const float lse = row_log_sum_exp(x, vocab, shared);
  const unsigned t = targets[row];
  for (int j = threadIdx.x; j < vocab; j += blockDim.x)
    dx[j] = gw * (expf(x[j] - lse) - (j == t ? 1.f : 0.f));
}

// ---- One AdamW step over a parameter in place, PyTorch's arithmetic (as StepValues::chunk).

extern "C" __global__ void adamw_step(float* p, const float* g, float* m, float* v, size_t n,
                                      float scale, float beta1, float beta2, float eps,
                                      float step_size, float bias2_sqrt, float decay) {
  const size_t at = (size_t)blockIdx.x * blockDim.x + threadIdx.x;
  if (at >= n) return;
  const float gs = g[at] * scale;
  const float mi = beta1 * m[at] + (1.f - beta1) * gs;
  const float vi = beta2 * v[at] + (1.f - beta2) * gs * gs;
  m[at] = mi;
  v[at] = vi;
  const float denom = sqrtf(vi) / bias2_sqrt + eps;
  p[at] = p[at] * decay - step_size * mi / denom;
}

// Sums of squares of `n` values, one partial per block (grid-stride; the gradient norm's first
// stage; the second runs it again over the partials with one block). Deterministic.
extern "C" __global__ void square_sums(const float* x, float* partial, size_t n, int square) {
  __shared__ float shared[32];
  float s = 0.f;
  for (size_t at = (size_t)blockIdx.x * blockDim.x + threadIdx.x; at < n;
       at += (size_t)gridDim.x * blockDim.x)
    s += square ? x[at] * x[at] : x[at];
  s = block_sum(s, shared);
  if (threadIdx.x == 0) partial[blockIdx.x] = s;
}
