"""Screen: pixels scaled to [0, 1] (DrQ's obs / 255) instead of [-0.5, 0.5], by patching softac.encoder.scale_pixels.
usage: unit_screen.py RUN_DIR STEPS KEY=VALUE ..."""
import sys, jax.numpy as jnp
import softac.encoder as E
E.scale_pixels = lambda images: images.astype(jnp.float32) / 255.0
from softac import SAC, SACConfig
over = dict(kv.split("=", 1) for kv in sys.argv[3:])
cfg = SACConfig.preset("InvertedPendulum-v5").replace(pixels="true", seed="100", eval_interval="1000", **over)
SAC(cfg).learn(int(sys.argv[2]), run_dir=sys.argv[1], progress=False)
