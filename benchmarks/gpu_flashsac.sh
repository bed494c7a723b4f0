#!/usr/bin/env bash
# Issue 66 on a lent GPU machine (the device tool): FlashSAC and XQC at their published sizes, whose 100k-step runs
# take 2-3.3 hours of one CPU core (docs/performance.md), as GPU points of the v4 front:
#   1. each preset's update time per env step at HalfCheetah's sizes (benchmarks/update_time.py), at most
#      UPDATE_LIMIT s each;
#   2. the RUNS (PRESET:ENV:SEED, default flashsac on HalfCheetah-v4 with fresh seed 0) one after the other, the
#      published protocol (100k steps, 10 deterministic evaluation episodes every 5k), each capped at LIMIT s: a
#      run cut short still brings back its evaluations and its steps per second.
# Everything comes back in $OUT: devices.txt, update_time.txt, runs.txt (each run's exit) and runs.tgz (each run's
# config.yaml, eval.csv, progress.csv, episodes.csv and summary.json; unpack into benchmarks/gpu/DATE-flashsac).
# Packages travel in .whl/site.tgz (bash benchmarks/gpu_site.sh, here, first). The device allows ~15 minutes a task
# in all, its start included: the defaults take about 7.
#   device run: bash benchmarks/gpu_flashsac.sh   (carry .whl; timeout_s 540)
#   here, on a CPU, tiny: DEVICE=cpu LIMIT=120 STEPS=600 UPDATE_LIMIT=60 EXTRA='learning_starts=200 batch_size=32
#     critic_hidden_sizes=16,16 actor_hidden_sizes=16,16 eval_interval=300 eval_episodes=1' bash benchmarks/gpu_flashsac.sh
set -u
source "$(dirname "$0")/gpu_common.sh"
gpu_setup flashsac
for preset in ${PRESETS:-flashsac xqc}; do
  timeout "${UPDATE_LIMIT:-100}" $PY benchmarks/update_time.py --preset "$preset" --obs 17 --act 6 --rounds 3 \
    --updates 50 ${extra[@]+--set "${extra[@]}"} 2>&1 | tail -n 1 | tee -a "$OUT/update_time.txt"
done
for run in ${RUNS:-flashsac:HalfCheetah-v4:0}; do
  IFS=: read -r preset env seed <<< "$run"
  dir=$WORK/runs/$env-$preset/seed=$seed
  log=$WORK/$preset-$env-$seed.log
  start=$SECONDS
  timeout "${LIMIT:-300}" $PY -m softac train --env "$env" --preset "$preset" --seed "$seed" --steps "${STEPS:-100000}" \
    --device "$DEVICE" --out "$dir" --no-progress --set loggers=none ${extra[@]+"${extra[@]}"} > "$log" 2>&1
  report_run "$run" $? "$start" "$dir" "$log"
  pack_runs
done
