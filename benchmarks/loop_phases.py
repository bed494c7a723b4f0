"""Where a training step's time goes: the training loop's phases timed one by one, for a preset on an env.

    taskset -c 0 python benchmarks/loop_phases.py --env Hopper-v5 --steps 3000
    taskset -c 0 python benchmarks/loop_phases.py --env Hopper-v5 --preset crossq --set matmul_dtype=float32

Trains `--warmup` steps untimed (compilation, learning_starts), then `--steps` steps with each phase of the
loop wrapped in a timer: the jitted act, the env step and buffer write (the collector's step), replay
sampling, the update call, and the update's XLA work (waited for right after the call, so it is charged to
the update and not to the next act, which would otherwise wait for it), and the rest of the loop (log rows,
progress, evaluations if due). Waiting for each update removes the overlap of the update with the next env
step, so the total is an upper bound of the loop's real step time, which is printed beside it
(docs/performance.md, "Where the time goes").
"""

from __future__ import annotations

import argparse
import collections
import sys
import time


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="Hopper-v5")
    p.add_argument("--preset", default=None, help="default: the env's preset")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    p.add_argument("--warmup", type=int, default=1500, help="untimed steps first (learning starts at 1000)")
    p.add_argument("--steps", type=int, default=3000, help="timed steps")
    a = p.parse_args(argv)

    import jax

    from softac import SAC, SACConfig

    base = SACConfig.preset(a.preset, env_id=a.env) if a.preset else SACConfig.for_env(a.env)
    config = base.with_overrides(a.set).replace(learning_starts=1000, eval_interval=0, checkpoint_interval=0,
                                                loggers="none")
    agent = SAC(config)
    agent.learn(a.warmup, progress=False)  # compiles, fills the buffer past learning_starts
    plain = time.perf_counter()
    agent.learn(a.steps, progress=False)
    plain_ms = (time.perf_counter() - plain) / a.steps * 1e3

    spent: dict[str, float] = collections.defaultdict(float)

    def timed(name: str, fn, wait: bool = False):
        def wrapper(*args, **kwargs):
            t = time.perf_counter()
            out = fn(*args, **kwargs)
            spent[name] += time.perf_counter() - t
            if wait:
                t = time.perf_counter()
                jax.block_until_ready(agent.learner.state)
                spent["update (XLA work)"] += time.perf_counter() - t
            return out
        return wrapper

    learner, collector = agent.learner, agent.collector
    learner.act = timed("act (jitted, one obs)", learner.act)
    collector.step = timed("env step + buffer write", collector.step)
    collector.sample = timed("replay sampling", collector.sample)
    learner.update = timed("update call (dispatch)", learner.update, wait=True)
    start = time.perf_counter()
    agent.learn(a.steps, progress=False)
    total = time.perf_counter() - start
    spent["rest of the loop"] = total - sum(spent.values())
    print(f"{a.env}, {a.preset or 'env preset'} {' '.join(a.set)} ({learner.matmul_dtype}), {a.steps} steps "
          f"after {a.warmup}: ms per step")
    for name, seconds in spent.items():
        print(f"  {name:28s} {seconds / a.steps * 1e3:6.3f}  ({100 * seconds / total:4.1f}%)")
    print(f"  {'total, each update waited':28s} {total / a.steps * 1e3:6.3f}")
    print(f"  {'the loop unwrapped':28s} {plain_ms:6.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
