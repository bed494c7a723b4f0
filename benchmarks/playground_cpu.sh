#!/usr/bin/env bash
# Issue 67's CPU measurements: softac's device loop beside Brax's own SAC trainer (`--framework brax-sac`) at the
# same settings, the `brax-sac` preset (Playground's DMC settings), on MuJoCo Playground's CartpoleSwingup
# (contact-free: MJX is fast on a CPU there), each trial alone on one pinned CPU, one after another:
#   throughput: 16 and 1024 envs, one seed each, evaluations every quarter of the run (16 episodes; Brax's trainer
#     then runs four epochs, so its later ones are past its compile): progress.csv's fps after the replay's
#     prefill, rows past the first compile;
#   returns: the preset's 128 envs, 3 seeds each, 500k env steps (the preset's budget is 5M, about two hours of one
#     core per run here: past what a session may spend).
# Run from a benchmark worktree (benchmarks/worktree.sh, or PYTHONPATH=its src), then copy the trials back with
# benchmarks/keep_trials.sh. Usage: CPU=1 PY=python PARTS="throughput returns" bash benchmarks/playground_cpu.sh
set -euo pipefail
CPU=${CPU:-1}
PY=${PY:-python}
PARTS=${PARTS:-throughput returns}
ENV=playground:CartpoleSwingup
OUT=benchmarks/sweeps
sweep() { taskset -c "$CPU" "$PY" -m softac sweep --env "$ENV" --preset brax-sac --max-concurrent 1 "$@"; }

if [[ " $PARTS " == *" throughput "* ]]; then
  for n in 16 1024; do
    steps=$(( n == 16 ? 24576 : 409600 ))
    for framework in softac brax-sac; do
      sweep --framework "$framework" --seeds 1 --steps "$steps" --out "$OUT/playground-CartpoleSwingup-$framework-n$n-throughput" \
        --set n_envs=$n eval_interval=$(( steps / 4 )) eval_episodes=16 log_interval=$(( n * 64 ))
    done
  done
fi
if [[ " $PARTS " == *" returns "* ]]; then
  for framework in softac brax-sac; do
    sweep --framework "$framework" --seeds 3 --steps 500000 --out "$OUT/playground-CartpoleSwingup-$framework-500k" \
      --set eval_interval=100000
  done
fi
