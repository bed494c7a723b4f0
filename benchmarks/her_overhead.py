"""What HER's relabelling adds to an update step: the same transitions sampled from the HER buffer and from the
plain replay buffer, beside the jitted update they feed.

    taskset -c 0 python benchmarks/her_overhead.py --env FetchPush-v4          # the [robotics] extra
    taskset -c 0 python benchmarks/her_overhead.py --env FetchReach-v4 --preset FetchReach-v4

Fills both buffers with the same `--fill` random-action transitions of the env, then alternates rounds of
`--calls` timed calls of each (HER sampling, plain sampling, and the learner's update on a sampled batch),
and prints the medians and the overhead: (HER sample - plain sample) / (plain sample + update), i.e. how
much longer a training step's sampling and update take with HER (docs/performance.md, "HER's relabelling").
"""

from __future__ import annotations

import argparse
import json
import statistics
import time


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="FetchPush-v4")
    p.add_argument("--preset", default=None, help="config preset (default: the env's own, else default)")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    p.add_argument("--fill", type=int, default=20_000, help="transitions in the buffers")
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--calls", type=int, default=200, help="timed calls per round and kind")
    a = p.parse_args(argv)

    import numpy as np

    from softac import SAC, SACConfig
    from softac.replay.buffer import ReplayBuffer

    base = SACConfig.preset(a.preset, env_id=a.env) if a.preset else SACConfig.for_env(a.env)
    config = base.with_overrides(a.set).replace(her="on", eval_interval=0, buffer_size=max(a.fill, 1000))
    agent = SAC(config)
    collector, learner = agent.collector, agent.learner
    collector.start(0)
    plain = ReplayBuffer(config.buffer_size, agent.spaces.obs_dim, agent.spaces.act_dim)
    rng = np.random.default_rng(0)
    obs = collector.obs
    for _ in range(a.fill // config.n_envs):  # random actions: the same transitions into both buffers
        actions = rng.uniform(-1, 1, (config.n_envs, agent.spaces.act_dim)).astype(np.float32)
        result = collector.step(obs, actions, learner.scaler.to_env(actions), 0)
        plain.add(obs, actions, result.rewards, result.next_obs, result.terminated, result.terminated | result.truncated)
        obs = collector.obs
    her = collector.buffer

    def timed(fn) -> float:
        t0 = time.perf_counter()
        for _ in range(a.calls):
            fn()
        return (time.perf_counter() - t0) / a.calls * 1e3

    batch = her.sample(rng, config.batch_size, config.gradient_steps)
    for _ in range(20):  # compile and warm up
        learner.update(batch)

    def update() -> None:
        metrics = learner.update(batch)
        next(iter(metrics.values())).block_until_ready()

    times: dict[str, list[float]] = {"her_sample": [], "plain_sample": [], "update": []}
    for _ in range(a.rounds):
        times["her_sample"].append(timed(lambda: her.sample(rng, config.batch_size, config.gradient_steps)))
        times["plain_sample"].append(timed(lambda: plain.sample(rng, config.batch_size, config.gradient_steps)))
        times["update"].append(timed(update))
    med = {k: statistics.median(v) for k, v in times.items()}
    overhead = (med["her_sample"] - med["plain_sample"]) / (med["plain_sample"] + med["update"])
    print(json.dumps({"env": a.env, "batch_size": config.batch_size, "hidden_sizes": config.hidden_sizes,
                      "gradient_steps": config.gradient_steps, "her_k": config.her_k,
                      "median_ms": {k: round(v, 4) for k, v in med.items()},
                      "overhead_of_a_step": round(overhead, 4),
                      "rounds_ms": {k: [round(x, 4) for x in v] for k, v in times.items()}}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
