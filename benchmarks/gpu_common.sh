# What the device scripts (benchmarks/gpu_*.sh) share; sourced by them, not run. gpu_setup NAME: OUT and WORK
# (defaults /tmp/gpu-NAME-out and /tmp/gpu-NAME), DEVICE (gpu), the packages of .whl/site.tgz on a GPU (this
# checkout's src on PYTHONPATH either way), PY, the EXTRA settings as the array `extra` (default: the second
# argument), and devices.txt. report_run LABEL CODE START DIR LOG: a run's exit, seconds, last progress row and
# last evaluation appended to $OUT/runs.txt (the log's tail too when it failed). pack_runs: each run's results under
# $WORK/runs into $OUT/runs.tgz.
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

report_run() {
  echo "$1: exit $2 after $((SECONDS - $3)) s; last row: $(tail -n 1 "$4/progress.csv" 2>/dev/null | cut -d, -f1-4);" \
    "last evaluation: $(tail -n 1 "$4/eval.csv" 2>/dev/null)" | tee -a "$OUT/runs.txt"
  [ "$2" = 0 ] || tail -n 3 "$5"
}

pack_runs() {
  (cd "$WORK/runs" && find . \( -name config.yaml -o -name eval.csv -o -name progress.csv -o -name episodes.csv \
    -o -name summary.json \) -print0 | tar -czf "$OUT/runs.tgz" --null -T -)
}
