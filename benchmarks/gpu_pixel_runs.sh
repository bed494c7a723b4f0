#!/usr/bin/env bash
# Issue 44's measured pixel runs on a lent GPU machine (the device tool: one GPU, 16 cores, nothing installable
# from outside), all at once on the one GPU, each run capped at LIMIT seconds:
#   - DMC cartpole-swingup from pixels, the drq preset (84x84, 3 frames, batch 512), action repeat 8 as DrQ's
#     PlaNet setting, 12,500 agent steps = 100k frames, evaluation every 10k frames (10 episodes), seeds DMC_SEEDS;
#   - InvertedPendulum-v5 from pixels, the drq preset, PEND_STEPS steps, seeds PEND_SEEDS, and beside it SB3's SAC
#     with its CnnPolicy on the same frames (benchmarks/sb3_pixels.py), the same steps and evaluations.
# Python packages travel unpacked in .whl/site.tgz (gymnasium, mujoco, dm_control without its locomotion assets,
# shimmy, stable-baselines3, ...), Debian's GL loaders in .gl/ (see the device notes); everything the runs write
# comes back as one results.tgz.
#   device run: bash benchmarks/gpu_pixel_runs.sh   (carry .whl and .gl)
#   here, on a CPU, tiny: DEVICE=cpu LIMIT=300 DMC_STEPS=300 PEND_STEPS=300 EXTRA='pixel_size=32 batch_size=16
#     learning_starts=100' SB3_EXTRA='--pixel-size 32 --learning-starts 100' bash benchmarks/gpu_pixel_runs.sh
set -u
OUT=${OUT:-/tmp/gpu-pixel-out}
mkdir -p "$OUT"
WORK=${WORK:-/tmp/gpu-pixel-runs}
rm -rf "$WORK" && mkdir -p "$WORK"
DEVICE=${DEVICE:-gpu}
LIMIT=${LIMIT:-450}
if [ "$DEVICE" = gpu ]; then
  for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig
  export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json MUJOCO_GL=egl
  mkdir -p /tmp/site && tar -C /tmp/site -xzf .whl/site.tgz || exit 1
  export PYTHONPATH=/tmp/site:$PWD/src
  PY=python3
  nvidia-smi -L; nproc
else
  PY=${PY:-.venv/bin/python}
fi
# seven processes share the GPU: no process may take JAX's default 75% of its memory
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false XLA_PYTHON_CLIENT_MEM_FRACTION=0.12
$PY -c "import jax, gymnasium, mujoco; print('jax', jax.__version__, jax.devices(), 'mujoco', mujoco.__version__)" || exit 1
DMC_STEPS=${DMC_STEPS:-12500}
PEND_STEPS=${PEND_STEPS:-10000}
start=$(date +%s)
for seed in ${DMC_SEEDS-0 1 2}; do
  timeout $LIMIT $PY -m softac train --env dmc:cartpole-swingup --preset drq --steps $DMC_STEPS --device $DEVICE \
    --out $WORK/dmc-cartpole-swingup-drq-s$seed --no-progress \
    --set seed=$seed action_repeat=8 eval_interval=1250 eval_episodes=10 ${EXTRA:-} --logger none \
    > $WORK/dmc-s$seed.log 2>&1 &
done
for seed in ${PEND_SEEDS-0 1}; do
  timeout $LIMIT $PY -m softac train --env InvertedPendulum-v5 --preset drq --steps $PEND_STEPS --device $DEVICE \
    --out $WORK/pendulum-drq-s$seed --no-progress \
    --set seed=$seed eval_interval=2000 eval_episodes=5 ${EXTRA:-} --logger none > $WORK/pend-s$seed.log 2>&1 &
  timeout $LIMIT $PY benchmarks/sb3_pixels.py --env InvertedPendulum-v5 --steps $PEND_STEPS --seed $seed \
    --eval-interval 2000 --eval-episodes 5 ${SB3_EXTRA:-} --device $([ $DEVICE = gpu ] && echo cuda || echo cpu) \
    --out $WORK/pendulum-sb3-cnn-s$seed > $WORK/sb3-s$seed.log 2>&1 &
done
(while sleep 60; do nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader 2>/dev/null
   echo "t=$(( $(date +%s) - start )) s"; tail -qn1 $WORK/*.log 2>/dev/null | cut -c1-150; done) &
watcher=$!
wait $(jobs -p | grep -v "^$watcher$") 2>/dev/null
kill $watcher 2>/dev/null
echo "all runs ended after $(( $(date +%s) - start )) s"
for log in $WORK/*.log; do echo "== $log"; tail -n 4 "$log"; done
for d in $WORK/*/; do echo "== $d"; cat "$d/eval.csv" 2>/dev/null | tail -n 8; done
tar -C $WORK --exclude=checkpoints --exclude='*.npz' -czf "$OUT/results.tgz" .
ls -la "$OUT"
