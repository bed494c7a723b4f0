#!/usr/bin/env bash
# Issue 44 on a lent GPU machine (the device tool; nothing can be installed there from outside): the image
# agent's update time per batch size, then InvertedPendulum-v5 from 84x84 frames (3 stacked) with the preset's
# settings. Wheels (gymnasium, mujoco, ...) travel in .whl/, Debian's GL loaders in .gl/ (see the device notes).
#   device run: bash benchmarks/gpu_pixels.sh   (carry .whl and .gl)
# BATCHES (update-time batch sizes, '' for none), STEPS, SEEDS, TRAIN_TIMEOUT, EVAL_INTERVAL change what it runs.
set -u
for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD/src MUJOCO_GL=egl PYTHONUNBUFFERED=1
nvidia-smi -L; nproc
python3 -c "import jax; print(jax.__version__, jax.devices())"
for b in ${BATCHES-128 256 512}; do
  python3 benchmarks/update_time.py --preset InvertedPendulum-v5 --image 84x84x9 --act 1 --rounds 3 --updates 50 \
    --set batch_size=$b
done
steps=${STEPS:-30000}
for seed in ${SEEDS:-0}; do
  run=/tmp/pend-s$seed
  timeout ${TRAIN_TIMEOUT:-420} python3 -m softac train --env InvertedPendulum-v5 --steps $steps --device gpu \
    --out $run --no-progress --set pixels=true seed=$seed loggers=none eval_interval=${EVAL_INTERVAL:-5000} eval_episodes=5
  echo "train exit $?"
  for f in eval.csv progress.csv summary.json config.yaml; do [ -f $run/$f ] && cp $run/$f "${OUT:-/tmp}/s$seed-$f"; done
  cat $run/eval.csv 2>/dev/null
done
