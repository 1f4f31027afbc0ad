#!/usr/bin/env bash
# Builds motionscale with `--features cuda` for CUDA 13.0 into target-cuda/release/motionscale.
#
# With a CUDA toolkit and driver installed, `cargo build --release --features cuda` is all it
# takes. This script is for a build machine without them (no GPU): it fetches nvcc, the headers
# and the link-time libraries (cuBLAS, cuRAND, NVRTC, the runtime) from PyPI into CUDA_DIR and
# links against a stand-in libcuda.so.1 whose every driver entry point reports "no device";
# on the GPU machine the driver's own libcuda.so.1 takes its place (scripts/cuda-check.sh).
#
#   CUDA_COMPUTE_CAP=90 CUDA_DIR=$HOME/.cache/motionscale/cuda13 bash scripts/build-cuda.sh
#   bash scripts/build-cuda.sh --check   # cargo check --workspace --all-targets --features cuda
#
# CUDA_COMPUTE_CAP: the GPU's compute capability (90: H100/H200); candle's kernels are built
# for it (nvidia-smi is not asked, there is none here).
set -euo pipefail
cd "$(dirname "$0")/.."
export CUDA_COMPUTE_CAP=${CUDA_COMPUTE_CAP:-90}
cuda=${CUDA_DIR:-$HOME/.cache/motionscale/cuda13}
if [ ! -x "$cuda/nvidia/cu13/bin/nvcc" ]; then
  pip install --quiet --no-deps --target "$cuda" nvidia-cuda-nvcc==13.0.88 nvidia-cuda-crt==13.0.88 \
    nvidia-nvvm==13.0.88 nvidia-cuda-runtime==13.0.96 nvidia-cuda-nvrtc==13.0.88 \
    nvidia-cublas==13.1.0.3 nvidia-curand==10.4.0.35 nvidia-cuda-cccl==13.0.85
fi
export CUDA_HOME=$cuda/nvidia/cu13 PATH=$cuda/nvidia/cu13/bin:$PATH
link=$cuda/link
mkdir -p "$link"
for n in cublas cublasLt cudart nvrtc; do ln -sf "$CUDA_HOME/lib/lib$n.so.13" "$link/lib$n.so"; done
ln -sf "$CUDA_HOME/lib/libcurand.so.10" "$link/libcurand.so"
if [ ! -f "$link/libcuda.so.1" ]; then
  # The stand-in: one function per driver entry point that cudarc binds.
  bindings=$(ls -d ~/.cargo/registry/src/*/cudarc-0.19.10/src/driver/sys/mod.rs | head -1)
  { echo 'typedef int CUresult;'
    echo 'CUresult cuGetErrorString(int e, const char **s) { if (s) *s = "no CUDA driver"; return 0; }'
    echo 'CUresult cuGetErrorName(int e, const char **s) { if (s) *s = "CUDA_ERROR_NO_DEVICE"; return 0; }'
    grep -oE '^\s+fn cu[A-Za-z0-9_]+\(' "$bindings" | sed 's/^\s*fn //;s/($//' | sort -u |
      grep -v -x -e cuGetErrorString -e cuGetErrorName |
      while read -r s; do echo "CUresult $s(void) { return 100; /* CUDA_ERROR_NO_DEVICE */ }"; done
  } > "$link/libcuda_stub.c"
  gcc -shared -fPIC -O1 -Wl,-soname,libcuda.so.1 -o "$link/libcuda.so.1" "$link/libcuda_stub.c"
  ln -sf libcuda.so.1 "$link/libcuda.so"
fi
target=${CARGO_TARGET_DIR:-target-cuda}
if [ "${1-}" = "--check" ]; then
  CARGO_TARGET_DIR=$target RUSTFLAGS="-L native=$link" \
    cargo check --release --workspace --all-targets --features cuda
  exit
fi
CARGO_TARGET_DIR=$target RUSTFLAGS="-L native=$link" \
  cargo build --release --features cuda --bin motionscale
echo "$target/release/motionscale (needs libcuda.so.1, libcublas.so.13, libcublasLt.so.13, libcurand.so.10, libcudart.so.13 at run time)"
