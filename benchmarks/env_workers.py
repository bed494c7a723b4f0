"""Training steps/s with the envs stepped in-process or in env worker processes (`env_workers`).

    python benchmarks/env_workers.py                     # n_envs=4; env_workers 0, 2, 4; slow and plain pendulum
    python benchmarks/env_workers.py --steps 2000 --workers 0,4 --sleep-ms 10 --json

docs/performance.md, "Env worker processes". The slow env stands in for a slow simulator: InvertedPendulum-v5
sleeping `--sleep-ms` in every step, registered here as SlowInvertedPendulum-v5; plain InvertedPendulum-v5
(tens of microseconds a step) shows what workers cost where the env is fast. Per setting: one agent at the
env's preset, a warm-up `learn()` (compilation; learning has started), then the workers' start-up and a
`learn(--steps)`: steps/s over its training loop, the workers' start-up and shutdown timed apart.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import gymnasium as gym
from gymnasium.envs.mujoco.inverted_pendulum_v5 import InvertedPendulumEnv

SLOW_ENV = "SlowInvertedPendulum-v5"


class SlowInvertedPendulum(InvertedPendulumEnv):
    def __init__(self, sleep_ms: float = 5.0, **kwargs):
        super().__init__(**kwargs)
        self.sleep_s = sleep_ms / 1000.0

    def step(self, action):
        time.sleep(self.sleep_s)
        return super().step(action)


# at import, so that the spawned workers (which import this script) know the class the spec names
gym.register(SLOW_ENV, entry_point=SlowInvertedPendulum, max_episode_steps=1000)


def measure(env_id: str, env_workers: int, a: argparse.Namespace) -> dict:
    from softac import SAC, SACConfig

    config = SACConfig.preset("InvertedPendulum-v5", env_id=env_id).replace(
        n_envs=a.n_envs, env_workers=env_workers, eval_interval=0, checkpoint_interval=0).with_overrides(a.set)
    agent = SAC(config, env=gym.make(env_id, sleep_ms=a.sleep_ms) if env_id == SLOW_ENV else env_id)
    agent.learn(max(a.warmup, config.learning_starts + config.n_envs), progress=False)
    start = time.perf_counter()
    agent.collector.start(agent.num_steps)  # the workers start here (learn() closed the warm-up's)
    started = time.perf_counter()
    training_s = agent.learn(a.steps, progress=False)["wall_s"]  # the loop alone: learn() closes workers after it
    done = time.perf_counter()
    return {"env": env_id, "sleep_ms": a.sleep_ms if env_id == SLOW_ENV else 0.0, "n_envs": a.n_envs,
            "env_workers": env_workers, "steps": a.steps, "steps_per_s": round(a.steps / training_s, 1),
            "startup_s": round(started - start, 2), "shutdown_s": round(done - started - training_s, 2)}


def markdown(rows: list[dict]) -> str:
    lines = ["| env | env_workers | steps/s | vs in-process | workers' start-up, shutdown |",
             "| --- | --- | --- | --- | --- |"]
    base = {row["env"]: row["steps_per_s"] for row in rows if row["env_workers"] == 0}
    for row in rows:
        env = row["env"] + (f" ({row['sleep_ms']:g} ms a step)" if row["sleep_ms"] else "")
        ratio = f"{row['steps_per_s'] / base[row['env']]:.2f}x" if row["env"] in base else ""
        startup = f"{row['startup_s']:.2f} s, {row['shutdown_s']:.2f} s" if row["env_workers"] else ""
        lines.append(f"| {env} | {row['env_workers']} | {row['steps_per_s']:.1f} | {ratio} | {startup} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", default=f"{SLOW_ENV},InvertedPendulum-v5", help="comma list of env ids")
    p.add_argument("--workers", default="0,2,4", help="comma list of env_workers settings")
    p.add_argument("--n-envs", type=int, default=4)
    p.add_argument("--sleep-ms", type=float, default=5.0, help=f"{SLOW_ENV}'s sleep per step")
    p.add_argument("--steps", type=int, default=3000, help="timed env steps per setting")
    p.add_argument("--warmup", type=int, default=1000, help="env steps before timing (at least learning_starts)")
    p.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides")
    p.add_argument("--json", action="store_true", help="print the rows as JSON (the table goes to stderr)")
    a = p.parse_args(argv)

    rows = []
    for env_id in a.envs.split(","):
        for env_workers in map(int, a.workers.split(",")):
            rows.append(measure(env_id, env_workers, a))
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    table = markdown(rows)
    if a.json:
        print(json.dumps(rows))
        print(table, file=sys.stderr)
    else:
        print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
