#!/usr/bin/env bash
# Smoke test for the local cluster from scripts/slurm-setup.sh: a throttled 3-task job array
# plus a job that depends on it (afterok) and concatenates what the tasks wrote.
# There is no slurmdbd, so sacct is unavailable: completion is polled with squeue and the
# final states are read from `scontrol show job` (kept for MinJobAge after the jobs end).
set -euo pipefail
TIMEOUT=${SLURM_SMOKE_TIMEOUT:-120}

die() { echo "slurm-smoke: FAIL: $*" >&2; exit 1; }
# "COMPLETED x3" style summary of the states of a job (all tasks of an array job).
job_states() {
  scontrol -o show job "$1" | grep -o 'JobState=[A-Z_]*' | cut -d= -f2 | sort | uniq -c \
    | awk '{printf "%s%s x%s", (NR > 1 ? ", " : ""), $2, $1}'
}

sinfo -h >/dev/null 2>&1 || die "no Slurm controller answers; run scripts/slurm-setup.sh first"
dir=$(mktemp -d -t slurm-smoke.XXXXXX)
array='' dep=''
# On failure, cancel what is still queued (so a rerun does not wait behind it) and keep the
# logs for inspection; on success, remove them.
cleanup() {
  local rc=$?
  if ((rc != 0)); then
    [[ -n $array ]] && scancel "$array" ${dep:+"$dep"} 2>/dev/null
  else
    rm -rf "$dir"
  fi
  exit "$rc"
}
trap cleanup EXIT

# Single quotes: the variable must expand inside the job, not here.
# shellcheck disable=SC2016
array=$(sbatch --parsable --job-name=smoke-array --array=0-2%2 --chdir="$dir" \
  --output="$dir/array-%A_%a.log" --wrap='echo "$SLURM_ARRAY_TASK_ID" > "task-$SLURM_ARRAY_TASK_ID.txt"')
dep=$(sbatch --parsable --job-name=smoke-concat --dependency="afterok:$array" --chdir="$dir" \
  --output="$dir/concat.log" --wrap='cat task-0.txt task-1.txt task-2.txt > all.txt')
echo "slurm-smoke: submitted array job $array (tasks 0-2, at most 2 at once) and job $dep (afterok:$array) in $dir"

start=$SECONDS
while [[ -n $(squeue -h -j "$array,$dep" -o %i 2>/dev/null) ]]; do
  # A failed array task leaves the afterok job pending forever: fail now, not at the timeout.
  [[ $(squeue -h -j "$dep" -o %r 2>/dev/null) != DependencyNeverSatisfied ]] \
    || die "array job $array failed: $(job_states "$array") (logs in $dir)"
  ((SECONDS - start < TIMEOUT)) || die "jobs still queued after ${TIMEOUT}s: $(squeue -j "$array,$dep" 2>&1)"
  sleep 1
done

echo "slurm-smoke: array job states: $(job_states "$array"); job $dep: $(job_states "$dep")"
tasks=$(scontrol -o show job "$array") # one line per array task
[[ $tasks == *ArrayTaskThrottle=2* ]] || die "array job $array lost its %2 throttle"
[[ $(grep -c 'JobState=COMPLETED' <<<"$tasks") == 3 ]] || die "not all 3 array tasks COMPLETED (logs in $dir)"
[[ $(job_states "$dep") == "COMPLETED x1" ]] || die "dependent job $dep did not complete (logs in $dir)"
[[ -f $dir/all.txt && $(tr '\n' ' ' <"$dir/all.txt") == '0 1 2 ' ]] \
  || die "unexpected $dir/all.txt: $(cat "$dir/all.txt" 2>&1)"
echo "slurm-smoke: OK in $((SECONDS - start))s: all.txt = $(tr '\n' ' ' <"$dir/all.txt")"
