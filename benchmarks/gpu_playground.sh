#!/usr/bin/env bash
# Issue 67 on a lent GPU machine (the device tool): MuJoCo Playground's envs collected on the device, softac's
# device source (collect_on=device) at the brax-sac preset's settings, then Brax's own SAC trainer at the same ones,
# for the steps per second that thousands of envs give and the first part of a learning curve:
#   the RUNS (PRESET:ENV:N_ENVS:SEED, default brax-sac on CheetahRun with 128 and 1024 envs, fresh seed 0) one after
#   the other, each framework's capped at LIMIT s (a run cut short still brings back its log rows and evaluations).
# Everything comes back in $OUT: devices.txt, runs.txt (each run's exit and last rows) and runs.tgz (config.yaml,
# eval.csv, progress.csv, episodes.csv, summary.json; unpack into benchmarks/gpu/DATE-playground).
# Packages travel in .whl/site.tgz: PLAYGROUND=1 bash benchmarks/gpu_site.sh, here, first.
#   device run: bash benchmarks/gpu_playground.sh   (carry .whl; timeout_s 540)
#   here, on a CPU, tiny: DEVICE=cpu LIMIT=200 STEPS=4096 RUNS=brax-sac:CartpoleSwingup:64:0 EXTRA='learning_starts=1024
#     buffer_size=50000 eval_interval=2048 eval_episodes=4 log_interval=1024 checkpoint_interval=2048' bash benchmarks/gpu_playground.sh
set -u
source "$(dirname "$0")/gpu_common.sh"
gpu_setup playground "log_interval=102400 eval_interval=512000 checkpoint_interval=512000 eval_episodes=128"
# Brax's SAC trainer beside each (FRAMEWORKS="softac brax-sac"), at the same settings: its evaluations every
# eval_interval of those settings (python -m softac.peers takes them as flags), no checkpoints (it cannot continue)
setting() { local pair; for pair in ${extra[@]+"${extra[@]}"}; do [[ $pair == "$1="* ]] && value=${pair#*=}; done; }
value=512000; setting eval_interval; eval_interval=$value
value=128; setting eval_episodes; eval_episodes=$value
for run in ${RUNS:-brax-sac:CheetahRun:128:0 brax-sac:CheetahRun:1024:0}; do
  IFS=: read -r preset env n seed <<< "$run"
  for framework in ${FRAMEWORKS:-softac brax-sac}; do
    dir=$WORK/runs/$env-$framework-$preset-n$n/seed=$seed
    log=$WORK/$framework-$preset-$env-$n.log
    start=$SECONDS
    if [ "$framework" = softac ]; then
      timeout "${LIMIT:-200}" $PY -m softac train --env "playground:$env" --preset "$preset" --n-envs "$n" --seed "$seed" \
        --steps "${STEPS:-5000000}" --device "$DEVICE" --out "$dir" --no-progress \
        --set loggers=none ${extra[@]+"${extra[@]}"} > "$log" 2>&1
    else  # on the GPU where JAX finds one, as Brax's trainer runs wherever JAX does
      timeout "${LIMIT:-200}" $PY -m softac.peers run brax-sac --env "playground:$env" --seed "$seed" \
        --steps "${STEPS:-5000000}" --out "$dir" --eval-interval "$eval_interval" --eval-episodes "$eval_episodes" \
        --preset "$preset" --set "n_envs=$n" ${extra[@]+"${extra[@]}"} > "$log" 2>&1
    fi
    report_run "$run $framework" $? "$start" "$dir" "$log"
    pack_runs
  done
done
