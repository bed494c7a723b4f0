#!/usr/bin/env bash
# Issue 68's measurement: RLPD (`--preset rlpd`) from datasets softac makes from its own runs, beside crossq-avg from
# scratch and RLPD's settings without the data, on Hopper-v5 and HalfCheetah-v5, each trial alone on one pinned CPU.
#   sources:  for each env, two crossq-avg runs of seed 1000 (not a measured seed): "expert", 100k steps (its best
#             checkpoint acts), and "medium", stopped once its evaluation reaches a third of crossq-avg's 100k-step
#             return on v4 (docs/results.md: Hopper 2,781 -> 927, HalfCheetah 6,405 -> 2,135; a selection rule only).
#             HalfCheetah's medium source must run upright (benchmarks/upright.py on its dataset: seed 1000's ran on
#             its back): the seeds of MEDIUM_SEEDS are tried in turn, a flipped one's source and dataset renamed
#             *-flipped-seedN.
#   datasets: 100k transitions of each source's deterministic policy (`softac dataset --steps 100000`), in DATA.
#             LEVELS (default "medium expert") picks the sources and datasets made.
#   trials:   seeds 0..SEEDS-1, 100k env steps, evaluations every 5k (the 10k, 25k, 50k and 100k rows): rlpd with the
#             medium data, with the expert data, without data; crossq-avg from scratch.
#   cpu:      the CPU form, what fits one core: crossq-avg with each of LEVELS' data (half of each batch, as rlpd
#             mixes it) and crossq-avg from scratch, the same seeds and evaluations (~6 minutes a trial on one core).
# benchmarks/results_offline.py tables the offline-ENV-* sweeps in docs/results.md.
# Each part skips what exists, so a stopped script picks up where it was. Cost, one Xeon core (AMX): rlpd's 20 updates
# of 10 critics per env step are its bulk (docs/performance.md has the probe); a GPU (`--device gpu`) or several
# sessions' cores. Run from a benchmark worktree (benchmarks/worktree.sh), then copy the trials back with
# benchmarks/keep_trials.sh. Usage: CPU=1 PY=python ENVS="Hopper-v5" SEEDS=5 PARTS="sources datasets trials" \
#   bash benchmarks/offline_rlpd.sh
set -euo pipefail
CPU=${CPU:-1}
PY=${PY:-python}
ENVS=${ENVS:-Hopper-v5 HalfCheetah-v5}
SEEDS=${SEEDS:-5}
PARTS=${PARTS:-sources datasets trials}
LEVELS=${LEVELS:-medium expert}
MEDIUM_SEEDS=${MEDIUM_SEEDS:-1000 1001 1002 1003}
SRC=${SRC:-benchmarks/offline-sources}
DATA=${DATA:-benchmarks/offline-datasets}
OUT=benchmarks/sweeps
softac() { taskset -c "$CPU" "$PY" -m softac "$@"; }
# HalfCheetah's first CPU sweep with the medium data (offline-HalfCheetah-v5-crossq-avg-medium) learned from seed
# 1000's flipped policy; the sweep with an upright one's data is named apart. Usage: data_sweep ENV LEVEL
data_sweep() { case $1:$2 in HalfCheetah-*:medium) echo medium-upright;; *) echo "$2";; esac; }
medium_return() { case $1 in Hopper-*) echo 927;; HalfCheetah-*) echo 2135;; *) echo "no medium return for $1" >&2; exit 2;; esac; }

for env in $ENVS; do
  if [[ " $PARTS " == *" sources "* ]]; then
    [[ " $LEVELS " != *" expert "* ]] || [ -e "$SRC/$env-expert" ] || softac train --env "$env" --preset crossq-avg \
      --seed 1000 --steps 100000 --out "$SRC/$env-expert" --no-progress
    if [[ " $LEVELS " == *" medium "* ]]; then
      for seed in $MEDIUM_SEEDS; do
        [ -e "$SRC/$env-medium" ] && break
        [ -e "$SRC/$env-medium-flipped-seed$seed" ] && continue
        softac train --env "$env" --preset crossq-avg --seed "$seed" --steps 100000 \
          --target-return "$(medium_return "$env")" --out "$SRC/$env-medium" --no-progress
        [[ $env == HalfCheetah-* ]] || break
        softac dataset "$SRC/$env-medium" --steps 100000 --seed 1000 --out "$DATA/softac/$env-medium-v0"
        taskset -c "$CPU" "$PY" benchmarks/upright.py "$DATA/softac/$env-medium-v0" && break
        mv "$SRC/$env-medium" "$SRC/$env-medium-flipped-seed$seed"
        mv "$DATA/softac/$env-medium-v0" "$DATA/softac/$env-medium-flipped-seed$seed-v0"
      done
      [ -e "$SRC/$env-medium" ] || { echo "no upright medium source for $env among seeds $MEDIUM_SEEDS" >&2; exit 3; }
    fi
  fi
  if [[ " $PARTS " == *" datasets "* ]]; then
    for level in $LEVELS; do
      [ -e "$DATA/softac/$env-$level-v0" ] || softac dataset "$SRC/$env-$level" --steps 100000 --seed 1000 \
        --out "$DATA/softac/$env-$level-v0"
    done
  fi
  sweep() { softac sweep --env "$env" --seeds "$SEEDS" --steps 100000 --max-concurrent 1 "$@"; }
  if [[ " $PARTS " == *" trials "* ]]; then
    for level in medium expert; do
      sweep --preset rlpd --out "$OUT/offline-$env-rlpd-$level" \
        --set offline_data="$(realpath "$DATA/softac/$env-$level-v0")" eval_interval=5000
    done
    sweep --preset rlpd --out "$OUT/offline-$env-rlpd-no-data" --set eval_interval=5000
    sweep --preset crossq-avg --out "$OUT/offline-$env-crossq-avg-scratch" --set eval_interval=5000
  fi
  if [[ " $PARTS " == *" cpu "* ]]; then
    for level in $LEVELS; do
      sweep --preset crossq-avg --out "$OUT/offline-$env-crossq-avg-$(data_sweep "$env" "$level")" \
        --set offline_data="$(realpath "$DATA/softac/$env-$level-v0")" eval_interval=5000
    done
    sweep --preset crossq-avg --out "$OUT/offline-$env-crossq-avg-scratch" --set eval_interval=5000
  fi
done
