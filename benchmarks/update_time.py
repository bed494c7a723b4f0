"""Milliseconds per SAC/CrossQ update for a preset and overrides, in-process, on random batches.

    taskset -c 0 python benchmarks/update_time.py --preset HalfCheetah-v5 --obs 17 --act 6
    taskset -c 0 python benchmarks/update_time.py --preset sac-100k --set matmul_dtype=bfloat16
    taskset -c 0 python benchmarks/update_time.py --peer sbx-crossq-softac --env Hopper-v5   # needs [bench]
    taskset -c 0 python benchmarks/update_time.py --preset InvertedPendulum-v5 --image 3x84x84x3 --act 1  # pixels (frames x H x W x C)

Isolates the jitted update from the env and the loop (docs/performance.md, "The MuJoCo presets' update"):
warm-up updates first (the first call's seconds, mostly compilation, printed too), then rounds of updates each
timed to completion; prints the median and every round. Compare configurations by alternating runs of this
script; the machine drifts.
`--peer` times a peer's own gradient step instead (`model.train(gradient_steps=1)` after a 2,000-step random
buffer on `--env`: its replay sampling and host bookkeeping included, as they are in its training loop).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="HalfCheetah-v5")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    p.add_argument("--obs", type=int, default=17, help="observation size (HalfCheetah-v5: 17)")
    p.add_argument("--act", type=int, default=6, help="action size (HalfCheetah-v5: 6)")
    p.add_argument("--image", default=None, metavar="HxWxC",
                   help="image observations of this shape (uint8; C = frames x 3) through the encoder, instead of --obs")
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--updates", type=int, default=100, help="updates per round")
    p.add_argument("--peer", default=None, help="a peer (softac.peers.PEERS) to time instead of softac")
    p.add_argument("--env", default="Hopper-v5", help="the peer's env")
    a = p.parse_args(argv)
    if a.peer:
        return peer_update_time(a)

    import jax
    import numpy as np

    from softac.learner import build, losses
    from softac.config.sac_config import SACConfig

    config = SACConfig.preset(a.preset).with_overrides(a.set)
    image = tuple(int(n) for n in a.image.lower().split("x")) if a.image else None
    fns = build.build(config, a.obs, a.act, image_shape=image)
    state = fns.init(0)
    rng = np.random.default_rng(0)
    size = (config.gradient_steps, config.batch_size)

    def observations() -> np.ndarray:
        if image is not None:
            return rng.integers(0, 256, (*size, *image), dtype=np.uint8)
        return rng.standard_normal((*size, a.obs), dtype=np.float32)

    def batch() -> losses.Batch:
        return losses.Batch(obs=observations(), actions=rng.uniform(-1, 1, (*size, a.act)).astype(np.float32),
                         rewards=rng.standard_normal(size, dtype=np.float32), next_obs=observations(),
                         terminated=np.zeros(size, np.float32), steps=np.ones(size, np.float32))

    batches = [batch() for _ in range(8)]
    start = time.perf_counter()
    state, _ = fns.update(state, batches[0])
    jax.block_until_ready(state)
    first = time.perf_counter() - start  # tracing and XLA's compilation, then one update
    for i in range(1, 20):
        state, _ = fns.update(state, batches[i % 8])
    jax.block_until_ready(state)
    rounds = []
    for _ in range(a.rounds):
        start = time.perf_counter()
        for i in range(a.updates):
            state, _ = fns.update(state, batches[i % 8])
        jax.block_until_ready(state)
        rounds.append((time.perf_counter() - start) / a.updates * 1e3)
    print(f"{a.preset} {' '.join(a.set)} ({fns.matmul_dtype}): {statistics.median(rounds):.2f} ms per update call "
          f"(rounds: {' '.join(f'{r:.2f}' for r in rounds)}); first call (compiling) {first:.1f} s")
    return 0


def peer_update_time(a: argparse.Namespace) -> int:
    from softac.peers import peer_model

    model = peer_model(a.peer, a.env, 0, learning_starts=2000)
    model.learn(2000)  # fills the replay buffer; no gradient step yet
    for _ in range(20):
        model.train(gradient_steps=1, batch_size=model.batch_size)
    rounds = []
    for _ in range(a.rounds):
        start = time.perf_counter()
        for _ in range(a.updates):
            model.train(gradient_steps=1, batch_size=model.batch_size)
        rounds.append((time.perf_counter() - start) / a.updates * 1e3)  # train() reads its losses back: synced
    print(f"{a.peer} on {a.env}: {statistics.median(rounds):.2f} ms per train(gradient_steps=1) "
          f"(rounds: {' '.join(f'{r:.2f}' for r in rounds)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
