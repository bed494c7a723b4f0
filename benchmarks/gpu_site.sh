#!/usr/bin/env bash
# .whl/site.tgz for a lent GPU machine (the device tool): the Python packages softac needs that the machine's image
# lacks, unpacked, at this checkout's .venv versions. That image's python3 is 3.12 on x86-64 Linux with JAX (CUDA),
# optax, NumPy, SciPy, PyYAML, tqdm, Matplotlib, imageio and filelock; nothing can be installed there from outside
# (the device notes). Gymnasium, MuJoCo and tensorboardX go in here (absl-py and etils are there; no PyOpenGL or
# imageio-ffmpeg: the runs render nothing, and the carry holds 64 MiB). Run it here, then name .whl in the carry:
#   bash benchmarks/gpu_site.sh && ls -l .whl/site.tgz          (PLAYGROUND=1 for benchmarks/gpu_playground.sh)
# OFFLINE=1 (benchmarks/gpu_rlpd.sh): also Minari and h5py, which read the datasets, and .whl/offline-datasets.tgz,
# the datasets of DATA (default benchmarks/offline-datasets, made by benchmarks/offline_rlpd.sh) named by
# OFFLINE_DATASETS (default the medium ones: 15 MB packed, with the 27 MB site and the 23 MB tree near the carry's
# 64 MiB).
set -euo pipefail
cd "$(dirname "$0")/.."
PYVER=${PYVER:-3.12}
grep -qx '/.whl/' .git/info/exclude 2>/dev/null || echo '/.whl/' >> .git/info/exclude  # never committed
pins=$(.venv/bin/pip freeze | grep -iE '^(gymnasium|mujoco|farama-notifications|cloudpickle|tensorboardx|glfw)==')
# PLAYGROUND=1: also MuJoCo Playground and what importing it loads (issue 67; not NVIDIA Warp, 392 MB unpacked, which
# MJX imports only if present: the runs use MJX's JAX implementation)
if [ "${PLAYGROUND:-0}" = 1 ]; then
  pins="$pins $(.venv/bin/pip freeze | grep -iE '^(playground|mujoco-mjx|brax|flax|jaxopt|ml.collections|lxml|trimesh|mediapy|msgpack|treescope)==' | tr '\n' ' ')"
fi
if [ "${OFFLINE:-0}" = 1 ]; then
  pins="$pins $(.venv/bin/pip freeze | grep -iE '^(minari|h5py)==' | tr '\n' ' ')"
  data=${DATA:-benchmarks/offline-datasets}
  names=${OFFLINE_DATASETS:-softac/Hopper-v5-medium-v0 softac/HalfCheetah-v5-medium-v0}
  for name in $names; do
    [ -d "$data/$name" ] || { echo "gpu_site.sh: no dataset $data/$name (offline_rlpd.sh makes it)" >&2; exit 2; }
  done
  mkdir -p .whl
  # shellcheck disable=SC2086  # names are words
  tar -C "$data" -czf .whl/offline-datasets.tgz $names
  echo "wrote .whl/offline-datasets.tgz ($(du -h .whl/offline-datasets.tgz | cut -f1)):" $names
fi
site=$(mktemp -d)
.venv/bin/pip install -q --target "$site" --no-deps --only-binary=:all: --python-version "$PYVER" --implementation cp \
  --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux_2_28_x86_64 $pins
mkdir -p .whl
tar -C "$site" -czf .whl/site.tgz .
rm -rf "$site"
echo "wrote .whl/site.tgz ($(du -h .whl/site.tgz | cut -f1)) for Python $PYVER:" $pins
