#!/usr/bin/env bash
# A benchmark worktree: this checkout's HEAD (or COMMIT) in DIR with a venv of its own, so that hours of sweeps
# run one fixed commit while the code here changes. Peers (SB3, SBX) need the bench extra, which installs the
# CPU build of torch first (as `make bench` does). The numerics' packages get this checkout's .venv versions.
# Usage: bash benchmarks/worktree.sh DIR [COMMIT] [EXTRAS]      (EXTRAS default: ray,bench,dmc,box2d)
# Then, e.g.: cd DIR && taskset -c 0 .venv/bin/softac sweep --env Hopper-v4 --seeds 0,1 --max-concurrent 1 --out benchmarks/sweeps/X
# and, as each trial finishes: bash benchmarks/keep_trials.sh DIR benchmarks/sweeps/X (from this checkout).
set -euo pipefail
[ $# -ge 1 ] || { echo "usage: bash benchmarks/worktree.sh DIR [COMMIT] [EXTRAS]" >&2; exit 2; }
dir=$1
commit=${2:-HEAD}
extras=${3:-ray,bench,dmc,box2d}
if [ -e "$dir" ]; then echo "worktree.sh: $dir exists; pick a new directory" >&2; exit 2; fi
dir=$(realpath -m "$dir")
cd "$(dirname "$0")/.."
git worktree prune
git worktree add --detach "$dir" "$commit"
python3 -m venv "$dir/.venv"
if [[ ",$extras," == *",bench,"* ]]; then "$dir/.venv/bin/pip" install -q torch==2.13.0; fi
# the versions this checkout's .venv has of what a trial's numbers depend on (and config.yaml records): with
# another MuJoCo (4.0 where no extra caps it at 3.11) a seed's physics, and so its run, differ from the first step
constraints=$dir/.venv/constraints.txt
: > "$constraints"
if [ -x .venv/bin/pip ]; then
  .venv/bin/pip freeze 2>/dev/null | grep -iE '^(jax|jaxlib|optax|numpy|gymnasium|mujoco)==' > "$constraints" || true
fi
"$dir/.venv/bin/pip" install -q -c "$constraints" -e "$dir[$extras]"
echo "worktree $dir at $(git -C "$dir" rev-parse --short HEAD), venv $dir/.venv ($extras)"
