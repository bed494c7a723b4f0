#!/usr/bin/env bash
# Issue 68 on a lent GPU machine (the device tool): `rlpd` (20 updates of 10 critics per env step: ~10 hours of a CPU
# core a 100k-step run, docs/performance.md) from the datasets softac made from its own runs, up to the goal's point
# (25k online steps: does it reach `crossq-avg`'s 100k-step return from scratch by then?):
#   1. rlpd's update time per env step at Hopper-v5's sizes (benchmarks/update_time.py), at most UPDATE_LIMIT s;
#   2. the RUNS (PRESET:ENV:LEVEL:SEED; LEVEL "no-data" trains without data, the paper's ablation,
#      named as benchmarks/offline_rlpd.sh names it), default rlpd from the
#      medium datasets on fresh seeds 0-4 of Hopper-v5 and HalfCheetah-v5, STEPS online steps each (default 25k),
#      evaluations every 5k, CONCURRENT at a time sharing the GPU (default all; each on its own CPU core, JAX's
#      memory grown as needed, not preallocated), each capped at LIMIT s: a run cut short still brings back its
#      evaluations and its steps per second.
# Everything comes back in $OUT: devices.txt, update_time.txt, runs.txt (each run's exit and last evaluation) and
# runs.tgz (each run's config.yaml, eval.csv, progress.csv, episodes.csv, summary.json; unpack into
# benchmarks/gpu/DATE-rlpd). The datasets and packages travel in .whl (OFFLINE=1 bash benchmarks/gpu_site.sh, here,
# first: site.tgz with Minari, and offline-datasets.tgz). The device allows ~15 minutes a task in all, its start
# included: the defaults take about 7, so a rerun fits.
#   device run: bash benchmarks/gpu_rlpd.sh   (carry .whl; timeout_s 420)
#   here, on a CPU, tiny: DEVICE=cpu LIMIT=200 STEPS=600 UPDATE_LIMIT=60 CONCURRENT=2 RUNS='rlpd:Hopper-v5:medium:0
#     rlpd:Hopper-v5:no-data:0' EXTRA='learning_starts=200 batch_size=32 hidden_sizes=16,16 gradient_steps=2
#     policy_delay=2 eval_interval=300 eval_episodes=1' bash benchmarks/gpu_rlpd.sh
set -u
source "$(dirname "$0")/gpu_common.sh"
gpu_setup rlpd
DATA=${DATA:-}
if [ -z "$DATA" ]; then
  if [ -f .whl/offline-datasets.tgz ]; then
    DATA=$WORK/datasets && mkdir -p "$DATA" && tar -C "$DATA" -xzf .whl/offline-datasets.tgz
  else
    DATA=benchmarks/offline-datasets  # where benchmarks/offline_rlpd.sh makes them
  fi
fi
export XLA_PYTHON_CLIENT_PREALLOCATE=false  # several runs share the GPU
timeout "${UPDATE_LIMIT:-100}" $PY benchmarks/update_time.py --preset rlpd --obs 11 --act 3 --rounds 3 --updates 10 \
  ${extra[@]+--set "${extra[@]}"} 2>&1 | tail -n 1 | tee -a "$OUT/update_time.txt"

default_runs=""
for env in Hopper-v5 HalfCheetah-v5; do for seed in 0 1 2 3 4; do default_runs+=" rlpd:$env:medium:$seed"; done; done
read -r -a runs <<< "${RUNS:-$default_runs}"
concurrent=${CONCURRENT:-${#runs[@]}}
cores=$(nproc)
one_run() {  # PRESET:ENV:LEVEL:SEED CORE
  local preset env level seed data=() dir log start
  IFS=: read -r preset env level seed <<< "$1"
  [ "$level" = no-data ] || data=("offline_data=$(realpath "$DATA/softac/$env-$level-v0")")
  dir=$WORK/runs/offline-$env-$preset-$level/seed=$seed
  log=$WORK/$preset-$env-$level-$seed.log
  start=$SECONDS
  timeout "${LIMIT:-330}" taskset -c "$2" $PY -m softac train --env "$env" --preset "$preset" --seed "$seed" \
    --steps "${STEPS:-25000}" --device "$DEVICE" --out "$dir" --no-progress \
    --set loggers=none eval_interval=5000 ${data[@]+"${data[@]}"} ${extra[@]+"${extra[@]}"} > "$log" 2>&1
  report_run "$1" $? "$start" "$dir" "$log"
}
i=0
for run in "${runs[@]}"; do
  while [ "$(jobs -rp | wc -l)" -ge "$concurrent" ]; do wait -n; done
  one_run "$run" $((i % cores)) &
  i=$((i + 1))
done
wait
pack_runs
