# What the device scripts (benchmarks/gpu_*.sh) share; sourced by them, not run. gpu_setup NAME: OUT and WORK
# (defaults /tmp/gpu-NAME-out and /tmp/gpu-NAME), DEVICE (gpu), the packages of .whl/site.tgz on a GPU (this
# checkout's src on PYTHONPATH either way), PY, the EXTRA settings as the array `extra` (default: the second
# argument), and devices.txt. pack_runs: each run's results under $WORK/runs into $OUT/runs.tgz.
gpu_setup() {
  OUT=${OUT:-/tmp/gpu-$1-out}
  WORK=${WORK:-/tmp/gpu-$1}
  DEVICE=${DEVICE:-gpu}
  mkdir -p "$OUT"
  rm -rf "$WORK" && mkdir -p "$WORK/runs"
  if [ "$DEVICE" = gpu ]; then
    mkdir -p /tmp/site && tar -C /tmp/site -xzf .whl/site.tgz || exit 1
    export PYTHONPATH=/tmp/site:$PWD/src
    PY=python3
    nvidia-smi -L
  else
    export PYTHONPATH=$PWD/src
    PY=${PY:-.venv/bin/python}
  fi
  export PYTHONUNBUFFERED=1
  read -r -a extra <<< "${EXTRA:-${2:-}}"
  $PY -c "import jax; print('jax', jax.__version__, jax.devices())" 2>&1 | tee "$OUT/devices.txt"
}

pack_runs() {
  (cd "$WORK/runs" && find . \( -name config.yaml -o -name eval.csv -o -name progress.csv -o -name episodes.csv \
    -o -name summary.json \) -print0 | tar -czf "$OUT/runs.tgz" --null -T -)
}
