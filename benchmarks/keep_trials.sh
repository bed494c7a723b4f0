#!/usr/bin/env bash
# Copy the finished trials of sweeps that ran in a benchmark worktree (benchmarks/worktree.sh) into this
# checkout, results only (what git keeps: config.yaml, eval.csv, progress.csv, episodes.csv, summary.json, with
# averaging the actor's evaluation of the last checkpoint (actor-eval.json: `softac eval --policy actor --json`), and
# the sweep's summary and spec; no weights, TensorBoard files or Ray state), ready to commit while the worktree
# runs on. A trial counts as finished once its summary.json is written; unfinished ones are left out.
# Usage: bash benchmarks/keep_trials.sh WORKTREE SWEEP_DIR...   (SWEEP_DIR relative to the repository root)
set -euo pipefail
[ $# -ge 1 ] || { echo "usage: bash benchmarks/keep_trials.sh WORKTREE SWEEP_DIR..." >&2; exit 2; }
src_root=$1
shift
[ $# -gt 0 ] || { echo "keep_trials.sh: name at least one sweep directory" >&2; exit 2; }
dst_root=$(cd "$(dirname "$0")/.." && pwd)
for rel in "$@"; do
  src=$src_root/$rel dst=$dst_root/$rel
  [ -f "$src/sweep.json" ] || { echo "keep_trials.sh: $src is not a sweep directory (no sweep.json)" >&2; exit 2; }
  mkdir -p "$dst"
  for f in summary.csv summary.md sweep.json; do [ -f "$src/$f" ] && cp "$src/$f" "$dst/"; done
  kept=()
  for trial in "$src"/*/; do
    trial=${trial%/}
    [ -f "$trial/summary.json" ] || continue
    name=$(basename "$trial")
    mkdir -p "$dst/$name"
    for f in summary.json episodes.csv eval.csv progress.csv config.yaml actor-eval.json; do
      [ -f "$trial/$f" ] && cp "$trial/$f" "$dst/$name/"
    done
    kept+=("$name")
  done
  echo "$rel: ${kept[*]:-no finished trials}"
done
