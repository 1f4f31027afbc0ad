#!/usr/bin/env bash
# Sourced by scripts/cuda-check.sh and scripts/gpu-check.sh on the GPU machine: unpacks $BIN
# (a gzip-compressed binary is unpacked into $WORK), finds the CUDA libraries the binary links
# (the driver's libcuda.so.1; cuBLAS, cuRAND, NVRTC and the runtime, e.g. from a PyTorch
# install), sets LD_LIBRARY_PATH and checks with ldd. Needs BIN, WORK and OUT; returns 2 when a
# library stays unresolved.
cuda_env() {
# ---- 1. binary (gzip-compressed binaries are unpacked first)
BIN=${BIN:?set BIN to the cuda-built motionscale}
case "$BIN" in
  *.gz) gzip -dc "$BIN" > "$WORK/motionscale"; chmod +x "$WORK/motionscale"; BIN=$WORK/motionscale;;
esac
sha256sum "$BIN" 2>/dev/null | tee "$OUT/binary.sha256"

# ---- libraries: known places first, then ONE filesystem search for the rest (never */stubs/*)
LIBS="libcuda.so.1 libcudart.so.13 libcublas.so.13 libcublasLt.so.13 libcurand.so.10 libnvrtc.so.13"
KNOWN=(/usr/local/nvidia/lib64 /usr/local/nvidia/lib /usr/lib/x86_64-linux-gnu /usr/lib64 /lib/x86_64-linux-gnu
       /opt/torch/.venv/lib/python3*/site-packages/nvidia/cu13/lib /opt/torch/.venv/lib/python3*/site-packages/nvidia/*/lib
       /usr/local/cuda/lib64 /usr/local/cuda/targets/x86_64-linux/lib)
declare -A FOUND=()
for lib in $LIBS; do
  for d in "${KNOWN[@]}"; do if [ -f "$d/$lib" ]; then FOUND[$lib]=$d; break; fi; done
done
MISSING=""; for lib in $LIBS; do [ -n "${FOUND[$lib]-}" ] || MISSING="$MISSING $lib"; done
if [ -n "$MISSING" ]; then
  echo "searching / for:$MISSING"
  expr=(); for lib in $MISSING; do expr+=(-o -name "$lib"); done
  while read -r f; do
    b=$(basename "$f"); if [ -z "${FOUND[$b]-}" ] && [ -f "$f" ]; then FOUND[$b]=$(dirname "$f"); fi
  done < <(timeout 90 find / \( -path /proc -o -path /sys -o -path '*/stubs' -o -path '*/.debug' \) -prune \
             -o \( -false "${expr[@]}" \) -print 2>/dev/null)
fi
LIBDIRS=()
for lib in $LIBS; do
  d=${FOUND[$lib]-}
  echo "lib $lib -> ${d:-NOT FOUND}"
  if [ -n "$d" ]; then
    case " ${LIBDIRS[*]-} " in *" $d "*) ;; *) LIBDIRS+=("$d");; esac
  fi
done
LD=$(IFS=:; echo "${LIBDIRS[*]-}")
export LD_LIBRARY_PATH=$LD${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
echo "LD_LIBRARY_PATH=$LD_LIBRARY_PATH"
echo "== ldd"; ldd "$BIN" > "$OUT/ldd.txt" 2>&1; cat "$OUT/ldd.txt"
if grep -q -i 'not found\|error' "$OUT/ldd.txt"; then echo "FATAL: unresolved libraries"; return 2; fi
}
