#!/usr/bin/env bash
# Where a bench's timed CPU time goes, by category (gemm microkernels, gemm packing, our
# kernels, memory, threads and the OS), to compare machine classes (#40):
#
#   scripts/profile-cpu.sh OUT [BENCH ARGS...]
#   (default: bench train --sizes 256x4 --no-generate --min-time 10; generation alone:
#   train --no-train)
#
# perf samples the cpu-clock (so it works in VMs without hardware counters) over the timed
# calls only: the bench enables and disables it through perf's control FIFOs. Writes
# OUT/bench.{txt,json} (figures and machine), OUT/report.txt (every symbol's share) and
# OUT/profile.{md,json} (the categories). Needs perf (Debian: linux-perf).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: scripts/profile-cpu.sh OUT [BENCH ARGS...]}
shift
args=("$@")
[ ${#args[@]} -gt 0 ] || args=(train --sizes 256x4 --no-generate --min-time 10)
command -v perf >/dev/null || { echo "perf not found (Debian: apt-get install linux-perf)" >&2; exit 1; }
mkdir -p "$out"
cargo build --release --quiet -p motionscale
fifos=$(mktemp -d)
trap 'rm -rf "$fifos"' EXIT
mkfifo "$fifos/ctl" "$fifos/ack"
exec {ctl}<>"$fifos/ctl" {ack}<>"$fifos/ack"
MOTIONSCALE_PERF_CTL=$fifos/ctl MOTIONSCALE_PERF_ACK=$fifos/ack \
  perf record -q -e cpu-clock -F 1999 -D -1 --control "fd:$ctl,$ack" -o "$out/perf.data" -- \
  target/release/motionscale bench "${args[@]}" --json "$out/bench.json" | tee "$out/bench.txt"
perf report -i "$out/perf.data" --stdio --no-children --sort dso,sym --percent-limit 0.05 \
  2>/dev/null > "$out/report.txt"
python3 scripts/profile_categories.py "$out/report.txt" "$out/profile.json" "$out/bench.json" | tee "$out/profile.md"
